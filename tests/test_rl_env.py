"""`CrossGap-v0`: registered, a one-vehicle view passes gymnasium's and SB3's checks, the batch sees what
the `e2e` pilot sees and commands the FC as the link does, the imitation policy crosses in it, the reward
terms are the release's (and the paper's on its switch), a collision ends an episode with its
penalty, and crossings are seeded."""

from __future__ import annotations

import math
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from emulator.mocap import MocapConfig, measured_pose
from emulator.uwb import UwbConfig
from hil.link.mavlink import euler_from_quat, quat_enu_flu_to_ned_frd_tuple, quat_from_euler_tuple
from hil.rl import ENV_ID
from hil.rl.env import REWARD_TERMS, CrossGapCore, CrossGapEnv, CrossGapVecEnv, EnvConfig, RewardWeights
from hil.rl.link_observe import QUEUE, LinkModel
from hil.rl.reward import pack_weights, score_rows
from hil.rl.scenarios import CrossingPool, CrossingRanges, draw_crossings
from policies.learning.learned_pilots import EndToEndPilot
from policies.learning.onnx_runtime import load_shipped
from policies.onboard.estimator import PoseEstimator
from policies.onboard.pilots import Observation

SMALL = EnvConfig(pool_size=6, seed=3)


@pytest.fixture(scope="module")
def pool() -> CrossingPool:
    core = CrossGapCore(1, SMALL)
    return core.pool


def test_registered_and_one_vehicle_view_passes_the_checkers(pool):
    env = gym.make(ENV_ID, config=SMALL, pool=pool)
    assert isinstance(env.unwrapped, CrossGapEnv)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(CrossGapEnv(SMALL, pool), warn=False)


def test_observation_is_what_the_e2e_pilot_builds(pool):
    core = CrossGapCore(3, SMALL, pool)
    core.reset_rows(np.arange(3), np.array([0, 1, 2]))
    rng = np.random.default_rng(0)
    for _ in range(30):  # fly a little, with some tilt, so that the state is no hover
        core.step(np.column_stack([rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3), np.full(3, 9.5)]))
    x, aux, _ = core.physics.kernel_arrays
    pilot = EndToEndPilot(model=object())  # no network needed to build inputs
    h = SMALL.lead_s
    for i in range(3):
        plan = pool.crossings[core.which[i]].plan
        pos, vel, acc = x[i, 0:3], x[i, 3:6], aux[i, 3:6]
        pred = pos + vel * h + acc * (0.5 * h * h)
        obs = Observation(core.tick[i] * SMALL.dt_s + h, pred, vel + acc * h, acc,
                          np.array(euler_from_quat(x[i, 6:10])), plan.gap, plan)
        # the same functions on the same state: the same inputs to the bit (the environment compiles the
        # pilot's own arithmetic)
        np.testing.assert_array_equal(core._obs[i], pilot.inputs(obs))


def test_command_reaches_the_fc_as_through_the_link(pool):
    # the FC's NED target is what SET_ATTITUDE_TARGET's quaternion of the ENU command reads as
    core = CrossGapCore(1, SMALL, pool)
    yaw = float(pool.yaw_rad[core.which[0]])
    core.step(np.array([[0.3, -0.2, 9.0]]))
    q = quat_enu_flu_to_ned_frd_tuple(*quat_from_euler_tuple(0.3, -0.2, yaw))
    roll, pitch, yaw_ned = euler_from_quat(np.array(q))
    np.testing.assert_allclose(core._targets[0, :3], [roll, pitch, yaw_ned], atol=1e-9)
    assert core._targets[0, 3] == pytest.approx(9.0)  # thrust (N) for the 0.9 kg vehicle


def test_tilt_and_thrust_are_limited_as_the_fc_does(pool):
    core = CrossGapCore(1, SMALL, pool)
    core.step(np.array([[1.5, 0.5, 100.0]]))
    roll, pitch = core._targets[0, 0], core._targets[0, 1]
    tilt = math.degrees(math.acos(math.cos(roll) * math.cos(pitch)))
    assert tilt == pytest.approx(core.profile.max_tilt_deg, abs=1e-6)
    assert core._targets[0, 3] == core.profile.n3_full_thrust_n
    with pytest.raises(ValueError, match="finite"):
        core.step(np.array([[np.nan, 0.0, 9.0]]))
    with pytest.raises(ValueError, match="shape"):
        core.step(np.zeros((2, 3)))


