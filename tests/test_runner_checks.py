"""The checks a run is judged by, on what a run observed: a diverged simulation fails its own check (and
never passes as a flight that stayed in the lab), and a run that lost lockstep fails the lockstep check."""

from __future__ import annotations

import numpy as np
import pytest

from emulator.profile import load_profile
from hil.link.clock import GapStats, SimClock
from hil.link.memory import MemoryTransport
from hil.runner.checks import Observations, evaluate
from hil.runner.emulator_side import EmulatorSide
from hil.runner.flight_quality import measure
from hil.runner.lockstep import run_lockstep
from hil.runner.onboard_side import InProcessOnboard, onboard_options, program_config
from hil.scenario import loads_scenarios
from hil.scenario.schema import Scenario

LEVEL = """
description: a level gap, hovering at the start
gap: {roll_deg: 0}
initial: {pos_m: [-2, -1, 1.0]}
duration_s: 2.0
"""


def _observations(emu: EmulatorSide, **overrides) -> Observations:
    rec = emu.recorder
    cols = rec.columns()
    fields = dict(
        sim_time_s=emu.time_s, crossed_gap=False, crossing_time_s=None, collision=None,
        collision_time_s=None, min_clearance_m=None, min_clearance_time_s=None, attitude_error_deg=None,
        max_outside_lab_m=rec.max_outside_lab_m, failsafe_states=(), onboard_abort_s=None,
        hover_point_m=None, columns=cols, link={}, nonfinite_state_s=emu.diverged_s,
        quality=measure(cols, []),
    )
    fields.update(overrides)
    return Observations(**fields)


def _rig() -> tuple[Scenario, EmulatorSide, InProcessOnboard]:
    """The level scenario's emulator side and onboard program over in-memory links."""
    s = loads_scenarios(LEVEL)[0]
    profile = load_profile(s.vehicle)
    cmd_fc, cmd_ob = MemoryTransport.pair()
    moc_fc, moc_ob = MemoryTransport.pair()
    emu = EmulatorSide(s, profile, np.random.default_rng(0), cmd_fc, moc_fc, clock=SimClock(),
                       backend="native", tlog=None, duration_s=s.duration_s)
    return s, emu, InProcessOnboard(cmd_ob, moc_ob, program_config(onboard_options(s)))


@pytest.mark.parametrize("force_n", [1e300, 1e308], ids=["past_float32", "to_inf_and_nan"])
def test_a_diverged_simulation_ends_the_run_and_fails_it(force_n):
    # a force no airframe sees makes the physics diverge: the run must end there with a failed check,
    # not crash while packing telemetry or mocap, and not pass `stays_in_lab` on NaN positions
    s, emu, onboard = _rig()
    emu.vehicle.backend.set_external_force(np.array([force_n, 0.0, 0.0]))
    loop = run_lockstep(emu, onboard, s.duration_s)
    assert emu.diverged_s is not None and emu.diverged_s < 1.0
    assert loop.ended_early is not None and "diverged" in loop.ended_early
    assert loop.ticks < 100  # stopped, not flown on to 2 s
    checks = {c.name: c for c in evaluate(s, _observations(emu))}
    assert not checks["finite_state"].passed and "diverged" in checks["finite_state"].observed
    assert checks["finite_state"].time_s == emu.diverged_s
    assert not checks["stays_in_lab"].passed


@pytest.mark.parametrize("force_n", [1e300, 1e308], ids=["past_float32", "to_inf_and_nan"])
def test_advance_to_hands_back_where_the_state_diverged(force_n):
    # the lockstep loop reads `diverged_s` from what each `advance_to` returns: the same, call by call
    _, emu, _ = _rig()
    emu.vehicle.backend.set_external_force(np.array([force_n, 0.0, 0.0]))
    for k in range(1, 101):
        assert emu.advance_to(k * 0.01) == emu.diverged_s
        emu.recorder.flush()  # (where the recorder notes a state that is no number any more)
    assert emu.diverged_s is not None and emu.advance_to(1.01) == emu.diverged_s


def test_a_calm_run_keeps_a_finite_state_and_lockstep():
    s, emu, onboard = _rig()
    loop = run_lockstep(emu, onboard, s.duration_s)
    assert loop.ended_early is None and loop.ticks == 200
    checks = {c.name: c for c in evaluate(s, _observations(emu))}
    assert checks["finite_state"].passed and checks["stays_in_lab"].passed
    assert checks["lockstep"].passed
    lost = {c.name: c for c in evaluate(s, _observations(emu, lockstep_lost_s=0.73, lockstep_short_reads=2))}
    assert not lost["lockstep"].passed and lost["lockstep"].time_s == 0.73
    assert "2 tick read(s) short" in lost["lockstep"].observed
    realtime = {c.name for c in evaluate(s, _observations(emu, lockstep=False))}
    assert "lockstep" not in realtime  # a real-time run has no lockstep to lose


def _health(late_ms: float, gap_ms: float, gap_end_s: float) -> dict:
    loop = {"late_worst_ms": late_ms, "late_worst_at_s": 2.0, "late_median_ms": 0.1, "late_p99_ms": 1.0,
            "caught_up_steps": 0}
    return {"contact_s": 0.3, "loop": loop,
            "setpoints_at_fc": {"max_gap_ms": gap_ms, "max_gap_end_s": gap_end_s}}


def test_the_realtime_check_fails_a_run_whose_onboard_side_starved_with_the_moment():
    from hil.runner.checks import check_realtime
    from hil.scenario.schema import Fault, NoParams

    # the emulator's loop kept time (12 ms late at worst) but no setpoint reached the FC for 296 ms
    starved = check_realtime(50.0, _health(12.0, 296.0, 5.2))
    assert not starved.passed and starved.time_s == 5.2
    assert "setpoint gap at the FC 296 ms" in starved.observed
    assert check_realtime(50.0, _health(12.0, 60.0, 5.2)).passed  # a control period or two: kept
    # a silence a fault or the program's abort explains is no starved onboard side
    down = Fault("command_link_down", 5.0, 5.1, NoParams())
    assert check_realtime(50.0, _health(12.0, 296.0, 5.2), (down,)).passed
    assert not check_realtime(50.0, _health(12.0, 296.0, 7.5), (down,)).passed  # long after it
    gust = Fault("wind_gust", 0.0, None, NoParams())
    assert not check_realtime(50.0, _health(12.0, 296.0, 5.2), (gust,)).passed  # a gust silences nothing
    assert check_realtime(50.0, _health(12.0, 296.0, 5.2), abort_s=4.0).passed  # silent after its abort
    # a program that aborts once it runs again (its mocap went stale while it was starved) is no excuse
    assert not check_realtime(50.0, _health(12.0, 296.0, 5.2), abort_s=5.19).passed
    assert check_realtime(50.0, _health(12.0, 296.0, 5.2), bursty=True).passed  # a link that loses bursts
    late = check_realtime(50.0, _health(80.0, 90.0, 5.2))
    assert not late.passed and late.time_s == 2.0  # the loop's own lateness, at its moment


def test_a_streams_rate_counts_the_moves_after_its_first_reading():
    """The wire's rate of a counter (setpoints applied, mocap frames written) is what moved while it was
    watched: a first reading that finds 60 frames already written (a late start) does not raise it."""
    watch = GapStats()
    watch.update(1.0, 60)
    for k in range(1, 121):  # 120 Hz for a second
        watch.update(1.0 + k / 120, 60 + k)
    stats = watch.as_dict()
    assert stats["rate_hz"] == 120.0 and stats["count"] == 180
    assert stats["max_gap_ms"] == pytest.approx(1000 / 120, abs=0.01)
