"""Flight-quality figures of a run, read from its time series and the onboard program's events after the
run (nothing per tick): heading error, attitude tracking, position error against the plan per segment,
time at thrust saturation and settling after each manoeuvre, each with its worst moment (sim s).

- Heading: the measured heading against the one the FC steers to (``yaw_sp_deg``), apart for the
  heading it holds itself (hold, hover, land: ``held``) and the offboard setpoints' (``commanded``).
- Attitude tracking (roll, pitch, in offboard): the measured attitude against the command passed through
  the FC's nominal attitude response, a first-order lag of 1 / its attitude loop's gain (the runner
  passes the vehicle's; `ATTITUDE_LAG_S` for the n3_tx2, whose emulated N3 answers a 20 deg roll step
  with an equivalent lag of about 0.09 s): what remains is what a healthy loop would not
  show (overshoot, ringing, a sluggish or saturated loop), not the lag every FC has.
- Position against the plan: the plan is derived again, here, from the inputs the program's ``plan``
  event records (`MissionRequest`), so the reference is the one the program flew without sending it every
  tick; per segment (approach, traverse, recovery), while the program flies the mission in offboard
  (its setpoints fresh: after a kill or a stall the FC flies the last one, which is no plan).
- Thrust saturation: time with a motor commanded at full throttle (no headroom left for attitude).
- Settling: after each manoeuvre (the takeoff, the crossing's recovery into the hover), the time until
  the position stays within ``SETTLE_BAND_M`` of where the manoeuvre ends, over the hold that follows
  (up to the plan, and up to the mission's end).
- Per segment of the mission, from the program's ``segment`` events (approach: what a learned pilot
  flies; traverse and recovery: the expert's or the pilot's, as it says; ``crossing``: approach and
  traverse): its window, and the angular rate and thrust over time there (`hil.runner.over_time`: mean,
  maximum and integral, each sample weighted by the time it holds, not counted once).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numba import njit

from hil.runner.over_time import hold_weights_s, window_figures
from hil.runner.recorder import FC_STATE_CODES
from policies.gap_planning import MissionPlan, MissionRequest, Segment

ATTITUDE_LAG_S = 0.09  # the n3_tx2's nominal attitude response, a first-order lag (s): 1 / its 11 /s loop
SATURATED_PCT = 99.9  # a motor command at or above this (% of full throttle) is saturated
SETTLE_BAND_M = 0.1  # settled: within this of the manoeuvre's end point (m)
OFFBOARD_CODE = FC_STATE_CODES["offboard"]
#: setpoints older than this (s; ten periods at 100 Hz): the program no longer flies the vehicle (killed,
#: stalled, its link down) and the FC flies the last one until its failsafe: not a flight to the plan
FRESH_SETPOINT_S = 0.1
PLAN_SEGMENTS = (Segment.APPROACH, Segment.TRAVERSE, Segment.RECOVERY)
_SEGMENT_ORDER = list(Segment)  # (`MissionPlan.segment_indices`' indices)
#: onboard events that end the mission (its plan no longer flown)
_MISSION_ENDS = ("mission_done", "abort", "done", "error", "link_lost", "fc_lost")


@dataclass(frozen=True)
class Figure:
    """One flight-quality figure: its value (None: nothing to measure in this run) and the sim time (s)
    of its worst moment."""

    value: float | None
    time_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "time_s": self.time_s}


NONE = Figure(None)


@dataclass(frozen=True)
class SegmentFigures:
    """Angular rate and thrust over one segment's window [start_s, end_s) of sim time, weighted by time
    (`hil.runner.over_time`); None where the window holds no sample."""

    start_s: float
    end_s: float
    mean_angular_rate_rad_s: float | None
    max_angular_rate_rad_s: float | None
    angular_rate_integral_rad: float | None  # the body rate's norm integrated over the window
    mean_thrust_n: float | None
    max_thrust_n: float | None
    thrust_impulse_n_s: float | None

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "duration_s": self.duration_s}


@dataclass(frozen=True)
class FlightQuality:
    """The figures of one run (see the module docstring); units in the names."""

    heading_error_deg: dict[str, Figure]  # "held" (the FC's own hover/land), "commanded" (offboard)
    attitude_tracking_deg: Figure
    position_error_m: dict[str, Figure]  # by plan segment
    thrust_saturation_s: Figure  # total time; time_s: the start of the longest stretch
    settling_time_s: dict[str, Figure]  # by manoeuvre ("takeoff", "crossing"); time_s: when settled
    settled: dict[str, bool]  # by manoeuvre: within the band at the end of its window
    #: by mission segment ("approach", "traverse", "recovery", "hover", and "crossing": approach and
    #: traverse), those the program entered
    segments: dict[str, SegmentFigures] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "segments": {k: f.to_dict() for k, f in self.segments.items()},
            "heading_error_deg": {k: f.to_dict() for k, f in self.heading_error_deg.items()},
            "attitude_tracking_deg": self.attitude_tracking_deg.to_dict(),
            "position_error_m": {k: f.to_dict() for k, f in self.position_error_m.items()},
            "thrust_saturation_s": self.thrust_saturation_s.to_dict(),
            "settling_time_s": {k: f.to_dict() for k, f in self.settling_time_s.items()},
            "settled": dict(self.settled),
        }


def measure(cols: Mapping[str, np.ndarray], events: Sequence[Mapping[str, Any]],
            attitude_lag_s: float = ATTITUDE_LAG_S) -> FlightQuality:
    """The flight-quality figures of a run's columns (`recorder.COLUMNS`) and onboard events;
    ``attitude_lag_s`` is the FC's nominal attitude response (s): 1 / its attitude loop's gain."""
    t = np.asarray(cols["t_s"], dtype=float)
    pos = np.column_stack([cols["pos_m_x"], cols["pos_m_y"], cols["pos_m_z"]])
    offboard = np.asarray(cols["fc_state"]) == OFFBOARD_CODE
    flown = offboard & (np.asarray(cols["setpoint_age_s"]) <= FRESH_SETPOINT_S)  # by the program
    plan, t_plan = mission_plan(events)
    t_end = _first_time(events, _MISSION_ENDS, after_s=-math.inf if t_plan is None else t_plan)
    # settling over the hold after each manoeuvre, where the program held it to its end (a hold cut
    # short by an abort, a lost link or a failsafe is not measured)
    settling, settled = {}, {}
    takeoff = _event(events, "takeoff")
    if takeoff is not None and t_plan is not None and "duration_s" in takeoff and "target_m" in takeoff:
        t0 = float(takeoff["t_s"]) + float(takeoff["duration_s"])
        settling["takeoff"], settled["takeoff"] = settling_time(
            t, pos, flown, np.asarray(takeoff["target_m"], dtype=float), t0, t_plan
        )
    done = _event(events, "mission_done")
    if plan is not None and t_plan is not None and done is not None:
        t0 = t_plan + plan.t_hover_start_s
        settling["crossing"], settled["crossing"] = settling_time(
            t, pos, flown, np.asarray(plan.hover_m), t0, float(done["t_s"])
        )
    return FlightQuality(
        heading_error_deg=heading_errors(t, cols["yaw_deg"], cols["yaw_sp_deg"], offboard),
        attitude_tracking_deg=attitude_tracking(t, cols, offboard, attitude_lag_s),
        position_error_m={}
        if plan is None or t_plan is None
        else position_errors(t, pos, flown, plan, t_plan, t_end),
        thrust_saturation_s=saturation(t, cols["motor_max_pct"]),
        settling_time_s=settling,
        settled=settled,
        segments={name: segment_figures(cols, w) for name, w in segment_windows(events, float(t[-1])).items()}
        if len(t) else {},
    )


def segment_windows(events: Sequence[Mapping[str, Any]], end_s: float) -> dict[str, tuple[float, float]]:
    """Sim-time windows (s) of the mission's segments from the program's ``segment`` events: each from
    its event to the next segment's, to the mission's end (done, abort, a lost link) or to ``end_s``;
    ``crossing``: from the approach to the end of the traverse, when both were flown."""
    marks = [(float(ev["t_s"]), str(ev.get("segment"))) for ev in events
             if ev.get("event") == "segment" and isinstance(ev.get("t_s"), int | float)]
    out: dict[str, tuple[float, float]] = {}
    for i, (t0, name) in enumerate(marks):
        t1 = marks[i + 1][0] if i + 1 < len(marks) else min(end_s, _first_time(events, _MISSION_ENDS, t0))
        if name not in out:  # a segment entered twice (not in a mission as planned) counts its first time
            out[name] = (t0, max(t0, t1))
    if str(Segment.APPROACH) in out and str(Segment.TRAVERSE) in out:
        out["crossing"] = (out[str(Segment.APPROACH)][0], out[str(Segment.TRAVERSE)][1])
    return out


def segment_figures(cols: Mapping[str, np.ndarray], window: tuple[float, float]) -> SegmentFigures:
    """Angular rate and thrust over ``window`` (s) of a run's columns, weighted by time."""
    t0, t1 = window
    (rate_mean, rate_max, rate_int), (thrust_mean, thrust_max, thrust_int) = window_figures(
        cols["t_s"], (cols["body_rate_rad_s"], cols["thrust_n"]), t0, t1)
    return SegmentFigures(t0, t1, rate_mean, rate_max, rate_int, thrust_mean, thrust_max, thrust_int)


