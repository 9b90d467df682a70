"""What the live view shows, read from a flying emulator by the view's own thread (nothing per tick in
the loop): the scene (lab, wall and gap, body box, the onboard program's plan once it has one) and, a
few tens of times a second, a frame: the vehicle's pose and attitude against the command, thrust,
clearance, the links' health and the FC state, with a banner on a failsafe, an abort or a collision."""

from __future__ import annotations

import contextlib
import json
import math
import threading
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from emulator.mocap_link import MocapLinkServer
from emulator.servers.registry import FcServer
from emulator.vehicle import EmulatedVehicle
from emulator.world import World
from hil.runner.flight_quality import mission_plan
from hil.runner.recorder import state_values

#: the window the live rates are counted over (s of sim time)
RATE_WINDOW_S = 1.0
#: the plan's polyline: one point per this much mission time (s)
PLAN_STEP_S = 0.05


def scene(world: World | None, body_box_m: tuple[float, float, float], title: str,
          links: dict[str, Any] | None = None, max_thrust_n: float | None = None) -> dict[str, Any]:
    """The still part of the view: the lab box, the wall and its opening, the body box (m, world ENU),
    the vehicle's full thrust (N: the thrust chart's scale)."""
    out: dict[str, Any] = {"title": title, "body_box_m": list(body_box_m), "links": links or {},
                           "max_thrust_n": max_thrust_n}
    if world is not None:
        g = world.gap
        out["lab"] = {"min_m": list(world.lab.min_m), "max_m": list(world.lab.max_m)}
        out["gap"] = {"centre_m": [float(v) for v in g.centre_m], "axes": g.axes().tolist(),
                      "width_m": g.width_m, "height_m": g.height_m, "wall_width_m": g.wall_width_m,
                      "wall_height_m": g.wall_height_m}
    return out


def plan_points(events: list[dict[str, Any]]) -> list[list[float]] | None:
    """The onboard program's plan (from its ``plan`` event) as a polyline (m, world ENU), or None."""
    plan, _ = mission_plan(events)
    if plan is None:
        return None
    n = int((plan.t_hover_start_s + 1.0) / PLAN_STEP_S) + 1
    return [[round(v, 4) for v in plan.reference_tuples(k * PLAN_STEP_S)[0]] for k in range(n)]


#: the flight phase before the mission's first segment
TAKEOFF_PHASE = "takeoff"


def phase_after(event: dict[str, Any], phase: str) -> str:
    """The flight phase after the onboard ``event``, ``phase`` before it: a segment's name from its start
    on, "abort" from an abort on."""
    name = event.get("event")
    if name == "segment":
        return str(event.get("segment", phase)).lower()
    return "abort" if name == "abort" else phase


def banner(fc_state: str, fc_failsafe: bool, fc_reason: str, abort: str | None, collision: str | None,
           ) -> str | None:
    """The banner over the view: a failsafe, an onboard abort, a collision (None: nothing to say)."""
    parts = []
    if fc_failsafe:
        parts.append(f"FC FAILSAFE: {fc_state}" + (f" ({fc_reason})" if fc_reason else ""))
    if abort is not None:
        parts.append(f"ONBOARD ABORT: {abort}")
    if collision is not None:
        parts.append(f"COLLISION: {collision}")
    return " | ".join(parts) or None


