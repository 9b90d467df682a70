"""Minimum-jerk motion primitives after Mueller, Hehn and D'Andrea (2015), vectorised over a batch.

Each axis is a quintic in time whose jerk is a quadratic, ``j(t) = alpha t^2/2 + beta t + gamma``,
the minimiser of the cost ``J = (1/T) * integral_0^T |j(t)|^2 dt`` (summed over the three axes) from a
fixed start state (p0, v0, a0) to an end state whose position, velocity and acceleration may each be
fixed or free (``None``). Free end states use the optimal-control transversality conditions; the
closed form is a constant 3 x k gain per fixed/free combination in normalised time (``GAINS``): a
solve is a handful of array operations (millions of solves per second when batched).

Feasibility tests after the same paper:
- ``Trajectory.input_feasible``: the recursive interval-splitting test on the mass-normalised thrust
  ``f = |a - g|`` (m/s^2) and the roll/pitch body rates ``|omega_xy| <= |j| / f`` (rad/s). Bounds over an
  interval come from the extrema of each axis' acceleration (roots of the jerk) and jerk (root of the
  snap); undecided intervals are halved down to ``min_dt``. Points sampled on the way (every interval's
  ends and midpoints) are checked exactly, so a violation found there is definite.
- ``Trajectory.position_feasible``: the half-space test, exact: the signed distance to the plane is a
  quintic in t, its extrema on [0, T] are among the ends and the real roots of its quartic derivative
  (found as companion-matrix eigenvalues, batched).

Minimum-snap primitives (``solve(..., j0=...)``, ``solve_floats(..., j0=..., jf=...)``) also fix the start's
jerk: each axis is then a polynomial of degree 7 whose jerk is a quartic, ``j(t) = epsilon t^4/24 +
delta t^3/6 + alpha t^2/2 + beta t + gamma`` (``gamma`` = the jerk given), the minimiser of the integral
of |snap|^2 with the end's jerk fixed or free (``SNAP_GAINS``, the same construction). A start at low thrust
(the end of a steep traverse) then turns the body from rest: the body rate is |j| / f, and the
minimum-jerk primitive's free start jerk turns it at once. The same `Trajectory` and `FloatTrajectory`
hold both (``delta`` and ``epsilon`` are None for the quintic); the feasibility and half-space tests find
the extrema of a degree-7 polynomial's derivatives from companion-matrix roots.

Shapes: positions, velocities and accelerations are (..., 3), durations (...); they broadcast.

The input-feasibility recursion runs in plain floats, one trajectory at a time (the planner tests a few
at once, where numpy calls on 3-vectors cost microseconds each). The planner's single trajectories are
``FloatTrajectory`` objects from ``solve_floats`` (the numbers of ``solve``, in plain floats);
``FloatTrajectory.planes_ok`` decides most half-space tests from Bernstein bounds and leaves the rest to
the exact ``min_plane_distance``.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import TypeVar

import numpy as np

from policies.frames import GRAVITY_VEC_M_S2


class Feasibility(IntEnum):
    """Outcome of the input-feasibility test, per trajectory."""

    FEASIBLE = 0
    INFEASIBLE = 1
    INDETERMINABLE = 2


# --- closed-form gains in normalised time ------------------------------------------------------
# With tau = t / T and x = (A, B, C) = (alpha T^5/120, beta T^4/24, gamma T^3/6), the end constraints
# read M x = (dp, dv T, da T^2) and the cost J T^5 = x' Q x with the jerk basis (60 tau^2, 24 tau, 6).
_M = np.array([[1.0, 1.0, 1.0], [5.0, 4.0, 3.0], [20.0, 12.0, 6.0]])
_Q = np.array([[720.0, 360.0, 120.0], [360.0, 192.0, 72.0], [120.0, 72.0, 36.0]])
# Minimum snap, the start's jerk fixed too: x = (c7, c6, c5, c4), the coefficients of tau^7 ... tau^4 (m) of
# what the fixed start state leaves; the end constraints read M x = (dp, dv T, da T^2, dj T^3) and the
# snap cost (T^7 times the integral of the snap squared) x' Q x with the snap basis
# (840 tau^3, 360 tau^2, 120 tau, 24): Q_ik = b_i b_k / (n_i + n_k + 1), n the basis' powers.
_M_SNAP = np.array([[1.0, 1.0, 1.0, 1.0], [7.0, 6.0, 5.0, 4.0], [42.0, 30.0, 20.0, 12.0],
                    [210.0, 120.0, 60.0, 24.0]])
_Q_SNAP = np.array([[b * c / (m + n + 1) for c, n in ((840, 3), (360, 2), (120, 1), (24, 0))]
                    for b, m in ((840, 3), (360, 2), (120, 1), (24, 0))])


def _gain(fixed: tuple[bool, ...], m_all: np.ndarray = _M, q: np.ndarray = _Q) -> np.ndarray:
    """Map from the fixed end-state residuals (in order p, v, a[, j]) to x: the KKT solution of min x'Qx."""
    rows = [i for i in range(len(fixed)) if fixed[i]]
    if not rows:
        return np.zeros((len(q), 0))
    m = m_all[rows]
    q_inv = np.linalg.inv(q)
    return q_inv @ m.T @ np.linalg.inv(m @ q_inv @ m.T)


