"""TRPO fine-tuning of the imitation policy in `CrossGap-v0` (sb3-contrib's TRPO), its evaluation on
held-out crossings, checkpoint selection on that evaluation, and the export as ``e2e_rl.onnx``.

Two methods (`METHODS`, `hil train rl --method`): ``release``, TRPO as the paper's release ran it (OpenAI
baselines' trpo_mpi defaults and its command line: `RLConfig()`), and ``fine_tune``, the release's
with the deviations of `DEVIATIONS` switched on (`RLConfig.fine_tune()`). Every setting is a field of
`RLConfig`; where even the release's method departs from the release, `DEVIATIONS` says so and why.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnvWrapper

from hil.report.paired import paired_difference
from hil.rl.env import REWARD_TERMS, CrossGapCore, CrossGapVecEnv, EnvConfig
from hil.rl.fine_tune import FineTuneTRPO, MaskedRolloutBuffer
from hil.rl.link_observe import LinkModel
from hil.rl.policy import ImitationInitPolicy, imitation_policy
from hil.rl.scenarios import Crossing, CrossingPool, CrossingRanges, draw_crossings
from hil.runner.over_time import time_mean
from policies.learning.export import EXPORT_DTYPES, EXPORT_HIDDEN, N_INPUTS, export_onnx

#: the steepest and fastest crossings, for the selection (`RLConfig.select_extra`): the paper's RL case's
#: roll either way at its speed, and 60-70 deg at 3-4 m/s through a 0.65 m opening, as the shipped
#: scenarios past the paper's envelope (4 m/s has no plan through the default 0.45 m opening)
STEEP_FAST: tuple[CrossingRanges, ...] = (
    CrossingRanges(roll_deg=(55.0, 65.0), speeds_m_s=(2.5, 3.0)),
    CrossingRanges(roll_deg=(-65.0, -55.0), speeds_m_s=(2.5, 3.0)),
    CrossingRanges(roll_deg=(60.0, 70.0), speeds_m_s=(3.0, 4.0), gap_height_m=0.65),
    CrossingRanges(roll_deg=(-70.0, -60.0), speeds_m_s=(3.0, 4.0), gap_height_m=0.65),
)


@dataclass(frozen=True)
class RLConfig:
    """TRPO's settings. Defaults: the release's method, baselines' trpo_mpi defaults with the release's
    command line (``--timesteps_per_batch=10000 --max_kl=0.0000001 --cg_iters=10``), except where
    `DEVIATIONS` names a field."""

    #: vehicles flown at once; with ``n_steps`` each, 64 x 160 = 10,240 control steps a batch (the
    #: release's timesteps_per_batch 10,000), about 37 whole episodes (an episode is 220-300 steps)
    n_envs: int = 64
    n_steps: int = 160
    target_kl: float = 1e-7  # the release's max_kl (baselines' default 0.001)
    gamma: float = 0.99  # baselines
    gae_lambda: float = 1.0  # baselines' lam
    cg_max_steps: int = 10  # cg_iters
    cg_damping: float = 0.01  # baselines
    line_search_max_iter: int = 10  # baselines: 10 backtracking steps,
    line_search_shrinking_factor: float = 0.5  # each halving the step
    sub_sampling_factor: int = 1  # baselines takes the natural gradient over the whole batch
    critic_lr: float = 3e-4  # baselines' vf_stepsize (Adam)
    n_critic_updates: int = 3  # baselines' vf_iters: passes over the batch
    critic_batch: int = 64  # baselines' value minibatch
    critic_hidden: tuple[int, ...] = (256, 256)  # see DEVIATIONS["critic"]
    log_std_init: tuple[float, float, float] = (-4.0, -4.0, -2.0)  # see DEVIATIONS["log_std_init"]
    train_planner: bool = False  # see DEVIATIONS["train_planner"]
    reward_scale: float = 1e-6  # see DEVIATIONS["reward_scale"]
    #: leave out of the update the steps whose action has no effect (the expert's traverse); see DEVIATIONS
    mask_expert_steps: bool = False
    #: fit the critic alone until its explained variance on a fresh batch reaches this (None: no); see
    #: DEVIATIONS
    critic_pretrain_ev: float | None = None
    critic_pretrain_epochs: int = 60
    critic_pretrain_batch: int = 256  # minibatch of the critic's own fitting (its passes are many)
    critic_pretrain_max_batches: int = 20
    #: every this many updates, fly the held-out crossings and keep the actor whose approach is smoothest
    #: against the imitation policy's, paired by crossing, without fewer successes (0: no selection,
    #: the last actor ships); see DEVIATIONS
    select_every: int = 0
    select_size: int = 32  # held-out crossings flown for the selection (from ``eval_seed_offset`` + 1)
    #: more selection crossings, ``select_extra_size`` drawn from each of these ranges (each from a seed
    #: of its own, ``eval_seed_offset`` + 2, + 3, ...): the steepest and fastest cases; see DEVIATIONS
    select_extra: tuple[CrossingRanges, ...] = ()
    select_extra_size: int = 8
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
    #: torch CPU threads: one, so that the weights do not depend on the host's cores (and on a host shared
    #: with other work two threads of every parallel region wait for each other)
    threads: int = 1
    checkpoint_every: int = 10  # updates

    @classmethod
    def release(cls) -> RLConfig:
        """The release's method (the defaults)."""
        return cls()

    @classmethod
    def fine_tune(cls) -> RLConfig:
        """The release's method with the deviations a practitioner would use (`DEVIATIONS`): expert
        steps masked, the critic fitted first (explained variance 0.8), a KL bound of 0.001 (baselines'
        default), the world checked every physics step, the actor chosen on held-out crossings that
        include the steepest and fastest."""
        return cls(mask_expert_steps=True, critic_pretrain_ev=0.8, target_kl=1e-3, select_every=2,
                   select_extra=STEEP_FAST, world_check="physics")