class LiveSource:
    """Frames of a running emulator: ``vehicle``, its MAVLink ``server``, the ``mocap`` link (or None),
    the ``world`` (or None); ``lock`` (if given) is held while reading; ``events_path`` is the onboard
    program's event log (JSON lines) to take the plan and an abort from; ``faults`` answers which
    faults act (`hil.runner.faults.FaultSchedule`)."""

    def __init__(self, vehicle: EmulatedVehicle, server: FcServer, mocap: MocapLinkServer | None,
                 world: World | None, *, title: str, lock: threading.Lock | None = None,
                 events_path: Path | None = None, faults: Any = None, links: dict[str, Any] | None = None,
                 ) -> None:
        self.vehicle, self.server, self.mocap, self.world = vehicle, server, mocap, world
        self.lock = lock or contextlib.nullcontext()
        self.events_path, self.faults = events_path, faults
        self.profile = vehicle.profile
        self._scene = scene(world, self.profile.body_box_m, title, links, self.profile.max_total_thrust_n)
        self._events: list[dict[str, Any]] = []
        self._read_at = 0
        self._history: deque[tuple[float, int, int, int, int]] = deque()
        self._abort: str | None = None
        self._collision: str | None = None
        self._hit_pose: tuple[list[float | None], list[float | None]] | None = None  # where it hit
        self._phase = TAKEOFF_PHASE
        self._fc_events_seen = 0

    def scene(self) -> dict[str, Any]:
        if "plan_m" not in self._scene:
            plan = plan_points(self._events)
            if plan is not None:
                self._scene["plan_m"] = plan
        return self._scene

    def _read_events(self) -> list[str]:
        """New onboard events (their texts), the abort noted."""
        if self.events_path is None or not self.events_path.is_file():
            return []
        with self.events_path.open("rb") as f:
            if f.seek(0, 2) < self._read_at:  # written afresh since (a program started again): from 0
                self._read_at, self._events, self._abort = 0, [], None
                self._scene.pop("plan_m", None)
            f.seek(self._read_at)
            data = f.read()
        end = data.rfind(b"\n") + 1  # whole lines only
        self._read_at += end
        texts = []
        for line in data[:end].splitlines():
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            self._events.append(ev)
            name = ev.get("event")
            if name == "abort" and self._abort is None:
                self._abort = str(ev.get("reason", "?"))
            self._phase = phase_after(ev, self._phase)
            if name not in ("summary",):
                extra = ev.get("segment") or ev.get("reason") or ""
                texts.append(f"onboard {name}" + (f": {extra}" if extra else ""))
        return texts

    def frame(self) -> dict[str, Any]:
        """The latest frame (see the module docstring); JSON-ready."""
        texts = self._read_events()
        with self.lock:
            v, fc, server = self.vehicle, self.vehicle.fc, self.server
            t = v.time_s
            x = v.state_vector().copy()
            target, state, last_sp = fc.target, fc.state, fc.last_setpoint_s
            fc_events = list(fc.events[self._fc_events_seen:])
            applied = server.stats.setpoints_applied
            wire = getattr(server.codec.transport, "to_fc", None)
            cmd_lost = 0 if wire is None else wire.frames_lost + wire.frames_dropped_fault
            frames = 0 if self.mocap is None else self.mocap.frames_written
            mocap_lost = 0 if self.mocap is None else self.mocap.radio.stats.lost
        self._fc_events_seen += len(fc_events)
        texts += [f"FC {e.from_state.value} -> {e.to_state.value}: {e.reason}" for e in fc_events]
        row = state_values(t, x, target, self.profile)
        clearance = None
        if self.world is not None and np.all(np.isfinite(x[:10])):
            codes, clr, in_slab = self.world.check_states_values(x[None, 0:3], x[None, 6:10])
            clearance = float(clr[0]) if in_slab[0] else None
            hit = World.obstacle(int(codes[0]))
            if hit is not None and self._collision is None and not fc.landed:
                self._collision = str(hit)
        hist = self._history
        hist.append((t, applied, frames, cmd_lost, mocap_lost))
        while len(hist) > 2 and hist[0][0] < t - RATE_WINDOW_S:
            hist.popleft()
        t0, a0, f0, _, _ = hist[0]
        span = t - t0
        reason = fc.events[-1].reason if fc.events else ""
        active = [] if self.faults is None else sorted(
            {f.kind for f in self.faults.faults if f.active(t)})

        def num(value: float) -> float | None:
            return round(value, 4) if math.isfinite(value) else None

        pos = [num(row[k]) for k in ("pos_m_x", "pos_m_y", "pos_m_z")]
        rpy = [num(row[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg")]
        if self._collision is not None:  # the vehicle stays where it hit (the physics has no contact)
            self._hit_pose = self._hit_pose or (pos, rpy)
            pos, rpy = self._hit_pose
        return {
            "t": round(t, 4),
            "phase": self._phase,
            "pos": pos,
            "rpy": rpy,
            "cmd": [num(row[k]) for k in ("roll_cmd_deg", "pitch_cmd_deg", "yaw_cmd_deg", "thrust_cmd_pct")],
            "thrust_n": num(row["thrust_n"]),
            "speed": num(math.sqrt(sum(row[f"vel_m_s_{a}"] ** 2 for a in "xyz"))),
            "clearance": None if clearance is None else round(clearance, 4),
            "fc": state.value,
            "links": {
                "cmd_hz": round((applied - a0) / span, 1) if span > 0 else None,
                "mocap_hz": round((frames - f0) / span, 1) if span > 0 else None,
                "cmd_lost": cmd_lost, "mocap_lost": mocap_lost,
                "sp_age_ms": round(max(t - last_sp, 0.0) * 1e3, 1) if math.isfinite(last_sp) else None,
            },
            "faults": active,
            "banner": banner(state.value, state.failsafe, reason, self._abort, self._collision),
            "events": texts,
        }


def run_source(emu: Any, events_path: Path, title: str) -> LiveSource:
    """The live source of a run's emulator side (`hil.runner.emulator_side.EmulatorSide`)."""
    s = emu.scenario
    links = {"command": {"latency_ms": s.links.command.latency_ms, "loss": s.links.command.loss},
             "mocap": {"latency_ms": s.links.mocap.latency_ms, "loss": s.links.mocap.loss}}
    return LiveSource(emu.vehicle, emu.server, emu.mocap, emu.world, title=title, events_path=events_path,
                      faults=emu.faults, links=links)