GAINS: dict[tuple[bool, bool, bool], np.ndarray] = {
    (p, v, a): _gain((p, v, a)) for p in (True, False) for v in (True, False) for a in (True, False)
}
#: the minimum-snap primitive's gains per fixed (p, v, a, j) end state
SNAP_GAINS: dict[tuple[bool, bool, bool, bool], np.ndarray] = {
    (p, v, a, j): _gain((p, v, a, j), _M_SNAP, _Q_SNAP)
    for p in (True, False) for v in (True, False) for a in (True, False) for j in (True, False)
}


_Num = TypeVar("_Num", float, np.ndarray)


def _vec3(name: str, value: object) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0 or arr.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def _poly_state(t1: _Num, p0: _Num, v0: _Num, a0: _Num, al: _Num, be: _Num, ga: _Num,
                de: _Num | None = None, ep: _Num | None = None) -> tuple[_Num, _Num, _Num]:
    """Position, velocity and acceleration at ``t1`` of the quintic, or of the degree-7 polynomial where
    ``de`` and ``ep`` are given: one formula for arrays and floats."""
    t2, t3 = t1 * t1, t1 * t1 * t1
    p = p0 + v0 * t1 + a0 * t2 / 2 + ga * t3 / 6 + be * t2 * t2 / 24 + al * t3 * t2 / 120
    v = v0 + a0 * t1 + ga * t2 / 2 + be * t3 / 6 + al * t2 * t2 / 24
    a = a0 + ga * t1 + be * t2 / 2 + al * t3 / 6
    if de is None:
        return p, v, a
    t4 = t2 * t2
    return (p + de * t3 * t3 / 720 + ep * t4 * t3 / 5040, v + de * t3 * t2 / 120 + ep * t3 * t3 / 720,
            a + de * t4 / 24 + ep * t3 * t2 / 120)


def _jerk(t1: _Num, al: _Num, be: _Num, ga: _Num, de: _Num | None = None,
          ep: _Num | None = None) -> _Num:
    """Jerk at ``t1`` (as `_poly_state`)."""
    j = ga + be * t1 + al * t1 * t1 / 2
    if de is None:
        return j
    return j + de * t1 * t1 * t1 / 6 + ep * t1 * t1 * t1 * t1 / 24


