"""The TRPO actor is the imitation policy before its first update (normalisation and planner included),
with small log-stds and a critic of its own; an update moves the controller within the KL bound and
holds the planner; `hil train rl` writes its outputs, resumes, and refuses bad input."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from hil.cli import main as hil_main
from hil.rl.env import REWARD_TERMS, CrossGapCore, CrossGapVecEnv, EnvConfig
from hil.rl.policy import imitation_policy
from hil.rl.train import RLConfig, make_model, train_rl
from policies.learning.onnx_runtime import load_shipped

SMALL = EnvConfig(pool_size=4, seed=5)


@pytest.fixture(scope="module")
def pool():
    return CrossGapCore(1, SMALL).pool


def _observations(pool, n=16, steps=40):
    core = CrossGapCore(n, SMALL, pool)
    model = load_shipped("e2e")
    seen = []
    for _ in range(steps):
        obs = core.observations()
        seen.append(obs)
        core.step(model.run(obs.astype(np.float64)))
    return np.concatenate(seen)


def test_actor_mean_is_the_imitation_policy_before_the_first_update(pool):
    env = CrossGapVecEnv(4, SMALL, pool)
    cfg = RLConfig()
    model = make_model(env, cfg, seed=0, device="cpu")
    obs = _observations(pool)
    mean, _ = model.predict(obs, deterministic=True)
    with torch.no_grad():
        want = imitation_policy()(torch.as_tensor(obs)).numpy()
    np.testing.assert_array_equal(mean, np.clip(want, env.action_space.low, env.action_space.high))
    # and the shipped e2e network (what the e2e pilot flies) agrees with it
    np.testing.assert_allclose(mean, load_shipped("e2e").run(obs.astype(np.float64)), atol=2e-4)
    np.testing.assert_allclose(model.policy.log_std.detach().numpy(), cfg.log_std_init)
    actor = {id(p) for p in model.policy.mlp_extractor.actor.parameters()}
    critic = {id(p) for p in model.policy.mlp_extractor.value_mlp.parameters()}
    assert not actor & critic and critic


def test_an_update_moves_the_controller_within_the_kl_bound_and_holds_the_planner(pool):
    torch.manual_seed(0)
    env = CrossGapVecEnv(4, SMALL, pool)
    cfg = RLConfig(n_steps=64, critic_batch=64, sub_sampling_factor=1, n_critic_updates=2, target_kl=0.01)
    model = make_model(env, cfg, seed=0, device="cpu")
    actor = model.policy.mlp_extractor.actor
    planner0 = [p.detach().clone() for p in actor.planner.parameters()]
    controller0 = [p.detach().clone() for p in actor.controller.parameters()]
    model.learn(total_timesteps=4 * 64)
    assert all(torch.equal(a, b) for a, b in zip(planner0, actor.planner.parameters(), strict=True))
    pairs = zip(controller0, actor.controller.parameters(), strict=True)
    moved = max(float((a - b).detach().abs().max()) for a, b in pairs)
    assert moved > 0
    obs = torch.as_tensor(_observations(pool, n=4, steps=20))
    with torch.no_grad():
        before = imitation_policy()(obs)
        after = actor(obs)
    std = model.policy.log_std.exp().detach()
    kl = (((after - before) / std) ** 2).sum(-1).mean() / 2  # KL of equal-std Gaussians, over these states
    assert kl < 20 * cfg.target_kl  # near the bound TRPO kept on its own batch


def test_train_rl_refuses_bad_input(tmp_path, capsys):
    assert hil_main(["train", "rl", "--minutes", "0", "--out", str(tmp_path)]) == 1
    assert "minutes must be positive" in capsys.readouterr().err
    assert hil_main(["train", "rl", "--minutes", "1", "--envs", "0", "--out", str(tmp_path)]) == 1
    assert hil_main(["train", "rl", "--updates", "0", "--out", str(tmp_path)]) == 1
    assert "updates must be a whole number >= 1, got 0" in capsys.readouterr().err


@pytest.mark.slow
def test_a_number_of_updates_gives_the_same_weights_whatever_the_clock(tmp_path):
    """The budget in updates stops after that many, however much time is left, and two trainings with the
    same seed end with the same weights, file for file (on one machine: between instruction sets torch's
    kernels round differently)."""
    cfg = RLConfig(n_envs=4, n_steps=40, critic_batch=40, sub_sampling_factor=2, n_critic_updates=1,
                   pool_size=4, eval_size=2, checkpoint_every=1)
    runs = [train_rl(tmp_path / name, 30.0, seed=3, cfg=cfg, progress=False, updates=2) for name in "ab"]
    for m in runs:
        assert m["updates"] == 2 and m["timesteps"] <= 2 * 4 * 40 + 4  # (the third rollout's first step)
        assert m["train_minutes"] < 5
    assert (tmp_path / "a" / "e2e_rl.onnx").read_bytes() == (tmp_path / "b" / "e2e_rl.onnx").read_bytes()
    judged = train_rl(tmp_path / "c", 30.0, seed=3, cfg=replace(cfg, world_check="physics"), progress=False,
                      updates=1)  # trained and evaluated with the world checked as the runner checks it
    assert judged["config"]["world_check"] == "physics" and judged["updates"] == 1
    with pytest.raises(ValueError, match="world_check must be 'control' or 'physics'"):
        train_rl(tmp_path / "d", 1.0, cfg=replace(cfg, world_check="sometimes"), progress=False, updates=1)
    linked = train_rl(tmp_path / "e", 30.0, seed=3, cfg=replace(cfg, observe="link"), progress=False,
                      updates=1)  # trained and evaluated observing through the link model
    assert linked["config"]["observe"] == "link" and linked["held_out"]["crossings"] == 2
    with pytest.raises(ValueError, match="observe must be 'state' or 'link'"):
        train_rl(tmp_path / "f", 1.0, cfg=replace(cfg, observe="mocap"), progress=False, updates=1)


@pytest.mark.slow
def test_train_rl_writes_its_outputs_and_resumes(tmp_path):
    cfg = RLConfig(n_envs=4, n_steps=80, critic_batch=80, sub_sampling_factor=2, n_critic_updates=1,
                   pool_size=4, eval_size=3, checkpoint_every=1)
    first = train_rl(tmp_path, 0.01, seed=1, cfg=cfg, progress=False)  # one update, then the budget is spent
    for name in ("checkpoint.zip", "returns.csv", "e2e_rl.pt", "e2e_rl.onnx", "metrics.json"):
        assert (tmp_path / name).exists(), name
    assert first["held_out"]["crossings"] == 3
    assert set(first["held_out"]["rl"]["mean_terms"]) == set(REWARD_TERMS)
    again = train_rl(tmp_path, 0.01, seed=1, cfg=cfg, resume=True, progress=False)
    assert again["timesteps"] > first["timesteps"]  # went on from the checkpoint
