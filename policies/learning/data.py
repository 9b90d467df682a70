"""Training data: planner trajectories from the motion primitives and controller samples from the expert.

Planner set (the paper's): ``n_trajectories`` random boundary-value problems over ``PlannerRanges``,
each discretised at ``samples_per_trajectory`` times uniformly over [0, T]. Trajectories with too
large outputs are dropped (the paper does this without a number; here: any sample with
|p(t) - p0| > ``max_pos_m``, |v| > ``max_vel_m_s`` or |a| > ``max_acc_m_s2``, per axis). Only the
trajectories (their primitive coefficients) are stored; ``PlannerSampler`` draws (trajectory, grid
time) pairs on the fly and evaluates the closed form, which is the same data set without storing
20k x 1000 rows. Augmentation after the paper: sign flip of inputs 2..16 and outputs, and scaling of
inputs 1..16 and outputs by k ~ U[1, k_max].

Controller sets (the paper's large- and short-range sets): uniform errors and Euler angles, labelled
by the expert law (``policies.controller.expert_command_batch``) with desired yaw 0; the reference
acceleration fed to the expert is the acceleration error input (the expert has no other acceleration
term), the Euler angles do not change the label.

Everything is seeded and cached on disk under ``cache_dir()`` keyed by a hash of the parameters.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from policies.controller import expert_command_batch
from policies.learning.features import (
    CONTROLLER_MASS_KG,
    LARGE_RANGE,
    SHORT_RANGE,
    ControllerRanges,
    PlannerRanges,
    planner_inputs,
)
from policies.primitives import Trajectory, solve


def cache_dir() -> Path:
    """Cache directory: $HIL_CACHE_DIR, else ~/.cache/crossgap-hil."""
    env = os.environ.get("HIL_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "crossgap-hil"


def cache_key(kind: str, params: object) -> str:
    """Short hash of a data set's kind and parameters (a dataclass)."""
    text = json.dumps({"kind": kind, **asdict(params)}, sort_keys=True, default=float)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# --- planner -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlannerDataConfig:
    """Parameters of a planner data set; the defaults are the paper's."""

    n_trajectories: int = 20_000
    samples_per_trajectory: int = 1000
    seed: int = 0
    ranges: PlannerRanges = field(default_factory=PlannerRanges)
    max_pos_m: float = 100.0  # "too large outputs" thresholds, per axis
    max_vel_m_s: float = 40.0
    max_acc_m_s2: float = 60.0

    def __post_init__(self) -> None:
        if self.n_trajectories < 1 or self.samples_per_trajectory < 2:
            raise ValueError("need n_trajectories >= 1 and samples_per_trajectory >= 2")