class Trajectory:
    """A batch of minimum-jerk (or minimum-snap) trajectories (coefficients per axis); build with ``solve``.

    Attributes (read-only by convention): ``p0, v0, a0, alpha, beta, gamma`` of shape (..., 3) and
    ``T`` of shape (...) in seconds; ``batch_shape`` is the leading shape; ``delta, epsilon`` (the
    jerk's t^3/6 and t^4/24 coefficients) are (..., 3) for a minimum-snap primitive, else None.
    """

    def __init__(self, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, alpha: np.ndarray,
                 beta: np.ndarray, gamma: np.ndarray, T: np.ndarray, delta: np.ndarray | None = None,
                 epsilon: np.ndarray | None = None) -> None:
        self.p0, self.v0, self.a0 = p0, v0, a0
        self.alpha, self.beta, self.gamma = alpha, beta, gamma
        self.delta, self.epsilon = delta, epsilon
        self.T = T
        self.batch_shape: tuple[int, ...] = T.shape

    def _coefficients(self) -> tuple[np.ndarray, ...]:
        """(p0, v0, a0, alpha, beta, gamma[, delta, epsilon]): `_poly_state`'s order."""
        coeffs = (self.p0, self.v0, self.a0, self.alpha, self.beta, self.gamma)
        return coeffs if self.delta is None else (*coeffs, self.delta, self.epsilon)

    def __len__(self) -> int:
        return int(self.T.shape[0]) if self.T.ndim else 1

    # --- evaluation ------------------------------------------------------------------------------
    def _coeffs_for(self, t: object) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Broadcast ``t`` against the batch: returns t[..., None] and the coefficient arrays.

        ``t`` of ndim <= len(batch_shape) broadcasts with the batch (output (..., 3)); ``t`` with one
        more dimension than the batch carries a trailing sample axis (output (..., S, 3)).
        """
        tt = np.asarray(t, dtype=float)
        coeffs = self._coefficients()
        nb = len(self.batch_shape)
        if tt.ndim == nb + 1:
            coeffs = tuple(c[..., None, :] for c in coeffs)
        elif tt.ndim > nb + 1:
            raise ValueError(f"t has shape {tt.shape}; batch shape is {self.batch_shape} "
                             "(allowed: broadcastable with the batch, or one extra trailing sample axis)")
        return tt[..., None], coeffs

    def state(self, t: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (m), velocity (m/s), acceleration (m/s^2) at time ``t`` (s) from the start.

        ``t`` is a scalar, an array broadcastable with the batch shape (one time per trajectory;
        outputs (..., 3)), or an array of the batch shape plus a trailing sample axis of length S (S
        times per trajectory; outputs (..., S, 3)). The polynomial is evaluated as is outside [0, T].
        """
        t1, coeffs = self._coeffs_for(t)
        return _poly_state(t1, *coeffs)

    def state_tuples(self, t: float) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """`state` of a single trajectory (empty batch shape) at one time ``t`` (s) in plain floats (the
        per-step path): position (m), velocity (m/s), acceleration (m/s^2), each an (x, y, z) tuple."""
        coeffs = self.__dict__.get("_floats")
        if coeffs is None:
            if self.batch_shape:
                raise ValueError(f"state_tuples needs a single trajectory, batch shape is {self.batch_shape}")
            coeffs = self._floats = tuple(zip(*(c.tolist() for c in self._coefficients()), strict=True))
        t1 = float(t)
        cx, cy, cz = coeffs
        x, y, z = _poly_state(t1, *cx), _poly_state(t1, *cy), _poly_state(t1, *cz)
        return (x[0], y[0], z[0]), (x[1], y[1], z[1]), (x[2], y[2], z[2])

    def jerk(self, t: object) -> np.ndarray:
        """Jerk (m/s^3) at ``t`` (s); same shape rules as ``state``."""
        t1, coeffs = self._coeffs_for(t)
        return _jerk(t1, *coeffs[3:])

    @property
    def cost(self) -> np.ndarray:
        """Mueller et al.'s J: (1/T) * integral of |jerk|^2 over [0, T], summed over axes; shape (...)."""
        al, be, ga, T = self.alpha, self.beta, self.gamma, self.T[..., None]
        if self.delta is not None:  # the jerk's coefficients in t (ascending), squared, integrated
            jc = [ga, be, al / 2, self.delta / 6, self.epsilon / 24]
            integral = sum(jc[i] * jc[k] * T ** (i + k + 1) / (i + k + 1) for i in range(5) for k in range(5))
            return integral.sum(axis=-1) / self.T
        integral = (ga**2 * T + be * ga * T**2 + (be**2 + al * ga) * T**3 / 3
                    + al * be * T**4 / 4 + al**2 * T**5 / 20)
        return integral.sum(axis=-1) / self.T

    # --- feasibility -----------------------------------------------------------------------------
    def input_feasible(self, f_min_m_s2: float, f_max_m_s2: float, w_max_rad_s: float,
                       min_dt: float = 0.02) -> np.ndarray:
        """Mueller et al.'s recursive input-feasibility test; returns ``Feasibility`` codes, shape (...).

        ``f_min_m_s2``/``f_max_m_s2``: mass-normalised thrust limits (m/s^2, f_min > 0);
        ``w_max_rad_s``: roll/pitch body-rate limit; ``min_dt``: smallest interval (s) before the
        test gives up on it (INDETERMINABLE).
        """
        _check_limits(f_min_m_s2, f_max_m_s2, w_max_rad_s, min_dt)
        return np.array([_verdict(axes, T, f_min_m_s2, f_max_m_s2, w_max_rad_s, min_dt)
                         for axes, T in _axis_floats(self)], dtype=np.int8).reshape(self.batch_shape)

    def min_plane_distance(self, point: object, normal: object) -> np.ndarray:
        """Smallest signed distance (m) over [0, T] to the plane through ``point`` with ``normal``.

        Positive is the side the normal points to. Exact up to round-off: the extrema are among the
        ends and the real roots of the derivative (a quartic). Shape (...).
        """
        pt = _vec3("point", point)
        nrm = _vec3("normal", normal)
        length = np.linalg.norm(nrm, axis=-1, keepdims=True)
        if np.any(length < 1e-12):
            raise ValueError("normal must be non-zero")
        nrm = nrm / length
        T = self.T
        dot = lambda c: np.sum(np.broadcast_to(c, np.broadcast_shapes(c.shape, nrm.shape)) * nrm, -1)  # noqa: E731
        # signed distance as a polynomial in normalised time tau in [0, 1]: coefficients d0..d5 (a quintic)
        # or d0..d7
        terms = [dot(self.p0 - pt), dot(self.v0) * T, dot(self.a0) * T**2 / 2, dot(self.gamma) * T**3 / 6,
                 dot(self.beta) * T**4 / 24, dot(self.alpha) * T**5 / 120]
        if self.delta is not None:
            terms += [dot(self.delta) * T**6 / 720, dot(self.epsilon) * T**7 / 5040]
        n = len(terms) - 1  # the degree
        d = np.stack(np.broadcast_arrays(*terms), -1)
        shape = d.shape[:-1]
        d = d.reshape(-1, n + 1)
        best = np.minimum(d[:, 0], d.sum(axis=1))
        deriv = d[:, 1:] * np.arange(1, n + 1)  # e0..e(n-1) of the derivative
        scale = np.max(np.abs(deriv), axis=1)
        regular = np.abs(deriv[:, n - 1]) > 1e-9 * scale
        powers = np.arange(n + 1)
        if np.any(regular):
            e = deriv[regular]
            comp = np.zeros((e.shape[0], n - 1, n - 1))
            for i in range(1, n - 1):
                comp[:, i, i - 1] = 1.0
            comp[:, :, n - 2] = -e[:, :n - 1] / e[:, n - 1:n]
            roots = np.linalg.eigvals(comp)
            real = np.abs(roots.imag) <= 1e-7 * (1.0 + np.abs(roots.real))
            tau = np.clip(np.where(real, roots.real, 0.0), 0.0, 1.0)
            vals = np.sum(d[regular][:, None, :] * tau[..., None] ** powers, axis=-1)
            best[regular] = np.minimum(best[regular], vals.min(axis=1))
        for row in np.flatnonzero(~regular):
            roots = np.roots(deriv[row, ::-1]) if scale[row] > 0 else np.array([])
            roots = roots.real[(np.abs(roots.imag) <= 1e-7) & (roots.real > 0) & (roots.real < 1)]
            if roots.size:
                best[row] = min(best[row], float(np.min(np.polyval(d[row, ::-1], roots))))
        return best.reshape(shape)

    def position_feasible(self, point: object, normal: object, margin_m: float = 0.0) -> np.ndarray:
        """True where the trajectory stays on the normal's side of the plane (by ``margin_m``) on [0, T]."""
        return self.min_plane_distance(point, normal) >= margin_m - 1e-9


