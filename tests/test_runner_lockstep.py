"""The runner in lockstep: determinism of the .tlog on both paths, batched physics equal to the FC's own
stepping, the lockstep wire's framing, and fault effects a user relies on."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from onboard_rig import rewrite_mocap_from

from emulator.fc import FcState
from emulator.fc.n3 import N3Setpoint
from emulator.loops.batched_steps import FastStepper
from emulator.physics.native import hover_state
from emulator.profile import load_profile
from emulator.vehicle import EmulatedVehicle
from hil.link.lockstep import answered_ns
from hil.link.mavlink import (
    FrameSplitter,
    mav,
)
from hil.link.tlog import read_tlog
from hil.runner import RunOptions, RunSetupError, run_scenario
from hil.runner.emulator_side import EmulatorSide, _FaultyLink
from hil.runner.lockstep import SPIN_S, kept_to, lockstep_cpu, lockstep_spin_s
from hil.scenario import load_scenarios, loads_scenarios

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
SHORT = """
description: a level gap, cut short after the takeoff (determinism only)
gap: {roll_deg: 0}
links:
  mocap: {latency_ms: 20, jitter_ms: 4, loss: 0.05}
  command: {latency_ms: 1, jitter_ms: 0.5, loss: 0.02}
duration_s: 2.0
seed: 7
"""


@pytest.mark.parametrize("in_process", [True, False], ids=["in_process", "ptys"])
def test_a_whole_crossing_gives_the_same_tlog_and_time_series_twice(tmp_path, in_process):
    # takeoff, approach, traverse, recovery, hover and the hand-back: the whole mission, not its start
    s = load_scenarios(SCENARIOS / "gap_roll30_2ms.scenario.yaml")[0]
    a, b = (run_scenario(s, tmp_path / name, RunOptions(in_process=in_process)) for name in "ab")
    assert a.passed, [f"{c.name}: {c.observed}" for c in a.failed_checks]
    log = (a.out_dir / "onboard_events.jsonl").read_text()
    events = [json.loads(line)["event"] for line in log.splitlines()]
    assert {"mission_done", "done"} <= set(events)  # the program flew all of it and handed back
    assert a.summary["lockstep"] == {"held": True, "short_mocap_reads": 0, "lost_at_s": None}
    assert a.tlog_path.read_bytes() == b.tlog_path.read_bytes()
    ta, tb = (np.load(r.out_dir / "timeseries.npz") for r in (a, b))
    assert ta.files == tb.files and len(ta["t_s"]) > 1000
    for name in ta.files:
        np.testing.assert_array_equal(ta[name], tb[name], err_msg=name)
    # (not ticks_answered: whether a tick already in flight when the program finishes gets an answer
    # before it exits is the OS's scheduling, and changes nothing that was flown or recorded)
    for key in ("crossing", "min_clearance_m", "attitude_error_deg", "mean_thrust_n", "checks"):
        assert a.summary[key] == b.summary[key], key


@pytest.mark.parametrize("in_process", [True, False], ids=["in_process", "ptys"])
def test_same_scenario_and_seed_give_the_same_tlog(tmp_path, in_process):
    s = loads_scenarios(SHORT)[0]
    a = run_scenario(s, tmp_path / "a", RunOptions(in_process=in_process))
    b = run_scenario(s, tmp_path / "b", RunOptions(in_process=in_process))
    ta, tb = a.tlog_path.read_bytes(), b.tlog_path.read_bytes()
    assert len(ta) > 10_000  # telemetry and setpoints both ways
    assert ta == tb
    c = run_scenario(s, tmp_path / "c", RunOptions(in_process=in_process, seed=8))
    assert c.tlog_path.read_bytes() != ta  # the seed reaches the link models
    # the program flies on past 2 s: every tick is answered, none lost or given up
    assert a.summary["ticks"] == 200 and a.summary["ticks_answered"] == 200
    # a program still flying when the run ends (a process: ended by SIGTERM) leaves its counters too
    onboard = a.summary["onboard"]
    assert onboard["phase"] == "takeoff" and onboard["mocap"]["frames_ok"] > 100
    assert a.summary["onboard_exit_code"] == (None if in_process else 143)


def test_batched_offboard_flight_equals_per_step_flight():
    profile = load_profile("n3_tx2")
    runs = []
    for batched in (False, True):
        v = EmulatedVehicle(profile, initial_state=hover_state(profile, (0.0, 0.0, 1.0)))
        v.fc.arm(0.0)
        sp = N3Setpoint(0x20, 10.0, -5.0, 42.0, 30.0)  # ANGLE | THRUST | YAW_ANGLE | GROUND
        for k in range(3):
            v.fc.set_setpoint(sp, 0.001 * k)
        assert v.fc.request_offboard(0.003).accepted
        stepper = FastStepper.for_vehicle(v)
        if batched:
            stepper.step(500)
            assert stepper.batched_steps > 400
        else:
            v.step(500)
        runs.append(v.state.to_vector())
    np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=1e-12)


def test_a_setpoint_timeout_past_any_step_count_still_flies_in_batches():
    """A failsafe timeout longer than an int64 count of steps (a parameter set to 1e17 s): the batches
    fly the whole advance, the same flight as the FC's own steps."""
    profile = load_profile("n3_tx2")
    runs = []
    for batched in (False, True):
        v = EmulatedVehicle(profile, initial_state=hover_state(profile, (0.0, 0.0, 1.0)))
        v.fc.reconfigure(failsafe_timeout_s=1e17)
        v.fc.arm(0.0)
        for k in range(3):
            v.fc.set_setpoint(N3Setpoint(0x20, 5.0, 0.0, 40.0, 0.0), 0.001 * k)
        assert v.fc.request_offboard(0.003).accepted
        if batched:
            stepper = FastStepper.for_vehicle(v)
            stepper.step(300)
            assert stepper.batched_steps == 300
        else:
            v.step(300)
        runs.append(v.state.to_vector())
    np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=1e-12)


