"""The onboard program against the real FC emulator, mocap link and world, joined by in-memory links:
the mission sequence, the safe hover on stale mocap, lockstep ticks, and refusing bad settings."""

from __future__ import annotations

import math

import numpy as np
import pytest
from onboard_rig import fc_holding, run_mission

from hil.cli import main as hil_main
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import MavlinkCodec, mav
from hil.runner.lockstep import tick_frames
from policies.onboard import OnboardProgram, PoseEstimator, ProgramConfig, make_pilot, pilot_names
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


def test_a_tick_whose_announced_mocap_never_arrives_is_reported_as_lockstep_lost():
    # the harness announces 500 mocap bytes with the tick at 10 ms, but only 120 arrive: the program
    # reads what there is, says that lockstep was lost (the harness fails the run on it), and answers
    cmd_fc, cmd_ob = MemoryTransport.pair()
    moc_fc, moc_ob = MemoryTransport.pair()
    program = OnboardProgram(cmd_ob, moc_ob, ProgramConfig())
    program.link.lockstep = True
    moc_fc.send(bytes(120))
    cmd_fc.send(tick_frames(0.01, 500))
    assert program.lockstep_poll() == [0.01]
    lost = [e for e in program.events.events if e["event"] == "lockstep_lost"]
    assert lost == [{"event": "lockstep_lost", "t_s": 0.01, "short_reads": 1}]
    codec = MavlinkCodec(cmd_fc, SimClock(), 1, mav.MAV_COMP_ID_AUTOPILOT1)
    answers = [m for m in codec.receive() if m.get_type() == "TIMESYNC"]
    assert [(m.tc1, m.ts1) for m in answers] == [(10_000_000, 10_000_000)]  # the tick is still answered
    # the next tick announces what has been written by then in all: read in full, nothing more reported
    moc_fc.send(bytes(400))
    cmd_fc.send(tick_frames(0.02, 520))
    assert program.lockstep_poll() == [0.02]
    assert len([e for e in program.events.events if e["event"] == "lockstep_lost"]) == 1
