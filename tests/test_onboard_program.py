"""The onboard program against the real FC emulator, mocap link and world, joined by in-memory links:
the mission sequence, the safe hover on stale mocap, lockstep ticks, and refusing bad settings."""

from __future__ import annotations

import math

import numpy as np
import pytest
from onboard_rig import fc_holding, run_mission

from hil.cli import main as hil_main
from policies.onboard import PoseEstimator, ProgramConfig, make_pilot, pilot_names
from policies.onboard.pilots import UnknownPilot


def test_mission_runs_its_phases_in_order_and_hands_back_to_hold():
    r = run_mission(0.0, 1.5)
    names = r.event_names
    expected = ["start", "mocap_ok", "authority", "armed", "takeoff", "plan", "mission_done", "done"]
    assert [n for n in names if n in expected] == expected
    segments = [e["segment"] for e in r.program.events.events if e["event"] == "segment"]
    assert segments == ["approach", "traverse", "recovery", "hover"]
    assert r.program.exit_code == 0
    assert r.event("done")["hold"] is True and fc_holding(r.vehicle)
    # every control step went out as a setpoint the FC applied, at the configured rate
    plan_t, done_t = r.event("plan")["t_s"], r.event("mission_done")["t_s"]
    assert r.program.control_steps >= 0.95 * (done_t - plan_t) * 100
    assert r.program.skipped_steps == 0


def test_stale_mocap_aborts_to_a_safe_hover_and_the_fc_holds():
    r = run_mission(0.0, 1.5, mocap_cut_s=5.0)  # mid-takeoff
    abort = r.event("abort")
    assert abort["reason"] == "stale_mocap"
    assert 5.0 < abort["t_s"] < 5.0 + 0.1 + 0.04  # stale after 100 ms (+ the link's latency)
    assert r.event_names[-1] == "hold"
    assert r.program.exit_code == 3
    assert fc_holding(r.vehicle)
    assert r.vehicle.state.pos_m[2] > 0.2  # still flying: the FC holds it, no fall


def test_no_plan_for_the_body_aborts_before_takeoff_with_the_reason():
    """A lab whose ceiling leaves the body box no room over the gap (2.1 m up, ceiling at 2.4 m): the
    program says why and never arms; the vehicle stays on the ground."""
    r = run_mission(0.0, 2.0, t_end_s=5.0, lab_max_m=(5.0, 5.0, 2.4))
    abort = r.event("abort")
    assert abort["reason"] == "planning_failed" and abort["phase"] == "wait"
    assert "no plan keeps the body's 0.43 m clearance" in abort["detail"]
    assert "lab's faces" in abort["detail"]
    assert not {"authority", "armed", "takeoff", "plan"} & set(r.event_names)
    assert r.program.exit_code == 3 and r.event_names[-1] == "aborted"
    assert r.vehicle.state.pos_m[2] < 0.2  # never left the ground
    # a bigger body than the default needs more room than the same lab has at a 2.6 m ceiling
    assert "plan" in run_mission(0.0, 2.0, t_end_s=6.0, lab_max_m=(5.0, 5.0, 2.6)).event_names
    big = run_mission(0.0, 2.0, t_end_s=5.0, lab_max_m=(5.0, 5.0, 2.6), body_box_m=(0.9, 0.9, 0.3))
    assert big.event("abort")["reason"] == "planning_failed" and big.program.exit_code == 3


def test_the_harness_gives_the_program_the_vehicles_body_box():
    from emulator.profile import load_profile
    from hil.runner.onboard_side import onboard_options, program_config
    from hil.scenario import loads_scenarios

    (s,) = loads_scenarios("description: d\nvehicle: f450\n")
    profile = load_profile("f450")
    assert program_config(onboard_options(s, profile)).body_box_m == tuple(profile.body_box_m)
    with pytest.raises(ValueError, match="body box"):
        ProgramConfig(body_box_m=(0.5, 0.0, -0.1))


def test_lockstep_answers_every_tick_with_its_own_time_and_flies():
    r = run_mission(0.0, 1.5, lockstep_period_s=0.01, t_end_s=6.0)
    assert len(r.tick_answers) >= 590
    assert all(tc1 == ts1 for tc1, ts1 in r.tick_answers)
    times = [ts1 for _, ts1 in r.tick_answers]
    assert times[0] == 10_000_000  # the first tick, at 10 ms, in ns
    assert set(np.diff(times)) == {10_000_000}  # one answer per tick, in order, none missed
    assert "armed" in r.event_names and "takeoff" in r.event_names
    assert r.vehicle.state.pos_m[2] > 0.3  # taking off under lockstep control


def test_rate_below_the_n3_minimum_is_refused(capsys):
    with pytest.raises(ValueError, match="50 Hz"):
        ProgramConfig(rate_hz=49.0)
    code = hil_main(["onboard", "--command-link", "udpout:127.0.0.1:9", "--mocap-link", "udp:127.0.0.1:0",
                     "--rate-hz", "20"])
    assert code == 2
    assert "50 Hz" in capsys.readouterr().err


def test_bad_link_spec_and_unknown_pilot_are_clear_errors(capsys):
    assert hil_main(["onboard", "--command-link", "bogus:1", "--mocap-link", "udp:127.0.0.1:0"]) == 2
    assert "unknown link kind" in capsys.readouterr().err
    assert hil_main(["onboard", "--command-link", "udpout:127.0.0.1:9", "--mocap-link", "udp:127.0.0.1:0",
                     "--pilot", "nobody"]) == 2
    assert "traditional" in capsys.readouterr().err
    with pytest.raises(UnknownPilot, match="traditional"):
        make_pilot("nobody")
    assert "traditional" in pilot_names()


def test_estimator_recovers_velocity_and_acceleration_from_poses():
    rng = np.random.default_rng(0)
    est = PoseEstimator()
    a = np.array([1.0, -2.0, 0.5])
    v0 = np.array([0.5, 1.0, 0.0])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for k in range(120):  # one second at 120 Hz, mocap-grade noise
        t = k / 120
        p = v0 * t + a * t * t / 2 + rng.normal(0, 2e-4, 3)
        assert est.update(t, p, q, t)
    t = 119 / 120
    s = est.estimate(t - est.config.latency_s)  # predicted to the last exposure
    assert np.allclose(s.vel_m_s, v0 + a * t, atol=0.05)
    assert np.allclose(s.acc_m_s2, a, atol=0.5)
    assert not est.update(t, np.zeros(3), q, t)  # a repeated stamp is rejected
    assert not est.update(t + 1, np.array([math.nan, 0, 0]), q, t + 1)