def heading_errors(
    t: np.ndarray, yaw_deg: np.ndarray, yaw_sp_deg: np.ndarray, offboard: np.ndarray
) -> dict[str, Figure]:
    """Largest |measured - steered| heading (deg, wrapped) where the FC steers one: ``held`` by its own
    hover/land controller, ``commanded`` by the offboard setpoints."""
    err = np.abs((np.asarray(yaw_deg) - np.asarray(yaw_sp_deg) + 180.0) % 360.0 - 180.0)
    return {"held": _worst(t[~offboard], err[~offboard]), "commanded": _worst(t[offboard], err[offboard])}


def attitude_tracking(t: np.ndarray, cols: Mapping[str, np.ndarray], offboard: np.ndarray,
                      lag_s: float = ATTITUDE_LAG_S) -> Figure:
    """Largest roll or pitch error (deg) in offboard against the command through a first-order lag of
    ``lag_s`` (s)."""
    worst = NONE
    for axis in ("roll", "pitch"):
        ref = lagged_command(t, cols[f"{axis}_cmd_deg"], cols[f"{axis}_deg"], offboard, lag_s)
        f = _worst(t, np.abs(np.asarray(cols[f"{axis}_deg"]) - ref))
        if f.value is not None and (worst.value is None or f.value > worst.value):
            worst = f
    return worst