def solve(p0: object, v0: object, a0: object, pf: object | None, vf: object | None, af: object | None,
          T: object, j0: object | None = None, jf: object | None = None) -> Trajectory:
    """Minimum-jerk trajectories from (p0, v0, a0) to the end state (pf, vf, af) in ``T`` seconds; with
    the start's jerk ``j0`` (m/s^3) given, minimum-snap ones (degree 7) from (p0, v0, a0, j0) to (pf,
    vf, af, jf).

    Arrays are (..., 3) (m, m/s, m/s^2, m/s^3) and ``T`` is (...) (s); they broadcast. ``None`` leaves
    that end state free for all axes (the cost is then minimised over it too). Raises ValueError for
    non-finite inputs or non-positive durations, or ``jf`` without ``j0``.
    """
    p0a, v0a, a0a = _vec3("p0", p0), _vec3("v0", v0), _vec3("a0", a0)
    ends = [None if e is None else _vec3(name, e) for name, e in (("pf", pf), ("vf", vf), ("af", af))]
    if j0 is None and jf is not None:
        raise ValueError("an end jerk jf needs the start's jerk j0 (the minimum-snap primitive)")
    Ta = np.asarray(T, dtype=float)
    if not np.all(np.isfinite(Ta)) or np.any(Ta <= 0):
        raise ValueError("T must be finite and positive")
    shapes = [p0a.shape[:-1], v0a.shape[:-1], a0a.shape[:-1], Ta.shape]
    shapes += [e.shape[:-1] for e in ends if e is not None]
    if j0 is not None:
        return _solve_snap(p0a, v0a, a0a, _vec3("j0", j0), ends, None if jf is None else _vec3("jf", jf),
                           Ta, shapes)
    batch = np.broadcast_shapes(*shapes)
    Ta = np.broadcast_to(Ta, batch)
    Tc = Ta[..., None]
    p0a, v0a, a0a = (np.broadcast_to(x, (*batch, 3)) for x in (p0a, v0a, a0a))
    residuals = []
    if ends[0] is not None:
        residuals.append(ends[0] - p0a - v0a * Tc - a0a * Tc**2 / 2)
    if ends[1] is not None:
        residuals.append((ends[1] - v0a - a0a * Tc) * Tc)
    if ends[2] is not None:
        residuals.append((ends[2] - a0a) * Tc**2)
    gain = GAINS[tuple(e is not None for e in ends)]
    if residuals:
        rhs = np.stack(np.broadcast_arrays(*residuals), -1)  # (..., 3 axes, k)
        x = np.einsum("ik,...ak->...ai", gain, rhs)  # (..., 3 axes, 3 coefficients)
    else:
        x = np.zeros((*batch, 3, 3))
    alpha = 120 * x[..., 0] / Tc**5
    beta = 24 * x[..., 1] / Tc**4
    gamma = 6 * x[..., 2] / Tc**3
    return Trajectory(np.array(p0a), np.array(v0a), np.array(a0a), alpha, beta, gamma, np.array(Ta))


def _snap_residuals(p0: _Num, v0: _Num, a0: _Num, j0: _Num, pf: _Num | None, vf: _Num | None,
                    af: _Num | None, jf: _Num | None, T: _Num) -> list[_Num]:
    """The minimum-snap primitive's end residuals (dp, dv T, da T^2, dj T^3) of the fixed end states."""
    T2 = T * T
    out = []
    if pf is not None:
        out.append(((pf - p0) - v0 * T) - a0 * T2 / 2 - j0 * T2 * T / 6)
    if vf is not None:
        out.append(((vf - v0) - a0 * T - j0 * T2 / 2) * T)
    if af is not None:
        out.append(((af - a0) - j0 * T) * T2)
    if jf is not None:
        out.append((jf - j0) * T2 * T)
    return out


def _snap_coefficients(x: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, ...]:
    """(alpha, beta, delta, epsilon) from x = (c7, c6, c5, c4) (..., 4) per axis and T (...)."""
    Tc = T[..., None]
    return (120 * x[..., 2] / Tc**5, 24 * x[..., 3] / Tc**4, 720 * x[..., 1] / Tc**6,
            5040 * x[..., 0] / Tc**7)


def _solve_snap(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, j0: np.ndarray, ends: list[np.ndarray | None],
                jf: np.ndarray | None, T: np.ndarray, shapes: list[tuple[int, ...]]) -> Trajectory:
    """`solve`'s minimum-snap primitives (inputs checked there)."""
    shapes = [*shapes, j0.shape[:-1]] + ([] if jf is None else [jf.shape[:-1]])
    batch = np.broadcast_shapes(*shapes)
    Ta = np.broadcast_to(T, batch)
    p0, v0, a0, j0 = (np.broadcast_to(x, (*batch, 3)) for x in (p0, v0, a0, j0))
    residuals = _snap_residuals(p0, v0, a0, j0, *ends, jf, Ta[..., None])
    gain = SNAP_GAINS[(*(e is not None for e in ends), jf is not None)]
    if residuals:
        rhs = np.stack(np.broadcast_arrays(*residuals), -1)  # (..., 3 axes, k)
        x = np.einsum("ik,...ak->...ai", gain, rhs)  # (..., 3 axes, 4 coefficients)
    else:
        x = np.zeros((*batch, 3, 4))
    alpha, beta, delta, epsilon = _snap_coefficients(x, Ta)
    return Trajectory(np.array(p0), np.array(v0), np.array(a0), alpha, beta, np.array(j0), np.array(Ta),
                      delta, epsilon)


