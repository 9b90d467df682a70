"""`hil train planner|controller|export`: train the imitation networks, export them to ONNX; `hil train rl`:
fine-tune the end-to-end policy with TRPO in `CrossGap-v0` (`hil.rl.train`)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path


def _common(p: argparse.ArgumentParser, out: str, batch: int, lr: float) -> None:
    p.add_argument("--out", default=out, help=f"output folder (default {out})")
    p.add_argument("--epochs", type=float, default=1000.0,
                   help="epoch budget (default 1000; --minutes usually ends first)")
    p.add_argument("--minutes", type=float, default=None, help="wall-clock budget in minutes")
    p.add_argument("--batch-size", type=int, default=batch, help=f"minibatch size (default {batch})")
    p.add_argument("--lr", type=float, default=lr, help=f"initial Adam learning rate (default {lr})")
    p.add_argument("--lr-final-frac", type=float, default=0.01,
                   help="final lr as a fraction of --lr (default 0.01)")
    p.add_argument("--schedule", choices=("exp", "cosine"), default="exp",
                   help="lr decay from --lr to --lr x --lr-final-frac: exp(onential) or half cosine "
                        "(default exp)")
    p.add_argument("--seed", type=int, default=0, help="seed of the data and of the training (default 0)")
    p.add_argument("--no-resume", action="store_true", help="start afresh even if OUT/checkpoint.pt exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=int, default=2, help="CPU threads for torch (default 2)")
    p.add_argument("--bf16-fraction", type=float, default=0.0,
                   help="share of the budget trained under bfloat16 autocast, the rest in float32 "
                        "(about 2x faster where the CPU has AVX512-BF16 or AMX; default 0)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the planner/controller networks (imitation of the expert)")
    tsub = p.add_subparsers(dest="what", metavar="WHAT", required=True)
    pl = tsub.add_parser("planner", help="imitate the motion primitives (17 -> 9)")
    _common(pl, "out/planner", 1024, 7e-4)
    pl.add_argument("--trajectories", type=int, default=20_000, help="training trajectories (default 20000)")
    pl.add_argument("--samples-per-trajectory", type=int, default=1000,
                    help="time grid per trajectory (default 1000)")
    pl.add_argument("--end-fraction", type=float, default=0.0,
                    help="fraction of training samples timed by the arcsine law, denser near t = 0 and "
                         "t = T (default 0: uniform)")
    pl.set_defaults(func=main)
    co = tsub.add_parser("controller", help="imitate the expert controller (12 -> 3)")
    _common(co, "out/controller", 1024, 1e-3)
    co.add_argument("--samples-per-set", type=int, default=6_000_000,
                    help="samples in each of the large- and short-range sets (default 6e6)")
    co.set_defaults(func=main)
    ex = tsub.add_parser("export", help="write planner.onnx, controller.onnx, e2e.onnx and metrics.json from "
                                        "state dicts (and the metrics.json files beside them)")
    ex.add_argument("--planner", required=True, help="planner state dict (planner.pt)")
    ex.add_argument("--controller", required=True, help="controller state dict (controller.pt)")
    ex.add_argument("--out", required=True, help="output folder")
    ex.set_defaults(func=main)
    rl = tsub.add_parser("rl", help="fine-tune the end-to-end policy with TRPO in CrossGap-v0 (imitate, then "
                                    "reinforce); writes e2e_rl.onnx, returns.csv, curve.png, metrics.json")
    rl.add_argument("--minutes", type=float, default=20.0, help="wall-clock budget in minutes (default 20)")
    rl.add_argument("--updates", type=int, default=None,
                    help="stop after this many TRPO updates in all (the budget that gives the same weights "
                         "on any machine; the minutes still bound it)")
    rl.add_argument("--world-check", choices=("control", "physics"), default=None,
                    help="when the environment checks the world, in training and in the held-out evaluation: "
                         "once a control step or after every physics step, as the runner does (default: the "
                         "method's: control for release, physics for fine_tune)")
    rl.add_argument("--observe", choices=("state", "link"), default=None,
                    help="what the policy sees, in training and in the held-out evaluation: the true state "
                         "(default) or the onboard filter's estimate from the mocap frames through the radio")
    rl.add_argument("--method", choices=("release", "fine_tune"), default="release",
                    help="release: TRPO as the paper's release ran it (default); fine_tune: with the "
                         "documented deviations (expert steps masked, the critic fitted first, a larger "
                         "batch and KL bound, the actor chosen on held-out crossings; "
                         "hil.rl.train.DEVIATIONS)")
    rl.add_argument("--envs", type=int, default=None,
                    help="vehicles flown at once (default 64; the batch keeps its size in steps)")
    rl.add_argument("--seed", type=int, default=0, help="seed of the crossings and of TRPO (default 0)")
    rl.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.zip")
    rl.add_argument("--out", default="out/rl", help="output folder (default out/rl)")
    rl.add_argument("--no-progress", action="store_true", help="no progress lines")
    rl.set_defaults(func=main_rl)


def main_rl(args: argparse.Namespace) -> int:
    try:
        from hil.rl.train import METHODS, train_rl  # (torch and gymnasium: the optional 'learn' extra)
    except ImportError as exc:  # the 'learn' extra
        print(f"hil train rl: needs the 'learn' extra (torch, gymnasium, stable-baselines3, sb3-contrib): "
              f"{exc}", file=sys.stderr)
        return 2
    # (the method's own world check and observation unless asked otherwise)
    asked = {k: v for k, v in (("world_check", args.world_check), ("observe", args.observe)) if v is not None}
    try:
        metrics = train_rl(args.out, args.minutes, seed=args.seed, resume=args.resume, n_envs=args.envs,
                           progress=not args.no_progress, updates=args.updates,
                           cfg=replace(METHODS[args.method](), **asked))
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"hil train rl: {exc}", file=sys.stderr)
        return 1
    shown = ("updates", "timesteps", "train_minutes", "held_out")
    print(json.dumps({k: metrics[k] for k in shown}, indent=2))
    print(f"wrote {metrics['onnx']}, {Path(args.out) / 'returns.csv'}, {Path(args.out) / 'curve.png'}, "
          f"{Path(args.out) / 'metrics.json'}")
    return 0


def main(args: argparse.Namespace) -> int:
    try:
        # (torch: the optional 'learn' extra, imported only for this command)
        from policies.learning import export, train
        from policies.learning.data import ControllerDataConfig, PlannerDataConfig
    except ImportError as exc:  # torch is an optional dependency
        print(f"hil train: needs the 'learn' extra (torch, onnx, onnxruntime, tqdm): {exc}", file=sys.stderr)
        return 2
    try:
        if args.what == "export":
            planner, controller = export.load_planner(args.planner), export.load_controller(args.controller)
            paths = export.export_all(planner, controller, args.out)
            paths["metrics"] = export.export_metrics(args.planner, args.controller, args.out)
            for name, path in paths.items():
                print(f"{name}: {path}")
            return 0
        cfg = train.TrainConfig(out_dir=args.out, epochs=args.epochs, minutes=args.minutes,
                                batch_size=args.batch_size, lr=args.lr, lr_final_frac=args.lr_final_frac,
                                schedule=args.schedule,
                                seed=args.seed, resume=not args.no_resume, threads=args.threads,
                                progress=not args.no_progress, bf16_fraction=args.bf16_fraction)
        if args.what == "planner":
            data = PlannerDataConfig(n_trajectories=args.trajectories,
                                     samples_per_trajectory=args.samples_per_trajectory, seed=args.seed)
            print(f"hil train planner: device {train.device()}, {args.trajectories} trajectories x "
                  f"{args.samples_per_trajectory} samples, out {args.out}", file=sys.stderr)
            result = train.train_planner(data, cfg, end_fraction=args.end_fraction)
            net = export.load_planner(result.weights_path)
            onnx_path = export.export_onnx(net, export.N_INPUTS["planner"], Path(args.out) / "planner.onnx",
                                           export.EXPORT_DTYPES["planner"])
            summary = {"holdout": result.metrics["holdout"], "paper_case": result.metrics["paper_case"]}
        else:
            data = ControllerDataConfig(n_per_set=args.samples_per_set, seed=args.seed)
            print(f"hil train controller: device {train.device()}, 2 x {args.samples_per_set} samples, "
                  f"out {args.out}", file=sys.stderr)
            result = train.train_controller(data, cfg)
            net = export.load_controller(result.weights_path)
            onnx_path = export.export_onnx(net, export.N_INPUTS["controller"],
                                           Path(args.out) / "controller.onnx",
                                           export.EXPORT_DTYPES["controller"])
            summary = {"holdout_large": result.metrics["holdout_large"],
                       "holdout_short": result.metrics["holdout_short"]}
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"hil train: {exc}", file=sys.stderr)
        return 1
    report = {"steps": result.steps, "train_time_s": round(result.train_time_s, 1), **summary}
    print(json.dumps(report, indent=2))
    print(f"wrote {result.weights_path}, {onnx_path}, {result.out_dir / 'metrics.json'}, "
          f"{result.out_dir / 'curve.png'}")
    return 0