@dataclass(frozen=True)
class PlannerData:
    """Boundary states (N, 3), durations (N,) in s, and the solved primitives of the kept trajectories."""

    config: PlannerDataConfig
    dp_m: np.ndarray
    v0_m_s: np.ndarray
    a0_m_s2: np.ndarray
    vf_m_s: np.ndarray
    af_m_s2: np.ndarray
    duration_s: np.ndarray
    n_dropped: int
    trajectory: Trajectory = field(init=False, repr=False)

    def __post_init__(self) -> None:
        traj = solve(np.zeros(3), self.v0_m_s, self.a0_m_s2, self.dp_m, self.vf_m_s, self.af_m_s2,
                     self.duration_s)
        object.__setattr__(self, "trajectory", traj)

    def __len__(self) -> int:
        return int(self.duration_s.shape[0])

    def inputs_outputs(self, idx: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Planner inputs (B, 17) and labels (B, 9) for trajectories ``idx`` at grid points ``grid``."""
        T = self.duration_s[idx]
        t = grid / (self.config.samples_per_trajectory - 1) * T
        tr = self.trajectory
        sub = Trajectory(tr.p0[idx], tr.v0[idx], tr.a0[idx], tr.alpha[idx], tr.beta[idx], tr.gamma[idx], T)
        p, v, a = sub.state(t)
        x = planner_inputs(t, self.dp_m[idx], self.v0_m_s[idx], self.a0_m_s2[idx], self.vf_m_s[idx],
                           self.af_m_s2[idx], T)
        return x, np.concatenate([p, v, a], axis=-1)

    def all_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Every (trajectory, grid time) pair: inputs (N*S, 17) and labels (N*S, 9)."""
        s = self.config.samples_per_trajectory
        idx = np.repeat(np.arange(len(self)), s)
        grid = np.tile(np.arange(s), len(self))
        return self.inputs_outputs(idx, grid)


def _draw_planner(cfg: PlannerDataConfig) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(cfg.seed)
    r, n = cfg.ranges, cfg.n_trajectories
    dp = rng.uniform(-r.dp_m, r.dp_m, (n, 3))
    v_bar = rng.uniform(r.v_bar_min_m_s, r.v_bar_max_m_s, n)
    v0, vf = (rng.uniform(-r.vel_m_s, r.vel_m_s, (n, 3)) for _ in range(2))
    a0, af = (rng.uniform(-r.acc_m_s2, r.acc_m_s2, (n, 3)) for _ in range(2))
    T = np.linalg.norm(dp, axis=1) / v_bar
    return dp, v0, a0, vf, af, T


def _keep_mask(cfg: PlannerDataConfig, dp: np.ndarray, v0: np.ndarray, a0: np.ndarray, vf: np.ndarray,
               af: np.ndarray, T: np.ndarray, chunk: int = 500) -> np.ndarray:
    keep = np.ones(T.shape[0], dtype=bool)
    s = cfg.samples_per_trajectory
    tau = np.linspace(0.0, 1.0, s)
    for lo in range(0, T.shape[0], chunk):
        sl = slice(lo, lo + chunk)
        tr = solve(np.zeros(3), v0[sl], a0[sl], dp[sl], vf[sl], af[sl], T[sl])
        p, v, a = tr.state(tau[None, :] * T[sl, None])
        keep[sl] = ((np.abs(p).max(axis=(1, 2)) <= cfg.max_pos_m)
                    & (np.abs(v).max(axis=(1, 2)) <= cfg.max_vel_m_s)
                    & (np.abs(a).max(axis=(1, 2)) <= cfg.max_acc_m_s2))
    return keep


def planner_data(cfg: PlannerDataConfig, use_cache: bool = True) -> PlannerData:
    """The planner data set for ``cfg`` (from the cache when there, else generated and cached)."""
    path = cache_dir() / f"planner-{cache_key('planner', cfg)}.npz"
    if use_cache and path.exists():
        z = np.load(path)
        return PlannerData(cfg, z["dp"], z["v0"], z["a0"], z["vf"], z["af"], z["T"], int(z["n_dropped"]))
    dp, v0, a0, vf, af, T = _draw_planner(cfg)
    keep = _keep_mask(cfg, dp, v0, a0, vf, af, T)
    arrays = {k: x[keep] for k, x in zip(("dp", "v0", "a0", "vf", "af", "T"), (dp, v0, a0, vf, af, T),
                                          strict=True)}
    if not keep.any():
        raise ValueError("every trajectory exceeded the output thresholds; "
                         "raise max_pos_m, max_vel_m_s or max_acc_m_s2")
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, n_dropped=int((~keep).sum()), params=json.dumps(asdict(cfg), default=float), **arrays)
        tmp.replace(path)
    return PlannerData(cfg, arrays["dp"], arrays["v0"], arrays["a0"], arrays["vf"], arrays["af"], arrays["T"],
                       int((~keep).sum()))


