"""Paired comparisons of two pilots over the same units (a scenario flown with a seed): the mean of the
per-unit differences with a percentile bootstrap interval, and the verdict it allows.

Interval: 95 % by default, the 2.5th and 97.5th percentiles of the mean difference over `BOOTSTRAP_DRAWS`
resamples (with replacement) of the paired differences, drawn from a seeded Generator (the same data
give the same interval). The pairs are resampled as independent units: where the scenarios differ from
each other as well as the seeds, that counts the spread between scenarios as noise too (conservative for
the scenario set as fixed). No difference is resolved when the interval spans zero.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

BOOTSTRAP_DRAWS = 10_000
CONFIDENCE = 0.95
INTERVAL_METHOD = "paired percentile bootstrap (10,000 resamples of the per-unit differences)"
NOT_RESOLVED = "no difference resolved"


@dataclass(frozen=True)
class PairedDifference:
    """``b - a`` over the units both have a figure for: its mean, the interval, and what it shows."""

    a: str
    b: str
    units: int
    mean_a: float | None
    mean_b: float | None
    mean_difference: float | None
    ci_low: float | None
    ci_high: float | None
    b_lower_in: int  # units where b's figure is below a's
    confidence: float = CONFIDENCE

    @property
    def verdict(self) -> str:
        """"b lower", "b higher" (the interval excludes zero) or `NOT_RESOLVED`."""
        if self.ci_low is None or self.ci_high is None:
            return NOT_RESOLVED
        if self.ci_high < 0.0:
            return f"{self.b} lower"
        if self.ci_low > 0.0:
            return f"{self.b} higher"
        return NOT_RESOLVED

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "verdict": self.verdict, "method": INTERVAL_METHOD}


def paired_difference(a: str, b: str, values_a: Sequence[float | None], values_b: Sequence[float | None],
                      seed: int = 0, confidence: float = CONFIDENCE,
                      draws: int = BOOTSTRAP_DRAWS) -> PairedDifference:
    """``b - a`` paired unit by unit (the two sequences in the same unit order; a unit where either
    figure is None or not finite is left out); ``seed`` seeds the bootstrap."""
    if len(values_a) != len(values_b):
        raise ValueError(f"paired figures must be as many for both: {len(values_a)} and {len(values_b)}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be between 0 and 1, got {confidence}")
    pairs = np.array([(x, y) for x, y in zip(values_a, values_b, strict=True)
                      if x is not None and y is not None], dtype=float).reshape(-1, 2)
    pairs = pairs[np.isfinite(pairs).all(axis=1)]
    n = len(pairs)
    if n == 0:
        return PairedDifference(a, b, 0, None, None, None, None, None, 0, confidence)
    d = pairs[:, 1] - pairs[:, 0]
    lo = hi = None
    if n >= 2:
        rng = np.random.default_rng(seed)
        means = d[rng.integers(0, n, size=(draws, n))].mean(axis=1)
        tail = 100.0 * (1.0 - confidence) / 2.0
        lo, hi = (float(v) for v in np.percentile(means, [tail, 100.0 - tail]))
    return PairedDifference(a, b, n, float(pairs[:, 0].mean()), float(pairs[:, 1].mean()), float(d.mean()),
                            lo, hi, int(np.sum(d < 0.0)), confidence)