#: where the methods depart from the release, field -> why (the fields of `RLConfig`)
DEVIATIONS: dict[str, str] = {
    "critic": "the release's value network copied the policy network's layout (a planner and a "
              "controller, built to make commands); here an MLP (critic_hidden) on the inputs scaled to "
              "about unit spread, which predicts a return without the command structure",
    "log_std_init": "baselines starts its Gaussian at std 1 (rad, rad, N); around a 0.3 rad command that "
                    "crashes nearly every episode, so the first batches would teach nothing: std 0.018 rad "
                    "and 0.14 N, small beside the commands' own motion (the release's pretrain network's "
                    "initial std is not in its code)",
    "train_planner": "the planner part's imitation target (the minimum-jerk primitive) is exact, and the "
                     "conjugate gradient through it is four fifths of an update's time: TRPO steps the "
                     "controller network and the log-stds only (switch: train_planner)",
    "reward_scale": "the reward times 1e-6 before TRPO sees it (the release's returns are -1e6 to -3e6 an "
                    "episode, mostly its angular-acceleration term): the policy step is unchanged "
                    "(advantages are normalised per batch), the critic's targets are near unit size, which "
                    "Adam at 3e-4 can reach (at 1e-4 they were hundreds and its explained variance stayed "
                    "0 over 12 batches; switch: reward_scale = 1)",
    "world_and_time": "the release's step was the wall-clock time between AirSim calls and its angular "
                      "acceleration AirSim's own; here the 10 ms control step of simulated time and the "
                      "change of the body rates over it (deterministic, the same on any machine)",
    "mask_expert_steps": "fine_tune: steps where the expert flies the traverse (the action ignored) are "
                         "left out of the surrogate, the KL and the critic's loss; their returns still "
                         "carry the expert's outcome back to the policy's last steps",
    "critic_pretrain_ev": "fine_tune: the critic is fitted on imitation roll-outs until its explained "
                          "variance on a fresh batch reaches 0.8 before the first policy update (it began "
                          "at 0.29, so the first advantages were mostly its error)",
    "target_kl": "fine_tune: max_kl 0.001 (baselines' default) rather than the release's 1e-7, which moves "
                 "the mean action by about 1e-4 std an update",
    "select_every": "fine_tune: the actor shipped is the one whose held-out approach is smoothest against "
                    "the imitation policy's (paired by crossing, the interval below zero) with no fewer "
                    "successes, not the last one",
    "select_extra": "fine_tune: the selection's crossings include the steepest and fastest (STEEP_FAST): "
                    "drawn over the whole range they are rare, and an actor smoother on the rest grazed "
                    "the wall on them",
    "world_check": "fine_tune: the world checked after every physics step in training too (as the runner "
                   "and the selection check it): a graze shorter than a control step is a collision the "
                   "training sees (about 2x slower steps)",
}

