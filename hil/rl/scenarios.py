"""Randomised gap crossings for the RL environment: each one a gap pose, a start and the onboard program's
plan of it, drawn from one seeded Generator and kept in a `CrossingPool` (arrays the batched environment
indexes per episode).

The plan is the one the onboard program makes (`MissionRequest` with `ProgramConfig`'s defaults and
the drawn crossing speed), so the reference the environment's expert tracks on the traverse and the 17
planner inputs the policy sees are those of a flight through the links.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from emulator.profile import VehicleProfile
from emulator.world import Gap, LabVolume, World
from policies.gap_planning import BodyClearance, GapPose, MissionPlan, MissionRequest, PlanningError
from policies.gap_planning import LabVolume as PlanLab
from policies.learning.learned_pilots import approach_planner_inputs
from policies.onboard.program import ProgramConfig


@dataclass(frozen=True)
class CrossingRanges:
    """Where gaps and starts are drawn (uniform; m, deg, m/s). The gap centre is drawn relative to the
    start (x ahead, y aside), its height absolute; the gap's yaw is 0 (crossing along +x), as in every
    shipped scenario. Defaults span the shipped gap scenarios and the paper's RL case."""

    start_x_m: tuple[float, float] = (-2.5, 0.5)
    start_y_m: tuple[float, float] = (-1.8, 0.5)
    start_z_m: tuple[float, float] = (0.5, 1.0)
    ahead_m: tuple[float, float] = (1.5, 2.6)
    aside_m: tuple[float, float] = (-0.5, 1.8)
    gap_z_m: tuple[float, float] = (1.4, 2.3)
    roll_deg: tuple[float, float] = (-60.0, 60.0)
    speeds_m_s: tuple[float, ...] = (1.5, 2.0, 2.5, 3.0)
    #: the opening's height (m; None: the onboard program's default), for sets like the shipped
    #: scenarios past the paper's envelope (a 0.65 m opening at 70 deg)
    gap_height_m: float | None = None

    def __post_init__(self) -> None:
        for name in ("start_x_m", "start_y_m", "start_z_m", "ahead_m", "aside_m", "gap_z_m", "roll_deg"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"CrossingRanges.{name}: want finite (lo, hi) with lo <= hi, got {(lo, hi)}")
        if not self.speeds_m_s or not all(0 < s <= 6 for s in self.speeds_m_s):
            raise ValueError(f"CrossingRanges.speeds_m_s: want speeds in (0, 6] m/s, got {self.speeds_m_s}")
        if self.gap_height_m is not None and not (0.0 < self.gap_height_m <= 2.0):
            raise ValueError(f"CrossingRanges.gap_height_m: want (0, 2] m or None, got {self.gap_height_m}")


@dataclass(frozen=True)
class Crossing:
    """One drawn crossing: the start (m), the gap (roll in deg), the crossing speed (m/s) and its plan."""

    start_m: tuple[float, float, float]
    gap_centre_m: tuple[float, float, float]
    roll_deg: float
    speed_m_s: float
    plan: MissionPlan


def plan_crossing(start_m: tuple[float, float, float], centre_m: tuple[float, float, float], roll_deg: float,
                  speed_m_s: float, config: ProgramConfig | None = None,
                  gap_height_m: float | None = None) -> MissionPlan:
    """The onboard program's plan from a hover at ``start_m`` through the gap (PlanningError if none),
    the opening ``gap_height_m`` high (None: the program's)."""
    cfg = config or ProgramConfig()
    if gap_height_m is not None:
        cfg = replace(cfg, gap_height_m=gap_height_m)
    gap = GapPose.from_deg(centre_m, roll_deg, width_m=cfg.gap_width_m, height_m=cfg.gap_height_m)
    request = MissionRequest(start_m, (0.0, 0.0, 0.0), gap, PlanLab(cfg.lab_min_m, cfg.lab_max_m),
                             cfg.approach_duration_s, speed_m_s, cfg.traverse_lead_m,
                             BodyClearance(cfg.body_box_m, cfg.clearance_margin_m), cfg.max_body_rate_rad_s)
    return request.plan()


