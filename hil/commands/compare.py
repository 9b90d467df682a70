"""`hil compare SCENARIO... [--pilots P,Q,...] [--seeds N]`: the same scenarios flown by several pilots
through the links (by default two processes over ptys, lockstep, as `hil run`), compared as the paper's
figure and as a paired experiment: one HTML page (trajectories overlaid through the gap, per pilot;
tables) and ``compare.json`` with, per run, pooled per pilot and paired over the units (scenario, seed),
each pilot's success, minimum clearance, and angular rate and thrust over time (`FIGURES`).

Figures are the run summary's per-segment ones (`hil.runner.flight_quality`, weighted by time): the
approach (what a learned pilot flies), the traverse and recovery (the expert's in the e2e pilots), both
first two ("crossing"), and the whole flight. Paired differences carry a 95 % interval
(`hil.report.paired`); the paper's findings (`FINDINGS`) are each reproduced, not reproduced or not
resolved by it. Success: crossed through the opening with no collision. Exit 0 when every run completed,
2 for bad input.
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
from hil.report.paired import INTERVAL_METHOD, paired_difference
from hil.report.svg import View
from hil.runner import RunOptions, RunSetupError, run_scenario
from hil.runner.emulator_side import make_gap
from hil.scenario import ScenarioError, load_scenarios, loads_scenarios
from hil.scenario.schema import Scenario
from policies.onboard.pilots import pilot_names

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
    p.add_argument("--seed", type=int, default=None, help="seed instead of each scenario's (with --seeds: "
                                                          "the first seed, default 0)")
    p.add_argument("--seeds", type=int, default=1, metavar="N",
                   help="fly every scenario with N seeds (--seed, --seed + 1, ...) and compare the pilots "
                        "paired over scenarios x seeds, with 95 %% intervals (default 1)")
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

    docs = []
    for i, c in enumerate(draw_crossings(n, np.random.default_rng(seed))):
        centre = ", ".join(f"{v:.4f}" for v in c.gap_centre_m)
        start = ", ".join(f"{v:.4f}" for v in c.start_m)
        docs.append(f"description: held-out crossing {i} (seed {seed})\n"
                    f"gap: {{centre_m: [{centre}], roll_deg: {c.roll_deg:.4f}}}\n"
                    f"initial: {{pos_m: [{start}]}}\n"
                    f"approach: {{speed_m_s: {c.speed_m_s:g}}}\nduration_s: 11\n")
    return loads_scenarios("---\n".join(docs), source=f"held_out_{seed}")


#: per-run figures compared, each over time (`hil.runner.over_time`): the approach is what a learned
#: pilot flies itself, the crossing adds the expert's traverse, the flight is the whole run
FIGURES = (
    ("approach_mean_angular_rate_rad_s", "mean angular rate, approach (rad/s)"),
    ("approach_mean_thrust_n", "mean thrust, approach (N)"),
    ("approach_max_angular_rate_rad_s", "max angular rate, approach (rad/s)"),
    ("crossing_mean_angular_rate_rad_s", "mean angular rate, approach + traverse (rad/s)"),
    ("crossing_mean_thrust_n", "mean thrust, approach + traverse (N)"),
    ("traverse_mean_angular_rate_rad_s", "mean angular rate, traverse (rad/s)"),
    ("recovery_mean_angular_rate_rad_s", "mean angular rate, recovery (rad/s)"),
    ("flight_mean_angular_rate_rad_s", "mean angular rate, flight (rad/s)"),
    ("flight_mean_thrust_n", "mean thrust, airborne (N)"),
)
#: the paper's findings (section VI): (what it says, figure, pilot a, pilot b): b's figure below a's
FINDINGS = (
    ("RL mitigates the attitude's vibration: e2e_rl turns less than e2e", "approach_mean_angular_rate_rad_s",
     "e2e", "e2e_rl"),
    ("RL's thrust is the lowest: e2e_rl below traditional", "approach_mean_thrust_n", "traditional",
     "e2e_rl"),
    ("RL's thrust is the lowest: e2e_rl below e2e", "approach_mean_thrust_n", "e2e", "e2e_rl"),
)
_SEGMENT_FIGURES = ("mean_angular_rate_rad_s", "mean_thrust_n", "max_angular_rate_rad_s")


def flight_figures(summary: dict[str, Any], cols: dict[str, np.ndarray]) -> dict[str, Any]:
    """One run's figures (`FIGURES`, from the summary's per-segment figures; None for a segment not
    flown) and its trajectory over the crossing +-0.5 s."""
    segments = (summary.get("flight_quality") or {}).get("segments") or {}
    fig: dict[str, Any] = {
        "success": bool(summary["crossed_gap"] and summary["collision"] is None),
        "crossed_gap": bool(summary["crossed_gap"]),
        "collision": summary["collision"],
        "min_clearance_m": summary["min_clearance_m"],
        "flight_mean_angular_rate_rad_s": summary["mean_angular_rate_rad_s"],
        "flight_mean_thrust_n": summary["mean_thrust_n"],
        "segments_s": {k: [v["start_s"], v["end_s"]] for k, v in segments.items()},
        "trajectory_m": [],
    }
    for seg in ("approach", "traverse", "recovery", "crossing"):
        for k in _SEGMENT_FIGURES:
            fig[f"{seg}_{k}"] = segments[seg][k] if seg in segments else None
    if "crossing" in segments:
        t = cols["t_s"]
        near = (t >= segments["crossing"]["start_s"] - 0.5) & (t <= segments["crossing"]["end_s"] + 0.5)
        pos = np.stack([cols["pos_m_x"], cols["pos_m_y"], cols["pos_m_z"]], 1)[near]
        fig["trajectory_m"] = np.round(pos[:: max(1, len(pos) // 200)], 4).tolist()
    return fig


def pooled(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """A pilot's figures over runs: success rate, the least clearance, the mean of each figure over the
    runs that have it."""
    def mean(key: str) -> float | None:
        vals = [r[key] for r in runs if r.get(key) is not None]
        return float(np.mean(vals)) if vals else None

    clear = [r["min_clearance_m"] for r in runs if r["min_clearance_m"] is not None]
    rate = float(np.mean([r["success"] for r in runs])) if runs else None
    return {"runs": len(runs), "success_rate": rate, "min_clearance_m": min(clear) if clear else None,
            **{k: mean(k) for k, _ in FIGURES}}


def paired_comparisons(units: list[dict[str, dict[str, Any]]], pilots: list[str]) -> dict[str, Any]:
    """Every pair of ``pilots`` (the later against the earlier) over ``units`` (per unit: pilot -> its
    run's figures), per figure of `FIGURES` and success (1/0): `hil.report.paired`."""
    out: dict[str, Any] = {}
    for i, a in enumerate(pilots):
        for b in pilots[i + 1:]:
            per: dict[str, Any] = {}
            for key in ("success", *(k for k, _ in FIGURES)):
                va = [None if u[a].get(key) is None else float(u[a][key]) for u in units]
                vb = [None if u[b].get(key) is None else float(u[b][key]) for u in units]
                per[key] = paired_difference(a, b, va, vb).to_dict()
            out[f"{b} - {a}"] = per
    return out


def findings(paired: dict[str, Any]) -> list[dict[str, Any]]:
    """The paper's findings (`FINDINGS`) among the pairs flown: reproduced (b below a, the interval
    excluding zero), not reproduced (b above a, the interval excluding zero) or not resolved."""
    out = []
    for text, key, a, b in FINDINGS:
        d = paired.get(f"{b} - {a}", {}).get(key)
        if d is None:
            continue
        status = {f"{b} lower": "reproduced", f"{b} higher": "not reproduced"}.get(d["verdict"],
                                                                                  "not resolved")
        out.append({"finding": text, "figure": key, "status": status, **{k: d[k] for k in (
            "a", "b", "units", "mean_a", "mean_b", "mean_difference", "ci_low", "ci_high", "b_lower_in")}})
    return out


def compare(scenarios: list[Scenario], pilots: list[str], out: Path, options: RunOptions,
            progress: Any = print, seeds: list[int] | None = None,
            groups: dict[str, str] | None = None) -> dict[str, Any]:
    """Fly each scenario with each pilot, once per seed of ``seeds`` (None: once, with the options' or
    the scenario's seed; runs under ``out/<scenario>[/seed<k>]/<pilot>``); write and return the
    comparison (``out/compare.json``, ``out/compare.html``): per run, pooled per pilot, and paired over
    the units (scenario, seed), over all and per group (``groups``: scenario id -> group name)."""
    result: dict[str, Any] = {"pilots": pilots, "seeds": seeds, "interval": INTERVAL_METHOD,
                              "scenarios": {}, "pooled": {}}
    units: list[tuple[str, dict[str, dict[str, Any]]]] = []
    for s in scenarios:
        runs: dict[str, dict[str, Any]] = {}
        for seed in [None] if seeds is None else seeds:
            per: dict[str, Any] = {}
            where = out / s.id if seed is None else out / s.id / f"seed{seed}"
            for pilot in pilots:
                opts = replace(options, pilot=pilot) if seed is None else replace(
                    options, pilot=pilot, seed=seed, html_report="failed")
                run = run_scenario(s, where / pilot, opts)
                if run.summary.get("refused"):  # nothing flown: no figures to compare
                    raise RunSetupError(f"{s.id}: refused before take-off: {run.summary['refused']}")
                data = np.load(run.out_dir / "timeseries.npz")
                per[pilot] = flight_figures(run.summary, {k: data[k] for k in data.files})
                progress(f"{s.id}{'' if seed is None else f' seed {seed}'} {pilot}: "
                         f"{'crossed' if per[pilot]['success'] else 'FAILED'}, approach: mean rate "
                         f"{_fmt(per[pilot]['approach_mean_angular_rate_rad_s'])} rad/s, mean thrust "
                         f"{_fmt(per[pilot]['approach_mean_thrust_n'])} N")
            runs[str(run.summary["mode"]["seed"])] = per
            units.append(((groups or {}).get(s.id, "scenarios"), per))
        result["scenarios"][s.id] = {"description": s.description, "gap": _gap_outline(s),
                                     "pilots": next(iter(runs.values())), "seeds": runs}
    for pilot in pilots:
        result["pooled"][pilot] = pooled([u[pilot] for _, u in units])
    result["paired"] = {"all": paired_comparisons([u for _, u in units], pilots)}
    for g in sorted({g for g, _ in units}) if len({g for g, _ in units}) > 1 else []:
        result["paired"][g] = paired_comparisons([u for gg, u in units if gg == g], pilots)
    result["findings"] = findings(result["paired"]["all"])
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
    cols = (("runs", "runs"), ("success_rate", "success"), ("success", "success"),
            ("min_clearance_m", "min clearance (m)"), *FIGURES)
    keys = [(k, name) for k, name in cols if any(k in r for r in rows.values())]
    head = "".join(f"<th>{html.escape(name)}</th>" for _, name in keys)
    body = "".join(f'<tr><td style="color:{colours[p]}"><b>{html.escape(p)}</b></td>'
                   + "".join(f"<td>{_fmt(r.get(k))}</td>" for k, _ in keys) + "</tr>"
                   for p, r in rows.items())
    return f"<table><tr><th>pilot</th>{head}</tr>{body}</table>"


def _interval(d: dict[str, Any]) -> str:
    if d["ci_low"] is None:
        return "-"
    return f"[{d['ci_low']:+.4g}, {d['ci_high']:+.4g}]"


def _paired_table(paired: dict[str, Any]) -> str:
    labels = dict((("success", "success (1/0)"), *FIGURES))
    rows = []
    for pair, per in paired.items():
        for key, d in per.items():
            rows.append(f"<tr><td>{html.escape(pair)}</td><td>{html.escape(labels[key])}</td><td>{d['units']}</td>"
                        f"<td>{_fmt(d['mean_a'], 5)}</td><td>{_fmt(d['mean_b'], 5)}</td>"
                        f"<td>{_fmt(d['mean_difference'], 4)}</td><td>{_interval(d)}</td>"
                        f"<td>{d['b_lower_in']}/{d['units']}</td><td>{html.escape(d['verdict'])}</td></tr>")
    return ("<table><tr><th>b - a</th><th>figure</th><th>units</th><th>mean a</th><th>mean b</th>"
            "<th>mean difference</th><th>95 % interval</th><th>b lower in</th><th>verdict</th></tr>"
            + "".join(rows) + "</table>")


def _findings_table(found: list[dict[str, Any]]) -> str:
    rows = "".join(f"<tr><td>{html.escape(f['finding'])}</td><td>{html.escape(f['status'])}</td>"
                   f"<td>{_fmt(f['mean_difference'], 4)}</td><td>{_interval(f)}</td>"
                   f"<td>{f['units']}</td></tr>"
                   for f in found)
    return ("<table><tr><th>the paper's finding</th><th>here</th><th>mean difference</th>"
            f"<th>95 % interval</th><th>units</th></tr>{rows}</table>")


def render_html(result: dict[str, Any]) -> str:
    """The comparison as one self-contained page (no scripts, no network)."""
    colours = dict(zip(result["pilots"], COLOURS, strict=False))
    top, side = View(math.radians(-90), math.radians(89.9)), View(math.radians(180), 0.0)
    seeds = result.get("seeds")
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>hil compare</title><style>"
             "body{font-family:sans-serif;margin:20px}table{border-collapse:collapse;margin:8px 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}</style></head><body>",
             "<h1>Pilots compared through the links</h1>",
             "<p>Figures over time (each sample weighted by the time it holds): the approach (what a learned "
             "pilot flies), approach + traverse, the traverse and recovery (the expert's), the whole flight. "
             "Success: through the opening, no collision. "
             + (f"Each scenario flown with seeds {html.escape(str(seeds))}. " if seeds else "")
             + "Paired differences over the units (scenario, seed); interval: "
             + f"{html.escape(INTERVAL_METHOD)}."
             "</p>"]
    if result.get("findings"):
        parts += ["<h2>The paper's findings</h2>", _findings_table(result["findings"])]
    parts += ["<h2>Pooled over the runs</h2>", _table(result["pooled"], colours)]
    for group, paired in (result.get("paired") or {}).items():
        parts += [f"<h2>Paired differences ({html.escape(group)})</h2>", _paired_table(paired)]
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
    if args.seeds < 1:
        print(f"hil compare: --seeds must be 1 or more, got {args.seeds}", file=sys.stderr)
        return 2
    if output_folder(args.out, "hil compare") is None:
        return 2
    seeds = None if args.seeds == 1 else [(args.seed or 0) + k for k in range(args.seeds)]
    groups = {s.id: "held_out" if s.source.startswith("held_out_") else "scenarios" for s in scenarios}
    try:
        compare(scenarios, pilots, Path(args.out), RunOptions(in_process=args.in_process, seed=args.seed),
                seeds=seeds, groups=groups)
    except (RunSetupError, ValueError) as exc:
        print(f"hil compare: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {Path(args.out) / 'compare.html'}, {Path(args.out) / 'compare.json'}")
    return 0
