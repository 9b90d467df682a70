"""TRPO fine-tuning of the imitation policy in `CrossGap-v0` (sb3-contrib's TRPO), its evaluation on
held-out crossings and its export as ``e2e_rl.onnx``.

Hyperparameters are `RLConfig`, documented field by field; `hil train rl` runs `train_rl`.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sb3_contrib import TRPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnvWrapper

from hil.rl.env import REWARD_TERMS, CrossGapCore, CrossGapVecEnv, EnvConfig
from hil.rl.link_observe import LinkModel
from hil.rl.policy import ImitationInitPolicy, imitation_policy
from hil.rl.scenarios import CrossingPool, draw_crossings
from policies.learning.export import EXPORT_DTYPES, EXPORT_HIDDEN, N_INPUTS, export_onnx


@dataclass(frozen=True)
class RLConfig:
    """TRPO's settings, started from the paper's release (OpenAI baselines' TRPO: about 10,000 steps a
    batch, a very small KL bound) and chosen so that an update takes seconds on a 2-core CPU."""

    #: vehicles flown at once; with ``n_steps`` each, 64 x 160 = 10,240 control steps a batch (the
    #: release's 10,000), a batch holding about 37 whole episodes (an episode is 220-300 steps)
    n_envs: int = 64
    n_steps: int = 160
    #: the KL bound of each update: small, so that the fine-tuning stays near the imitation policy (which
    #: already crosses); 0.01 (baselines' MuJoCo setting) rather than the release's 0.001, since with the
    #: small initial std a KL of 0.001 moves the mean action by about 0.05 std (0.001 rad) an update
    target_kl: float = 0.01
    gamma: float = 0.99  # discount per 10 ms step (a 1 s horizon: the approach's last part and the crossing)
    gae_lambda: float = 0.95
    cg_max_steps: int = 10  # conjugate-gradient iterations (baselines: 10)
    cg_damping: float = 0.1
    line_search_max_iter: int = 10
    #: the actor's natural gradient is taken on every 4th sample (2,560 a batch): the conjugate gradient
    #: through the 100-wide planner dominates an update's time
    sub_sampling_factor: int = 4
    critic_lr: float = 1e-3
    n_critic_updates: int = 10
    critic_batch: int = 1024
    critic_hidden: tuple[int, ...] = (256, 256)
    #: initial log standard deviations of roll, pitch (rad) and thrust (N): std 0.018 rad and 0.14 N,
    #: small beside the commands' own motion, so that the first rollouts fly as the imitation policy does
    log_std_init: tuple[float, float, float] = (-4.0, -4.0, -2.0)
    #: TRPO steps the controller network's weights and the log-stds; the planner part (its imitation
    #: target, the minimum-jerk primitive, is exact) stays as imitated: a fifth of the actor's parameters,
    #: several times faster updates
    train_planner: bool = False
    #: the paper's reward (5e5 on arrival, -1e6 on a collision) times this before TRPO sees it (scaling
    #: changes no optimum; it keeps the critic's targets near unit size). Logs show the unscaled reward.
    reward_scale: float = 1e-4
    #: crossings drawn for training (each episode picks one) and held out for evaluation (each flown once)
    pool_size: int = 256
    eval_size: int = 256
    eval_seed_offset: int = 1_000_003
    #: when the environment checks the world (`EnvConfig.world_check`), in training and in the held-out
    #: evaluation: "control", once a control step, or "physics", after every physics step as the runner does
    world_check: str = "control"
    #: what the policy observes, in training and in the held-out evaluation (`EnvConfig.link`): "state",
    #: the true state, or "link", the onboard filter's estimate from the mocap frames through the radio
    observe: str = "state"
    threads: int = 2  # torch CPU threads
    checkpoint_every: int = 10  # updates


@dataclass
class EvalResult:
    """Deterministic flights of a policy over a pool's crossings, each once."""

    success_rate: float
    arrival_rate: float
    mean_return: float
    mean_terms: dict[str, float]
    mean_angular_rate_rad_s: float
    mean_thrust_n: float
    episodes: int
    per_crossing_success: list[bool] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("per_crossing_success")
        return d


