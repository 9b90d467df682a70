"""A sweep's page and JSON: go or no-go first, the success probability and its interval, the failures
ranked by check and phase with links to their runs' reports, the envelope map, the pass rate along each
dispersed field and the smallest clearances. One self-contained page (inline SVG, no scripts)."""

from __future__ import annotations

import json
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from hil.report.svg import colormap, nice_ticks
from hil.sweep.stats import SweepResult

SWEEP_JSON, SWEEP_HTML = "sweep.json", "sweep.html"
_STYLE = (
    "body{font:14px system-ui,sans-serif;margin:20px;color:#1d232b;max-width:1100px}"
    "table{border-collapse:collapse}td,th{border:1px solid #dde1e6;padding:4px 8px;text-align:left;"
    "vertical-align:top}.go{color:#1e8a4c}.nogo{color:#c0392b}.big{font-size:28px;font-weight:700}"
    "svg text{font:11px system-ui,sans-serif}"
)


def write_sweep(out: Path, result: SweepResult, description: str, wall_s: float) -> Path:
    """``out/sweep.json`` and ``out/sweep.html``; returns the page's path."""
    data = result.to_dict() | {"description": description, "wall_time_s": wall_s}
    (out / SWEEP_JSON).write_text(json.dumps(data, indent=1, default=str) + "\n", encoding="utf-8")
    path = out / SWEEP_HTML
    path.write_text(render(result, description, wall_s), encoding="utf-8")
    return path


def verdict_line(r: SweepResult) -> str:
    """``GO: 196/200 passed, P(success) 0.980 [0.950, 0.992] (95 %), needs >= 0.95``."""
    word = "GO" if r.go else "NO-GO"
    p = "n/a" if r.probability is None else f"{r.probability:.3f}"
    return (f"{word}: {r.passed}/{r.counted} passed, P(success) {p} [{r.interval[0]:.3f}, "
            f"{r.interval[1]:.3f}] ({r.confidence * 100:g} %), needs a lower bound >= {r.min_success:g}")


def render(r: SweepResult, description: str, wall_s: float) -> str:
    cls = "go" if r.go else "nogo"
    parts = [
        f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>Dry run: '
        f"{escape(r.scenario_id)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>Dry run: {escape(r.scenario_id)}</h1><p>{escape(description)}</p>",
        f'<p class="big {cls}">{"GO" if r.go else "NO-GO"}</p>',
        f"<p>{escape(verdict_line(r))}. {r.runs} runs ({len(r.invalid)} with draws that made no valid "
        f"scenario, not counted), {wall_s:.1f} s wall.</p>",
        "<p>Go when the lower end of the success probability's Wilson interval is at least the "
        "threshold (the scenario's <code>dispersions.go</code>).</p>",
        "<h2>What was varied</h2>", _varied(r.varied),
        "<h2>What fails</h2>", _failures(r),
        "<h2>Envelope</h2>", _envelope(r.envelope, r.min_success),
        "<h2>Pass rate along each dispersed field</h2>", _by_field(r.by_field, r.min_success),
        "<h2>Smallest clearance in the wall</h2>", _histogram(r.clearances_m),
    ]
    if r.invalid:
        parts += ["<h2>Draws that made no valid scenario</h2><ul>"]
        parts += [f"<li>run {d['index']}: {escape(str(d['why']))}</li>" for d in r.invalid[:20]]
        parts += ["</ul>"]
    parts.append("</body></html>")
    return "".join(parts)


def _failures(r: SweepResult) -> str:
    if not r.failures:
        return "<p>No run failed a check.</p>"
    rows = ["<table><tr><th>check</th><th>phase</th><th>runs</th><th>share</th><th>examples</th></tr>"]
    for f in r.failures:
        ex = "<br>".join(
            (f'<a href="{escape(e["report"])}">run {e["index"]}</a>' if e.get("report")
             else f"run {e['index']}")
            + f": {escape(str(e['observed']))[:160]}"
            for e in f["examples"]
        )
        rows.append(f"<tr><td>{escape(f['check'])}</td><td>{escape(f['phase'])}</td><td>{f['runs']}</td>"
                    f"<td>{f['fraction'] * 100:.1f} %</td><td>{ex}</td></tr>")
    rows.append("</table>")
    return "".join(rows)


def _varied(varied: list[dict[str, Any]]) -> str:
    if not varied:
        return "<p>No field dispersed.</p>"
    rows = ["<table><tr><th>field</th><th>drawn from</th><th>draws (smallest..largest)</th></tr>"]
    for v in varied:
        drawn = [f"{escape(name)}: {lo:.4g}..{hi:.4g}" for name, (lo, hi) in v["drawn"].items()]
        drawn += [escape(x) for x in v["values"]]
        rows.append(f"<tr><td>{escape(v['path'])}</td><td>{escape(v['how'])}</td>"
                    f"<td>{'<br>'.join(drawn) or '-'}</td></tr>")
    rows.append("</table>")
    return "".join(rows)