def _offboard_vehicle(height_m: float, thrust_pct: float, hold: bool = False) -> EmulatedVehicle:
    """A vehicle hovering at ``height_m``, in OFFBOARD on a held target of ``thrust_pct`` % (1 s
    setpoint-loss timeout from 3 ms), or holding on its own (``hold``)."""
    profile = load_profile("n3_tx2")
    v = EmulatedVehicle(profile, initial_state=hover_state(profile, (0.0, 0.0, height_m)))
    v.fc.arm(0.0)
    if not hold:
        for k in range(3):
            v.fc.set_setpoint(N3Setpoint(0x20, 4.0, -3.0, thrust_pct, 10.0), 0.001 * k)
        assert v.fc.request_offboard(0.003).accepted
    return v


def _fc_trace(v: EmulatedVehicle) -> tuple[object, ...]:
    fc = v.fc
    # (since when it is landed: the auto-disarm's clock in a landing state)
    events = tuple((e.to_state, e.time_s) for e in fc.events)
    return (fc.state, fc.landed, fc._landed_since_s, events, v.steps)


@pytest.mark.parametrize(("height_m", "thrust_pct", "hold", "ks", "n_after"), [
    (1.0, 40.0, False, (1, 137, 400), 250),  # flown through in one batch
    (1.0, 40.0, False, (960, 990, 1001, 1010), 40),  # the setpoint-loss failsafe near or inside the span
    (0.12, 10.0, False, tuple(range(5, 400, 9)), 60),  # touching down somewhere in the span
    (1.0, 40.0, True, (50,), 100),  # the FC's own hold: no attitude target to batch
])
def test_a_pose_captured_inside_the_steps_is_the_pose_between_two_advances(height_m, thrust_pct, hold, ks,
                                                                             n_after):
    """`FastStepper.step` with ``capture_at``: the same flight, FC bookkeeping and pose as two advances
    split at the capture with the pose read between them (what the run loop's exposure would read)."""
    for k in ks:
        split = _offboard_vehicle(height_m, thrust_pct, hold)
        s = FastStepper.for_vehicle(split)
        s.step(k)
        pose = split.pose_values()
        s.step(n_after)
        fused = _offboard_vehicle(height_m, thrust_pct, hold)
        f = FastStepper.for_vehicle(fused)
        f.step(k + n_after, None, k)
        assert f.pose_captured == pose, k
        assert np.array_equal(fused.state_vector(), split.state_vector()), k
        assert _fc_trace(fused) == _fc_trace(split), k
        assert (f.batched_steps, f.single_steps) == (s.batched_steps, s.single_steps), k