# --- plain-float paths ----------------------------------------------------------------------------
# The planner solves and tests a handful of single trajectories, where each numpy call on a 3-vector
# costs microseconds, so the feasibility test, `solve_floats` and `FloatTrajectory` work in plain floats.
# Two operations are taken from numpy, batched, as the shipped plans were computed: the cube of a time
# (`_cubes`; numpy's SIMD pow can differ from C's in the last bit) and the gain product of `solve_floats`
# (einsum's summation order, the same numbers as `solve`). Sums over the three axes are ((x + y) + z).

_GRAVITY = tuple(GRAVITY_VEC_M_S2.tolist())
_GAIN_ALL_FIXED = GAINS[(True, True, True)]

Vec3 = tuple[float, float, float]
#: per axis: a0 - g (m/s^2), alpha, beta, gamma[, delta, epsilon (a minimum-snap primitive's)]
AxisCoeffs = tuple[float, ...]


def _cubes(times: list[float]) -> list[float]:
    """``t**3`` for each time as numpy computes ``array**3`` (batched: one call)."""
    return np.power(np.array(times, dtype=float), 3.0).tolist()


def _axis_floats(traj: Trajectory) -> list[tuple[tuple[AxisCoeffs, ...], float]]:
    """Per trajectory of the batch: (a0 - g, alpha, beta, gamma[, delta, epsilon]) per axis and T, as plain
    floats."""
    shape = (*traj.batch_shape, 3)
    cols = [np.broadcast_to(c, shape).reshape(-1, 3).tolist() for c in traj._coefficients()[2:]]
    return [(tuple((a0[k] - _GRAVITY[k], *(c[k] for c in rest)) for k in range(3)), t)
            for (a0, *rest), t in zip(zip(*cols, strict=True), traj.T.reshape(-1).tolist(), strict=True)]


def _check_limits(f_min: float, f_max: float, w_max: float, min_dt: float) -> None:
    if not (0 < f_min < f_max and w_max > 0 and min_dt > 0):
        raise ValueError("need 0 < f_min_m_s2 < f_max_m_s2, w_max_rad_s > 0 and min_dt > 0")


def _verdict(axes: tuple[AxisCoeffs, ...], T: float, f_min: float, f_max: float, w_max: float,
             min_dt: float) -> int:
    """The input-feasibility verdict of one trajectory; INFEASIBLE where a coefficient is not finite."""
    if not math.isfinite(sum(map(abs, (*axes[0], *axes[1], *axes[2], T)))):
        return Feasibility.INFEASIBLE
    return _feasibility_floats(axes, T, f_min, f_max, w_max, min_dt)


def _high_acc(t: float, t4: float, de: float, ep: float) -> float:
    """A minimum-snap primitive's acceleration terms beyond the quintic's at ``t`` (``t4`` = t^4)."""
    return (de * t4) / 24 + (ep * t4 * t) / 120


def _high_jerk(t: float, t3: float, de: float, ep: float) -> float:
    """A minimum-snap primitive's jerk terms beyond the quintic's at ``t`` (``t3`` = t^3)."""
    return (de * t3) / 6 + (ep * t3 * t) / 24


def _roots_inside(coeffs: tuple[float, ...], T: float) -> list[float]:
    """The real parts, inside (0, T), of the roots of the polynomial with ascending ``coeffs`` (companion
    eigenvalues), of complex ones too: a near-real pair may be a double root that round-off split, and
    a value at any other point is one the function takes, so an extra candidate never loosens a bound."""
    if not any(coeffs):
        return []
    return [r for r in np.roots(coeffs[::-1]).real.tolist() if 0 < r < T]


