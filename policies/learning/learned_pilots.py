"""Learned pilots on onnxruntime: ``PlannerNetPilot`` (network planner + expert controller) and
``EndToEndPilot`` (the merged 29 -> 3 policy). Both fly the approach with their network and leave the
traverse, recovery and hover to the plan's reference and the expert controller, as the paper does.

The networks were trained for desired yaw 0 and a 0.9 kg vehicle: world vectors are turned into the
frame of the plan's yaw before the networks see them (roll/pitch then come out relative to that yaw,
the command convention), and thrust is scaled by mass / 0.9 kg. The controller network's acceleration
input is the expert's acceleration feed-forward; ``acc_input="zero"`` (default) feeds a zero current
acceleration so the network sees the reference acceleration there, as the expert law does;
``"measured"`` feeds the estimated acceleration (the paper's figure).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from policies.controller import AttitudeThrustCommand, ExpertController, ExpertGains
from policies.frames import rot_z
from policies.gap_planning import MissionPlan, Segment
from policies.learning.features import CONTROLLER_MASS_KG, planner_inputs
from policies.learning.onnx_runtime import OnnxModel, load_shipped
from policies.onboard.pilots import flown_by


def approach_planner_inputs(plan: MissionPlan, t_s: float,
                            yaw_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Planner inputs (17,) for the plan's approach at ``t_s`` (s), in the frame turned by -``yaw_rad``,
    and the approach start position (3,) in the world."""
    tr = plan.approach
    pf, vf, af = plan.traverse.start_state
    turn = rot_z(-yaw_rad)
    p0 = np.asarray(tr.p0, float)
    x = planner_inputs(min(max(t_s, 0.0), float(tr.T)), turn @ (pf - p0), turn @ tr.v0, turn @ tr.a0,
                       turn @ vf, turn @ af, float(tr.T))
    return x, p0


def e2e_state_row(px: float, py: float, pz: float, vx: float, vy: float, vz: float, ax: float, ay: float,
                  az: float, roll: float, pitch: float, yaw: float, plan_yaw: float, out: np.ndarray) -> None:
    """The end-to-end policy's first 12 inputs of one sample into ``out[0:12]``: position relative to the
    approach start (m), velocity (m/s), acceleration (m/s^2), world ENU turned by -``plan_yaw`` (rad),
    and the Euler angles (roll, pitch, yaw; rad) with the yaw taken relative to ``plan_yaw`` and wrapped
    to [-pi, pi). Plain arithmetic on floats: the onboard program runs it as it is, the RL environment
    compiled over its rows (`hil.rl.observe`), one definition."""
    c, s = math.cos(plan_yaw), math.sin(plan_yaw)
    out[0], out[1], out[2] = c * px + s * py, c * py - s * px, pz  # rot_z(-yaw) @ v
    out[3], out[4], out[5] = c * vx + s * vy, c * vy - s * vx, vz
    out[6], out[7], out[8] = c * ax + s * ay, c * ay - s * ax, az
    out[9], out[10] = roll, pitch
    out[11] = (yaw - plan_yaw + math.pi) % (2 * math.pi) - math.pi


def e2e_state_inputs(pos_rel_m: np.ndarray, vel_m_s: np.ndarray, acc_m_s2: np.ndarray, euler_rad: np.ndarray,
                     yaw_rad: float, out: np.ndarray) -> np.ndarray:
    """`e2e_state_row` of one sample given as (3,) arrays: position relative to the approach start (m),
    velocity (m/s), acceleration (m/s^2), Euler angles (rad), the plan's yaw (rad); into ``out[0:12]``."""
    p, v, a, e = (np.asarray(u, dtype=float).tolist() for u in (pos_rel_m, vel_m_s, acc_m_s2, euler_rad))
    e2e_state_row(*p, *v, *a, *e, float(yaw_rad), out)
    return out