def test_batches_stop_at_the_setpoint_timeout():
    profile = load_profile("n3_tx2")
    v = EmulatedVehicle(profile, initial_state=hover_state(profile, (0.0, 0.0, 1.0)))
    v.fc.arm(0.0)
    sp = N3Setpoint(0x20, 0.0, 0.0, 40.0, 0.0)
    for k in range(3):
        v.fc.set_setpoint(sp, 0.001 * k)
    v.fc.request_offboard(0.003)
    FastStepper.for_vehicle(v).step(1500)
    assert v.fc.state.failsafe  # the FC's own timeout (1 s) still fires inside a long advance


def test_frame_splitter_and_tick_answers():
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=191)
    answer = bytes(enc.timesync_encode(20_000_000, 20_000_000).pack(enc))
    request = bytes(enc.timesync_encode(0, 20_000_000).pack(enc))
    hb = bytes(enc.heartbeat_encode(18, 8, 0, 0, 4).pack(enc))
    sp = FrameSplitter()
    stream = b"\x00\x01" + hb + answer + request
    frames = sp.feed(stream[:7]) + sp.feed(stream[7:])
    assert frames == [b"\x00\x01", hb, answer, request]
    assert answered_ns(answer) == 20_000_000
    assert answered_ns(request) is None and answered_ns(hb) is None


FAULTY = """
description: command link down from 1 s, the FC must fail safe; killed onboard from 1.5 s
gap: {roll_deg: 0}
faults:
  - {kind: command_link_down, start_s: 1.0}
  - {kind: onboard_killed, at_s: 1.5}
duration_s: 3.0
expect:
  crosses_gap: false
  recovery: false
  failsafe_expected: hover
"""


def test_faults_make_the_fc_fail_safe_and_are_reported(tmp_path):
    s = loads_scenarios(FAULTY)[0]
    r = run_scenario(s, tmp_path, RunOptions(in_process=True))
    assert r.passed, r.failed_checks
    fs = r.summary["failsafe_events"]
    assert (
        fs and fs[0]["state"] == "failsafe_hover" and 1.9 <= fs[0]["time_s"] <= 2.1
    )  # 1 s after the last setpoint
    assert r.summary["links"]["command"]["to_fc_frames_dropped_fault"] > 50
    texts = [e["text"] for e in r.summary["events"]]
    assert "onboard program killed" in texts
    for name in ("summary.json", "run.tlog", "timeseries.npz", "report.html"):
        assert (tmp_path / name).stat().st_size > 0
    assert math.isfinite(r.summary["mean_thrust_n"]) and r.summary["mean_thrust_n"] > 5


FROZEN = """
description: mocap frozen for 50 ms during the settle; the freeze must end when its window does
gap: {roll_deg: 0}
approach: {speed_m_s: 2.0}
faults:
  - {kind: mocap_frozen, start_s: 3.0, end_s: 3.05}
duration_s: 11
"""


def test_a_mocap_freeze_ends_at_its_end_time(tmp_path):
    # 3.0 + 0.05 lands a rounding error off 3.05: the fault switch must still see the window close,
    # or the onboard program flies on one frozen pose for the rest of the run
    s = loads_scenarios(FROZEN)[0]
    r = run_scenario(s, tmp_path, RunOptions(in_process=True))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]


COMPUTE = """
description: a level gap, cut short; the onboard computer's modelled compute time
gap: {roll_deg: 0}
duration_s: 1.5
"""


def _setpoint_phases_ms(tlog_path, tick_ms: float) -> list[float]:
    """Where in the tick (ms) the FC read each SET_ATTITUDE_TARGET (the .tlog stamps received frames)."""
    out = []
    for stamp_us, frame in read_tlog(tlog_path):
        if frame[0] == 0xFD and frame[7] | frame[8] << 8 | frame[9] << 16 == 82:
            out.append((stamp_us / 1e3) % tick_ms)
    return out