def evaluate(predict: Any, pool: CrossingPool, config: EnvConfig | None = None) -> EvalResult:
    """Fly each crossing of ``pool`` once with ``predict`` (observations (N, 29) float32 -> actions (N, 3));
    the mean angular rate and thrust are over the approach and traverse of every episode."""
    core = CrossGapCore(len(pool), config, pool)
    core.reset_rows(np.arange(len(pool)), np.arange(len(pool)))
    done = np.zeros(core.n, bool)
    ret, terms = np.zeros(core.n), np.zeros((core.n, len(REWARD_TERMS)))
    success, arrived = np.zeros(core.n, bool), np.zeros(core.n, bool)
    rate_sum, thrust_sum, count = np.zeros(core.n), np.zeros(core.n), np.zeros(core.n)
    x, _, _ = core.physics.kernel_arrays
    while not done.all():
        reward, terminated, truncated, t, s = core.step(predict(core.observations()))
        live = ~done
        ret[live] += reward[live]
        terms[live] += t[live]
        rate_sum[live] += np.linalg.norm(x[live, 10:13], axis=1)
        thrust_sum[live] += core._targets[live, 3]
        count[live] += 1
        end = live & (terminated | truncated)
        success[end], arrived[end] = s[end], core.arrived[end]
        done |= end
    return EvalResult(float(success.mean()), float(arrived.mean()), float(ret.mean()),
                      dict(zip(REWARD_TERMS, terms.mean(0).tolist(), strict=True)),
                      float((rate_sum / count).mean()), float((thrust_sum / count).mean()), core.n,
                      success.tolist())