def _envelope(env: dict[str, Any] | None, go: float) -> str:
    if env is None:
        return "<p>No two scalar fields dispersed: no map.</p>"
    runs, passed = np.array(env["runs"]), np.array(env["passed"])
    ex, ey = env["x_edges"], env["y_edges"]
    nb = len(ex) - 1
    cell, left, top = 60, 70, 20
    w, h = left + nb * cell + 20, top + nb * cell + 50
    out = [f'<svg viewBox="0 0 {w} {h}" width="{w}" height="{h}" role="img">'
           "<title>pass rate over two dispersed fields</title>"]
    for iy in range(nb):
        for ix in range(nb):
            n, k = int(runs[iy, ix]), int(passed[iy, ix])
            x, y = left + ix * cell, top + (nb - 1 - iy) * cell
            fill = "#eeeeee" if n == 0 else rate_colour(k / n, go)
            label = "" if n == 0 else f"{k}/{n}"
            out.append(f'<rect x="{x}" y="{y}" width="{cell}" height="{cell}" fill="{fill}" stroke="#fff"/>'
                       f'<text x="{x + cell / 2}" y="{y + cell / 2 + 4}" text-anchor="middle">{label}</text>')
    for i, v in enumerate(ex):
        out.append(
            f'<text x="{left + i * cell}" y="{top + nb * cell + 14}" text-anchor="middle">{v:.3g}</text>')
    for i, v in enumerate(ey):
        out.append(f'<text x="{left - 4}" y="{top + (nb - i) * cell + 4}" text-anchor="end">{v:.3g}</text>')
    out.append(f'<text x="{left + nb * cell / 2}" y="{h - 8}" text-anchor="middle">{escape(env["x"])}</text>')
    out.append(f'<text x="12" y="{top + nb * cell / 2}" transform="rotate(-90 12 {top + nb * cell / 2})" '
               f'text-anchor="middle">{escape(env["y"])}</text></svg>')
    return ("<p>Each cell: runs passed / runs with draws in it. " + _COLOURS.format(go=go * 100) + "</p>"
            + "".join(out))


_COLOURS = ("Green: a pass rate at or above the go threshold ({go:g} %); below it amber, turning red "
            "as the rate falls to 0.")


def rate_colour(rate: float, go: float) -> str:
    """A pass rate's colour against the go threshold ``go``: green at or above it; below it from amber
    (just under) to red (0 % passed)."""
    if rate >= go:
        return "#8fd19e"
    t = rate / go if go > 0 else 0.0
    return f"#{240:02x}{round(90 + 110 * t):02x}{round(80 + 10 * t):02x}"


def _by_field(by_field: dict[str, list[dict[str, Any]]], go: float) -> str:
    if not by_field:
        return "<p>No numeric field dispersed.</p>"
    rows = ["<table><tr><th>field</th><th>pass rate by bin of the drawn values (runs)</th></tr>"]
    for path, bins in by_field.items():
        cells = "".join(
            f'<span style="display:inline-block;min-width:110px;padding:2px 4px;margin:1px;background:'
            f'{"#eee" if not b["runs"] else rate_colour(b["passed"] / b["runs"], go)}">'
            f'{b["lo"]:.3g}..{b["hi"]:.3g}: '
            + ("-" if not b["runs"] else f'{b["passed"]}/{b["runs"]}') + "</span>"
            for b in bins
        )
        rows.append(f"<tr><td>{escape(path)}</td><td>{cells}</td></tr>")
    rows.append("</table><p>" + _COLOURS.format(go=go * 100) + "</p>")
    return "".join(rows)


def _histogram(values: list[float]) -> str:
    if not values:
        return "<p>No run reached the wall.</p>"
    v = np.asarray(values, dtype=float)
    counts, edges = np.histogram(v, bins=min(20, max(5, len(v) // 5)))
    w, h, left, bottom = 600, 200, 40, 30
    pw, ph = w - left - 10, h - bottom - 10
    top_count = max(int(counts.max()), 1)
    out = [f'<svg viewBox="0 0 {w} {h}" width="{w}" height="{h}" role="img">'
           "<title>smallest clearance</title>"]
    bw = pw / len(counts)
    for i, c in enumerate(counts):
        bh = ph * c / top_count
        colour = colormap(i / max(len(counts) - 1, 1))
        out.append(f'<rect x="{left + i * bw:.1f}" y="{10 + ph - bh:.1f}" width="{bw - 1:.1f}" '
                   f'height="{bh:.1f}" fill="{colour}"><title>{edges[i]:.3f}..{edges[i + 1]:.3f} m: {c}'
                   f"</title></rect>")
    lo, hi = float(edges[0]), float(edges[-1])
    for t in nice_ticks(lo, hi):
        x = left + (t - lo) / (hi - lo or 1.0) * pw
        out.append(f'<text x="{x:.1f}" y="{h - 12}" text-anchor="middle">{t:g}</text>')
    out.append(f'<text x="{left + pw / 2}" y="{h - 1}" text-anchor="middle">m</text></svg>')
    return (f"<p>Median {np.median(v) * 100:.1f} cm, 5th percentile {np.percentile(v, 5) * 100:.1f} cm, "
            f"smallest {v.min() * 100:.1f} cm ({len(v)} runs reached the wall).</p>" + "".join(out))