class PlannerNetPilot:
    """Approach reference from the planner network, tracked by the expert controller."""

    def __init__(self, mass_kg: float = 0.9, model: OnnxModel | None = None,
                 max_tilt_deg: float = 75.0) -> None:
        self.model = model or load_shipped("planner")
        self.controller = ExpertController(mass_kg, ExpertGains(tilt_max_rad=math.radians(max_tilt_deg)))
        self.flies = flown_by(approach="planner network's reference, expert controller")

    def reference(self, plan: MissionPlan, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (m), velocity (m/s), acceleration (m/s^2) of the approach at ``t_s`` from the network."""
        x, p0 = approach_planner_inputs(plan, t_s)
        y = self.model.predict(x)
        return p0 + y[0:3], y[3:6], y[6:9]

    def command(self, obs: object) -> AttitudeThrustCommand:
        plan: MissionPlan = obs.plan  # type: ignore[attr-defined]
        if plan.segment_at(obs.t_s) is Segment.APPROACH:  # type: ignore[attr-defined]
            p, v, a = self.reference(plan, obs.t_s)  # type: ignore[attr-defined]
            yaw = plan.yaw_rad
        else:
            ref = plan.reference(obs.t_s)  # type: ignore[attr-defined]
            p, v, a, yaw = ref.pos_m, ref.vel_m_s, ref.acc_m_s2, ref.yaw_rad
        return self.controller.command(p, v, a, yaw, obs.pos_m, obs.vel_m_s)  # type: ignore[attr-defined]


class EndToEndPilot:
    """The merged policy network on the approach; the expert on the plan's reference afterwards."""

    def __init__(self, mass_kg: float = 0.9, model: OnnxModel | None = None, acc_input: str = "zero",
                 max_tilt_deg: float = 75.0, shipped: str = "e2e") -> None:
        if acc_input not in ("zero", "measured"):
            raise ValueError(f"acc_input must be 'zero' or 'measured', got {acc_input!r}")
        if not (math.isfinite(mass_kg) and mass_kg > 0):
            raise ValueError("mass_kg must be positive")
        self.model = model or load_shipped(shipped)
        self.mass_kg, self.acc_input = mass_kg, acc_input
        self.expert = ExpertController(mass_kg, ExpertGains(tilt_max_rad=math.radians(max_tilt_deg)))
        self.flies = flown_by(approach="end-to-end network" if shipped == "e2e" or model is not None
                              else f"end-to-end network ({shipped})")

    def inputs(self, obs: object) -> np.ndarray:
        """The policy's 29 inputs for an observation (in the frame of the plan's yaw)."""
        plan: MissionPlan = obs.plan  # type: ignore[attr-defined]
        yaw = plan.yaw_rad
        x17, p0 = approach_planner_inputs(plan, obs.t_s, yaw)  # type: ignore[attr-defined]
        acc = np.asarray(obs.acc_m_s2, float) if self.acc_input == "measured" else np.zeros(3)  # type: ignore[attr-defined]
        out = np.empty(29)
        e2e_state_inputs(np.asarray(obs.pos_m, float) - p0, np.asarray(obs.vel_m_s, float), acc,  # type: ignore[attr-defined]
                         np.asarray(obs.euler_rad, float), yaw, out)  # type: ignore[attr-defined]
        out[12:] = x17
        return out

    def command(self, obs: object) -> AttitudeThrustCommand:
        plan: MissionPlan = obs.plan  # type: ignore[attr-defined]
        if plan.segment_at(obs.t_s) is not Segment.APPROACH:  # type: ignore[attr-defined]
            ref = plan.reference(obs.t_s)  # type: ignore[attr-defined]
            return self.expert.command(ref.pos_m, ref.vel_m_s, ref.acc_m_s2, ref.yaw_rad, obs.pos_m,  # type: ignore[attr-defined]
                                       obs.vel_m_s)  # type: ignore[attr-defined]
        roll, pitch, thrust = self.model.predict(self.inputs(obs))
        return AttitudeThrustCommand(float(roll), float(pitch), plan.yaw_rad,
                                     float(thrust) * self.mass_kg / CONTROLLER_MASS_KG)


def _options(options: tuple[tuple[str, str], ...]) -> dict[str, str]:
    known = {"onnx", "acc_input"}
    opts = dict(options)
    unknown = sorted(set(opts) - known)
    if unknown:
        raise ValueError(f"unknown pilot option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    return opts


def make_planner_net(mass_kg: float, options: tuple[tuple[str, str], ...] = (),
                     max_tilt_deg: float = 75.0) -> PlannerNetPilot:
    """``planner_net`` pilot; option ``onnx=<path>`` replaces the shipped planner."""
    opts = _options(options)
    model = OnnxModel(Path(opts["onnx"])) if "onnx" in opts else None
    return PlannerNetPilot(mass_kg, model, max_tilt_deg)


def make_e2e(mass_kg: float, options: tuple[tuple[str, str], ...] = (), max_tilt_deg: float = 75.0,
             shipped: str = "e2e") -> EndToEndPilot:
    """``e2e`` pilot (``e2e_rl`` with ``shipped="e2e_rl"``: the policy fine-tuned by RL); options
    ``onnx=<path>`` and ``acc_input=zero|measured``."""
    opts = _options(options)
    model = OnnxModel(Path(opts["onnx"])) if "onnx" in opts else None
    return EndToEndPilot(mass_kg, model, opts.get("acc_input", "zero"), max_tilt_deg, shipped)
