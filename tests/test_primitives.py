"""Tests for policies.primitives: boundary conditions, cost, batching, feasibility checks."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from policies.primitives import Feasibility, Trajectory, solve

COMBOS = list(itertools.product((True, False), repeat=3))


def _random_case(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    return {
        "p0": rng.uniform(-5, 5, (n, 3)), "v0": rng.uniform(-3, 3, (n, 3)), "a0": rng.uniform(-3, 3, (n, 3)),
        "pf": rng.uniform(-5, 5, (n, 3)), "vf": rng.uniform(-3, 3, (n, 3)), "af": rng.uniform(-3, 3, (n, 3)),
        "T": rng.uniform(0.5, 4.0, n),
    }


def _rel_err(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.max(np.abs(x - ref) / np.maximum(1.0, np.abs(ref))))


@pytest.mark.parametrize("fixed", COMBOS, ids=lambda f: "".join("F" if x else "-" for x in f))
def test_boundary_conditions_every_fixed_free_combination(fixed: tuple[bool, bool, bool]) -> None:
    c = _random_case(np.random.default_rng(1), 200)
    ends = [c[k] if f else None for k, f in zip(("pf", "vf", "af"), fixed, strict=True)]
    tr = solve(c["p0"], c["v0"], c["a0"], *ends, c["T"])
    p, v, a = tr.state(0.0)
    assert _rel_err(p, c["p0"]) < 1e-9 and _rel_err(v, c["v0"]) < 1e-9 and _rel_err(a, c["a0"]) < 1e-9
    p, v, a = tr.state(c["T"])
    for got, want in zip((p, v, a), ends, strict=True):
        if want is not None:
            assert _rel_err(got, want) < 1e-9
    # transversality: a free end acceleration leaves zero jerk at the end (its costate vanishes at T)
    if not fixed[2]:
        assert np.abs(tr.jerk(c["T"])).max() < 1e-7


@pytest.mark.parametrize("fixed", COMBOS[:-1], ids=lambda f: "".join("F" if x else "-" for x in f))
def test_free_end_states_are_optimal(fixed: tuple[bool, bool, bool]) -> None:
    """Fixing a free end state at any other value than the optimum's costs more."""
    rng = np.random.default_rng(2)
    c = _random_case(rng, 50)
    ends = [c[k] if f else None for k, f in zip(("pf", "vf", "af"), fixed, strict=True)]
    tr = solve(c["p0"], c["v0"], c["a0"], *ends, c["T"])
    p, v, a = tr.state(c["T"])
    opt = (p, v, a)
    for _ in range(5):
        pert = [o + rng.normal(0, 0.3, o.shape) if e is None else o for o, e in zip(opt, ends, strict=True)]
        other = solve(c["p0"], c["v0"], c["a0"], *pert, c["T"])
        assert np.all(other.cost >= tr.cost - 1e-9)
    same = solve(c["p0"], c["v0"], c["a0"], *opt, c["T"])
    np.testing.assert_allclose(same.cost, tr.cost, rtol=1e-8, atol=1e-9)


def test_cost_equals_integrated_squared_jerk() -> None:
    c = _random_case(np.random.default_rng(3), 20)
    tr = solve(c["p0"], c["v0"], c["a0"], c["pf"], c["vf"], c["af"], c["T"])
    n = 4001
    ts = np.linspace(0.0, 1.0, n)[None, :] * c["T"][:, None]  # trailing sample axis
    j2 = np.sum(tr.jerk(ts) ** 2, axis=-1)
    w = np.ones(n)
    w[1:-1:2], w[2:-1:2] = 4, 2  # Simpson
    integral = np.sum(j2 * w, axis=1) * (c["T"] / (n - 1)) / 3
    np.testing.assert_allclose(tr.cost, integral / c["T"], rtol=1e-6)


