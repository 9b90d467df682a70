"""Dispersed runs of one scenario (`hil dryrun`): each run's draws, flying them as Ray tasks, and the
answer: success probability with its interval, what fails, where the envelope ends, go or no-go."""

from hil.sweep.fly import RunRecord, fly
from hil.sweep.stats import SweepResult, summarise, wilson_interval
from hil.sweep.sweep import SweepPlan, plan_sweep, run_sweep

__all__ = [
    "RunRecord",
    "SweepPlan",
    "SweepResult",
    "fly",
    "plan_sweep",
    "run_sweep",
    "summarise",
    "wilson_interval",
]