def torch_predict(module: torch.nn.Module) -> Any:
    """``predict`` of a torch policy module (no gradient, float32)."""
    def predict(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return module(torch.as_tensor(obs)).numpy().astype(np.float64)
    return predict


class _ScaledReward(VecEnvWrapper):
    """The env's rewards times a constant (infos, and so the logged returns, stay unscaled)."""

    def __init__(self, venv: CrossGapVecEnv, scale: float) -> None:
        super().__init__(venv)
        self.scale = scale

    def reset(self) -> np.ndarray:
        return self.venv.reset()

    def step_wait(self) -> Any:
        obs, reward, done, infos = self.venv.step_wait()
        return obs, reward * self.scale, done, infos


class _Progress(BaseCallback):
    """Per update: a CSV row (returns, success, each reward term), checkpoints, the progress line, and
    the budget: the wall clock, and ``max_updates`` (None: no limit) updates in all."""

    def __init__(self, out: Path, deadline_s: float, every: int, progress: bool, start_update: int,
                 max_updates: int | None = None) -> None:
        super().__init__()
        self.out, self.deadline_s, self.every, self.progress = out, deadline_s, every, progress
        self.update = start_update
        self.max_updates = max_updates
        self.episodes: list[dict[str, Any]] = []
        self.started = time.perf_counter()
        self.bar = None
        if progress:
            from tqdm import tqdm

            total = max(0.0, deadline_s - self.started)
            self.bar = tqdm(total=round(total), unit="s", desc="hil train rl", leave=False)
        self.csv_path = out / "returns.csv"
        if not self.csv_path.exists():
            with self.csv_path.open("w", newline="") as f:
                csv.writer(f).writerow(["update", "timesteps", "wall_s", "episodes", "mean_return",
                                        "success_rate", "arrival_rate", *REWARD_TERMS])

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                self.episodes.append(info)
        if self.max_updates is not None and self.update >= self.max_updates:
            return False  # (the rollout after the last update is dropped at its first step)
        return time.perf_counter() < self.deadline_s

    def _on_rollout_end(self) -> None:
        eps, self.episodes = self.episodes, []
        self.update += 1
        if eps:
            row = [self.update, self.num_timesteps, round(time.perf_counter() - self.started, 1), len(eps),
                   np.mean([e["episode"]["r"] for e in eps]), np.mean([e["success"] for e in eps]),
                   np.mean([e["arrived"] for e in eps]),
                   *[np.mean([e["reward_terms"][k] for e in eps]) for k in REWARD_TERMS]]
            with self.csv_path.open("a", newline="") as f:
                csv.writer(f).writerow(row)
            if self.bar is not None:
                self.bar.n = min(self.bar.total, round(time.perf_counter() - self.started))
                self.bar.set_postfix_str(f"update {self.update}, return {row[4]:.4g}, success {row[5]:.2f}")
                self.bar.write(f"update {self.update}: {self.num_timesteps} steps, return {row[4]:.4g}, "
                               f"success {row[5]:.2f}, angular acceleration term {row[10]:.4g}")
        if self.update % self.every == 0:
            self.model.save(self.out / "checkpoint.zip")


def make_model(env: Any, cfg: RLConfig, seed: int, device: str) -> TRPO:
    policy_kwargs = {"log_std_init_per_action": cfg.log_std_init, "critic_hidden": cfg.critic_hidden,
                     "train_planner": cfg.train_planner}
    return TRPO(ImitationInitPolicy, env, learning_rate=cfg.critic_lr, n_steps=cfg.n_steps,
                batch_size=cfg.critic_batch, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda,
                cg_max_steps=cfg.cg_max_steps, cg_damping=cfg.cg_damping,
                line_search_max_iter=cfg.line_search_max_iter, n_critic_updates=cfg.n_critic_updates,
                target_kl=cfg.target_kl, sub_sampling_factor=cfg.sub_sampling_factor,
                policy_kwargs=policy_kwargs, seed=seed, device=device, verbose=0)


def device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def train_rl(out_dir: str | Path, minutes: float, seed: int = 0, resume: bool = False,
             cfg: RLConfig | None = None, n_envs: int | None = None, progress: bool = True,
             updates: int | None = None) -> dict[str, Any]:
    """Fine-tune for ``minutes`` of wall clock or ``updates`` TRPO updates in all (None: no limit),
    whichever ends first; writes into ``out_dir``: checkpoint.zip, returns.csv, curve.png, e2e_rl.pt (the
    actor's state dict), e2e_rl.onnx and metrics.json (held-out evaluation of the imitation policy and
    the fine-tuned one). Returns the metrics. A number of updates is the budget that gives the same
    weights on any machine (the seed fixes the crossings, the rollouts and TRPO's samples); minutes
    give as many updates as the machine manages."""
    cfg = cfg or RLConfig()
    if not (math.isfinite(minutes) and minutes > 0):
        raise ValueError(f"minutes must be positive, got {minutes}")
    if cfg.world_check not in ("control", "physics"):
        raise ValueError(f"world_check must be 'control' or 'physics', got {cfg.world_check!r}")
    if cfg.observe not in ("state", "link"):
        raise ValueError(f"observe must be 'state' or 'link', got {cfg.observe!r}")
    if updates is not None and (isinstance(updates, bool) or not isinstance(updates, int) or updates < 1):
        raise ValueError(f"updates must be a whole number >= 1, got {updates!r}")
    if n_envs is not None:
        if n_envs < 1:
            raise ValueError(f"--envs must be >= 1, got {n_envs}")
        cfg = RLConfig(**{**asdict(cfg), "n_envs": n_envs, "n_steps": max(1, math.ceil(10_240 / n_envs))})
    torch.set_num_threads(cfg.threads)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    env_cfg = EnvConfig(pool_size=cfg.pool_size, seed=seed, world_check=cfg.world_check,
                        link=LinkModel() if cfg.observe == "link" else None)
    venv = CrossGapVecEnv(cfg.n_envs, env_cfg)
    env = _ScaledReward(venv, cfg.reward_scale)
    ckpt = out / "checkpoint.zip"
    start_update = 0
    if resume and ckpt.exists():
        model = TRPO.load(ckpt, env=env, device=device())
        start_update = model.num_timesteps // (cfg.n_envs * cfg.n_steps)
    else:
        model = make_model(env, cfg, seed, device())
    deadline = time.perf_counter() + minutes * 60.0
    callback = _Progress(out, deadline, cfg.checkpoint_every, progress, start_update, updates)
    if progress:
        budget = f"{minutes:g} min" + ("" if updates is None else f" or {updates} updates in all")
        print(f"hil train rl: device {device()}, {cfg.n_envs} envs x {cfg.n_steps} steps a batch, "
              f"{budget}, out {out}", flush=True)
    model.learn(total_timesteps=10**12, callback=callback, reset_num_timesteps=not resume)
    if callback.bar is not None:
        callback.bar.close()
    train_s = time.perf_counter() - t0
    model.save(ckpt)
    actor = model.policy.actor_module().cpu().eval()
    torch.save(actor.state_dict(), out / "e2e_rl.pt")
    onnx_path = export_onnx(actor, N_INPUTS["e2e"], out / "e2e_rl.onnx", EXPORT_DTYPES["e2e"],
                            hidden_dtype=EXPORT_HIDDEN["e2e"])
    held_out = CrossingPool(draw_crossings(cfg.eval_size, np.random.default_rng(seed + cfg.eval_seed_offset),
                                           env_cfg.ranges), venv.core.profile, env_cfg.dt_s, env_cfg.lead_s)
    before = evaluate(torch_predict(imitation_policy().eval()), held_out, env_cfg)
    after = evaluate(torch_predict(actor), held_out, env_cfg)
    metrics = {"config": asdict(cfg), "seed": seed, "updates": callback.update,
               "timesteps": int(model.num_timesteps),
               "train_minutes": round(train_s / 60.0, 2), "device": device(),
               "held_out": {"crossings": cfg.eval_size, "imitation": before.to_dict(), "rl": after.to_dict()}}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    plot_curve(out / "returns.csv", out / "curve.png")
    metrics["onnx"] = str(onnx_path)
    return metrics


def plot_curve(csv_path: Path, png_path: Path) -> None:
    """curve.png: the mean episode return and each penalty term per update."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(csv_path.open()))
    if not rows:
        return
    steps = np.array([float(r["timesteps"]) for r in rows])
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    axes[0].plot(steps, [float(r["mean_return"]) for r in rows])
    axes[0].set(xlabel="control steps", ylabel="mean episode return", title="return (paper's reward)")
    for k in ("rate", "angular_acceleration", "jerk"):
        axes[1].plot(steps, [float(r[k]) for r in rows], label=k)
    axes[1].set(xlabel="control steps", ylabel="episode sum", title="penalty terms")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)
