"""Fine-tuning that can learn (`hil.rl.fine_tune`, `RLConfig.fine_tune`): the expert's steps are left out
of the update (and only they), the critic is fitted on imitation roll-outs until its explained variance
on a fresh batch reaches the target before the policy moves, and the methods and their deviations are
named."""

from __future__ import annotations

from dataclasses import fields, replace

import numba
import numpy as np
import pytest
import torch

from hil.rl.env import CrossGapCore, CrossGapVecEnv, EnvConfig
from hil.rl.fine_tune import MaskedRolloutBuffer
from hil.rl.scenarios import CrossingRanges, draw_crossings
from hil.rl.train import (
    DEVIATIONS,
    METHODS,
    STEEP_FAST,
    RLConfig,
    _Progress,
    _ScaledReward,
    make_model,
    selection_crossings,
)
from policies.onboard.program import ProgramConfig

SMALL = EnvConfig(pool_size=4, seed=5)


@pytest.fixture(scope="module")
def pool():
    return CrossGapCore(1, SMALL).pool


def _model(pool, tmp_path, cfg: RLConfig, n_envs: int):
    env = CrossGapVecEnv(n_envs, SMALL, pool)
    model = make_model(_ScaledReward(env, cfg.reward_scale), cfg, seed=0, device="cpu")
    progress = _Progress(tmp_path, float("inf"), 10**6, False, 0, core=env.core)
    model.progress_callback = progress
    return model, env, progress


def test_the_expert_steps_and_only_they_are_left_out_of_the_update(pool, tmp_path):
    cfg = replace(RLConfig(), n_steps=300, mask_expert_steps=True, critic_batch=256, n_critic_updates=1)
    model, _env, progress = _model(pool, tmp_path, cfg, 4)
    model.learn(total_timesteps=4 * 300, callback=progress)
    buf = model.rollout_buffer
    assert isinstance(buf, MaskedRolloutBuffer)
    active = buf.active_flat()
    obs = buf.observations  # flattened env by env, as the update read them
    # each step's crossing from its planner inputs, and whether the expert flew it: mission time + lead
    # (input 12) at or past the crossing's approach time
    which = [int(np.argmin(np.abs(pool.x17[:, 1:] - o[13:]).sum(1))) for o in obs]
    expert = obs[:, 12] >= pool.t_approach_s[which] - 1e-6
    np.testing.assert_array_equal(active, ~expert)
    assert 0.03 < expert.mean() < 0.3  # the traverse: a small part of each episode
    (everything,) = list(buf.get(None))
    assert len(everything.observations) == active.sum()
    served = {tuple(o) for o in everything.observations.numpy()}
    assert served == {tuple(o) for o in obs[active]}


@pytest.fixture
def one_thread():
    """torch and numba on one thread each (on a shared host two threads a parallel region wait for each
    other), restored after."""
    threads, parallel = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
    numba.set_num_threads(parallel)


def test_the_critic_is_fitted_before_the_policy_moves(pool, tmp_path, one_thread):
    torch.manual_seed(0)
    cfg = replace(RLConfig(), n_steps=300, mask_expert_steps=True, critic_pretrain_ev=0.8,
                  critic_pretrain_max_batches=4, critic_pretrain_epochs=100, critic_pretrain_batch=256,
                  critic_batch=128, target_kl=1e-3)
    model, _env, progress = _model(pool, tmp_path, cfg, 8)
    actor = model.policy.actor_module()
    start = [p.detach().clone() for p in actor.controller.parameters()]
    updates = 0
    while not model.critic_ready:
        model.learn(total_timesteps=8 * 300, callback=progress, reset_num_timesteps=False)
        updates += 1
        if not model.critic_ready:  # a critic-only batch: the policy has not moved
            assert all(torch.equal(a, b) for a, b in zip(start, actor.controller.parameters(), strict=True))
    print("critic explained variance per batch, before fitting on it:", model.critic_evs)
    assert model.critic_batches >= 1 and model.critic_evs[0] < 0.8  # the critic began untrained
    assert model.critic_evs[-1] >= 0.8  # reached on a batch it had not been fitted on
    assert updates == model.critic_batches + 1
    moved = max(float((a - b).abs().max()) for a, b in zip(start, actor.controller.parameters(), strict=True))
    assert moved > 0  # the first policy update came with the batch that showed the target met
    rows = (tmp_path / "returns.csv").read_text().splitlines()
    assert rows[0].endswith("explained_variance,critic_only") and rows[-1].endswith(",0")
    assert all(r.endswith(",1") for r in rows[1:-1])


def test_methods_and_deviations_are_named():
    release, tuned = METHODS["release"](), METHODS["fine_tune"]()
    assert release == RLConfig()
    assert (release.gae_lambda, release.cg_damping, release.target_kl) == (1.0, 0.01, 1e-7)
    assert release.sub_sampling_factor == 1 and not release.mask_expert_steps
    assert release.critic_pretrain_ev is None
    changed = {f.name for f in fields(RLConfig) if getattr(release, f.name) != getattr(tuned, f.name)}
    assert changed <= set(DEVIATIONS)  # every change of fine_tune is a listed deviation, with its reason
    assert {"mask_expert_steps", "critic_pretrain_ev"} <= changed


def test_the_selection_holds_the_steepest_and_fastest_crossings():
    tuned = replace(RLConfig.fine_tune(), select_size=3, select_extra_size=2)
    assert tuned.select_extra == STEEP_FAST and tuned.world_check == "physics"  # trained as judged
    chosen = selection_crossings(tuned, 0, CrossingRanges())
    assert len(chosen) == 3 + 2 * len(STEEP_FAST)
    for i, ranges in enumerate(STEEP_FAST):
        for c in chosen[3 + 2 * i: 5 + 2 * i]:
            assert ranges.roll_deg[0] <= c.roll_deg <= ranges.roll_deg[1] and c.speed_m_s in ranges.speeds_m_s
            assert c.plan.gap.height_m == (ranges.gap_height_m or ProgramConfig().gap_height_m)
    again = selection_crossings(tuned, 0, CrossingRanges())
    assert [c.gap_centre_m for c in again] == [c.gap_centre_m for c in chosen]  # seeded
    held_out = draw_crossings(3, np.random.default_rng(tuned.eval_seed_offset), CrossingRanges())
    assert not {c.gap_centre_m for c in held_out} & {c.gap_centre_m for c in chosen}  # none evaluated on