@pytest.mark.parametrize("in_process", [True, False], ids=["in_process", "ptys"])
def test_onboard_outputs_reach_the_fc_compute_time_after_their_tick(tmp_path, in_process):
    wire_ms = 51 * 10 / 921600 * 1e3  # one SET_ATTITUDE_TARGET at the default baud
    for compute_ms in (0.0, 6.0):
        s = loads_scenarios(COMPUTE + f"onboard_compute_ms: {compute_ms}\n")[0]
        r = run_scenario(s, tmp_path / f"c{compute_ms:g}", RunOptions(in_process=in_process))
        phases = _setpoint_phases_ms(r.tlog_path, 10.0)
        assert len(phases) > 100  # the onboard program streams setpoints from its first ticks
        # none before the tick + compute + wire time; most at it (a few queue behind other frames)
        assert min(phases) > compute_ms + wire_ms - 0.01, sorted(set(phases))[:5]
        assert float(np.median(phases)) == pytest.approx(compute_ms + wire_ms, abs=0.01)


def test_a_compute_time_longer_than_a_tick_is_refused(tmp_path):
    s = loads_scenarios(COMPUTE + "onboard_compute_ms: 15\n")[0]
    with pytest.raises(RunSetupError, match="onboard_compute_ms is 15 ms, longer than the lockstep tick"):
        run_scenario(s, tmp_path, RunOptions(in_process=True))


@pytest.mark.parametrize("mode", ["hold", "land", "failsafe"])
def test_batched_hold_hover_and_land_equal_per_step_flight(mode):
    # the FC's own velocity controller, batched, down to the landing and the disarm that follows
    profile = load_profile("n3_tx2")
    runs = []
    for batched in (False, True):
        v = EmulatedVehicle(profile, initial_state=hover_state(profile, (0.0, 0.0, 1.0)))
        v.backend.reset(replace(v.state, vel_m_s=np.array([1.0, -0.5, 0.3])))  # drifting: the hold works
        v.invalidate_state()
        v.fc.arm(0.0)
        if mode == "land":
            assert v.fc.request_land(0.0).accepted
        elif mode == "failsafe":  # a stream that stops: failsafe hover after 1 s, land 5 s later
            for k in range(3):
                v.fc.set_setpoint(N3Setpoint(0x20, 0.0, 0.0, 40.0, 0.0), 0.001 * k)
            assert v.fc.request_offboard(0.003).accepted
        stepper = FastStepper.for_vehicle(v)
        if batched:
            for _ in range(40):  # in pieces, as the runner's stops cut them
                stepper.step(250)
            assert stepper.batched_steps > (1500 if mode == "land" else 7000)  # land: down in 1.7 s
        else:
            v.step(10_000)
        runs.append((v.state.to_vector(), v.fc.state, [(e.time_s, e.reason) for e in v.fc.events]))
    np.testing.assert_allclose(runs[0][0], runs[1][0], rtol=0, atol=1e-9)
    assert runs[0][1:] == runs[1][1:]
    if mode != "hold":
        assert runs[1][1] is FcState.DISARMED  # it came down, and the batches stopped for the landing


CORRUPT = """
description: corrupt bytes on the command link, some lockstep ticks swallowed by a bad frame in front
gap: {roll_deg: 0}
faults:
  - {kind: corrupt_bytes, start_s: 0.0, params: {link: command, fraction: 0.03}}
duration_s: 2.0
seed: 2
"""


def test_ticks_lost_to_corrupt_bytes_are_sent_again_and_the_run_stays_deterministic(tmp_path):
    s = loads_scenarios(CORRUPT)[0]
    runs = [run_scenario(s, tmp_path / name, RunOptions(in_process=False)) for name in ("a", "b")]
    for r in runs:
        texts = [e["text"] for e in r.summary["events"]]
        assert not any("declared dead" in t for t in texts), texts
        assert r.summary["ticks_answered"] == r.summary["ticks"]  # every tick answered, none given up
        assert r.summary["links"]["command"]["to_onboard_bytes_corrupted"] > 0
    assert runs[0].tlog_path.read_bytes() == runs[1].tlog_path.read_bytes()


def test_the_onboard_program_ends_on_a_silent_fc_naming_the_phase_it_was_in(tmp_path):
    # the command link dies for good: the FC fails safe, and the onboard program, hearing no
    # heartbeat, ends with an fc_lost event saying in which phase (in one process, a crash here would
    # take the run down with it)
    s = load_scenarios(SCENARIOS / "command_link_down.scenario.yaml")[0]
    r = run_scenario(s, tmp_path, RunOptions(in_process=True))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    events = [json.loads(line) for line in (tmp_path / "onboard_events.jsonl").read_text().splitlines()]
    lost = [e for e in events if e.get("event") == "fc_lost"]
    assert len(lost) == 1 and lost[0]["phase"] and lost[0]["silence_s"] >= 3.0



