"""Training loops for the planner and controller networks: time/epoch budget, checkpoints, resume, eval.

Both loops draw random minibatches, use Adam with a learning rate decaying exponentially or along a half
cosine (``schedule``) from ``lr`` to ``lr * lr_final_frac`` over the budget (the sooner of ``epochs``
and ``minutes``),
checkpoint to ``out_dir/checkpoint.pt`` every ``checkpoint_every_s`` seconds and at the end, and
resume from that file. They finish by writing ``out_dir/<name>.pt`` (the state dict),
``metrics.json`` (held-out errors in physical units) and ``curve.png`` (training and validation loss).
The GPU is used when torch sees one.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from policies.learning.data import (
    ControllerDataConfig,
    PlannerData,
    PlannerDataConfig,
    PlannerSampler,
    controller_data,
    planner_data,
)
from policies.learning.evaluate import controller_errors, paper_case_errors, planner_errors
from policies.learning.losses import controller_loss, planner_loss
from policies.learning.networks import ControllerNet, PlannerNet


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings shared by both trainings."""

    out_dir: str = "out/train"
    epochs: float = 1.0
    minutes: float | None = None  # wall-clock budget; stops at the sooner of this and ``epochs``
    batch_size: int = 8192
    lr: float = 1e-3
    lr_final_frac: float = 0.01
    schedule: str = "exp"  # lr from lr to lr * lr_final_frac: "exp" (exponential) or "cosine" (half cosine)
    weight_decay: float = 0.0  # the paper's "g" (L2 on the weights)
    seed: int = 0
    checkpoint_every_s: float = 60.0
    log_every: int = 50  # steps between validation points on the curve
    resume: bool = True
    threads: int = 2
    progress: bool = True
    #: share of the budget (0..1) run under bfloat16 autocast (about 2x faster on CPUs with AVX512-BF16
    #: or AMX, and on GPUs); the rest, the low-learning-rate end, runs in float32 for full precision
    bf16_fraction: float = 0.0

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.lr <= 0 or not 0 < self.lr_final_frac <= 1 or self.epochs <= 0:
            raise ValueError("need batch_size >= 1, lr > 0, 0 < lr_final_frac <= 1 and epochs > 0")
        if self.schedule not in ("exp", "cosine"):
            raise ValueError(f"schedule must be 'exp' or 'cosine', got {self.schedule!r}")
        if self.minutes is not None and self.minutes <= 0:
            raise ValueError("minutes must be positive")
        if not 0.0 <= self.bf16_fraction <= 1.0:
            raise ValueError(f"bf16_fraction must be in [0, 1], got {self.bf16_fraction}")


@dataclass
class TrainResult:
    """What a training produced: files, steps, wall time (s) and held-out metrics."""

    out_dir: Path
    weights_path: Path
    steps: int
    train_time_s: float
    metrics: dict[str, object] = field(default_factory=dict)