def augment_planner(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, p_flip: float = 0.5,
                    p_scale: float = 0.5, k_max: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's augmentation, per sample: sign flip (inputs 2..16, outputs) with ``p_flip``, then
    scaling of v_bar, the boundary states and the outputs by k ~ U[1, k_max] with ``p_scale``.
    Both are exact symmetries of the primitive (T and t unchanged)."""
    n = x.shape[0]
    sign = np.where(rng.random(n) < p_flip, -1.0, 1.0)
    k = np.where(rng.random(n) < p_scale, rng.uniform(1.0, k_max, n), 1.0)
    x2, y2 = x.copy(), y * (sign * k)[:, None]
    x2[:, 1] *= k
    x2[:, 2:] *= (sign * k)[:, None]
    return x2, y2


class PlannerSampler:
    """Random training batches from a ``PlannerData``: uniform trajectory; grid time uniform, or for a
    fraction ``end_fraction`` of the samples from the arcsine (Chebyshev) law on the grid, which is
    denser near t = 0 and t = T, where the boundary conditions must be met exactly."""

    def __init__(self, data: PlannerData, rng: np.random.Generator, augment: bool = True,
                 end_fraction: float = 0.0) -> None:
        if not 0.0 <= end_fraction <= 1.0:
            raise ValueError(f"end_fraction must be in [0, 1], got {end_fraction}")
        self.data, self.rng, self.augment, self.end_fraction = data, rng, augment, end_fraction

    def batch(self, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Inputs (size, 17) and labels (size, 9), float64."""
        idx = self.rng.integers(0, len(self.data), size)
        last = self.data.config.samples_per_trajectory - 1
        grid = self.rng.integers(0, last + 1, size)
        if self.end_fraction > 0.0:
            ends = self.rng.random(size) < self.end_fraction
            cheb = np.rint(last * 0.5 * (1.0 - np.cos(np.pi * self.rng.random(size)))).astype(grid.dtype)
            grid = np.where(ends, cheb, grid)
        x, y = self.data.inputs_outputs(idx, grid)
        return augment_planner(x, y, self.rng) if self.augment else (x, y)


def planner_samples_per_s(n: int = 100_000, seed: int = 0) -> float:
    """Labelled planner samples per second (solve + evaluate + augment), one core, numpy."""
    data = planner_data(PlannerDataConfig(n_trajectories=2000, samples_per_trajectory=1000, seed=seed),
                        use_cache=False)
    sampler = PlannerSampler(data, np.random.default_rng(seed))
    start = time.perf_counter()
    sampler.batch(n)
    return n / (time.perf_counter() - start)


# --- controller ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class ControllerDataConfig:
    """Parameters of the controller data: samples per set (large- and short-range), seed."""

    n_per_set: int = 6_000_000
    seed: int = 0
    large: ControllerRanges = LARGE_RANGE
    short: ControllerRanges = SHORT_RANGE

    def __post_init__(self) -> None:
        if self.n_per_set < 1:
            raise ValueError("n_per_set must be >= 1")


def label_controller(x: np.ndarray) -> np.ndarray:
    """Expert labels (N, 3) = [roll, pitch (rad), thrust (N)] for controller inputs (N, 12)."""
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or x.shape[1] != 12:
        raise ValueError(f"controller inputs must have shape (N, 12), got {x.shape}")
    zero = np.zeros((x.shape[0], 3))
    roll, pitch, _, thrust = expert_command_batch(x[:, 0:3], x[:, 3:6], x[:, 6:9], 0.0, zero, zero,
                                                  mass_kg=CONTROLLER_MASS_KG)
    return np.stack([roll, pitch, thrust], axis=1)


def draw_controller_inputs(r: ControllerRanges, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform controller inputs (n, 12) over one set's ranges."""
    half = np.repeat([r.pos_err_m, r.vel_err_m_s, r.acc_err_m_s2, r.euler_rad], 3)
    return rng.uniform(-half, half, (n, 12))


def controller_data(cfg: ControllerDataConfig, use_cache: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Inputs (2N, 12) and labels (2N, 3), float32: the large-range set followed by the short-range set."""
    path = cache_dir() / f"controller-{cache_key('controller', cfg)}.npz"
    if use_cache and path.exists():
        z = np.load(path)
        return z["x"], z["y"]
    rng = np.random.default_rng(cfg.seed)
    xs, ys, chunk = [], [], 500_000
    for r in (cfg.large, cfg.short):
        for lo in range(0, cfg.n_per_set, chunk):
            x = draw_controller_inputs(r, min(chunk, cfg.n_per_set - lo), rng)
            xs.append(x.astype(np.float32))
            ys.append(label_controller(x).astype(np.float32))
    x, y = np.concatenate(xs), np.concatenate(ys)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, x=x, y=y, params=json.dumps(asdict(cfg), default=float))
        tmp.replace(path)
    return x, y