def test_a_program_ending_mid_run_is_noted_alike_on_a_busy_and_an_idle_host(tmp_path, monkeypatch):
    # the program hears no FC for 3 s and ends at about 4 s: whether it is already gone when the next
    # tick is due depends on how long the harness's own work takes on the host; what the run counts and
    # records must not (once, under load, one of its frames went uncounted)
    s = load_scenarios(SCENARIOS / "command_link_down.scenario.yaml")[0]
    idle = run_scenario(s, tmp_path / "idle", RunOptions(in_process=False))
    advance = EmulatorSide.advance_to

    def busy(emu: EmulatorSide, t_end_s: float) -> None:
        if 3.9 <= t_end_s <= 4.3:
            time.sleep(0.03)  # (wall s: time enough for an ending program to be gone)
        advance(emu, t_end_s)

    monkeypatch.setattr(EmulatorSide, "advance_to", busy)
    loaded = run_scenario(s, tmp_path / "busy", RunOptions(in_process=False))
    exits = [[e["time_s"] for e in r.summary["events"] if e["text"] == "onboard program exited"]
             for r in (idle, loaded)]
    assert len(exits[0]) == 1 and 3.9 < exits[0][0] < 4.3 and exits[0] == exits[1]
    # (all but the FC codec's frames received and ignored: frames a program writes as it closes, read
    # or not before the run's end, which nothing flown or recorded depends on)
    teardown = ("fc_codec_frames_received", "fc_codec_frames_ignored")
    counts = [{k: v for k, v in r.summary["links"]["command"].items() if k not in teardown}
              for r in (idle, loaded)]
    assert counts[0]["to_fc_frames_dropped_fault"] > 100 and counts[0] == counts[1]
    assert loaded.tlog_path.read_bytes() == idle.tlog_path.read_bytes()
    ta, tb = (np.load(r.out_dir / "timeseries.npz") for r in (idle, loaded))
    for name in ta.files:
        np.testing.assert_array_equal(ta[name], tb[name], err_msg=name)

BAD_MOCAP_SINGLE = """
description: one mocap frame stamped 2^62 us and one with NaN poses during the approach
gap: {roll_deg: 30}
duration_s: 11
"""
BAD_MOCAP_STREAM = """
description: every vehicle pose NaN (or stamped 2^62 us) from 5 s on; the program must abort
gap: {roll_deg: 30}
duration_s: 7
expect:
  crosses_gap: false
  recovery: false
  onboard_abort_expected: true
"""


def _tamper_mocap_link(monkeypatch, tamper) -> None:
    """Rewrite the mocap bytes the emulator side writes to the real link, by sim time (s)."""
    send = _FaultyLink._send_internal
    monkeypatch.setattr(_FaultyLink, "_send_internal",
                        lambda link, data: send(link, tamper(link.clock.now_s(), data)))


def test_single_bad_mocap_frames_on_the_pty_are_refused_and_the_crossing_flies_on(tmp_path, monkeypatch):
    tampers = [rewrite_mocap_from(5.0, 1, stamp_us=2**62), rewrite_mocap_from(5.3, 1, pos_m=(math.nan,) * 3)]

    def both(t: float, data: bytes) -> bytes:
        for tamper in tampers:
            data = tamper(t, data)
        return data

    _tamper_mocap_link(monkeypatch, both)
    r = run_scenario(loads_scenarios(BAD_MOCAP_SINGLE)[0], tmp_path, RunOptions(in_process=False))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["onboard_exit_code"] == 0 and s["onboard_abort_s"] is None
    mocap = s["onboard"]["mocap"]  # the onboard program's own counters, from its closing summary
    assert (mocap["bodies_stamp_future"], mocap["bodies_non_finite"]) == (2, 2)
    assert mocap["bodies_stamp_backwards"] == mocap["clock_jumps"] == 0


@pytest.mark.parametrize("bad", [{"pos_m": (math.nan, 0.0, 1.0)}, {"stamp_us": 2**62}],
                         ids=["nan_position", "stamp_2_62"])
