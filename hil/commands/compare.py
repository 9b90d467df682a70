"""`hil compare SCENARIO... [--pilots P,Q,...]`: the same scenarios flown by several pilots through the
links (by default two processes over ptys, lockstep, as `hil run`), compared as the paper's figure: one
HTML page (trajectories overlaid through the gap, per pilot) and ``compare.json`` with, per scenario and
pooled over them, each pilot's success rate, minimum clearance, mean angular rate and mean thrust.

Means are taken over the crossing (the mission's approach and traverse, from the onboard program's
``segment`` events: where the pilots differ; the takeoff and hover before and the recovery after are the
same expert's in every pilot) and over the whole flight (the run summary's figures). Success: crossed
through the opening with no collision. Exit 0 when every run completed, 2 for bad input.
"""

from __future__ import annotations

import argparse
import html
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hil.commands import output_folder
from hil.report.svg import View
from hil.runner import RunOptions, RunSetupError, run_scenario
from hil.runner.emulator_side import make_gap
from hil.scenario import ScenarioError, load_scenarios
from hil.scenario.schema import Scenario

DEFAULT_PILOTS = ("traditional", "e2e", "e2e_rl")
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="fly scenarios with several pilots through the links and compare them "
                                       "(trajectories, mean angular rate and thrust, success, clearance)")
    p.add_argument("scenarios", nargs="*", metavar="SCENARIO", help="*.scenario.yaml files or folders")
    p.add_argument("--held-out", type=int, default=0, metavar="N",
                   help="also fly N randomised crossings drawn as CrossGap-v0 draws them, from a seed of "
                        "their own (--held-out-seed), none of them a training crossing")
    p.add_argument("--held-out-seed", type=int, default=1_000_003,
                   help="seed of the --held-out crossings (default: the evaluation seed of hil train rl "
                        "--seed 0)")
    p.add_argument("--pilots", default=",".join(DEFAULT_PILOTS),
                   help=f"comma-separated pilots (default {','.join(DEFAULT_PILOTS)})")
    p.add_argument("--out", default="reports/compare", metavar="DIR", help="output folder (default "
                                                                           "reports/compare)")
    p.add_argument("--in-process", action="store_true", default=None,
                   help="both sides in this process over memory links (default: two processes over ptys)")
    p.add_argument("--seed", type=int, default=None, help="seed instead of each scenario's")
    p.set_defaults(func=main)