def test_imitation_policy_crosses_and_reward_terms_are_the_releases(pool):
    model = load_shipped("e2e")
    env = CrossGapVecEnv(len(pool), SMALL, pool)
    obs = env.reset()
    ends = {}
    for _ in range(400):
        obs, _, done, infos = env.step(model.run(obs.astype(np.float64)))
        for i in np.flatnonzero(done):
            ends.setdefault(i, infos[i])
        if len(ends) == env.num_envs:
            break
    assert len(ends) == env.num_envs
    for info in ends.values():
        terms = info["reward_terms"]
        assert set(terms) == set(REWARD_TERMS)
        assert info["success"] and info["arrived"] and info["TimeLimit.truncated"]
        assert terms["arrival"] == 5e5 and terms["collision"] == 0.0
        assert 0 < terms["position"] < 1000 * 0.2 * info["episode"]["l"]  # per step, unscaled
        # the release's offsets: 2 x 57.3 x (2 - |w|) x 2 a step, positive while |w| < 2 rad/s
        assert 0 < terms["rate"] < 2 * 57.3 * 2 * 2 * info["episode"]["l"]
        assert terms["angular_acceleration"] < 10 * 57.3 * 2 * 2 * info["episode"]["l"] and terms["jerk"] < 0
        assert info["episode"]["r"] == pytest.approx(sum(terms.values()), rel=1e-4)
        assert info["terminal_observation"].shape == (29,)


def _fall(env: CrossGapEnv) -> tuple[float, bool, bool, dict]:
    """Fly with no thrust until the episode ends (it falls to the floor); the last step's results."""
    env.reset(seed=0)
    for _ in range(300):
        _, reward, terminated, truncated, info = env.step(np.array([0.0, 0.0, 0.0], np.float32))
        if terminated or truncated:
            break
    return reward, terminated, truncated, info


def test_a_collision_terminates_with_the_penalty(pool):
    reward, terminated, truncated, info = _fall(CrossGapEnv(SMALL, pool))
    assert terminated and not truncated
    assert info["reward_terms"]["collision"] == -1e6 and reward < -0.99e6
    assert not info["success"]


def _score(weights: RewardWeights, w: tuple, dw: tuple, da: tuple, collided: bool = False,
           last: bool = False) -> np.ndarray:
    """One row scored after a control step of 10 ms: body rates ``w`` (rad/s) changed by ``dw`` and the
    acceleration by ``da`` (m/s^2) over the step, 1 m from the gap centre."""
    x = np.zeros((1, 17))
    x[0, 10:13] = w
    aux = np.zeros((1, 9))
    aux[0, 3:6] = da
    terms, reward = np.zeros((1, 6)), np.zeros(1)
    flags = [np.zeros(1, bool) for _ in range(4)]
    score_rows(x, aux, pack_weights(weights, 0.01), np.array([[1.0, 0.0, 0.0]]), np.array([[1.0, 0, 0]]),
               np.array([5 if last else 1]), np.array([5]), np.array([1 if collided else 0]), flags[0],
               np.array([np.subtract(w, dw)]), np.zeros((1, 3)), terms, reward, *flags[1:])
    assert reward[0] == pytest.approx(terms.sum())
    return terms[0]


def test_the_releases_reward_form_and_the_papers():
    """The release: 2 x 57.3 x (2 - |w|) and 10 x 57.3 x (2 - |alpha|) (alpha = dw/dt, rad/s^2) and
    -10 |a_t - a_(t-1)|, each x dt / 0.005; a collision's step pays -1e6 alone; the last step 0. The
    paper: -(2 x 57.3 |w| + 5 x 57.3 |dw/dt| + 10 |da/dt|) dt, a collision adds -1e9."""
    release, paper = RewardWeights(), RewardWeights.paper()
    t = _score(release, (0.3, 0.4, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 2.0))
    k = 0.01 / 0.005
    assert t[2] == pytest.approx(2 * 57.3 * (2 - 0.5) * k)
    assert t[3] == pytest.approx(10 * 57.3 * (2 - 5.0) * k)
    assert t[4] == pytest.approx(-10 * 2.0 * k) and t[0] == t[1] == t[5] == 0.0
    p = _score(paper, (0.3, 0.4, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 2.0))
    assert p[2] == pytest.approx(-2 * 57.3 * 0.5 * 0.01)
    assert p[3] == pytest.approx(-5 * 57.3 * 5.0 * 0.01) and p[4] == pytest.approx(-10 * 200.0 * 0.01)
    assert _score(release, (0.3, 0.4, 0.0), (0, 0, 0), (0, 0, 0), collided=True).tolist() == [0] * 5 + [-1e6]
    hit = _score(paper, (0.3, 0.4, 0.0), (0, 0, 0), (0, 0, 0), collided=True)
    assert hit[5] == -1e9 and hit[2] < 0
    assert _score(release, (0.3, 0.4, 0.0), (0, 0, 0), (0, 0, 0), last=True).tolist() == [0] * 6
    assert _score(paper, (0.3, 0.4, 0.0), (0, 0, 0), (0, 0, 0), last=True)[2] < 0


