"""`hil demo`: a short open-loop flight of one physics backend, plotted and summarised to a folder."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from emulator.physics import backend_names, make_backend
from emulator.physics.state import VehicleState
from emulator.profile import ProfileError, VehicleProfile, load_profile
from hil.link.mavlink import euler_from_quat

DURATION_S = 5.0
RECORD_EVERY_S = 0.01

# The open-loop sequence: (start time s, phase name). Throttles are set by `throttle_at`.
PHASES = ((0.0, "spin-up"), (1.0, "climb"), (1.8, "brake"), (2.6, "hover"), (3.0, "roll doublet"),
          (3.4, "settle"))


def throttle_at(t_s: float, hover: float) -> np.ndarray:
    """The demo's motor throttles (4,) at time ``t_s`` (s) for per-rotor hover throttle ``hover``."""
    if t_s < 1.0:  # spin up on the ground, below hover
        return np.full(4, 0.9 * hover * t_s)
    if t_s < 1.8:
        return np.full(4, 1.2 * hover)
    if t_s < 2.6:
        return np.full(4, 0.8 * hover)
    if 3.0 <= t_s < 3.4:  # 1-2-1 roll doublet: left rotors (1, 2) up, then down, then up
        sign = 1.0 if t_s < 3.1 or t_s >= 3.3 else -1.0
        d = 0.03 * sign
        return hover + np.array([-d, d, d, -d])
    return np.full(4, hover)


def fly(profile: VehicleProfile, backend_name: str, progress=print) -> dict[str, np.ndarray]:
    """Run the sequence from rest on the ground; returns time series sampled every 10 ms."""
    backend = make_backend(backend_name, profile)
    try:
        backend.reset(VehicleState(pos_m=[0.0, 0.0, 0.5 * profile.body_box_m[2]]))
        steps_per_record = max(1, round(RECORD_EVERY_S / backend.dt_s))
        n_records = round(DURATION_S / (steps_per_record * backend.dt_s))
        rows: dict[str, list] = {"t_s": [], "pos_m": [], "rpy_rad": [], "rotor_rad_s": [], "cmd": []}
        phase = 0
        for k in range(n_records):
            t = k * steps_per_record * backend.dt_s
            if phase < len(PHASES) and t >= PHASES[phase][0]:
                progress(f"  t = {t:4.2f} s  {PHASES[phase][1]}")
                phase += 1
            cmd = throttle_at(t, profile.hover_throttle)
            backend.step(cmd, steps_per_record)
            s = backend.state
            rows["t_s"].append(s.time_s)
            rows["pos_m"].append(s.pos_m)
            rows["rpy_rad"].append(euler_from_quat(s.quat_wxyz))
            rows["rotor_rad_s"].append(s.rotor_speed_rad_s)
            rows["cmd"].append(cmd)
        series = {key: np.array(value) for key, value in rows.items()}
        series["final"] = s  # type: ignore[assignment]
        return series
    finally:
        backend.close()


def plot(series: dict[str, np.ndarray], title: str, path: Path) -> None:
    """Position, attitude and rotor speeds against time, written as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = series["t_s"]
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for i, label in enumerate("xyz"):
        axes[0].plot(t, series["pos_m"][:, i], label=label)
    axes[0].set_ylabel("position ENU (m)")
    for i, label in enumerate(("roll", "pitch", "yaw")):
        axes[1].plot(t, np.degrees(series["rpy_rad"][:, i]), label=label)
    axes[1].set_ylabel("attitude (deg)")
    for i, label in enumerate(("FR", "RL", "FL", "RR")):
        axes[2].plot(t, series["rotor_rad_s"][:, i], label=label)
    axes[2].set_ylabel("rotor speed (rad/s)")
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        for start, _ in PHASES[1:]:
            ax.axvline(start, color="0.8", lw=0.8)
    axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="fly a short open-loop physics demo and plot it")
    p.add_argument("--out", required=True, type=Path, help="folder for demo.png and demo.json")
    p.add_argument("--profile", default="n3_tx2", help="built-in profile name or YAML path (default n3_tx2)")
    p.add_argument("--backend", default="native", choices=backend_names(), help="physics backend")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    try:
        profile = load_profile(args.profile)
        args.out.mkdir(parents=True, exist_ok=True)
    except (ProfileError, OSError) as exc:
        print(f"hil demo: {exc}", file=sys.stderr)
        return 2
    print(f"demo: {profile.name} on the {args.backend} backend, {DURATION_S:.0f} s simulated", flush=True)
    start = time.perf_counter()
    try:
        series = fly(profile, args.backend, progress=lambda msg: print(msg, flush=True))
    except RuntimeError as exc:  # e.g. a backend whose optional engine is missing
        print(f"hil demo: {exc}", file=sys.stderr)
        return 2
    wall_s = time.perf_counter() - start
    final: VehicleState = series.pop("final")  # type: ignore[assignment]
    png, js = args.out / "demo.png", args.out / "demo.json"
    plot(series, f"hil demo: {profile.name}, {args.backend} backend, open loop", png)
    summary = {
        "profile": profile.name,
        "backend": args.backend,
        "sim_time_s": final.time_s,
        "wall_time_s": wall_s,
        "max_height_m": float(series["pos_m"][:, 2].max()),
        "final_state": {
            "pos_m": final.pos_m.tolist(),
            "vel_m_s": final.vel_m_s.tolist(),
            "quat_wxyz": final.quat_wxyz.tolist(),
            "rpy_deg": [math.degrees(a) for a in euler_from_quat(final.quat_wxyz)],
            "omega_rad_s": final.omega_rad_s.tolist(),
            "rotor_speed_rad_s": final.rotor_speed_rad_s.tolist(),
        },
    }
    js.write_text(json.dumps(summary, indent=2) + "\n")
    pos = final.pos_m
    print(f"done: {final.time_s:.2f} s simulated in {wall_s:.2f} s wall; "
          f"final position ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}) m")
    print(f"wrote {png}")
    print(f"wrote {js}")
    return 0
