"""The onboard program against the real FC emulator, mocap link and world, joined by in-memory links:
the mission sequence, the safe hover on stale mocap (poses it cannot use included), lockstep ticks,
refusing bad settings, bad commands and messages from anyone but the FC."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from onboard_rig import all_of, fc_holding, rewrite_mocap, rewrite_mocap_from, run_mission

from hil.cli import main as hil_main
from hil.link import MemoryTransport, SimClock
from hil.link.lockstep import tick_frames
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, mav
from policies.controller import AttitudeThrustCommand
from policies.onboard import OnboardProgram, PoseEstimator, ProgramConfig, make_pilot, pilot_names
from policies.onboard.command_link import CommandLink
from policies.onboard.pilots import Observation, UnknownPilot
from policies.onboard.pilots.traditional import takeoff_heading


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


def test_on_the_wall_clock_the_program_reads_its_mocap_at_its_control_steps_as_in_lockstep():
    """Stepped every 1 ms (as `run_realtime` may wake), the program takes the 120 Hz poses at its 100 Hz
    control steps only, each stamped with the step's time, as lockstep's ticks give them: read as each
    came, its estimate was a few ms fresher on the wall clock than lockstep models, and the real-time
    crossings came 0.36 cm closer to the wall (docs/notes/realtime-vs-lockstep.md)."""
    stamps: set[float] = set()

    def probe(t: float, vehicle, program: OnboardProgram) -> None:
        pose = program.mocap.latest("vehicle")
        if program.plan is not None and pose is not None:
            stamps.add(round(pose.received_s, 6))

    r = run_mission(30.0, 2.0, probe=probe)
    assert r.program.exit_code == 0 and len(stamps) > 100
    first = min(stamps)
    steps = [(t - first) / r.program.config.period_s for t in stamps]
    assert all(abs(k - round(k)) < 1e-3 for k in steps), sorted(stamps)[:10]


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


@pytest.mark.parametrize("vehicle", ["n3_tx2", "f450"])
def test_the_program_plans_with_its_vehicles_body_box_which_matches_the_airframe(vehicle):
    # the onboard side knows its body box from its own configuration (never the emulator's profile);
    # for the shipped vehicles it is the box the emulator's world checks collisions with
    from emulator.profile import load_profile
    from hil.runner.onboard_side import onboard_options, program_config
    from hil.scenario import loads_scenarios
    from policies.vehicle import load_vehicle

    (s,) = loads_scenarios(f"description: d\nvehicle: {vehicle}\n")
    box = program_config(onboard_options(s)).body_box_m
    assert box == load_vehicle(vehicle).body_box_m == tuple(load_profile(vehicle).body_box_m)
    bigger = program_config([*onboard_options(s), "--body-box", "0.9", "0.9", "0.3"])
    assert bigger.body_box_m == (0.9, 0.9, 0.3)
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


def test_a_tick_whose_announced_mocap_never_arrives_is_reported_as_lockstep_lost():
    # the harness announces 500 mocap bytes with the tick at 10 ms, but only 120 arrive: the program
    # reads what there is, says that lockstep was lost (the harness fails the run on it), and answers
    cmd_fc, cmd_ob = MemoryTransport.pair()
    moc_fc, moc_ob = MemoryTransport.pair()
    program = OnboardProgram(cmd_ob, moc_ob, ProgramConfig())
    program.link.lockstep = True
    moc_fc.send(bytes(120))
    cmd_fc.send(tick_frames(0.01, 500, 1, mav.MAV_COMP_ID_AUTOPILOT1))
    assert program.lockstep_poll() == [0.01]
    lost = [e for e in program.events.events if e["event"] == "lockstep_lost"]
    assert lost == [{"event": "lockstep_lost", "t_s": 0.01, "short_reads": 1}]
    codec = MavlinkCodec(cmd_fc, SimClock(), 1, mav.MAV_COMP_ID_AUTOPILOT1)
    answers = [m for m in codec.receive() if m.get_type() == "TIMESYNC"]
    assert [(m.tc1, m.ts1) for m in answers] == [(10_000_000, 10_000_000)]  # the tick is still answered
    # the next tick announces what has been written by then in all: read in full, nothing more reported
    moc_fc.send(bytes(400))
    cmd_fc.send(tick_frames(0.02, 520, 1, mav.MAV_COMP_ID_AUTOPILOT1))
    assert program.lockstep_poll() == [0.02]
    assert len([e for e in program.events.events if e["event"] == "lockstep_lost"]) == 1


@pytest.mark.parametrize("bad", [{"pos_m": (math.nan, 0.0, 1.0)}, {"stamp_us": 2**62}],
                         ids=["nan_position", "stamp_2_62"])
def test_vehicle_poses_the_estimator_cannot_take_are_stale_mocap(bad):
    # from 5 s on (mid-takeoff) every vehicle pose is unusable: the program must not fly on the frozen
    # estimate, but abort to a safe hover as when the stream stops
    r = run_mission(0.0, 1.5, mocap_tamper=rewrite_mocap_from(5.0, body_ids=(1,), **bad))
    abort = r.event("abort")
    assert abort["reason"] == "stale_mocap"
    assert 5.0 < abort["t_s"] < 5.0 + 0.1 + 0.04  # stale after 100 ms (+ the link's latency)
    assert r.program.exit_code == 3 and fc_holding(r.vehicle) and r.vehicle.state.pos_m[2] > 0.2
    c = r.program.mocap.counters
    assert (c.bodies_non_finite if "pos_m" in bad else c.bodies_stamp_future) > 10


def test_a_mocap_jump_is_refused_and_counted_and_the_mission_flies_on():
    # a 3 m jump of the vehicle for one frame in the approach, the gap's pose swapped with the vehicle's
    # for two frames before planning: neither is flown on
    tamper = all_of(rewrite_mocap_from(5.5, 1, pos_shift_m=(3.0, 0.0, 0.0), body_ids=(1,)),
                    rewrite_mocap_from(3.0, 2, swap_poses=True, body_ids=()))
    r = run_mission(0.0, 1.5, mocap_tamper=tamper)
    assert r.program.exit_code == 0 and "abort" not in r.event_names
    assert r.tracker.crossed_through_opening and r.tracker.first_collision is None
    summary = r.program.summary()
    assert (summary["estimator_implausible"], summary["gap_implausible"]) == (2 + 1, 2)  # (+ the swap)
    assert summary["estimator_rejected"] == summary["estimator_implausible"]


def _drift(t0_s: float, metres_a_frame: float) -> Callable[[float, bytes], bytes]:
    """Vehicle poses from ``t0_s`` moved ``metres_a_frame`` further along x each frame."""
    k = [0]

    def tamper(t: float, data: bytes) -> bytes:
        if t < t0_s:
            return data
        k[0] += 1
        return rewrite_mocap(data, pos_shift_m=(k[0] * metres_a_frame, 0.0, 0.0), body_ids=(1,))

    return tamper


@pytest.mark.parametrize(("t0_s", "tamper", "reason"), [
    (5.0, _drift(5.0, 1.0), "implausible_mocap"),
    (5.0, rewrite_mocap_from(5.0, pos_shift_m=(3.0, 0.0, 0.0), body_ids=(1,)), "implausible_mocap"),
    # the gap reported where the vehicle stands: the gap's side of a swap, alone
    (2.0, rewrite_mocap_from(2.0, pos_shift_m=(-2.0, -1.5, -1.6), body_ids=(2,)), "implausible_gap_pose"),
    (2.0, rewrite_mocap_from(2.0, swap_poses=True, body_ids=()), "implausible_mocap"),  # both bodies' sides
], ids=["drift_1m_a_frame", "jump_3m_held", "gap_moved", "gap_and_vehicle_swapped"])
def test_a_run_of_implausible_poses_aborts_to_a_safe_hover_naming_why(t0_s, tamper, reason):
    r = run_mission(0.0, 1.5, mocap_tamper=tamper)
    abort = r.event("abort")
    assert abort["reason"] == reason and abort["refused"] >= 10 and abort["jump_m"] >= 1.0, abort
    assert t0_s < abort["t_s"] < t0_s + 0.1 + 0.04  # as stale mocap: after 100 ms (+ the link's latency)
    summary = r.program.summary()
    assert summary["estimator_implausible" if reason == "implausible_mocap" else "gap_implausible"] >= 10
    assert r.program.exit_code == 3 and r.event_names[-1] in ("hold", "aborted")
    assert fc_holding(r.vehicle) and r.vehicle.state.pos_m[2] > 0.2  # the FC holds it in the air


def test_single_bad_mocap_frames_are_refused_and_the_mission_flies_on():
    # one frame stamped 2^62 us and one with NaN poses during the approach, one NaN gap pose before planning
    tamper = all_of(rewrite_mocap_from(5.0, 1, stamp_us=2**62),
                    rewrite_mocap_from(5.5, 1, pos_m=(math.nan,) * 3),
                    rewrite_mocap_from(3.0, 1, pos_m=(math.nan,) * 3, body_ids=(2,)))
    r = run_mission(0.0, 1.5, mocap_tamper=tamper)
    assert r.program.exit_code == 0 and "abort" not in r.event_names
    assert r.tracker.crossed_through_opening and r.tracker.first_collision is None
    c = r.program.mocap.counters
    assert (c.bodies_stamp_future, c.bodies_non_finite) == (2, 3)
    assert r.program.summary()["mocap"]["bodies_stamp_future"] == 2


def test_a_mocap_clock_that_jumps_back_mid_flight_is_followed_without_an_abort():
    # the mocap system restarts its clock during the approach (stamps 3 s lower from then on): the
    # reader refuses the stamps until ten frames agree, the estimate follows, the mission goes on
    r = run_mission(0.0, 1.5, mocap_tamper=rewrite_mocap_from(5.0, stamp_shift_us=-3_000_000))
    assert r.program.exit_code == 0 and "abort" not in r.event_names
    assert r.tracker.crossed_through_opening and r.tracker.first_collision is None
    c = r.program.mocap.counters
    assert c.clock_jumps == 1 and c.bodies_stamp_backwards == 2 * 9


def test_a_nan_gap_pose_is_refused_never_a_crash():
    # every gap pose NaN from the start: the program waits for a gap pose and says so when it gives up
    nan_gap = rewrite_mocap_from(0.0, pos_m=(math.nan,) * 3, body_ids=(2,))
    r = run_mission(0.0, 1.5, mocap_tamper=nan_gap, t_end_s=11.0)
    end = r.event("error")
    assert r.program.exit_code == 1 and end["reason"] == "timed out waiting for mocap and the FC"
    assert end["gap_mocap"] is False and end["vehicle_mocap"] is True
    assert r.program.mocap.counters.bodies_non_finite > 1000


def test_a_non_finite_command_is_refused_and_aborts_to_a_safe_hover():
    class NanThrust:
        def command(self, obs: Observation) -> AttitudeThrustCommand:
            return AttitudeThrustCommand(0.0, 0.0, 0.0, math.nan)

    r = run_mission(0.0, 1.5, pilot=NanThrust())
    abort = r.event("abort")
    assert abort["reason"] == "bad_command" and "thrust nan" in abort["detail"]
    assert r.program.commands_refused == 1 and r.program.exit_code == 3
    assert fc_holding(r.vehicle) and r.vehicle.state.pos_m[2] > 0.2  # held by the FC, no fall
    link = CommandLink(MemoryTransport.pair()[0], SimClock())
    with pytest.raises(ValueError, match="not finite"):
        link.send_attitude_target(0.0, 0.0, 0.0, math.nan)
    assert link.setpoints_sent == 0


def test_heartbeats_acks_and_ticks_from_other_systems_are_ignored_and_counted():
    clock = SimClock()
    ob_end, fc_end = MemoryTransport.pair()
    link = CommandLink(ob_end, clock)
    link.lockstep = True
    armed_offboard = (mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, mav.MAV_MODE_FLAG_SAFETY_ARMED,
                      PX4_MAIN_OFFBOARD << 16, mav.MAV_STATE_ACTIVE)
    for sysid, compid in ((2, mav.MAV_COMP_ID_AUTOPILOT1), (1, mav.MAV_COMP_ID_CAMERA), (255, 190)):
        other = MavlinkCodec(fc_end, clock, sysid, compid)
        other.send(other.mav.heartbeat_encode(*armed_offboard))
        other.send(other.mav.command_ack_encode(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_ACCEPTED))
        other.send(other.mav.named_value_int_encode(0, b"mocap_n", 999))
        other.send(other.mav.timesync_encode(0, 10_000_000))
    link.read()
    assert link.status is None and link.acks == {} and link.take_ticks() == []
    assert link.mocap_announced is None
    assert link.foreign == {"heartbeats": 3, "acks": 3, "ticks": 6}
    fc = MavlinkCodec(fc_end, clock, 1, mav.MAV_COMP_ID_AUTOPILOT1)  # the FC's own are taken
    fc.send(fc.mav.heartbeat_encode(*armed_offboard))
    fc.send(fc.mav.command_ack_encode(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_ACCEPTED))
    fc.send(fc.mav.named_value_int_encode(0, b"mocap_n", 999))
    fc.send(fc.mav.timesync_encode(0, 10_000_000))
    link.read()
    assert link.status is not None and link.status.armed and link.status.offboard
    assert link.acks[mav.MAV_CMD_COMPONENT_ARM_DISARM].accepted
    assert link.take_ticks() == [0.01] and link.mocap_announced == 999
    assert link.foreign == {"heartbeats": 3, "acks": 3, "ticks": 6}


def test_estimator_follows_a_mocap_clock_that_went_back_once_it_has_taken_nothing_for_the_reset_time():
    est = PoseEstimator()
    q = np.array([1.0, 0.0, 0.0, 0.0])
    assert est.update(1e9, np.zeros(3), q, 0.0)  # a bad stamp taken as the first
    for k in range(1, 60):  # good poses after it: refused while the estimate is younger than 0.5 s
        t = k / 120
        assert est.update(t, np.array([t, 0.0, 0.0]), q, t + 0.02) is (t + 0.02 > est.config.reset_after_s)
    now = 59 / 120 + 0.02
    assert est.age_s(now) == 0.0 and est.estimate(now).pos_m[0] == pytest.approx(59 / 120, abs=0.05)


def test_the_traditional_pilots_compiled_step_flies_the_mission_its_command_flies():
    """The program runs the traditional pilot's step as one compiled call (`compiled_step`: the state,
    the command, the tilt-step limit); a pilot offering only `command` goes the long way. Both fly the
    same mission to the bit."""
    pilot = make_pilot("traditional")

    class CommandOnly:
        flies = pilot.flies

        def command(self, obs: Observation) -> AttitudeThrustCommand:
            return pilot.command(obs)

    def commands(r_pilot: object) -> tuple[list[tuple[float, ...]], object]:
        seen: list[tuple[float, ...]] = []

        def probe(t: float, vehicle: object, program: OnboardProgram) -> None:
            c = program._last_setpoint  # (roll, pitch, yaw, thrust)
            if c is not None:
                seen.append(c)

        r = run_mission(30.0, 2.0, pilot=r_pilot, probe=probe)  # type: ignore[arg-type]
        return seen, r

    fast, r_fast = commands(make_pilot("traditional"))
    slow, r_slow = commands(CommandOnly())
    assert r_fast.program._pilot_step is not None and r_slow.program._pilot_step is None
    assert r_fast.program.exit_code == r_slow.program.exit_code == 0
    assert len(fast) > 500 and fast == slow
    assert np.array_equal(r_fast.vehicle.state.pos_m, r_slow.vehicle.state.pos_m)


def test_the_take_off_turns_from_its_first_heading_to_the_missions_within_its_duration():
    assert takeoff_heading(0.5, 1.0, 2.0, 0.2, 1.0) == (0.0, 0.2)  # before the start: at the start
    assert takeoff_heading(2.0, 1.0, 2.0, 0.2, 1.0) == (1.0, 0.2 + 0.8 * 0.5)  # halfway: half turned
    assert takeoff_heading(9.0, 1.0, 2.0, 0.2, 1.0) == (2.0, 1.0)  # after the end: held at the end