def lagged_command(t: np.ndarray, cmd: np.ndarray, measured: np.ndarray, active: np.ndarray,
                   lag_s: float = ATTITUDE_LAG_S) -> np.ndarray:
    """The command ``cmd`` through a first-order lag of ``lag_s`` (s; the command held between samples),
    started from the measured value where ``active`` begins; NaN where not ``active``."""
    out = np.full(len(t), np.nan)
    _lag(np.asarray(t, dtype=np.float64), np.asarray(cmd, dtype=np.float64),
         np.asarray(measured, dtype=np.float64), np.asarray(active, dtype=np.bool_), float(lag_s), out)
    return out


@njit(cache=True)
def _lag(ts: np.ndarray, c: np.ndarray, m: np.ndarray, on: np.ndarray, lag_s: float,
         out: np.ndarray) -> None:  # pragma: no cover (compiled)
    """`lagged_command`'s recurrence, sample by sample (a sample's loop in Python took most of `measure`),
    into ``out`` (its NaN left where not ``on``)."""
    r = math.nan
    for i in range(len(ts)):
        if not on[i] or not math.isfinite(c[i]):
            r = math.nan
            continue
        if not math.isfinite(r):
            r = m[i]
        else:
            a = math.exp(-(ts[i] - ts[i - 1]) / lag_s)
            r = c[i - 1] + (r - c[i - 1]) * a
        out[i] = r