def test_crossings_are_seeded_and_vary():
    a = draw_crossings(5, np.random.default_rng(7))
    b = draw_crossings(5, np.random.default_rng(7))
    assert [c.gap_centre_m for c in a] == [c.gap_centre_m for c in b]
    assert len({c.roll_deg for c in a}) == 5
    env = CrossGapEnv(SMALL, CrossGapCore(1, SMALL).pool)
    picks = [env.reset(seed=s)[1]["crossing"] for s in (1, 1, 2, 3, 4, 5)]
    assert picks[0] == picks[1] and len(set(picks)) > 1


def test_crossings_through_a_smaller_opening_past_the_papers_envelope():
    steep = CrossingRanges(roll_deg=(60.0, 70.0), speeds_m_s=(4.0,), gap_height_m=0.65)
    drawn = draw_crossings(3, np.random.default_rng(3), steep)
    assert all(c.plan.gap.height_m == 0.65 and c.speed_m_s == 4.0 and 60 <= c.roll_deg <= 70 for c in drawn)
    with pytest.raises(RuntimeError, match="no plannable crossing"):  # none at 4 m/s through 0.45 m
        draw_crossings(1, np.random.default_rng(3), replace(steep, gap_height_m=None))
    with pytest.raises(ValueError, match="gap_height_m"):
        CrossingRanges(gap_height_m=0.0)


def test_world_checked_every_physics_step_flies_the_same_and_catches_a_collision(pool):
    with pytest.raises(ValueError, match="world_check"):
        EnvConfig(world_check="sometimes")
    fine = EnvConfig(pool_size=6, seed=3, world_check="physics")
    a, b = CrossGapCore(2, SMALL, pool), CrossGapCore(2, fine, pool)
    for core in (a, b):
        core.reset_rows(np.arange(2), np.array([0, 1]))
    rng = np.random.default_rng(1)
    for _ in range(50):
        act = np.column_stack([rng.normal(0, 0.05, 2), rng.normal(0, 0.05, 2), np.full(2, 8.9)])
        ra, ta, *_ = a.step(act)
        rb, tb, *_ = b.step(act)
        assert not ta.any() and not tb.any()
    np.testing.assert_array_equal(a.physics.kernel_arrays[0], b.physics.kernel_arrays[0])
    np.testing.assert_array_equal(ra, rb)
    _, terminated, _, info = _fall(CrossGapEnv(fine, pool))
    assert terminated and info["reward_terms"]["collision"] == -1e6


