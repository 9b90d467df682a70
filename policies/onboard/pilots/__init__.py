"""Pilots: what turns an observation into an attitude-thrust command, and the registry by name.

A pilot is any object with ``command(obs: Observation) -> AttitudeThrustCommand`` (the `Pilot`
protocol). Each module in this package is one pilot, named after the module, with a factory
``make_pilot(context: PilotContext) -> Pilot``; adding a pilot (e.g. ``planner_net.py``) is that one
file. Only the selected module is imported, so a pilot needing torch or onnxruntime costs nothing to
the others.

Conventions: world ENU (z up), body FLU, SI units. Commands are `policies.controller`'s
AttitudeThrustCommand: roll and pitch are the ZYX Euler angles of the desired body -> world rotation
``Rz(yaw) Ry(pitch) Rx(roll)`` (rad, relative to the ground frame, z up), yaw the heading from +x
(rad), thrust the total thrust (N). The command link converts them to the NED/FRD wire form.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from hil.link.mavlink import euler_from_quat
from hil.link.registry import Registry
from policies.controller import AttitudeThrustCommand
from policies.gap_planning import GapPose, MissionPlan, Vec3


@dataclass(frozen=True)
class Observation:
    """What a pilot sees at one control step.

    ``t_s``: time since the mission (approach) started (s); ``pos_m``, ``vel_m_s``, ``acc_m_s2``: the
    estimated state in world ENU; ``euler_rad``: (roll, pitch, yaw) ZYX of body FLU -> world ENU;
    ``gap``: the gap pose measured at mission start; ``plan``: the mission plan made then.
    """

    t_s: float
    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    euler_rad: np.ndarray
    gap: GapPose
    plan: MissionPlan

    def pos_vel(self) -> tuple[Any, Any]:
        """``pos_m`` and ``vel_m_s``: as (x, y, z) tuples of plain floats where the observation holds
        them so (`FloatObservation`: no arrays made), else the arrays."""
        floats = self.__dict__.get("_pos_vel")
        return floats if floats is not None else (self.pos_m, self.vel_m_s)


class FloatObservation(Observation):
    """An `Observation` held as plain floats (the onboard program's, one a control step): each array is
    made when a pilot first reads it, and `pos_vel` hands over the floats without making any (the
    traditional pilot's path). Build with `of_floats`."""

    @classmethod
    def of_floats(cls, t_s: float, pos_m: Vec3, vel_m_s: Vec3, acc_m_s2: Vec3,
                  quat_wxyz: tuple[float, float, float, float], gap: GapPose,
                  plan: MissionPlan) -> FloatObservation:
        """The observation at ``t_s`` (s) of the state ``pos_m`` (m), ``vel_m_s`` (m/s), ``acc_m_s2`` (m/s^2),
        attitude ``quat_wxyz`` (body FLU -> world ENU; ``euler_rad`` is its `euler_from_quat`)."""
        obs = object.__new__(cls)  # (a frozen dataclass: filled without its per-field __setattr__)
        obs.__dict__.update(t_s=t_s, gap=gap, plan=plan, _pos_vel=(pos_m, vel_m_s), _acc=acc_m_s2,
                            _quat=quat_wxyz)
        return obs

    # (non-data descriptors: each array, once made, is read from the instance like a field)
    @functools.cached_property
    def pos_m(self) -> np.ndarray:  # type: ignore[override]
        return np.array(self._pos_vel[0])

    @functools.cached_property
    def vel_m_s(self) -> np.ndarray:  # type: ignore[override]
        return np.array(self._pos_vel[1])

    @functools.cached_property
    def acc_m_s2(self) -> np.ndarray:  # type: ignore[override]
        return np.array(self._acc)

    @functools.cached_property
    def euler_rad(self) -> np.ndarray:  # type: ignore[override]
        return np.array(euler_from_quat(self._quat))


@dataclass(frozen=True)
class PilotContext:
    """What a pilot may need to be built: the vehicle's mass (kg), full thrust (N), tilt limit (deg)
    and options."""

    mass_kg: float = 0.9
    full_thrust_n: float = 24.0
    max_tilt_deg: float = 75.0
    options: tuple[tuple[str, str], ...] = ()  # free-form name=value pairs, e.g. a weights path


#: the mission's segments, in the order flown
SEGMENTS = ("approach", "traverse", "recovery", "hover")
#: what flies a segment the way the paper's conventional pipeline does
EXPERT = "expert controller on the plan's reference"


def flown_by(**learned: str) -> dict[str, str]:
    """A pilot's `Pilot.flies`: the segments named here by what computes their commands, the others by
    the expert controller on the plan's reference."""
    unknown = set(learned) - set(SEGMENTS)
    if unknown:
        raise ValueError(f"unknown segments {sorted(unknown)}; segments: {', '.join(SEGMENTS)}")
    return {seg: learned.get(seg, EXPERT) for seg in SEGMENTS}


@runtime_checkable
class Pilot(Protocol):
    """Observation -> attitude-thrust command. Must not block (it runs inside the control loop).

    ``flies`` says, per segment (`SEGMENTS`), what computes the commands (see `flown_by`): the onboard
    program reports it, so a run says which segments a network flew and which the expert did.

    A pilot may also offer ``compiled_step(plan)``: the program's whole control step on ``plan`` as one
    compiled call (the traditional pilot's `traditional_step`), which the program then runs instead of
    building an observation and calling ``command``; it must give ``command``'s numbers."""

    flies: dict[str, str]

    def command(self, obs: Observation) -> AttitudeThrustCommand: ...


class UnknownPilot(ValueError):
    """No pilot of that name; the message lists the known ones."""


#: the pilots: one module of this package each, built by its ``make_pilot``
PILOTS = Registry("pilot", package=__name__, attr="make_pilot", error=UnknownPilot)


def pilot_names() -> list[str]:
    """Names of the pilots available (modules of this package), sorted."""
    return PILOTS.names()


def make_pilot(name: str, context: PilotContext | None = None) -> Pilot:
    """Build the pilot called ``name``; UnknownPilot if there is none."""
    pilot = PILOTS.load(name)(context or PilotContext())  # type: ignore[operator]
    if not isinstance(pilot, Pilot):
        raise TypeError(f"pilot module {name!r} built {type(pilot).__name__}, which has no command(obs)")
    return pilot


__all__ = ["PILOTS", "FloatObservation", "Observation", "Pilot", "PilotContext", "UnknownPilot", "make_pilot",
           "pilot_names"]