def test_batched_and_scalar_calls_agree() -> None:
    c = _random_case(np.random.default_rng(4), 30)
    batch = solve(c["p0"], c["v0"], c["a0"], c["pf"], None, c["af"], c["T"])
    t_query = 0.37 * c["T"]
    pb, vb, ab = batch.state(t_query)
    for i in range(30):
        one = solve(c["p0"][i], c["v0"][i], c["a0"][i], c["pf"][i], None, c["af"][i], c["T"][i])
        assert one.batch_shape == ()
        p, v, a = one.state(t_query[i])
        np.testing.assert_allclose(p, pb[i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(v, vb[i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(a, ab[i], rtol=1e-12, atol=1e-12)
        assert one.cost == pytest.approx(batch.cost[i], rel=1e-12)
    # broadcasting: one start, many goals and durations
    many = solve(c["p0"][0], c["v0"][0], c["a0"][0], c["pf"], c["vf"], c["af"], c["T"])
    assert many.state(0.0)[0].shape == (30, 3)
    np.testing.assert_allclose(many.state(c["T"])[0], c["pf"], atol=1e-9)


def test_state_sample_axis_shapes() -> None:
    tr = solve([0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 2, 3], [0, 0, 0], [0, 0, 0], 2.0)
    p, _, _ = tr.state(np.linspace(0, 2, 7))
    assert p.shape == (7, 3)
    np.testing.assert_allclose(p[-1], [1, 2, 3], atol=1e-12)
    trb = solve(np.zeros((4, 3)), 0 * np.ones(3), np.zeros(3), np.ones((4, 3)), None, None, np.ones(4))
    assert trb.state(np.zeros((4, 5)))[0].shape == (4, 5, 3)
    with pytest.raises(ValueError):
        trb.state(np.zeros((4, 5, 6)))


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="T"):
        solve([0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 1, 1], None, None, 0.0)
    with pytest.raises(ValueError, match="p0"):
        solve([0, 0], [0, 0, 0], [0, 0, 0], [1, 1, 1], None, None, 1.0)
    with pytest.raises(ValueError, match="finite"):
        solve([0, np.nan, 0], [0, 0, 0], [0, 0, 0], [1, 1, 1], None, None, 1.0)


def test_input_feasibility_classifies() -> None:
    zero = np.zeros(3)
    hover = solve([0, 0, 1], zero, zero, [0, 0, 1], zero, zero, 2.0)
    assert hover.input_feasible(5.0, 30.0, 10.0) == Feasibility.FEASIBLE  # f = g throughout
    gentle = solve([0, 0, 1], zero, zero, [1, 0.5, 1.2], zero, zero, 3.0)
    assert gentle.input_feasible(5.0, 30.0, 10.0) == Feasibility.FEASIBLE
    huge = solve([0, 0, 1], zero, zero, [20, 0, 1], zero, zero, 0.5)  # 20 m in half a second
    assert huge.input_feasible(5.0, 30.0, 10.0) == Feasibility.INFEASIBLE
    free_fall_too_long = solve([0, 0, 10], zero, [0, 0, -9.8], None, None, [0, 0, -9.8], 1.0)
    assert free_fall_too_long.input_feasible(1.0, 30.0, 10.0) == Feasibility.INFEASIBLE  # f = 0 < f_min
    # batched: the verdicts match the one-at-a-time verdicts, and sampled truth agrees with FEASIBLE
    rng = np.random.default_rng(5)
    c = _random_case(rng, 300)
    tr = solve(c["p0"], c["v0"], c["a0"], c["pf"], c["vf"], c["af"], c["T"])
    verdict = tr.input_feasible(2.0, 25.0, 10.0, min_dt=0.01)
    assert set(np.unique(verdict)) >= {Feasibility.FEASIBLE, Feasibility.INFEASIBLE}
    ts = np.linspace(0, 1, 3001)[None, :] * c["T"][:, None]
    _, _, a = tr.state(ts)
    up = np.array([0.0, 0.0, 9.8])
    f = np.linalg.norm(a + up, axis=-1)
    j = tr.jerk(ts)
    z = (a + up) / f[..., None]
    rate = np.linalg.norm(j - np.sum(j * z, -1, keepdims=True) * z, axis=-1) / f
    sampled_ok = (f.min(1) >= 2.0) & (f.max(1) <= 25.0) & (rate.max(1) <= 10.0)
    assert np.all(sampled_ok[verdict == Feasibility.FEASIBLE])
    for i in range(0, 300, 37):
        one = solve(c["p0"][i], c["v0"][i], c["a0"][i], c["pf"][i], c["vf"][i], c["af"][i], c["T"][i])
        assert one.input_feasible(2.0, 25.0, 10.0, min_dt=0.01) == verdict[i]
    with pytest.raises(ValueError):
        hover.input_feasible(10.0, 5.0, 1.0)


def test_position_feasibility_catches_floor_dip() -> None:
    zero = np.zeros(3)
    # start at 0.5 m moving down at 3 m/s, end at 0.5 m at rest: dips below the floor
    dip = solve([0, 0, 0.5], [0, 0, -3], zero, [1, 0, 0.5], zero, zero, 1.5)
    ts = np.linspace(0, 1.5, 20001)
    z_min = dip.state(ts)[0][:, 2].min()
    assert z_min < 0
    assert not dip.position_feasible([0, 0, 0], [0, 0, 1])
    assert dip.min_plane_distance([0, 0, 0], [0, 0, 1]) == pytest.approx(z_min, abs=1e-6)
    level = solve([0, 0, 0.5], zero, zero, [1, 0, 0.5], zero, zero, 1.5)
    assert level.position_feasible([0, 0, 0], [0, 0, 1])
    assert not level.position_feasible([0, 0, 0], [0, 0, 1], margin_m=0.6)
    # batch with random planes: the exact minimum matches dense sampling
    rng = np.random.default_rng(6)
    c = _random_case(rng, 200)
    tr = solve(c["p0"], c["v0"], c["a0"], c["pf"], c["vf"], c["af"], c["T"])
    normal = rng.normal(size=(200, 3))
    point = rng.uniform(-3, 3, (200, 3))
    exact = tr.min_plane_distance(point, normal)
    ts = np.linspace(0, 1, 20001)[None, :] * c["T"][:, None]
    p = tr.state(ts)[0]
    unit = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    sampled = np.sum((p - point[:, None, :]) * unit[:, None], axis=-1).min(axis=1)
    assert np.all(exact <= sampled + 1e-9)
    np.testing.assert_allclose(exact, sampled, atol=1e-5)
    with pytest.raises(ValueError):
        tr.position_feasible([0, 0, 0], [0, 0, 0])


# --- input feasibility and the plain-float paths --------------------------------------------------------
def _feasibility_cases(rng: np.random.Generator, n: int) -> list[tuple[Trajectory, tuple[float, ...]]]:
    """(trajectory batch of 1..12, limits): random ones, straight lines, and limits set right at a
    trajectory's own thrust or body-rate extreme (deep recursion, INDETERMINABLE verdicts)."""
    out = []
    up = np.array([0.0, 0.0, 9.8])
    for i in range(n):
        b = int(rng.choice([1, 2, 5, 12]))
        c = _random_case(rng, b)
        vf, af = (c["vf"], c["af"]) if i % 3 else (np.zeros((b, 3)), np.zeros((b, 3)))
        if i % 11 == 0:  # straight lines: alpha = beta = gamma = 0 on every axis
            c["a0"] = af = np.zeros((b, 3))
            vf = c["v0"]
            c["pf"] = c["p0"] + c["v0"] * c["T"][:, None]
        tr = solve(c["p0"], c["v0"], c["a0"], c["pf"], vf, af, c["T"])
        limits = (float(rng.uniform(0.5, 5)), float(rng.uniform(10, 35)), float(rng.uniform(1, 25)),
                  float(rng.choice([0.002, 0.01, 0.02, 0.05])))
        if i % 2:  # at the first trajectory's extreme
            ts = np.linspace(0, float(tr.T[0]), 2001)
            a = tr.state(ts[None, :])[0][0]
            f = np.linalg.norm(a + up, axis=-1)
            j = tr.jerk(ts[None, :])[0]
            z = (a + up) / f[:, None]
            w = np.linalg.norm(j - np.sum(j * z, -1, keepdims=True) * z, axis=-1) / f
            scale = 1 + float(rng.choice([-1e-3, -1e-6, 0.0, 1e-6, 1e-3]))
            f_min, f_max, w_max, min_dt = 0.5, 60.0, 200.0, limits[3]
            if i % 4 == 1:
                f_max = max(float(f.max()) * scale, 1.0)
            else:
                w_max = max(float(w.max()) * scale, 1e-3)
            limits = (f_min, f_max, w_max, min_dt)
        out.append((tr, limits))
    return out


def test_input_feasibility_verdicts_agree_with_dense_sampling() -> None:
    """FEASIBLE: no sample breaks a limit; INFEASIBLE: some sample breaks one or comes within a hair of it
    (the recursion's point checks fall between samples); every verdict occurs; any batch shape."""
    up = np.array([0.0, 0.0, 9.8])
    seen = set()
    for tr, (f_min, f_max, w_max, min_dt) in _feasibility_cases(np.random.default_rng(21), 200):
        verdict = tr.input_feasible(f_min, f_max, w_max, min_dt)
        assert verdict.dtype == np.int8 and verdict.shape == tr.batch_shape
        ts = np.linspace(0, 1, 4001)[None, :] * tr.T[:, None]
        a, j = tr.state(ts)[2] + up, tr.jerk(ts)
        f = np.linalg.norm(a, axis=-1)
        z = a / f[..., None]
        w = np.linalg.norm(j - np.sum(j * z, -1, keepdims=True) * z, axis=-1) / f
        # the worst relative margin to a limit over the samples (< 0: a limit broken)
        margin = np.minimum(np.minimum(f.min(1) / f_min - 1, 1 - f.max(1) / f_max), 1 - w.max(1) / w_max)
        assert np.all(margin[verdict == Feasibility.FEASIBLE] >= -1e-9)
        assert np.all(margin[verdict == Feasibility.INFEASIBLE] <= 1e-2)
        seen.update(verdict.tolist())
    assert seen == {Feasibility.FEASIBLE, Feasibility.INFEASIBLE, Feasibility.INDETERMINABLE}
    c = _random_case(np.random.default_rng(22), 6)
    sub = solve(c["p0"].reshape(2, 3, 3), c["v0"].reshape(2, 3, 3), c["a0"].reshape(2, 3, 3),
                c["pf"].reshape(2, 3, 3), None, None, c["T"].reshape(2, 3))
    flat = solve(c["p0"], c["v0"], c["a0"], c["pf"], None, None, c["T"])
    np.testing.assert_array_equal(sub.input_feasible(2.0, 25.0, 10.0).reshape(-1),
                                  flat.input_feasible(2.0, 25.0, 10.0))


def test_solve_floats_gives_the_numbers_of_solve() -> None:
    from policies.primitives import solve_floats

    rng = np.random.default_rng(23)
    for _ in range(200):
        scale = 10.0 ** rng.uniform(-2, 2)
        p0, v0, a0, pf, vf, af = (tuple(rng.normal(0, scale, 3).tolist()) for _ in range(6))
        durations = rng.uniform(0.05, 6.0, int(rng.integers(1, 10))).tolist()
        batch = solve(p0, v0, a0, pf, vf, af, np.array(durations))
        for i, fl in enumerate(solve_floats(p0, v0, a0, pf, vf, af, durations)):
            got, one = fl.trajectory(), solve(p0, v0, a0, pf, vf, af, durations[i])
            assert got.batch_shape == one.batch_shape == ()
            for name in ("p0", "v0", "a0", "alpha", "beta", "gamma", "T"):
                a, b = getattr(got, name), getattr(one, name)
                assert a.shape == b.shape and a.dtype == b.dtype
                # the same operations in the same order: equal to the last bit on this machine; a tight
                # tolerance keeps the check meaningful where numpy's SIMD paths round differently
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
                np.testing.assert_allclose(a, getattr(batch, name)[i], rtol=1e-12, atol=1e-12)
            t = 0.37 * durations[i]
            for x, y in zip(got.state_tuples(t), one.state_tuples(t), strict=True):
                np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
    assert solve_floats((0.0,) * 3, (0.0,) * 3, (0.0,) * 3, (1.0,) * 3, (0.0,) * 3, (0.0,) * 3, []) == []


def test_planes_ok_gives_the_verdicts_of_min_plane_distance() -> None:
    from policies.primitives import Plane, solve_floats

    rng = np.random.default_rng(24)
    zero = (0.0, 0.0, 0.0)
    for i in range(150):
        p0, v0, a0, pf = (tuple(rng.normal(0, 1.5, 3).tolist()) for _ in range(4))
        fl = solve_floats(p0, v0, a0, pf, zero, zero, [float(rng.uniform(0.2, 4.0))])[0]
        tr = fl.trajectory()
        for k in range(4):
            if k < 2:  # axis-aligned, as the lab's walls
                normal = [0.0, 0.0, 0.0]
                normal[int(rng.integers(3))] = float(rng.choice([1.0, -1.0]))
            else:
                normal = (rng.normal(size=3) * rng.choice([0.2, 1.0, 3.0])).tolist()
            point = rng.normal(0, 1.5, 3).tolist()
            exact = float(tr.min_plane_distance(point, normal))
            # thresholds around the exact minimum down to round-off: there the exact test decides
            for thr in (float(rng.normal(0, 1.0)), exact, exact - 1e-12, exact + 1e-12, exact - 1e-9,
                        exact + 1e-9, exact - 1e-4, exact + 1e-4, -1e-9):
                want = bool(tr.min_plane_distance(point, normal) >= thr)
                assert fl.planes_ok([Plane(tuple(point), tuple(normal), thr)]) == want, (i, k, thr - exact)
        if i == 0:
            with pytest.raises(ValueError, match="non-zero"):
                Plane((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)


def test_single_trajectory_floats_match_the_array_evaluation():
    traj = solve((0.1, -2.0, 0.5), (0.3, 0.2, -0.1), (0.0, 0.5, 0.2), (1.0, 0.0, 1.5), (0.0, 2.0, 0.0),
                 (0.0, 0.0, -3.0), 2.6)
    for t in (0.0, 0.37, 1.3, 2.6, 3.1):
        p, v, a = traj.state(np.array([t]))  # the array path
        pf, vf, af = traj.state_tuples(t)
        assert np.array_equal(p[0], pf) and np.array_equal(v[0], vf) and np.array_equal(a[0], af)
    batch = solve(np.zeros((2, 3)), np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="single trajectory"):
        batch.state_tuples(0.5)


# --- minimum-snap primitives (the start's jerk fixed) ---------------------------------------------


def _snap_jerk_and_snap(tr: Trajectory, t: np.ndarray, h: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    return tr.jerk(t), (tr.jerk(t + h) - tr.jerk(t - h)) / (2 * h)


@pytest.mark.parametrize("fixed", list(itertools.product((True, False), repeat=4)),
                         ids=lambda f: "".join("F" if x else "-" for x in f))
def test_minimum_snap_boundary_conditions_and_optimality(fixed: tuple[bool, bool, bool, bool]) -> None:
    """With ``j0`` the primitive starts at (p0, v0, a0, j0) and ends at every fixed one of (pf, vf, af,
    jf); a free end state is the optimum (no perturbation of it lowers the integral of |snap|^2)."""
    rng = np.random.default_rng(31)
    c = _random_case(rng, 50)
    j0, jf = rng.uniform(-5, 5, (50, 3)), rng.uniform(-5, 5, (50, 3))
    ends = [c[k] if f else None for k, f in zip(("pf", "vf", "af"), fixed[:3], strict=True)]
    tr = solve(c["p0"], c["v0"], c["a0"], *ends, c["T"], j0=j0, jf=jf if fixed[3] else None)
    assert tr.delta is not None and tr.epsilon is not None
    p, v, a = tr.state(np.zeros(50))
    for got, want in ((p, c["p0"]), (v, c["v0"]), (a, c["a0"]), (tr.jerk(np.zeros(50)), j0)):
        assert _rel_err(got, want) < 1e-9
    p, v, a = tr.state(c["T"])
    for got, want in zip((p, v, a, tr.jerk(c["T"])), (*ends, jf if fixed[3] else None), strict=True):
        if want is not None:
            assert _rel_err(got, want) < 1e-7

    def snap_cost(traj: Trajectory) -> np.ndarray:
        ts = np.linspace(0, 1, 2001)[None, :] * traj.T[:, None]
        s = _snap_jerk_and_snap(traj, ts)[1]
        return np.trapezoid(np.sum(s * s, -1), ts, axis=-1)

    base = snap_cost(tr)
    p_end, v_end, a_end = tr.state(c["T"])
    free_ends = [p_end, v_end, a_end, tr.jerk(c["T"])]
    for k in range(4):
        if fixed[k]:
            continue
        nudged = list(free_ends)
        nudged[k] = nudged[k] + rng.normal(0, 0.3, (50, 3))
        other = solve(c["p0"], c["v0"], c["a0"], *nudged[:3], c["T"], j0=j0, jf=nudged[3])
        assert np.all(snap_cost(other) >= base * (1 - 1e-6))


def test_minimum_snap_primitive_is_degree_seven_and_its_free_end_jerk_ends_without_snap() -> None:
    rng = np.random.default_rng(32)
    p0, v0, a0, j0, pf = rng.normal(size=(5, 3))
    tr = solve(p0, v0, a0, pf, np.zeros(3), np.zeros(3), 1.7, j0=j0)
    assert np.abs(_snap_jerk_and_snap(tr, np.array(1.7))[1]).max() < 1e-4
    ts = np.linspace(0, 1.7, 9)  # eight points fit a degree-7 polynomial exactly: the ninth agrees
    pos = tr.state(ts)[0]
    fit = np.polynomial.polynomial.polyfit(ts[:8], pos[:8], 7)
    np.testing.assert_allclose(np.polynomial.polynomial.polyval(ts[8], fit), pos[8], atol=1e-8)
    # cost: (1/T) * integral of |jerk|^2, as for the quintic
    grid = np.linspace(0, 1.7, 20001)
    np.testing.assert_allclose(tr.cost, np.trapezoid(np.sum(tr.jerk(grid) ** 2, -1), grid) / 1.7, rtol=1e-6)
    with pytest.raises(ValueError, match="j0"):
        solve(p0, v0, a0, pf, None, None, 1.0, jf=np.zeros(3))


def test_minimum_snap_feasibility_and_plane_tests_agree_with_dense_sampling() -> None:
    """The input-feasibility and half-space tests of degree-7 primitives: FEASIBLE never breaks a limit
    at any sample, INFEASIBLE breaks one (or comes within a hair); the plane tests give the sampled
    minimum distance; `solve_floats` gives `solve`'s numbers."""
    from policies.primitives import Plane, solve_floats

    rng = np.random.default_rng(33)
    up = np.array([0.0, 0.0, 9.8])
    seen = set()
    zero = (0.0, 0.0, 0.0)
    for _ in range(150):
        p0, v0, pf = (tuple(rng.normal(0, 2, 3).tolist()) for _ in range(3))
        a0, j0 = (tuple(rng.normal(0, 3, 3).tolist()) for _ in range(2))
        T = float(rng.uniform(0.8, 3.0))
        (fl,) = solve_floats(p0, v0, a0, pf, zero, zero, [T], j0, zero)
        tr = fl.trajectory()
        one = solve(p0, v0, a0, pf, zero, zero, T, j0=j0, jf=zero)
        for name in ("p0", "v0", "a0", "alpha", "beta", "gamma", "delta", "epsilon", "T"):
            np.testing.assert_allclose(getattr(tr, name), getattr(one, name), rtol=1e-12, atol=1e-12)
        ts = np.linspace(0, T, 4001)
        pos, _, acc = tr.state(ts)
        a, j = acc + up, tr.jerk(ts)
        f = np.linalg.norm(a, axis=-1)
        z = a / f[:, None]
        w = np.linalg.norm(j - np.sum(j * z, -1, keepdims=True) * z, axis=-1) / f
        for w_max in (0.5 * w.max(), 1.01 * w.max(), 8.0):
            verdict = fl.input_feasible(2.0, 25.0, float(w_max), 0.005)
            margin = min(f.min() / 2.0 - 1, 1 - f.max() / 25.0, 1 - w.max() / w_max)
            if verdict == Feasibility.FEASIBLE:
                assert margin >= -1e-9
            elif verdict == Feasibility.INFEASIBLE:
                assert margin <= 1e-2
            seen.add(int(verdict))
        normal = rng.normal(size=3)
        point = rng.normal(0, 1.5, 3)
        exact = float(tr.min_plane_distance(point, normal))
        sampled = float(np.min((pos - point) @ (normal / np.linalg.norm(normal))))
        assert sampled - 1e-3 <= exact <= sampled + 1e-9
        for thr in (exact - 1e-4, exact + 1e-4, float(rng.normal())):
            assert fl.planes_ok([Plane(tuple(point.tolist()), tuple(normal.tolist()), thr)]) == (exact >= thr)
    assert {Feasibility.FEASIBLE, Feasibility.INFEASIBLE} <= seen
