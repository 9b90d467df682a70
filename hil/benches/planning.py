"""Planning figures: batched motion-primitive solves per second, the paper case's recovery search and the
whole mission search (approach, traverse, recovery for the body box) as the onboard program runs it."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from hil.benches import BenchRow, time_per_call
from policies.gap_planning import (
    GapPose,
    LabVolume,
    hover_point,
    plan_mission,
    plan_traverse,
    search_recovery,
)
from policies.primitives import solve


def collect(quick: bool) -> Iterator[BenchRow]:
    rng = np.random.default_rng(0)
    n = 100_000
    args = [rng.uniform(-5, 5, (n, 3)) for _ in range(6)] + [rng.uniform(0.5, 4.0, n)]
    min_time = 0.2 if quick else 1.0
    per_batch = time_per_call(lambda: solve(*args), min_time_s=min_time)
    yield BenchRow("primitive_solves_per_s", n / per_batch, "solves/s",
                   f"batch of {n:,} fully constrained solves, numpy")

    gap = GapPose.from_deg((0.0, 0.5, 2.1), -60.0, width_m=0.8, height_m=0.35)
    lab = LabVolume((-4.0, -3.0, 0.0), (4.0, 4.0, 4.0))
    trav = plan_traverse(gap, 2.0)
    pe, ve, ae = trav.end_state
    hover = hover_point(gap, np.array(trav.direction))
    wall = (gap.centre, np.array(trav.direction))
    per_search = time_per_call(lambda: search_recovery(pe, ve, ae, hover, lab, wall=wall),
                               min_time_s=min_time)
    yield BenchRow("recovery_search_ms", per_search * 1e3, "ms",
                   "paper case (gap roll -60 deg, 2 m/s), 9 durations; paper: < 50 ms on a TX2")

    # the whole search as the onboard program calls it (2.5 m/s, 0.25 m traverse lead, the default body box)
    lab5 = LabVolume((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
    cases = (
        ("mission_plan_paper_ms", (-2.0, -1.0, 0.5), gap, "paper case, gap roll -60 deg"),
        ("mission_plan_rl_case_ms", (0.0, 0.0, 0.5), GapPose.from_deg((2.0, 1.0, 1.5), 60.0, width_m=0.8,
                                                                      height_m=0.45),
         "the paper's RL case, gap (2, 1, 1.5) m roll 60 deg"),
    )
    for name, start, g, what in cases:
        def plan_it(s: tuple[float, float, float] = start, g: GapPose = g) -> object:
            return plan_mission(s, g, lab5, crossing_speed_m_s=2.5, d_min_m=0.25)

        plan = plan_it()
        per_plan = time_per_call(plan_it, min_time_s=min_time)
        yield BenchRow(name, per_plan * 1e3, "ms",
                       f"{what}: {plan.candidates_tried} approaches tried, recovery "
                       f"{plan.recovery.search_time_s * 1e3:.2f} ms of it")