def _feasibility_floats(axes: tuple[AxisCoeffs, ...], T: float, f_min: float, f_max: float, w_max: float,
                        min_dt: float) -> int:
    """Mueller et al.'s recursive input-feasibility test of one trajectory (`Trajectory.input_feasible`).

    Intervals are halved at ``(lo + hi) / 2``, one depth at a time; the verdict is INFEASIBLE once any
    check fails, else INDETERMINABLE once any interval is too small, else FEASIBLE. The bounds over an
    interval use the extrema of the acceleration (roots of the jerk) and of the jerk (roots of the snap);
    these roots are the same for every interval, so their values are computed once, and the values at
    interval ends are cached. A quintic's roots are in closed form, a degree-7 polynomial's (its jerk a
    quartic, its snap a cubic) companion eigenvalues.
    """
    fmax2, fmin2, w2 = f_max**2, f_min**2, w_max**2
    high = len(axes[0]) == 6  # a minimum-snap primitive: the jerk's t^3/6 and t^4/24 terms too
    # roots inside (0, T) of the jerk (acceleration extrema) and of the snap (jerk extrema); roots outside
    # an interval only repeat that interval's end values
    acc_roots: list[list[float]] = []
    snap_roots: list[list[float]] = []
    for _, al, be, ga, *hi_terms in axes:
        if high:
            de, ep = hi_terms
            rs = _roots_inside((ga, be, al / 2, de / 6, ep / 24), T)
            snap_roots.append(_roots_inside((be, al, de / 2, ep / 6), T))
        elif al != 0:
            q = be * be - 2 * al * ga
            rs = []
            if q >= 0:
                disc = math.sqrt(q)
                rs = [(-be + disc) / al, (-be - disc) / al]
            rsnap = -be / al
            snap_roots.append([rsnap] if 0 < rsnap < T else [])
        else:
            rs = [-ga / be] if be != 0 else []
            snap_roots.append([])
        acc_roots.append([r for r in rs if 0 < r < T])
    roots = [r for rs in acc_roots for r in rs]
    cubes = _cubes([0.0, T, *roots])
    cube_of = dict(zip([0.0, T, *roots], cubes, strict=True))
    # the acceleration at its extrema and |jerk| at its extrema
    acc_root_vals = [[((a0 + ga * r) + (be * (r * r)) / 2) + (al * cube_of[r]) / 6
                      + (_high_acc(r, cube_of[r] * r, *hi) if high else 0.0) for r in rs]
                     for (a0, al, be, ga, *hi), rs in zip(axes, acc_roots, strict=True)]
    acc_root_pairs = [list(zip(rs, vs, strict=True)) for rs, vs in zip(acc_roots, acc_root_vals, strict=True)]
    snap_pairs = [[(r, abs((ga + be * r) + (al * (r * r)) / 2
                        + (_high_jerk(r, r * r * r, *hi) if high else 0.0))) for r in rs]
                  for (_, al, be, ga, *hi), rs in zip(axes, snap_roots, strict=True)]

    (x0, xl, xb, xg, *x_hi), (y0, yl, yb, yg, *y_hi), (z0, zl, zb, zg, *z_hi) = axes

    def point_ok(t: float, t3: float) -> bool:
        """Exact thrust and roll/pitch-rate check at one time ``t`` (s; ``t3`` = its cube)."""
        fx = ((x0 + xg * t) + ((xb * t) * t) / 2) + (xl * t3) / 6
        fy = ((y0 + yg * t) + ((yb * t) * t) / 2) + (yl * t3) / 6
        fz = ((z0 + zg * t) + ((zb * t) * t) / 2) + (zl * t3) / 6
        if high:
            t4 = t3 * t
            fx, fy, fz = (fx + _high_acc(t, t4, *x_hi), fy + _high_acc(t, t4, *y_hi),
                          fz + _high_acc(t, t4, *z_hi))
        f = math.sqrt((fx * fx + fy * fy) + fz * fz)
        if not (f >= f_min and f <= f_max):
            return False
        jx = (xg + xb * t) + ((xl * t) * t) / 2
        jy = (yg + yb * t) + ((yl * t) * t) / 2
        jz = (zg + zb * t) + ((zl * t) * t) / 2
        if high:
            jx, jy, jz = (jx + _high_jerk(t, t3, *x_hi), jy + _high_jerk(t, t3, *y_hi),
                          jz + _high_jerk(t, t3, *z_hi))
        zx, zy, zz = fx / f, fy / f, fz / f
        dot = (jx * zx + jy * zy) + jz * zz
        px, py, pz = jx - dot * zx, jy - dot * zy, jz - dot * zz
        return math.sqrt((px * px + py * py) + pz * pz) / f <= w_max

    def ends(t: float, t3: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Thrust acceleration and |jerk| per axis at an interval end."""
        tt = t * t
        if high:
            t4 = t3 * t
            return ((((x0 + xg * t) + (xb * tt) / 2) + (xl * t3) / 6 + _high_acc(t, t4, *x_hi),
                     ((y0 + yg * t) + (yb * tt) / 2) + (yl * t3) / 6 + _high_acc(t, t4, *y_hi),
                     ((z0 + zg * t) + (zb * tt) / 2) + (zl * t3) / 6 + _high_acc(t, t4, *z_hi)),
                    (abs((xg + xb * t) + (xl * tt) / 2 + _high_jerk(t, t3, *x_hi)),
                     abs((yg + yb * t) + (yl * tt) / 2 + _high_jerk(t, t3, *y_hi)),
                     abs((zg + zb * t) + (zl * tt) / 2 + _high_jerk(t, t3, *z_hi))))
        return ((((x0 + xg * t) + (xb * tt) / 2) + (xl * t3) / 6,
                 ((y0 + yg * t) + (yb * tt) / 2) + (yl * t3) / 6,
                 ((z0 + zg * t) + (zb * tt) / 2) + (zl * t3) / 6),
                (abs((xg + xb * t) + (xl * tt) / 2), abs((yg + yb * t) + (yl * tt) / 2),
                 abs((zg + zb * t) + (zl * tt) / 2)))

    c0, cT = cube_of[0.0], cube_of[T]
    if not (point_ok(0.0, c0) and point_ok(T, cT)):
        return Feasibility.INFEASIBLE
    cache = {0.0: ends(0.0, c0), T: ends(T, cT)}
    indeterminable = False
    intervals = [(0.0, T)]
    while intervals:
        splits = []
        for lo, hi in intervals:
            (acc_lo, jer_lo), (acc_hi, jer_hi) = cache[lo], cache[hi]
            fsq_lo = fsq_hi = jsq_hi = 0.0
            for k in range(3):
                a_lo, a_hi = acc_lo[k], acc_hi[k]
                a_min, a_max = (a_lo, a_hi) if a_lo <= a_hi else (a_hi, a_lo)
                for r, v in acc_root_pairs[k]:
                    if lo < r < hi:
                        if v < a_min:
                            a_min = v
                        if v > a_max:
                            a_max = v
                sq_min, sq_max = a_min * a_min, a_max * a_max
                sq_hi, sq_lo = (sq_min, sq_max) if sq_min >= sq_max else (sq_max, sq_min)
                if a_min <= 0 and a_max >= 0:
                    sq_lo = 0.0
                j = jer_lo[k] if jer_lo[k] >= jer_hi[k] else jer_hi[k]
                for r, v in snap_pairs[k]:
                    if lo < r < hi and v > j:
                        j = v
                # the sums over axes in the numpy code's order: ((x + y) + z)
                fsq_lo, fsq_hi, jsq_hi = (sq_lo, sq_hi, j * j) if k == 0 else (
                    fsq_lo + sq_lo, fsq_hi + sq_hi, jsq_hi + j * j)
            if fsq_lo > fmax2 or fsq_hi < fmin2:
                return Feasibility.INFEASIBLE
            if fsq_hi <= fmax2 and fsq_lo >= fmin2 and jsq_hi <= w2 * fsq_lo:
                continue  # done
            if (hi - lo) / 2 < min_dt:
                indeterminable = True
            else:
                splits.append((lo, hi))
        if not splits:
            break
        mids = [(lo + hi) / 2 for lo, hi in splits]
        intervals = []
        for (lo, hi), mid, m3 in zip(splits, mids, _cubes(mids), strict=True):
            if not point_ok(mid, m3):
                return Feasibility.INFEASIBLE
            cache[mid] = ends(mid, m3)
            intervals += [(lo, mid), (mid, hi)]
    return Feasibility.INDETERMINABLE if indeterminable else Feasibility.FEASIBLE


_EXPONENTS_345 = np.array([3.0, 4.0, 5.0])
_PLANE_DEPTH = 6  # halvings of [0, T] the plane test tries before it asks the exact `min_plane_distance`


class Plane:
    """A half-space for `FloatTrajectory.planes_ok`: ``point`` and ``normal`` as given (m), the
    trajectory passes where its smallest signed distance (m) over [0, T] is >= ``threshold_m``."""

    __slots__ = ("axis", "normal", "point", "threshold_m", "unit")

    def __init__(self, point: Vec3, normal: Vec3, threshold_m: float) -> None:
        nx, ny, nz = normal
        length = math.sqrt((nx * nx + ny * ny) + nz * nz)
        if length < 1e-12:
            raise ValueError("normal must be non-zero")
        self.point, self.normal, self.threshold_m = point, normal, threshold_m
        self.unit = (nx / length, ny / length, nz / length)
        nonzero = [k for k in range(3) if normal[k] != 0]
        self.axis = nonzero[0] if len(nonzero) == 1 else -1  # axis-aligned: +-1 along that axis


#: per degree n, per Bernstein coefficient 0 < i < n: (C(i, k), C(n, k)) for k = 1 ... i
_BERNSTEIN_WEIGHTS = {n: [[(math.comb(i, k), math.comb(n, k)) for k in range(1, i + 1)] for i in range(1, n)]
                      for n in (5, 7)}


def _bernstein(c: list[float]) -> list[float]:
    """Bernstein coefficients on [0, 1] of the quintic or degree-7 polynomial in tau with ascending
    coefficients ``c``: b_i = sum_k C(i, k) / C(n, k) c_k, the last the plain sum (the value at 1)."""
    c0 = c[0]
    out = [c0]
    for row in _BERNSTEIN_WEIGHTS[len(c) - 1]:
        b = c0
        for k, (num, den) in enumerate(row, 1):
            b = b + (num * c[k]) / den
        out.append(b)
    out.append(sum(c))
    return out


def _bernstein_above(b: list[float], threshold: float, tol: float) -> bool | None:
    """Whether the polynomial with Bernstein coefficients ``b`` on [0, 1] stays >= ``threshold``: True when
    its coefficients (of halves, recursively) are all >= threshold + tol, False when a value at a
    (sub-)interval end is below threshold - tol, None when neither within `_PLANE_DEPTH` halvings."""
    stack = [(b, 0)]
    while stack:
        b, depth = stack.pop()
        if b[0] < threshold - tol or b[-1] < threshold - tol:
            return False
        if min(b) >= threshold + tol:
            continue
        if depth == _PLANE_DEPTH:
            return None
        left, right, w = [b[0]], [b[-1]], b
        for _ in range(len(b) - 1):  # de Casteljau at 1/2
            w = [(w[i] + w[i + 1]) / 2 for i in range(len(w) - 1)]
            left.append(w[0])
            right.append(w[-1])
        right.reverse()
        stack += [(right, depth + 1), (left, depth + 1)]
    return True


class FloatTrajectory:
    """One minimum-jerk (or minimum-snap) trajectory in plain floats (from `solve_floats`): ``axes`` holds
    per axis (p0, v0, a0, alpha, beta, gamma[, delta, epsilon]), ``T`` the duration (s); `trajectory` gives
    the numpy `Trajectory`."""

    __slots__ = ("T", "T3", "T4", "T5", "_traj", "axes")

    def __init__(self, axes: tuple[tuple[float, ...], ...], T: float, T3: float, T4: float,
                 T5: float) -> None:
        self.axes, self.T, self.T3, self.T4, self.T5 = axes, T, T3, T4, T5
        self._traj: Trajectory | None = None

    def trajectory(self) -> Trajectory:
        """The `Trajectory` (batch shape ()) `solve` gives for the same inputs."""
        if self._traj is None:
            cols = [np.array(c) for c in zip(*self.axes, strict=True)]
            tr = Trajectory(*cols[:6], np.array(self.T), *cols[6:])
            tr._floats = self.axes  # what `state_tuples` would cache: the same floats
            self._traj = tr
        return self._traj

    def input_feasible(self, f_min_m_s2: float, f_max_m_s2: float, w_max_rad_s: float,
                       min_dt: float = 0.02) -> Feasibility:
        """`Trajectory.input_feasible` of this trajectory."""
        axes = tuple((a0 - g, *rest) for (_, _, a0, *rest), g in zip(self.axes, _GRAVITY, strict=True))
        _check_limits(f_min_m_s2, f_max_m_s2, w_max_rad_s, min_dt)
        return Feasibility(_verdict(axes, self.T, f_min_m_s2, f_max_m_s2, w_max_rad_s, min_dt))

    def planes_ok(self, planes: list[Plane]) -> bool:
        """Whether ``min_plane_distance(plane.point, plane.normal) >= plane.threshold_m`` for every plane
        (the same verdicts).

        Most planes are decided from Bernstein bounds of the distance polynomial in normalised time (with a
        tolerance far above round-off, so a bound decides only where the exact test must agree); the
        rest go to the exact `Trajectory.min_plane_distance`, as do all of a minimum-snap primitive's.
        """
        T, T2 = self.T, self.T * self.T
        bern = []
        scale = 1.0
        for p0, v0, a0, al, be, ga, *hi in self.axes:
            cs = [p0, v0 * T, a0 * T2 / 2, ga * self.T3 / 6, be * self.T4 / 24, al * self.T5 / 120]
            if hi:  # a minimum-snap primitive's
                T6 = self.T3 * self.T3
                cs += [hi[0] * T6 / 720, hi[1] * T6 * T / 5040]
            scale += sum(map(abs, cs))
            bern.append(_bernstein(cs))
        for plane in planes:
            pt, n, thr = plane.point, plane.unit, plane.threshold_m
            tol = 1e-9 * (scale + abs(pt[0]) + abs(pt[1]) + abs(pt[2]))
            k = plane.axis
            if k >= 0:  # axis-aligned: the distance is +-(x_k - point_k)
                b = bern[k]
                low = min(b) - pt[k] if n[k] > 0 else pt[k] - max(b)
                if low >= thr + tol:
                    continue
            offset = (n[0] * pt[0] + n[1] * pt[1]) + n[2] * pt[2]
            b = [(n[0] * x + n[1] * y) + n[2] * z - offset for x, y, z in zip(*bern, strict=True)]
            verdict = _bernstein_above(b, thr, tol)
            if verdict is None:
                dist = self.trajectory().min_plane_distance(np.array(plane.point), np.array(plane.normal))
                verdict = bool(dist >= thr)
            if not verdict:
                return False
        return True


def solve_floats(p0: Vec3, v0: Vec3, a0: Vec3, pf: Vec3, vf: Vec3, af: Vec3,
                 durations_s: list[float], j0: Vec3 | None = None,
                 jf: Vec3 | None = None) -> list[FloatTrajectory]:
    """`solve` with the whole end state fixed, from one start state to one end state in each of several
    durations (s; finite, positive: not checked here), in plain floats: the same numbers as `solve`.
    With the jerks ``j0`` and ``jf`` (m/s^3) given, the minimum-snap primitives between them."""
    if not durations_s:
        return []
    if j0 is not None or jf is not None:
        if j0 is None or jf is None:
            raise ValueError("the minimum-snap primitive needs both jerks j0 and jf")
        return _solve_snap_floats(p0, v0, a0, j0, pf, vf, af, jf, durations_s)
    rhs = []
    for T in durations_s:
        T2 = T * T
        rhs.append([(((pf[k] - p0[k]) - v0[k] * T) - a0[k] * T2 / 2, ((vf[k] - v0[k]) - a0[k] * T) * T,
                     (af[k] - a0[k]) * T2) for k in range(3)])
    x = np.einsum("ik,...ak->...ai", _GAIN_ALL_FIXED, np.array(rhs)).tolist()
    powers = np.power(np.array(durations_s)[:, None], _EXPONENTS_345).tolist()
    out = []
    for T, (T3, T4, T5), xs in zip(durations_s, powers, x, strict=True):
        axes = tuple((p0[k], v0[k], a0[k], 120 * xs[k][0] / T5, 24 * xs[k][1] / T4, 6 * xs[k][2] / T3)
                     for k in range(3))
        out.append(FloatTrajectory(axes, T, T3, T4, T5))
    return out


def _solve_snap_floats(p0: Vec3, v0: Vec3, a0: Vec3, j0: Vec3, pf: Vec3, vf: Vec3, af: Vec3, jf: Vec3,
                       durations_s: list[float]) -> list[FloatTrajectory]:
    """`solve_floats`' minimum-snap primitives: `solve`'s arrays, per duration in plain floats."""
    T = np.array(durations_s, dtype=float)
    Tc = T[:, None]
    arr = [np.array(v, dtype=float) for v in (p0, v0, a0, j0, pf, vf, af, jf)]
    rhs = np.stack(_snap_residuals(*arr[:4], *arr[4:], Tc), -1)  # (n, 3 axes, 4)
    x = np.einsum("ik,...ak->...ai", SNAP_GAINS[(True, True, True, True)], rhs)
    alpha, beta, delta, epsilon = (c.tolist() for c in _snap_coefficients(x, T))
    powers = np.power(Tc, _EXPONENTS_345).tolist()
    return [FloatTrajectory(tuple((p0[k], v0[k], a0[k], alpha[i][k], beta[i][k], j0[k], delta[i][k],
                                   epsilon[i][k]) for k in range(3)), t, *powers[i])
            for i, t in enumerate(durations_s)]