METHODS: dict[str, Callable[[], RLConfig]] = {"release": RLConfig.release, "fine_tune": RLConfig.fine_tune}


@dataclass
class EvalResult:
    """Deterministic flights of a policy over a pool's crossings, each once. Angular rate and thrust are
    over time (`hil.runner.over_time`) on the steps the policy flew (the approach), per crossing and
    their mean."""

    success_rate: float
    arrival_rate: float
    mean_return: float
    mean_terms: dict[str, float]
    mean_angular_rate_rad_s: float
    mean_thrust_n: float
    episodes: int
    per_crossing_success: list[bool] = field(default_factory=list)
    per_crossing_rate_rad_s: list[float | None] = field(default_factory=list)
    per_crossing_thrust_n: list[float | None] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for k in ("per_crossing_success", "per_crossing_rate_rad_s", "per_crossing_thrust_n"):
            d.pop(k)
        return d


def evaluate(predict: Any, pool: CrossingPool, config: EnvConfig | None = None) -> EvalResult:
    """Fly each crossing of ``pool`` once with ``predict`` (observations (N, 29) float32 -> actions (N, 3));
    angular rate and thrust over the steps the policy flew (see `EvalResult`)."""
    core = CrossGapCore(len(pool), config, pool)
    core.reset_rows(np.arange(len(pool)), np.arange(len(pool)))
    done = np.zeros(core.n, bool)
    ret, terms = np.zeros(core.n), np.zeros((core.n, len(REWARD_TERMS)))
    success, arrived = np.zeros(core.n, bool), np.zeros(core.n, bool)
    rates, thrusts, flown = [], [], []
    x, _, _ = core.physics.kernel_arrays
    while not done.all():
        reward, terminated, truncated, t, s = core.step(predict(core.observations()))
        live = ~done
        ret[live] += reward[live]
        terms[live] += t[live]
        rates.append(np.linalg.norm(x[:, 10:13], axis=1))
        thrusts.append(core._targets[:, 3].copy())
        flown.append(live & core.policy_flew)
        end = live & (terminated | truncated)
        success[end], arrived[end] = s[end], core.arrived[end]
        done |= end
    t_s = np.arange(1, len(rates) + 1) * core.config.dt_s
    rate, thrust, mask = np.array(rates), np.array(thrusts), np.array(flown)
    per_rate = [time_mean(t_s, rate[:, i], mask=mask[:, i]) for i in range(core.n)]
    per_thrust = [time_mean(t_s, thrust[:, i], mask=mask[:, i]) for i in range(core.n)]
    return EvalResult(float(success.mean()), float(arrived.mean()), float(ret.mean()),
                      dict(zip(REWARD_TERMS, terms.mean(0).tolist(), strict=True)),
                      float(np.mean([v for v in per_rate if v is not None])),
                      float(np.mean([v for v in per_thrust if v is not None])), core.n,
                      success.tolist(), per_rate, per_thrust)