def _files(paths: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in map(Path, paths):
        out += sorted(p.rglob("*.scenario.yaml")) if p.is_dir() else [p]
    return out


def held_out_scenarios(n: int, seed: int) -> list[Scenario]:
    """``n`` scenarios of crossings drawn as `CrossGap-v0` draws them (`hil.rl.scenarios`, from
    ``seed``): a hover at the start, the gap, the crossing speed; 11 s each."""
    from hil.rl.scenarios import draw_crossings  # the 'learn' extra
    from hil.scenario import loads_scenarios

    docs = []
    for i, c in enumerate(draw_crossings(n, np.random.default_rng(seed))):
        centre = ", ".join(f"{v:.4f}" for v in c.gap_centre_m)
        start = ", ".join(f"{v:.4f}" for v in c.start_m)
        docs.append(f"description: held-out crossing {i} (seed {seed})\n"
                    f"gap: {{centre_m: [{centre}], roll_deg: {c.roll_deg:.4f}}}\n"
                    f"initial: {{pos_m: [{start}]}}\n"
                    f"approach: {{speed_m_s: {c.speed_m_s:g}}}\nduration_s: 11\n")
    return loads_scenarios("---\n".join(docs), source=f"held_out_{seed}")


def crossing_window(summary: dict[str, Any]) -> tuple[float, float] | None:
    """Sim times (s) of the mission's approach start and recovery start (the traverse's end), from the
    onboard program's events; None when the mission did not get so far."""
    start = end = None
    for ev in summary.get("events", []):
        if ev.get("source") != "onboard" or not isinstance(ev.get("time_s"), int | float):
            continue
        if ev["text"] == "segment: approach" and start is None:
            start = float(ev["time_s"])
        elif ev["text"] == "segment: recovery" and start is not None and end is None:
            end = float(ev["time_s"])
    return (start, end) if start is not None and end is not None else None


def flight_figures(summary: dict[str, Any], cols: dict[str, np.ndarray]) -> dict[str, Any]:
    """One run's figures (see the module doc) and its trajectory over the crossing +-0.5 s."""
    window = crossing_window(summary)
    t = cols["t_s"]
    fig: dict[str, Any] = {
        "success": bool(summary["crossed_gap"] and summary["collision"] is None),
        "crossed_gap": bool(summary["crossed_gap"]),
        "collision": summary["collision"],
        "min_clearance_m": summary["min_clearance_m"],
        "flight_mean_angular_rate_rad_s": summary["mean_angular_rate_rad_s"],
        "flight_mean_thrust_n": summary["mean_thrust_n"],
        "crossing_window_s": window,
        "mean_angular_rate_rad_s": None,
        "mean_thrust_n": None,
        "trajectory_m": [],
    }
    if window is not None:
        sel = (t >= window[0]) & (t < window[1])
        fig["mean_angular_rate_rad_s"] = float(np.mean(cols["body_rate_rad_s"][sel]))
        fig["mean_thrust_n"] = float(np.mean(cols["thrust_n"][sel]))
        near = (t >= window[0] - 0.5) & (t <= window[1] + 0.5)
        pos = np.stack([cols["pos_m_x"], cols["pos_m_y"], cols["pos_m_z"]], 1)[near]
        fig["trajectory_m"] = np.round(pos[:: max(1, len(pos) // 200)], 4).tolist()
    return fig


def pooled(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """A pilot's figures over scenarios: success rate, the least clearance, the mean of the per-run means
    (over the runs that have them)."""
    def mean(key: str) -> float | None:
        vals = [r[key] for r in runs if r[key] is not None]
        return float(np.mean(vals)) if vals else None

    clear = [r["min_clearance_m"] for r in runs if r["min_clearance_m"] is not None]
    rate = float(np.mean([r["success"] for r in runs])) if runs else None
    return {"runs": len(runs), "success_rate": rate,
            "min_clearance_m": min(clear) if clear else None,
            "mean_angular_rate_rad_s": mean("mean_angular_rate_rad_s"),
            "mean_thrust_n": mean("mean_thrust_n"),
            "flight_mean_angular_rate_rad_s": mean("flight_mean_angular_rate_rad_s"),
            "flight_mean_thrust_n": mean("flight_mean_thrust_n")}


def compare(scenarios: list[Scenario], pilots: list[str], out: Path, options: RunOptions,
            progress: Any = print) -> dict[str, Any]:
    """Fly each scenario with each pilot (runs under ``out/<scenario>/<pilot>``); write and return the
    comparison (``out/compare.json``, ``out/compare.html``)."""
    result: dict[str, Any] = {"pilots": pilots, "scenarios": {}, "pooled": {}}
    for s in scenarios:
        per: dict[str, Any] = {}
        for pilot in pilots:
            run = run_scenario(s, out / s.id / pilot, replace(options, pilot=pilot))
            if run.summary.get("refused"):  # nothing flown: no figures to compare
                raise RunSetupError(f"{s.id}: refused before take-off: {run.summary['refused']}")
            data = np.load(run.out_dir / "timeseries.npz")
            per[pilot] = flight_figures(run.summary, {k: data[k] for k in data.files})
            progress(f"{s.id} {pilot}: {'crossed' if per[pilot]['success'] else 'FAILED'}, mean rate "
                     f"{_fmt(per[pilot]['mean_angular_rate_rad_s'])} rad/s, mean thrust "
                     f"{_fmt(per[pilot]['mean_thrust_n'])} N")
        result["scenarios"][s.id] = {"description": s.description, "gap": _gap_outline(s), "pilots": per}
    for pilot in pilots:
        result["pooled"][pilot] = pooled([sc["pilots"][pilot] for sc in result["scenarios"].values()])
    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "compare.html").write_text(render_html(result))
    return result


def _gap_outline(s: Scenario) -> list[list[float]]:
    """The opening's corners (4, 3) in world ENU (m)."""
    gap = make_gap(s)
    axes = gap.axes()  # rows e0, e1, e2
    c = np.asarray(gap.centre_m)
    hw, hh = gap.width_m / 2, gap.height_m / 2
    corners = ((1, 1), (-1, 1), (-1, -1), (1, -1))
    return [(c + a * hw * axes[0] + b * hh * axes[2]).round(4).tolist() for a, b in corners]


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return f"{v:.{digits}g}" if isinstance(v, float) else html.escape(str(v))


def _overlay_svg(gap: list[list[float]], runs: dict[str, dict[str, Any]], view: View, title: str,
                 size: int = 300) -> str:
    """Trajectories of the pilots (one colour each) and the opening, seen by ``view``."""
    pts = [np.asarray(gap)] + [np.asarray(r["trajectory_m"]) for r in runs.values() if r["trajectory_m"]]
    xy_all = np.vstack([view.project(p)[0] for p in pts])
    lo, hi = xy_all.min(0), xy_all.max(0)
    span = float(max(hi - lo)) or 1.0
    scale, pad = (size - 30) / span, 15

    def path(p: np.ndarray, close: bool = False) -> str:
        xy = view.project(p)[0]
        sx = pad + (xy[:, 0] - lo[0]) * scale
        sy = size - pad - (xy[:, 1] - lo[1]) * scale
        d = "".join(f"{'M' if i == 0 else 'L'}{x:.1f},{y:.1f}"
                    for i, (x, y) in enumerate(zip(sx, sy, strict=True)))
        return d + ("Z" if close else "")

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" '
             f'style="border:1px solid #ccc;background:#fff">',
             f'<text x="6" y="13" font-size="11">{html.escape(title)}</text>',
             f'<path d="{path(np.asarray(gap), True)}" fill="none" stroke="#000" stroke-width="2"/>']
    for (pilot, r), colour in zip(runs.items(), COLOURS, strict=False):
        if r["trajectory_m"]:
            parts.append(f'<path d="{path(np.asarray(r["trajectory_m"]))}" fill="none" stroke="{colour}" '
                         f'stroke-width="1.5"><title>{html.escape(pilot)}</title></path>')
    parts.append("</svg>")
    return "".join(parts)


def _table(rows: dict[str, dict[str, Any]], colours: dict[str, str]) -> str:
    cols = (("success_rate", "success"), ("success", "success"), ("min_clearance_m", "min clearance (m)"),
            ("mean_angular_rate_rad_s", "mean angular rate, crossing (rad/s)"),
            ("mean_thrust_n", "mean thrust, crossing (N)"),
            ("flight_mean_angular_rate_rad_s", "mean angular rate, flight (rad/s)"),
            ("flight_mean_thrust_n", "mean thrust, flight (N)"))
    keys = [(k, name) for k, name in cols if any(k in r for r in rows.values())]
    head = "".join(f"<th>{html.escape(name)}</th>" for _, name in keys)
    body = "".join(f'<tr><td style="color:{colours[p]}"><b>{html.escape(p)}</b></td>'
                   + "".join(f"<td>{_fmt(r.get(k))}</td>" for k, _ in keys) + "</tr>"
                   for p, r in rows.items())
    return f"<table><tr><th>pilot</th>{head}</tr>{body}</table>"


def render_html(result: dict[str, Any]) -> str:
    """The comparison as one self-contained page (no scripts, no network)."""
    colours = dict(zip(result["pilots"], COLOURS, strict=False))
    top, side = View(math.radians(-90), math.radians(89.9)), View(math.radians(180), 0.0)
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>hil compare</title><style>"
             "body{font-family:sans-serif;margin:20px}table{border-collapse:collapse;margin:8px 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}</style></head><body>",
             "<h1>Pilots compared through the links</h1>",
             "<p>Means over the crossing: the mission's approach and traverse; over the flight: the whole "
             "run. "
             "Success: through the opening, no collision.</p>",
             "<h2>Pooled over the scenarios</h2>", _table(result["pooled"], colours)]
    for sid, sc in result["scenarios"].items():
        parts += [f"<h2>{html.escape(sid)}</h2><p>{html.escape(sc['description'] or '')}</p>",
                  _overlay_svg(sc["gap"], sc["pilots"], top, "top view (x right, y up)"), " ",
                  _overlay_svg(sc["gap"], sc["pilots"], side, "looking along +x (y left, z up)"),
                  _table(sc["pilots"], colours)]
    parts.append("</body></html>")
    return "".join(parts)


def main(args: argparse.Namespace) -> int:
    pilots = [p.strip() for p in args.pilots.split(",") if p.strip()]
    if not pilots:
        print("hil compare: --pilots names no pilot", file=sys.stderr)
        return 2
    if args.held_out < 0:
        print(f"hil compare: --held-out must be 0 or more crossings, got {args.held_out}", file=sys.stderr)
        return 2
    try:
        from policies.onboard.pilots import pilot_names

        unknown = sorted(set(pilots) - set(pilot_names()))
        if unknown:
            print(f"hil compare: unknown pilot(s) {', '.join(unknown)}; known: {', '.join(pilot_names())}",
                  file=sys.stderr)
            return 2
        scenarios = [s for f in _files(args.scenarios) for s in load_scenarios(f) if not s.skip]
        if args.held_out > 0:
            scenarios += held_out_scenarios(args.held_out, args.held_out_seed)
    except ScenarioError as exc:
        print(f"hil compare: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"hil compare: cannot read {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 2
    if not scenarios:
        print("hil compare: no scenario to fly", file=sys.stderr)
        return 2
    if output_folder(args.out, "hil compare") is None:
        return 2
    try:
        compare(scenarios, pilots, Path(args.out), RunOptions(in_process=args.in_process, seed=args.seed))
    except (RunSetupError, ValueError) as exc:
        print(f"hil compare: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {Path(args.out) / 'compare.html'}, {Path(args.out) / 'compare.json'}")
    return 0