def device() -> torch.device:
    """The GPU when torch sees one, else the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def lr_at(cfg: TrainConfig, frac: float) -> float:
    """Learning rate at ``frac`` (0..1) of the budget."""
    if cfg.schedule == "cosine":
        cos = 0.5 * (1.0 + math.cos(math.pi * min(frac, 1.0)))
        return cfg.lr * (cfg.lr_final_frac + (1.0 - cfg.lr_final_frac) * cos)
    return cfg.lr * cfg.lr_final_frac ** frac


def _loop(name: str, model: torch.nn.Module, cfg: TrainConfig, steps_per_epoch: int,
          batch: Callable[[int], tuple[torch.Tensor, torch.Tensor]], loss_fn: Callable[..., torch.Tensor],
          val: Callable[[], float], extra: dict[str, object]) -> tuple[int, float, list[list[float]]]:
    """The shared optimisation loop; returns (steps, training seconds, history rows)."""
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    total_steps = max(1, math.ceil(cfg.epochs * steps_per_epoch))
    budget_s = cfg.minutes * 60.0 if cfg.minutes is not None else math.inf
    step, elapsed, history = 0, 0.0, []
    if cfg.resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location=device(), weights_only=False)
        if ck.get("name") != name:
            raise ValueError(f"{ckpt_path} holds a {ck.get('name')!r} checkpoint, not {name!r}")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed, history = ck["step"], ck["elapsed_s"], ck["history"]

    def save() -> None:
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save({"name": name, "model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                    "elapsed_s": elapsed, "history": history, "config": asdict(cfg), **extra}, tmp)
        tmp.replace(ckpt_path)

    def progress_frac() -> float:
        return max(step / total_steps, elapsed / budget_s)

    bar = tqdm(total=total_steps, initial=step, desc=f"train {name}", disable=not cfg.progress,
               unit="step", dynamic_ncols=True)
    last_ckpt = time.perf_counter()
    dev_type = next(model.parameters()).device.type
    start = time.perf_counter() - elapsed
    running = None
    model.train()
    while progress_frac() < 1.0:
        lr = lr_at(cfg, progress_frac())
        for group in opt.param_groups:
            group["lr"] = lr
        x, y = batch(cfg.batch_size)
        with torch.autocast(dev_type, dtype=torch.bfloat16, enabled=progress_frac() < cfg.bf16_fraction):
            loss = loss_fn(model, x, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        elapsed = time.perf_counter() - start
        value = float(loss.detach())
        running = value if running is None else 0.98 * running + 0.02 * value
        bar.update(1)
        if step % cfg.log_every == 0 or progress_frac() >= 1.0:
            history.append([step, elapsed, running, val(), lr])
            bar.set_postfix(loss=f"{running:.4g}", val=f"{history[-1][3]:.4g}", lr=f"{lr:.2g}")
        if time.perf_counter() - last_ckpt > cfg.checkpoint_every_s:
            save()
            last_ckpt = time.perf_counter()
    bar.close()
    save()
    return step, elapsed, history


def _plot(history: list[list[float]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    h = np.asarray(history)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(h[:, 1] / 60.0, h[:, 2], label="train (running mean)")
    ax.semilogy(h[:, 1] / 60.0, h[:, 3], label="validation")
    ax.set_xlabel("training time (min)")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _finish(name: str, model: torch.nn.Module, cfg: TrainConfig, steps: int, elapsed: float,
            history: list[list[float]], metrics: dict[str, object]) -> TrainResult:
    out = Path(cfg.out_dir)
    weights = out / f"{name}.pt"
    torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, weights)
    metrics = {"steps": steps, "train_time_s": round(elapsed, 1), "device": str(device()),
               "config": asdict(cfg), **metrics}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float) + "\n")
    _plot(history, out / "curve.png", f"{name} training")
    return TrainResult(out, weights, steps, elapsed, metrics)


def predictor(model: torch.nn.Module, chunk: int = 65536) -> Callable[[np.ndarray], np.ndarray]:
    """A numpy predictor (float64 in and out) around a torch model, evaluated in chunks."""
    dev = next(model.parameters()).device

    def predict(x: np.ndarray) -> np.ndarray:
        model.eval()
        outs = []
        with torch.no_grad():
            for lo in range(0, x.shape[0], chunk):
                xt = torch.as_tensor(np.asarray(x[lo:lo + chunk], np.float32), device=dev)
                outs.append(model(xt).cpu().numpy().astype(np.float64))
        return np.concatenate(outs) if outs else np.zeros((0, 0))

    return predict


def train_planner(data_cfg: PlannerDataConfig, cfg: TrainConfig, holdout_trajectories: int = 100,
                  end_fraction: float = 0.0) -> TrainResult:
    """Train ``PlannerNet`` on the planner data set; evaluate on ``holdout_trajectories`` fresh ones.
    ``end_fraction`` of the training samples take their time from the arcsine law (see PlannerSampler)."""
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    dev = device()
    data = planner_data(data_cfg)
    hold_cfg = replace(data_cfg, n_trajectories=holdout_trajectories, seed=data_cfg.seed + 1_000_003)
    hold = planner_data(hold_cfg)
    sampler = PlannerSampler(data, np.random.default_rng(cfg.seed), end_fraction=end_fraction)
    model = PlannerNet().to(dev)
    x_val, y_val = PlannerSampler(hold, np.random.default_rng(cfg.seed + 1), augment=False).batch(8192)
    xv = torch.as_tensor(x_val, dtype=torch.float32, device=dev)
    yv = torch.as_tensor(y_val, dtype=torch.float32, device=dev)

    def batch(n: int) -> tuple[torch.Tensor, torch.Tensor]:
        x, y = sampler.batch(n)
        return (torch.as_tensor(x, dtype=torch.float32, device=dev),
                torch.as_tensor(y, dtype=torch.float32, device=dev))

    def loss_fn(m: PlannerNet, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        inp, s, scale = m.normalise(x)
        return planner_loss(m.mlp(inp), m.normalise_outputs(y, s, scale))

    def val() -> float:
        with torch.no_grad():
            return float(loss_fn(model, xv, yv))

    steps_per_epoch = math.ceil(len(data) * data_cfg.samples_per_trajectory / cfg.batch_size)
    extra = {"data_config": asdict(data_cfg), "end_fraction": end_fraction}
    steps, elapsed, history = _loop("planner", model, cfg, steps_per_epoch, batch, loss_fn, val, extra)
    metrics = {"data": {"trajectories": len(data), "dropped": data.n_dropped,
                        "samples_per_trajectory": data_cfg.samples_per_trajectory, **asdict(data_cfg),
                        "end_fraction": end_fraction},
               **planner_metrics(model, hold)}
    return _finish("planner", model, cfg, steps, elapsed, history, metrics)


def planner_metrics(model: PlannerNet, hold: PlannerData) -> dict[str, object]:
    """Held-out and paper-case errors in physical units, of the planner as deployed (the MLP's odd part)
    and of the bare MLP (``*_bare_mlp``)."""
    xh, yh = hold.all_samples()
    out: dict[str, object] = {}
    symmetric = model.odd_symmetric
    try:
        for odd, suffix in ((True, ""), (False, "_bare_mlp")):
            model.odd_symmetric = odd
            predict = predictor(model)
            out[f"holdout{suffix}"] = {"trajectories": len(hold), **planner_errors(predict(xh), yh)}
            out[f"paper_case{suffix}"] = paper_case_errors(predict)
    finally:
        model.odd_symmetric = symmetric
    return out


def train_controller(data_cfg: ControllerDataConfig, cfg: TrainConfig, holdout_per_set: int = 100_000
                     ) -> TrainResult:
    """Train ``ControllerNet`` on the large- and short-range sets; evaluate on fresh samples of each."""
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    dev = device()
    x_all, y_all = controller_data(data_cfg)
    xt = torch.as_tensor(x_all, device=dev)
    yt = torch.as_tensor(y_all, device=dev)
    gen = torch.Generator(device=dev).manual_seed(cfg.seed)
    hold_cfg = replace(data_cfg, n_per_set=holdout_per_set, seed=data_cfg.seed + 1_000_003)
    xh, yh = controller_data(hold_cfg, use_cache=False)
    pick = np.random.default_rng(cfg.seed).choice(xh.shape[0], min(8192, xh.shape[0]), replace=False)
    xv = torch.as_tensor(xh[pick], device=dev)
    yv = torch.as_tensor(yh[pick], device=dev)
    model = ControllerNet().to(dev)

    def batch(n: int) -> tuple[torch.Tensor, torch.Tensor]:
        idx = torch.randint(0, xt.shape[0], (n,), generator=gen, device=dev)
        return xt[idx], yt[idx]

    def loss_fn(m: ControllerNet, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return controller_loss(m(x), y)

    def val() -> float:
        with torch.no_grad():
            return float(loss_fn(model, xv, yv))

    steps_per_epoch = math.ceil(xt.shape[0] / cfg.batch_size)
    steps, elapsed, history = _loop("controller", model, cfg, steps_per_epoch, batch, loss_fn, val,
                                    {"data_config": asdict(data_cfg)})
    predict = predictor(model)
    n = holdout_per_set
    metrics = {"data": {"samples": int(xt.shape[0]), **asdict(data_cfg)},
               "holdout_large": controller_errors(predict(xh[:n]), yh[:n]),
               "holdout_short": controller_errors(predict(xh[n:]), yh[n:])}
    return _finish("controller", model, cfg, steps, elapsed, history, metrics)