def position_errors(
    t: np.ndarray, pos: np.ndarray, offboard: np.ndarray, plan: MissionPlan, t_plan_s: float, t_end_s: float
) -> dict[str, Figure]:
    """Largest distance (m) to the plan's reference per segment, from the plan's time ``t_plan_s`` (its
    mission time 0) to ``t_end_s``, where ``offboard`` (the program flying)."""
    out: dict[str, Figure] = {}
    idx = np.flatnonzero(offboard & (t >= t_plan_s) & (t < t_end_s))
    times = (t[idx] - t_plan_s).tolist()
    segs = plan.segment_indices(times)
    err = np.linalg.norm(pos[idx] - plan.reference_positions(times), axis=1)
    for seg in PLAN_SEGMENTS:
        mask = segs == _SEGMENT_ORDER.index(seg)
        out[str(seg)] = _worst(t[idx][mask], err[mask]) if mask.any() else NONE
    return out


def saturation(t: np.ndarray, motor_max_pct: np.ndarray) -> Figure:
    """Time (s) with a motor command saturated (each sample counts until the next); the worst moment
    is the start of the longest saturated stretch."""
    sat = np.asarray(motor_max_pct) >= SATURATED_PCT
    if len(t) < 2 or not sat.any():
        return Figure(0.0)
    dt = hold_weights_s(t)
    total = float(np.sum(dt[sat]))
    best, best_t, run, run_t = 0.0, None, 0.0, None
    for i in np.flatnonzero(sat).tolist():
        if i > 0 and sat[i - 1]:
            run += float(dt[i])
        else:
            run, run_t = float(dt[i]), float(t[i])
        if run > best:
            best, best_t = run, run_t
    return Figure(total, best_t)


def settling_time(
    t: np.ndarray, pos: np.ndarray, offboard: np.ndarray, target_m: np.ndarray, t0_s: float, t1_s: float
) -> tuple[Figure, bool]:
    """(time after ``t0_s`` until the position stays within `SETTLE_BAND_M` of ``target_m`` up to
    ``t1_s``, with the sim time it settled; whether it did): never settled counts the whole window. Not
    measured (None) unless the program flew the whole window in offboard (``offboard``: no failsafe, no
    hold, no stale setpoints)."""
    window = (t >= t0_s) & (t < t1_s)
    idx = np.flatnonzero(window)
    if len(idx) == 0 or not offboard[idx].all():
        return NONE, True
    out = np.linalg.norm(pos[idx] - target_m, axis=1) > SETTLE_BAND_M
    if not out.any():
        return Figure(0.0, float(t[idx[0]])), True
    last_out = int(np.flatnonzero(out)[-1])
    if last_out == len(idx) - 1:
        return Figure(float(t[idx[-1]]) - t0_s, float(t[idx[-1]])), False
    t_in = float(t[idx[last_out + 1]])
    return Figure(t_in - t0_s, t_in), True


def _worst(t: np.ndarray, err: np.ndarray) -> Figure:
    e = np.where(np.isfinite(err), err, -1.0)
    if len(e) == 0 or e.max() < 0:
        return NONE
    i = int(np.argmax(e))
    return Figure(float(e[i]), float(t[i]))


def _event(events: Sequence[Mapping[str, Any]], name: str) -> Mapping[str, Any] | None:
    return next((ev for ev in events if ev.get("event") == name and isinstance(ev.get("t_s"), int | float)),
                None)


def _first_time(events: Sequence[Mapping[str, Any]], names: Sequence[str], after_s: float) -> float:
    times = [float(ev["t_s"]) for ev in events
             if ev.get("event") in names and isinstance(ev.get("t_s"), int | float) and ev["t_s"] > after_s]
    return min(times, default=math.inf)


def mission_plan(events: Sequence[Mapping[str, Any]]) -> tuple[MissionPlan | None, float | None]:
    """The plan of the program's ``plan`` event and its time (s); (None, None) when there is none or it
    does not record its request."""
    ev = _event(events, "plan")
    if ev is None or not isinstance(ev.get("request"), Mapping):
        return None, None
    try:
        return MissionRequest.from_dict(ev["request"]).plan(), float(ev["t_s"])
    except (KeyError, TypeError, ValueError):
        return None, None
