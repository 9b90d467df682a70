"""Figures over time of a recorded signal: the project's one definition of a time-weighted mean, maximum
and integral.

The recorder samples every 10 ms, and every 1 ms within 0.6 m of the gap plane (`hil.runner.recorder`):
a plain mean over samples weighs the crossing ten times over. Here each sample holds its value until the
next sample (a zero-order hold; the last one holds no time: nothing is known after it), and a figure over
a window [start_s, end_s) weighs each sample by the part of its hold that lies inside the window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def hold_weights_s(t_s: np.ndarray, start_s: float = -math.inf, end_s: float = math.inf,
                   mask: np.ndarray | None = None) -> np.ndarray:
    """Seconds (N,) that each sample of the non-decreasing times ``t_s`` (N,) holds inside [start_s,
    end_s): sample i holds from t_i to t_{i+1}, the last one none; zero where ``mask`` (N, bool) is
    False."""
    t = np.asarray(t_s, dtype=float)
    if len(t) == 0:
        return np.zeros(0)
    nxt = np.append(t[1:], t[-1])
    w = np.clip(np.minimum(nxt, end_s) - np.maximum(t, start_s), 0.0, None)
    return w if mask is None else np.where(np.asarray(mask, dtype=bool), w, 0.0)


def _finite(values: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v) & (w > 0.0)
    return v[ok], w[ok]


def time_mean(t_s: np.ndarray, values: np.ndarray, start_s: float = -math.inf, end_s: float = math.inf,
              mask: np.ndarray | None = None) -> float | None:
    """Mean of ``values`` over time inside the window (`hold_weights_s`; non-finite values left out);
    None when no time is left."""
    return _mean(*_finite(values, hold_weights_s(t_s, start_s, end_s, mask)))


def time_integral(t_s: np.ndarray, values: np.ndarray, start_s: float = -math.inf, end_s: float = math.inf,
                  mask: np.ndarray | None = None) -> float | None:
    """Integral of ``values`` over time inside the window (value x s; non-finite values left out); None
    when no time is left."""
    return _integral(*_finite(values, hold_weights_s(t_s, start_s, end_s, mask)))


def time_max(t_s: np.ndarray, values: np.ndarray, start_s: float = -math.inf, end_s: float = math.inf,
             mask: np.ndarray | None = None) -> float | None:
    """Largest of ``values`` held for some time inside the window (non-finite left out); None when none."""
    return _max(*_finite(values, hold_weights_s(t_s, start_s, end_s, mask)))


def window_figures(t_s: np.ndarray, signals: Sequence[np.ndarray], start_s: float = -math.inf,
                   end_s: float = math.inf) -> list[tuple[float | None, float | None, float | None]]:
    """`time_mean`, `time_max` and `time_integral` of each of ``signals`` (each (N,) against ``t_s``) over
    one window [start_s, end_s) (s), its weights computed once for them all."""
    w = hold_weights_s(t_s, start_s, end_s)
    figures = []
    for values in signals:
        v, vw = _finite(values, w)
        figures.append((_mean(v, vw), _max(v, vw), _integral(v, vw)))
    return figures


def _mean(v: np.ndarray, w: np.ndarray) -> float | None:
    total = float(w.sum())
    return float(np.dot(v, w) / total) if total > 0.0 else None


def _integral(v: np.ndarray, w: np.ndarray) -> float | None:
    return float(np.dot(v, w)) if w.sum() > 0.0 else None


def _max(v: np.ndarray, _w: np.ndarray) -> float | None:
    return float(v.max()) if len(v) else None