def paired_against(base: EvalResult, other: EvalResult) -> dict[str, Any]:
    """``other`` against ``base`` over the same crossings: approach angular rate and thrust (paired
    differences with 95 % intervals, `hil.report.paired`) and the successes of each."""
    return {"angular_rate_rad_s": paired_difference("imitation", "rl", base.per_crossing_rate_rad_s,
                                                    other.per_crossing_rate_rad_s).to_dict(),
            "thrust_n": paired_difference("imitation", "rl", base.per_crossing_thrust_n,
                                          other.per_crossing_thrust_n).to_dict(),
            "successes": {"imitation": int(sum(base.per_crossing_success)),
                          "rl": int(sum(other.per_crossing_success))}}


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
    """Per update: a CSV row (returns, success, each reward term, the critic's explained variance and
    whether the update was the critic's alone), the steps' masks, the held-out selection, checkpoints, the
    progress line, and the budget: the wall clock, and ``max_updates`` (None: no limit) updates in all."""

    def __init__(self, out: Path, deadline_s: float, every: int, progress: bool, start_update: int,
                 max_updates: int | None = None, core: CrossGapCore | None = None,
                 select: Callable[[int, torch.nn.Module], None] | None = None, select_every: int = 0) -> None:
        super().__init__()
        self.out, self.deadline_s, self.every, self.progress = out, deadline_s, every, progress
        self.update = start_update
        self.max_updates = max_updates
        self.core, self.select, self.select_every = core, select, select_every
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
                                        "success_rate", "arrival_rate", *REWARD_TERMS, "explained_variance",
                                        "critic_only"])

    def _on_step(self) -> bool:
        buf = self.model.rollout_buffer
        if self.core is not None and isinstance(buf, MaskedRolloutBuffer):
            buf.mark(self.core.policy_flew)  # (SB3 adds the step to the buffer after this call)
        for info in self.locals["infos"]:
            if "episode" in info:
                self.episodes.append(info)
        if self.max_updates is not None and self.update >= self.max_updates:
            return False  # (the rollout after the last update is dropped at its first step)
        return time.perf_counter() < self.deadline_s

    def on_update(self, ev: float | None, critic_only: bool) -> None:
        """After the update that followed a rollout (TRPO's ``train``): log it, select, checkpoint."""
        eps, self.episodes = self.episodes, []
        self.update += 1
        if eps:
            row = [self.update, self.num_timesteps, round(time.perf_counter() - self.started, 1), len(eps),
                   np.mean([e["episode"]["r"] for e in eps]), np.mean([e["success"] for e in eps]),
                   np.mean([e["arrived"] for e in eps]),
                   *[np.mean([e["reward_terms"][k] for e in eps]) for k in REWARD_TERMS],
                   "" if ev is None else round(ev, 4), int(critic_only)]
            with self.csv_path.open("a", newline="") as f:
                csv.writer(f).writerow(row)
            if self.bar is not None:
                self.bar.n = min(self.bar.total, round(time.perf_counter() - self.started))
                self.bar.set_postfix_str(f"update {self.update}, return {row[4]:.4g}, success {row[5]:.2f}")
                self.bar.write(f"update {self.update}: {self.num_timesteps} steps, return {row[4]:.4g}, "
                               f"success {row[5]:.2f}, critic EV {row[-2]}{' (critic only)' * critic_only}")
        if self.select is not None and self.select_every and not critic_only \
                and self.update % self.select_every == 0:
            self.select(self.update, self.model.policy.actor_module())
        if self.update % self.every == 0:
            self.model.save(self.out / "checkpoint.zip")


class _ReportingTRPO(FineTuneTRPO):
    """`FineTuneTRPO` that tells the progress callback after each update (SB3 calls its callbacks'
    ``on_rollout_end`` before ``train``: the update's figures exist only after it)."""

    progress_callback: _Progress | None = None

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "progress_callback"]

    def train(self) -> None:
        ready = self.critic_ready
        super().train()
        if self.progress_callback is not None:
            self.progress_callback.on_update(self.last_ev, critic_only=not (ready or self.critic_ready))


def make_model(env: Any, cfg: RLConfig, seed: int, device: str) -> _ReportingTRPO:
    policy_kwargs = {"log_std_init_per_action": cfg.log_std_init, "critic_hidden": cfg.critic_hidden,
                     "train_planner": cfg.train_planner}
    return _ReportingTRPO(ImitationInitPolicy, env, learning_rate=cfg.critic_lr, n_steps=cfg.n_steps,
                          batch_size=cfg.critic_batch, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda,
                          cg_max_steps=cfg.cg_max_steps, cg_damping=cfg.cg_damping,
                          line_search_max_iter=cfg.line_search_max_iter,
                          line_search_shrinking_factor=cfg.line_search_shrinking_factor,
                          n_critic_updates=cfg.n_critic_updates, target_kl=cfg.target_kl,
                          sub_sampling_factor=cfg.sub_sampling_factor,
                          rollout_buffer_class=MaskedRolloutBuffer if cfg.mask_expert_steps else None,
                          critic_target_ev=cfg.critic_pretrain_ev, critic_epochs=cfg.critic_pretrain_epochs,
                          critic_max_batches=cfg.critic_pretrain_max_batches,
                          critic_fit_batch=cfg.critic_pretrain_batch,
                          policy_kwargs=policy_kwargs, seed=seed, device=device, verbose=0)