def test_observation_through_the_link_is_the_onboard_programs_estimate(pool):
    """With `EnvConfig.link`, a row's inputs are what the onboard program's own filter makes of the
    frames: the pose at each of the tracker's exposures (120 Hz; between two control steps, interpolated
    from the states at their ends), rounded as LinkTrack carries it, arriving after the tracker's and the
    radio's latency, fed in order into a `PoseEstimator`, its estimate taken at the step plus the control
    lead. Rebuilt here from the row's true states with the program's classes."""
    exact = MocapConfig(pos_noise_m=0.0, att_noise_rad=0.0, processing_s=0.0)
    link = LinkModel(exact, UwbConfig(jitter_s=0.0))
    cfg = EnvConfig(pool_size=6, seed=3, link=link)
    core = CrossGapCore(2, cfg, pool)
    core.reset_rows(np.arange(2), np.array([1, 4]))
    lk = link.packed()
    delay = lk[2] + lk[4] + lk[10]  # camera + radio + air and UART time (s): no noise, no jitter here
    period = exact.period_s
    pilot = EndToEndPilot(model=object())
    x = core.physics.kernel_arrays[0]
    est = [PoseEstimator(link.estimator) for _ in range(2)]
    for i in range(2):  # settled on the hover: 100 exact frames a period apart, the last stamped -delay
        for k in range(100):
            stamp = -delay - (99 - k) * period
            est[i].update(stamp, x[i, 0:3], x[i, 6:10], stamp + delay)
    frames: list[list[tuple]] = [[], []]  # in flight: those exposed since the last one arrived
    exposure = [-delay + period] * 2
    for i in range(2):
        q = x[i, 6:10]
        m = np.array(measured_pose(*x[i, 0:3], *q, q @ q, 0.0, 0.0, 0, 0, 0, 0, 0, 0), np.float32)
        m = m.astype(float)
        while exposure[i] <= 1e-9:
            frames[i].append((round(exposure[i] * 1e6) * 1e-6, m[0:3], m[3:7], exposure[i] + delay))
            exposure[i] += period
    rng = np.random.default_rng(2)
    dt = cfg.dt_s
    for step in range(1, 60):
        before = x[:, 0:10].copy()
        core.step(np.column_stack([rng.normal(0, 0.1, 2), rng.normal(0, 0.1, 2), np.full(2, 9.4)]))
        t = step * dt
        for i in range(2):
            while exposure[i] <= t + 1e-9:
                te = exposure[i]
                exposure[i] += period
                f = min(max((te - (t - dt)) / dt, 0.0), 1.0)
                a = before[i]
                sgn = -1.0 if before[i, 6:10] @ x[i, 6:10] < 0 else 1.0
                pos = a[0:3] + f * (x[i, 0:3] - a[0:3])
                q = sgn * a[6:10] + f * (x[i, 6:10] - sgn * a[6:10])
                m = measured_pose(*pos, *q, q @ q, 0.0, 0.0, 0, 0, 0, 0, 0, 0)
                m = np.array(m, np.float32).astype(float)
                arrival = te + lk[2] + lk[4] + lk[10]  # (summed in the radio's order: the same float)
                frames[i].append((round(te * 1e6) * 1e-6, m[0:3], m[3:7], arrival))
            while frames[i] and frames[i][0][3] <= t:
                est[i].update(*frames[i].pop(0))
            e = est[i].estimate(t + cfg.lead_s)
            plan = pool.crossings[core.which[i]].plan
            obs = Observation(t + cfg.lead_s, e.pos_m, e.vel_m_s, e.acc_m_s2, e.euler_rad, plan.gap, plan)
            np.testing.assert_allclose(core._obs[i], pilot.inputs(obs), rtol=0, atol=1e-9)
    # 26.8 ms of latency at 120 Hz: three or four frames in flight
    assert core.link.q_count.tolist() == [len(frames[0]), len(frames[1])] and 3 <= len(frames[0]) <= 4
    # the same link with its noise and jitter: the inputs move off the true state's by millimetres
    noisy = CrossGapCore(2, EnvConfig(pool_size=6, seed=3, link=LinkModel()), pool)
    true = CrossGapCore(2, EnvConfig(pool_size=6, seed=3), pool)
    for c in (noisy, true):
        c.reset_rows(np.arange(2), np.array([1, 4]))
        for _ in range(40):
            c.step(np.column_stack([np.full(2, 0.05), np.full(2, -0.05), np.full(2, 9.0)]))
    d = noisy._obs[:, 0:3] - true._obs[:, 0:3]
    assert 1e-5 < np.abs(d).max() < 0.02


def test_the_link_refuses_occlusions_and_counts_what_the_radio_loses(pool):
    with pytest.raises(ValueError, match="occlusion"):
        LinkModel(MocapConfig(occlusion_prob=0.1))
    lossy = LinkModel(uwb=UwbConfig(loss_prob=0.3))
    core = CrossGapCore(64, EnvConfig(pool_size=6, seed=3, link=lossy), pool)
    core.reset_rows(np.arange(64), np.zeros(64, np.int64))
    for _ in range(50):
        core.step(np.column_stack([np.zeros(64), np.zeros(64), np.full(64, 8.83)]))
    assert core.link.lost.sum() / (64 * 60) == pytest.approx(0.3, abs=0.03)  # (60 exposures in 0.5 s)
    assert np.isfinite(core._obs).all()
    # a pose the tracker cannot see (NaN: a diverged state) sends no frame: the row's estimate ages on
    x = core.physics.kernel_arrays[0]
    x[5, 0:10] = np.nan
    for _ in range(5):  # 50 ms: the frames in flight arrive, no new one is sent
        core.tick += 1
        core._observe_link()
    assert core.link.q_count[5] == 0 and np.isfinite(core._obs[5]).all()
    # a radio slower than the queue holds (400 ms: 48 frames in flight at 120 Hz, room for 32): the frames
    # that do not fit are counted lost, and the inputs stay finite
    slow = CrossGapCore(4, EnvConfig(pool_size=6, seed=3, link=LinkModel(uwb=UwbConfig(latency_s=0.4))), pool)
    slow.reset_rows(np.arange(4), np.zeros(4, np.int64))
    for _ in range(60):
        slow.step(np.column_stack([np.zeros(4), np.zeros(4), np.full(4, 8.83)]))
    assert (slow.link.q_count >= QUEUE - 2).all() and (slow.link.lost > 0).all()
    assert np.isfinite(slow._obs).all()