def test_a_stream_of_bad_mocap_frames_on_the_pty_aborts_with_stale_mocap(tmp_path, monkeypatch, bad):
    _tamper_mocap_link(monkeypatch, rewrite_mocap_from(5.0, body_ids=(1,), **bad))
    r = run_scenario(loads_scenarios(BAD_MOCAP_STREAM)[0], tmp_path, RunOptions(in_process=False))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    s = r.summary
    assert 5.0 < s["onboard_abort_s"] < 5.0 + 0.1 + 0.04  # 100 ms stale (+ the mocap chain's latency)
    events = [json.loads(line) for line in (tmp_path / "onboard_events.jsonl").read_text().splitlines()]
    assert next(e for e in events if e["event"] == "abort")["reason"] == "stale_mocap"
    assert s["onboard_exit_code"] == 3 and s["fc_final_state"] == "hold"
    kind = "bodies_non_finite" if "pos_m" in bad else "bodies_stamp_future"
    assert s["onboard"]["mocap"][kind] > 10 and s["onboard"]["estimator_rejected"] == 0


@pytest.mark.parametrize("realtime", [False, pytest.param(True, marks=pytest.mark.realtime)],
                         ids=["lockstep", "realtime"])
def test_a_run_goes_on_while_the_recovery_window_is_open(tmp_path, realtime):
    # crossing at about 6.6 s, the recovery check 4 s later: a 9 s run goes on to close the window,
    # on either clock, and says so in its sim time (by up to 3 s past its duration)
    s = replace(load_scenarios(SCENARIOS / "gap_roll30_2ms.scenario.yaml")[0], duration_s=9.0)
    r = run_scenario(s, tmp_path, RunOptions(in_process=True, realtime=realtime))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    crossing = r.summary["crossing"]["time_s"]
    start = r.summary["realtime"]["contact_s"] if realtime else 0.0
    assert crossing + 4.0 <= r.summary["sim_time_s"] <= crossing + 4.0 + 0.1
    assert r.summary["sim_time_s"] - start > 9.0


def test_run_reports_the_onboard_start_up_apart_from_the_loop(tmp_path: Path):
    # (a start beside the gap, not in the wall's plane: the program would refuse to plan from there)
    s = loads_scenarios("description: short hover\nduration_s: 0.5\ninitial: {pos_m: [-1, -2, 1.5]}\n")[0]
    sm = run_scenario(s, tmp_path / "run", RunOptions(in_process=False)).summary
    assert sm["onboard_startup_s"] > 0  # a process had to start and open its ports
    assert sm["loop_sim_time_s"] == pytest.approx(0.49)  # from the first answered tick (0.01 s) on
    assert sm["real_time_factor"] == pytest.approx(sm["loop_sim_time_s"] / sm["loop_wall_time_s"])
    assert sm["ticks_answered"] == sm["ticks"] == 50
    assert sm["wall_time_s"] >= sm["onboard_startup_s"] + sm["loop_wall_time_s"]


def test_the_sides_poll_only_while_each_process_of_the_runs_at_once_has_a_core():
    cores = len(os.sched_getaffinity(0))
    assert lockstep_spin_s(cores) == 0.0  # a suite filling the cores: each side sleeps while it waits
    assert lockstep_spin_s(1) == (SPIN_S if cores >= 2 else 0.0)


def test_a_lockstep_run_of_workers_filling_the_cores_keeps_to_its_workers_core_and_so_does_its_program(
    tmp_path,
):
    cores = sorted(os.sched_getaffinity(0))
    assert lockstep_cpu(None, len(cores)) is None  # no worker number: left to the scheduler
    assert lockstep_cpu(0, len(cores) - 1) is None  # fewer runs than cores
    cpu = lockstep_cpu(1, len(cores))
    assert cpu == cores[1 % len(cores)]
    s = loads_scenarios(CORRUPT.replace("duration_s: 2.0", "duration_s: 1.5"))[0]
    r = run_scenario(s, tmp_path / "r", RunOptions(parallel_runs=len(cores), worker=1))
    assert r.summary["mode"]["onboard_start"] == "warm"
    assert sorted(os.sched_getaffinity(0)) == cores  # as it was, after the run
    with kept_to(cpu):
        assert sorted(os.sched_getaffinity(0)) == [cpu]
        out = subprocess.run([sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"],
                             capture_output=True, text=True, check=True).stdout
        assert out.strip() == f"[{cpu}]"  # what the run starts keeps to it too
    assert sorted(os.sched_getaffinity(0)) == cores