def device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


class _Selection:
    """The held-out selection (`RLConfig.select_every`): flies the imitation policy once and each
    candidate actor over the same crossings, world checked every physics step and observed through the
    link model; keeps the candidate whose paired approach-rate difference is lowest with its interval
    below zero and no fewer successes (``best.pt``), and logs every candidate (selection.csv)."""

    def __init__(self, out: Path, pool: CrossingPool, config: EnvConfig) -> None:
        self.out, self.pool, self.config = out, pool, config
        self.base = evaluate(torch_predict(imitation_policy().eval()), pool, config)
        self.best: dict[str, Any] | None = None
        with (out / "selection.csv").open("w", newline="") as f:
            csv.writer(f).writerow(["update", "rate_difference_rad_s", "ci_low", "ci_high",
                                    "thrust_difference_n", "successes", "imitation_successes", "kept"])

    def __call__(self, update: int, actor: torch.nn.Module) -> None:
        was = actor.training
        cand = evaluate(torch_predict(actor.eval()), self.pool, self.config)
        actor.train(was)
        d = paired_against(self.base, cand)
        r = d["angular_rate_rad_s"]
        best = math.inf if self.best is None else self.best["angular_rate_rad_s"]["mean_difference"]
        ok = (r["ci_high"] is not None and r["ci_high"] < 0.0 and r["mean_difference"] < best
              and d["successes"]["rl"] >= d["successes"]["imitation"])
        if ok:
            self.best = {**d, "update": update}
            torch.save(actor.state_dict(), self.out / "best.pt")
        with (self.out / "selection.csv").open("a", newline="") as f:
            csv.writer(f).writerow([update, r["mean_difference"], r["ci_low"], r["ci_high"],
                                    d["thrust_n"]["mean_difference"], d["successes"]["rl"],
                                    d["successes"]["imitation"], int(ok)])


def selection_crossings(cfg: RLConfig, seed: int, ranges: CrossingRanges) -> list[Crossing]:
    """The held-out selection's crossings (`RLConfig.select_every`): ``select_size`` drawn from ``ranges``
    (seed ``seed + eval_seed_offset + 1``), then ``select_extra_size`` from each of ``select_extra`` (seeds
    ``+ 2``, ``+ 3``, ...); none of them a training or an evaluation crossing."""
    base = seed + cfg.eval_seed_offset + 1
    crossings = draw_crossings(cfg.select_size, np.random.default_rng(base), ranges)
    for i, extra in enumerate(cfg.select_extra):
        crossings += draw_crossings(cfg.select_extra_size, np.random.default_rng(base + 1 + i), extra)
    return crossings