def draw_crossings(n: int, rng: np.random.Generator, ranges: CrossingRanges | None = None,
                   max_tries: int = 20) -> list[Crossing]:
    """``n`` crossings drawn from ``rng``; a draw the planner finds no plan for is drawn again (at most
    ``max_tries`` times per crossing, then RuntimeError)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    r = ranges or CrossingRanges()
    out: list[Crossing] = []
    while len(out) < n:
        for _ in range(max_tries):
            start = (rng.uniform(*r.start_x_m), rng.uniform(*r.start_y_m), rng.uniform(*r.start_z_m))
            centre = (start[0] + rng.uniform(*r.ahead_m), start[1] + rng.uniform(*r.aside_m),
                      rng.uniform(*r.gap_z_m))
            roll = float(rng.uniform(*r.roll_deg))
            speed = float(r.speeds_m_s[rng.integers(len(r.speeds_m_s))])
            try:
                plan = plan_crossing(start, centre, roll, speed, gap_height_m=r.gap_height_m)
            except PlanningError:
                continue
            out.append(Crossing(tuple(map(float, start)), tuple(map(float, centre)), roll, speed, plan))
            break
        else:
            raise RuntimeError(f"no plannable crossing in {max_tries} draws: ranges {r}")
    return out


class CrossingPool:
    """Crossings as the arrays the environment reads per episode (K crossings, control period ``dt_s``,
    ``lead_s`` the onboard program's control lead): start (K, 3), plan yaw (K,), approach duration and
    episode length (K,), the planner inputs at t = 0 (K, 17), gap centre and packed world (K, 27), and the
    plan's reference (position, velocity, acceleration (K, S, 3)) at each control step's time + lead."""

    def __init__(self, crossings: list[Crossing], profile: VehicleProfile, dt_s: float, lead_s: float,
                 lab: LabVolume | None = None) -> None:
        if not crossings:
            raise ValueError("a pool needs at least one crossing")
        self.crossings = crossings
        k = len(crossings)
        lab = lab or LabVolume()
        self.start_m = np.array([c.start_m for c in crossings])
        self.yaw_rad = np.array([c.plan.yaw_rad for c in crossings])
        self.t_approach_s = np.array([c.plan.t_traverse_start_s for c in crossings])
        #: episode end (s): approach time + 2 x the traverse's time to the gap centre
        self.t_end_s = np.array([c.plan.t_traverse_start_s + 2 * c.plan.traverse.t_c_s for c in crossings])
        self.steps = np.ceil(self.t_end_s / dt_s - 1e-9).astype(np.int64)
        self.gap_centre_m = np.array([c.gap_centre_m for c in crossings])
        #: the crossing direction (K, 3): the level heading of the plan's yaw (the gap's e1, away from the
        #: start, for a gap of yaw and pitch 0)
        self.crossing_dir = np.stack([np.cos(self.yaw_rad), np.sin(self.yaw_rad), np.zeros(k)], -1)
        self.x17 = np.empty((k, 17))
        self.worlds = np.empty((k, 27))
        s_max = int(self.steps.max()) + 1
        self.ref = np.zeros((k, s_max, 9))
        for i, c in enumerate(crossings):
            self.x17[i], _ = approach_planner_inputs(c.plan, 0.0, c.plan.yaw_rad)
            gap = Gap.from_deg(c.gap_centre_m, c.roll_deg, width_m=c.plan.gap.width_m,
                               height_m=c.plan.gap.height_m)
            self.worlds[i] = World.for_profile(gap, lab, profile).packed
            for j in range(int(self.steps[i]) + 1):
                p, v, a, _ = c.plan.reference_tuples(j * dt_s + lead_s)
                self.ref[i, j] = (*p, *v, *a)

    def __len__(self) -> int:
        return len(self.crossings)