def train_rl(out_dir: str | Path, minutes: float, seed: int = 0, resume: bool = False,
             cfg: RLConfig | None = None, n_envs: int | None = None, progress: bool = True,
             updates: int | None = None) -> dict[str, Any]:
    """Fine-tune for ``minutes`` of wall clock or ``updates`` TRPO updates in all (None: no limit; an
    update the critic's alone counts), whichever ends first; writes into ``out_dir``: checkpoint.zip,
    returns.csv, curve.png, e2e_rl.pt (the actor's state dict: the selected one with ``select_every``,
    else the last), e2e_rl.onnx, selection.csv and best.pt (with ``select_every``) and metrics.json (the
    held-out evaluation of the imitation and the fine-tuned policy, paired by crossing). Returns the
    metrics. With the same seed and budget in updates the weights are the same on machines with the same
    instruction set (torch's CPU kernels differ in their last bits between AVX2 and AVX-512)."""
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
        cfg = replace(cfg, n_envs=n_envs, n_steps=max(1, math.ceil(cfg.n_envs * cfg.n_steps / n_envs)))
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
        model = _ReportingTRPO.load(ckpt, env=env, device=device())
        model.critic_ready = True  # (a checkpoint comes after the critic's own batches)
        start_update = model.num_timesteps // (cfg.n_envs * cfg.n_steps)
    else:
        model = make_model(env, cfg, seed, device())
    judge_cfg = replace(env_cfg, world_check="physics", link=LinkModel())  # as the runner flies it
    select = None
    if cfg.select_every:
        chosen_on = selection_crossings(cfg, seed, env_cfg.ranges)
        select = _Selection(out, CrossingPool(chosen_on, venv.core.profile, env_cfg.dt_s, env_cfg.lead_s),
                            judge_cfg)
    deadline = time.perf_counter() + minutes * 60.0
    callback = _Progress(out, deadline, cfg.checkpoint_every, progress, start_update, updates, venv.core,
                         select, cfg.select_every)
    model.progress_callback = callback
    if progress:
        budget = f"{minutes:g} min" + ("" if updates is None else f" or {updates} updates in all")
        print(f"hil train rl: device {device()}, {cfg.n_envs} envs x {cfg.n_steps} steps a batch, "
              f"{budget}, out {out}", flush=True)
    model.learn(total_timesteps=10**12, callback=callback, reset_num_timesteps=not resume)
    model.progress_callback = None
    if callback.bar is not None:
        callback.bar.close()
    train_s = time.perf_counter() - t0
    model.save(ckpt)
    actor = model.policy.actor_module().cpu().eval()
    if select is not None and select.best is not None:
        actor.load_state_dict(torch.load(out / "best.pt"))
    torch.save(actor.state_dict(), out / "e2e_rl.pt")
    onnx_path = export_onnx(actor, N_INPUTS["e2e"], out / "e2e_rl.onnx", EXPORT_DTYPES["e2e"],
                            hidden_dtype=EXPORT_HIDDEN["e2e"])
    held_out = CrossingPool(draw_crossings(cfg.eval_size, np.random.default_rng(seed + cfg.eval_seed_offset),
                                           env_cfg.ranges), venv.core.profile, env_cfg.dt_s, env_cfg.lead_s)
    before = evaluate(torch_predict(imitation_policy().eval()), held_out, judge_cfg)
    after = evaluate(torch_predict(actor), held_out, judge_cfg)
    metrics = {"config": asdict(cfg), "seed": seed, "updates": callback.update,
               "timesteps": int(model.num_timesteps), "critic_only_updates": model.critic_batches,
               "critic_explained_variance": model.critic_evs,
               "selected": None if select is None else select.best,
               "train_minutes": round(train_s / 60.0, 2), "device": device(),
               "held_out": {"crossings": cfg.eval_size, "judged": "world checked every physics step, "
                            "observed through the link model", "imitation": before.to_dict(),
                            "rl": after.to_dict(), "paired": paired_against(before, after)}}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    plot_curve(out / "returns.csv", out / "curve.png")
    metrics["onnx"] = str(onnx_path)
    return metrics


def plot_curve(csv_path: Path, png_path: Path) -> None:
    """curve.png: per update, the mean episode return, the smoothness terms and the critic's explained
    variance (on each batch before its update; updates that were the critic's alone marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(csv_path.open()))
    if not rows:
        return
    steps = np.array([float(r["timesteps"]) for r in rows])
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
    axes[0].plot(steps, [float(r["mean_return"]) for r in rows])
    axes[0].set(xlabel="control steps", ylabel="mean episode return", title="return")
    for k in ("rate", "angular_acceleration", "jerk"):
        axes[1].plot(steps, [float(r[k]) for r in rows], label=k)
    axes[1].set(xlabel="control steps", ylabel="episode sum", title="smoothness terms")
    axes[1].legend()
    ev = [(t, float(r["explained_variance"]), r.get("critic_only") == "1")
          for t, r in zip(steps, rows, strict=True) if r.get("explained_variance")]
    if ev:
        axes[2].plot([e[0] for e in ev], [e[1] for e in ev], marker=".")
        only = [e for e in ev if e[2]]
        axes[2].plot([e[0] for e in only], [e[1] for e in only], "o", mfc="none", label="critic alone")
        axes[2].legend()
    axes[2].set(xlabel="control steps", ylabel="explained variance", title="critic, before each update")
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)
