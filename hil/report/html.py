"""report.html: one self-contained page per run (inline CSS and SVG, no scripts, no external files).

Verdict and checks first, then the 3D trajectory through the gap, attitude against command, thrust,
clearance, position and link rates over sim time, the link-statistics table, events and the scenario.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from html import escape
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from emulator.world import DEFAULT_WALL_HEIGHT_M, DEFAULT_WALL_WIDTH_M, rotation_zyx
from hil.report.summary import to_jsonable
from hil.report.svg import Band, Chart, Scene, Series, View, line_chart, scene_svg
from hil.report.timeseries import check_columns
from hil.scenario.schema import Scenario


def _yaml(data: object) -> str:
    """``data`` as YAML in the given key order, with libyaml's safe dumper where PyYAML has it (the same
    text as its own, a few times faster)."""
    return yaml.dump(data, Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper), sort_keys=False)

REPORT_NAME = "report.html"
MEASURED, COMMANDED = "#1f5fa8", "#e0801e"

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;
  margin:0;background:#f4f5f7;color:#1d232b}
main{max-width:1260px;margin:0 auto;padding:18px}
h1{font-size:20px;margin:0 0 4px}
h2{font-size:17px;margin:26px 0 8px;border-bottom:1px solid #d5d9df;padding-bottom:4px}
.verdict{border-radius:10px;padding:16px 22px;color:#fff;display:flex;align-items:center;gap:26px}
.verdict.pass{background:#1e8a4c}
.verdict.fail{background:#c0392b}
.verdict .word{font-size:46px;font-weight:800;letter-spacing:2px}
.verdict .what{font-size:15px}
.verdict .what b{font-size:18px}
.meta{color:#4a5460;margin:8px 0 0;font-size:13px}
.meta span{margin-right:16px;white-space:nowrap}
table{border-collapse:collapse;background:#fff;width:100%;font-size:13px}
th,td{border:1px solid #dde1e6;padding:5px 9px;text-align:left;vertical-align:top}
th{background:#eceff3}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.ok{color:#1e8a4c;font-weight:700}
.bad{color:#c0392b;font-weight:700}
tr.failed td{background:#fdeceb}
.grid2{display:grid;grid-template-columns:repeat(2,minmax(0,1fr));gap:12px}
.card{background:#fff;border:1px solid #dde1e6;border-radius:8px;padding:6px}
svg{display:block;max-width:100%;height:auto}
svg text{font:11px system-ui,sans-serif;fill:#333}
svg .ct{font-size:13px;font-weight:600}
svg .tk{fill:#555}
svg .lg{font-size:11px}
svg .mk{fill:#7a2a90;font-size:10px}
svg .lbl{font-size:12px;font-weight:600}
.frame{fill:none;stroke:#9aa3ad}
.grid{stroke:#e6e9ed}
.band{fill:#f5b7b1;opacity:.45}
.mark{stroke:#7a2a90;stroke-dasharray:3 3}
.hline{stroke:#888;stroke-dasharray:6 4}
.floor{fill:#eef1f4;stroke:#b8c0c8}
.fgrid{stroke:#d5dbe1;fill:none}
.shadow{fill:none;stroke:#c3c9cf;stroke-width:1.5}
.wall{fill:#8d6e63;fill-opacity:.4;stroke:#5d4037}
.gapedge{fill:none;stroke:#3e2723;stroke-width:2}
.traj{stroke-width:3;stroke-linecap:round}
.start{fill:#1e8a4c;stroke:#fff;stroke-width:2}
.end{fill:#c0392b;stroke:#fff;stroke-width:2}
.cross{fill:#ffd400;stroke:#222;stroke-width:1.2}
.note{color:#5a6470;font-size:12px}
pre{background:#fff;border:1px solid #dde1e6;
  padding:10px;overflow:auto;font-size:12px}
"""


def write_report_html(
    out_dir: str | Path,
    summary: Mapping[str, Any],
    timeseries: Mapping[str, np.ndarray],
    scenario: Scenario,
) -> Path:
    """Write ``out_dir/report.html`` for one run; returns the path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / REPORT_NAME
    path.write_text(render_report_html(summary, timeseries, scenario), encoding="utf-8")
    return path


def render_report_html(
    summary: Mapping[str, Any], timeseries: Mapping[str, np.ndarray], scenario: Scenario
) -> str:
    """The report page as a string (see `write_report_html`)."""
    cols = {k: np.asarray(v, dtype=float) for k, v in check_columns(timeseries).items()}
    summary = to_jsonable(dict(summary))
    crossing = _crossing(summary, cols, scenario)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{'PASSED' if summary.get('passed') else 'FAILED'}: {escape(scenario.id)}</title>",
        f"<style>{_CSS}</style></head><body><main>",
        _verdict(summary, scenario),
        _checks(summary),
        "<h2>Trajectory through the gap</h2>",
        _scenes(cols, scenario, crossing),
        "<h2>Attitude, thrust and clearance</h2>",
        _charts(cols, scenario, crossing),
        _segments(summary),
        "<h2>Link statistics</h2>",
        _links(summary),
        _realtime(summary),
        _events(summary),
        "<h2>Scenario</h2>",
        f"<pre>{escape(_yaml(scenario.to_dict(include_meta=False)))}</pre>",
        f'<p class="note">From {escape(scenario.source)} line {scenario.line}. '
        "Data: summary.json and timeseries.npz next to this page.</p>",
        "</main></body></html>",
    ]
    return "\n".join(parts)


# --- sections ------------------------------------------------------------------------------------
def _fmt(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "—"
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:.3e}"
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, dict):
        return ", ".join(f"{k}: {_fmt(v)}" for k, v in value.items())
    return str(value)


def _verdict(summary: dict[str, Any], scenario: Scenario) -> str:
    passed = bool(summary.get("passed"))
    checks = summary.get("checks") or []
    failed = sum(1 for c in checks if isinstance(c, dict) and not c.get("passed"))
    meta = [
        ("scenario", scenario.id),
        ("pilot", scenario.pilot),
        ("flown by", _flown_by((summary.get("mode") or {}).get("pilot_flies"))),
        ("vehicle", scenario.vehicle),
        ("physics", scenario.physics),
        ("seed", scenario.seed),
        ("gap roll", f"{scenario.gap.roll_deg:g} deg"),
        ("end", summary.get("end_reason")),
        ("sim time", _seconds(summary.get("sim_time_s"))),
        ("wall time", _seconds(summary.get("wall_time_s"))),
        ("CPU time", _cpu(summary.get("cpu_s"))),
    ]
    meta_html = "".join(
        f"<span><b>{escape(k)}</b> {escape(_fmt(v))}</span>" for k, v in meta if v is not None
    )
    tally = f"{len(checks) - failed} of {len(checks)} checks passed" if checks else "no checks recorded"
    return (
        f'<section class="verdict {"pass" if passed else "fail"}"><div class="word">'
        f'{"PASSED" if passed else "FAILED"}</div><div class="what"><b>{escape(scenario.id)}</b><br>'
        f"{escape(scenario.description)}<br>{escape(tally)}</div></section>"
        f'<p class="meta">{meta_html}</p>'
    )


def _segments(summary: dict[str, Any]) -> str:
    """Angular rate and thrust per mission segment, over time (the summary's figures)."""
    segs = (summary.get("flight_quality") or {}).get("segments") or {}
    if not isinstance(segs, dict) or not segs:
        return ""
    keys = (("duration_s", "duration (s)"), ("mean_angular_rate_rad_s", "mean rate (rad/s)"),
            ("max_angular_rate_rad_s", "max rate (rad/s)"), ("mean_thrust_n", "mean thrust (N)"))
    rows = "".join(f"<tr><td>{escape(str(name))}</td>"
                   + "".join(f"<td>{escape(_fmt(f.get(k)))}</td>" for k, _ in keys) + "</tr>"
                   for name, f in segs.items() if isinstance(f, dict))
    head = "".join(f"<th>{escape(label)}</th>" for _, label in keys)
    return ("<h2>Per segment, over time</h2><table><tr><th>segment</th>" + head + "</tr>" + rows
            + '</table><p class="note">Each sample weighted by the time it holds (the recorder samples '
            "ten times as often near the gap).</p>")


def _flown_by(flies: Any) -> str | None:
    """"approach: end-to-end network; traverse, recovery, hover: expert ..." from the pilot's report."""
    if not isinstance(flies, dict) or not flies:
        return None
    groups: dict[str, list[str]] = {}
    for segment, what in flies.items():
        groups.setdefault(str(what), []).append(str(segment))
    return "; ".join(f"{', '.join(segs)}: {what}" for what, segs in groups.items())


def _seconds(value: Any) -> str | None:
    return None if not isinstance(value, int | float) else f"{value:.2f} s"


def _cpu(value: Any) -> str | None:
    """"harness 0.29 s, onboard 0.22 s" from the summary's ``cpu_s`` (the sides whose time is known)."""
    if not isinstance(value, dict):
        return None
    known = [f"{k} {v:.2f} s" for k, v in value.items()
             if isinstance(v, int | float) and not isinstance(v, bool) and 0.0 <= v < math.inf]
    return ", ".join(known) or None


def _checks(summary: dict[str, Any]) -> str:
    checks = [c for c in summary.get("checks") or [] if isinstance(c, dict)]
    if not checks:
        return '<h2>Checks</h2><p class="note">The run recorded no checks.</p>'
    rows = []
    for c in checks:
        ok = bool(c.get("passed"))
        rows.append(
            f'<tr class="{"" if ok else "failed"}">'
            f'<td class="{"ok" if ok else "bad"}">{"pass" if ok else "FAIL"}</td>'
            f"<td>{escape(str(c.get('name', '?')))}</td><td>{escape(_fmt(c.get('expected')))}</td>"
            f"<td>{escape(_fmt(c.get('observed')))}</td>"
            f'<td class="num">{escape(_fmt(c.get("time_s")))}</td></tr>'
        )
    return (
        "<h2>Checks</h2><table><tr><th></th><th>check</th><th>expected</th><th>observed</th>"
        f"<th>sim time (s)</th></tr>{''.join(rows)}</table>"
    )


def _crossing(
    summary: dict[str, Any], cols: dict[str, np.ndarray], scenario: Scenario
) -> dict[str, Any] | None:
    """The crossing from the summary, else where the path first crosses the gap plane (interpolated)."""
    given = summary.get("crossing")
    if isinstance(given, dict) and given.get("point_m") is not None:
        return given
    pos = _positions(cols)
    if pos is None:
        return None
    rot = rotation_zyx(scenario.gap.roll_rad, scenario.gap.pitch_rad, scenario.gap.yaw_rad)
    side = (pos - np.asarray(scenario.gap.centre_m)) @ rot[:, 0]
    hits = np.nonzero((side[:-1] < 0) & (side[1:] >= 0))[0]
    if len(hits) == 0:
        return None
    k = int(hits[0])
    f = float(-side[k] / (side[k + 1] - side[k])) if side[k + 1] != side[k] else 0.0
    t = cols["t_s"]
    return {
        "time_s": float(t[k] + f * (t[k + 1] - t[k])),
        "point_m": (pos[k] + f * (pos[k + 1] - pos[k])).tolist(),
    }


def _positions(cols: dict[str, np.ndarray]) -> np.ndarray | None:
    names = ("pos_m_x", "pos_m_y", "pos_m_z")
    return np.stack([cols[n] for n in names], axis=1) if all(n in cols for n in names) else None


def _speed(cols: dict[str, np.ndarray], pos: np.ndarray) -> np.ndarray:
    names = ("vel_m_s_x", "vel_m_s_y", "vel_m_s_z")
    if all(n in cols for n in names):
        return np.linalg.norm(np.stack([cols[n] for n in names], axis=1), axis=1)
    if len(pos) < 2:
        return np.zeros(len(pos))
    return np.linalg.norm(np.gradient(pos, cols["t_s"], axis=0), axis=1)


def _scenes(cols: dict[str, np.ndarray], scenario: Scenario, crossing: dict[str, Any] | None) -> str:
    pos = _positions(cols)
    if pos is None:
        return '<p class="note">No position columns (pos_m_x, pos_m_y, pos_m_z) were recorded.</p>'
    gap = scenario.gap
    rot = rotation_zyx(gap.roll_rad, gap.pitch_rad, gap.yaw_rad)
    point = crossing.get("point_m") if crossing else None
    scene = Scene(
        gap_centre_m=np.asarray(gap.centre_m, dtype=float),
        gap_rotation=rot,
        gap_width_m=gap.width_m,
        gap_height_m=gap.height_m,
        lab_min_m=np.asarray(scenario.lab.min_m, dtype=float),
        lab_max_m=np.asarray(scenario.lab.max_m, dtype=float),
        pos_m=pos,
        speed_m_s=_speed(cols, pos),
        crossing_m=np.asarray(point, dtype=float) if point is not None else None,
        wall_width_m=DEFAULT_WALL_WIDTH_M,
        wall_height_m=DEFAULT_WALL_HEIGHT_M,
    )
    oblique = View(azimuth_rad=gap.yaw_rad + math.radians(215.0), elevation_rad=math.radians(22.0))
    towards = -rot[:, 0]
    face_on = View(
        azimuth_rad=math.atan2(towards[1], towards[0]),
        elevation_rad=math.asin(max(-1.0, min(1.0, float(towards[2])))),
    )
    where = ""
    if crossing:
        p = crossing.get("point_m")
        through = crossing.get("through_opening")
        where = (
            f"Crossing (star) at {_fmt(crossing.get('time_s'))} s, point {_fmt(p)} m"
            + ("" if through is None else f", through the opening: {_fmt(through)}")
            + ". "
        )
    return (
        '<div class="grid2"><div class="card">'
        + scene_svg(scene, oblique, "Oblique view (world ENU, 1 m floor grid around the path)")
        + '</div><div class="card">'
        + scene_svg(scene, face_on, "Looking through the gap from the approach side", legend=False)
        + f'</div></div><p class="note">{escape(where)}Start: green circle; end: red square; '
        "line colour: speed. Wall drawn 4 m square around the opening.</p>"
    )


def _charts(cols: dict[str, np.ndarray], scenario: Scenario, crossing: dict[str, Any] | None) -> str:
    t = cols["t_s"]
    marks = (
        [(float(crossing["time_s"]), "crossing")] if crossing and crossing.get("time_s") is not None else []
    )
    bands = [
        Band(f.start_s, f.end_s if f.end_s is not None else float(t[-1]) if len(t) else f.start_s, f.kind)
        for f in scenario.faults
    ]
    charts: list[Chart] = []

    def add(
        title: str,
        unit: str,
        series: list[Series],
        hlines: tuple[tuple[float, str], ...] = (),
        min_span: float = 0.0,
    ) -> None:
        if series:
            charts.append(
                Chart(title, unit, t, series, marks=marks, bands=bands, hlines=hlines, min_span=min_span)
            )

    def s(name: str, label: str, colour: str, dashed: bool = False) -> list[Series]:
        return [Series(label, cols[name], colour, dashed)] if name in cols else []

    gap_roll = ((scenario.gap.roll_deg, "gap roll"),)
    for axis in ("roll", "pitch", "yaw"):
        # the heading the FC steers to (the command, or the heading it holds itself) where recorded
        cmd = s("yaw_sp_deg", "held or commanded", COMMANDED, True) if axis == "yaw" else []
        cmd = cmd or s(f"{axis}_cmd_deg", "commanded", COMMANDED, True)
        add(
            f"{axis.capitalize()}",
            "deg",
            s(f"{axis}_deg", "measured", MEASURED) + cmd,
            gap_roll if axis == "roll" else (),
            min_span=10.0,
        )
    add("Thrust command", "%", s("thrust_cmd_pct", "thrust", "#6c3483"))
    add("Largest motor command", "%", s("motor_max_pct", "motor", "#a04000"), ((100.0, "full throttle"),))
    add("Clearance to the gap's edges", "m", s("clearance_m", "clearance", "#117a65"), ((0.0, "contact"),))
    add(
        "Position",
        "m",
        s("pos_m_x", "x", "#c0392b") + s("pos_m_y", "y", "#27ae60") + s("pos_m_z", "z", "#2c6fbb"),
    )
    pos = _positions(cols)
    if pos is not None:
        add("Speed", "m/s", [Series("speed", _speed(cols, pos), "#34495e")])
    add(
        "Link rates",
        "Hz",
        s("command_rate_hz", "setpoints at FC", "#1f5fa8")
        + s("mocap_rate_hz", "mocap at onboard", "#e0801e"),
    )
    if not charts:
        return '<p class="note">No attitude, thrust or clearance columns were recorded.</p>'
    note = '<p class="note">Dashed: commanded. Purple line: gap crossing. Shaded: scheduled faults.</p>'
    return (
        '<div class="grid2">'
        + "".join(f'<div class="card">{line_chart(c)}</div>' for c in charts)
        + "</div>"
        + note
    )


def _links(summary: dict[str, Any]) -> str:
    links = summary.get("links")
    if not isinstance(links, dict) or not links:
        return '<p class="note">No link statistics recorded.</p>'
    return _stat_table(links)


def _realtime(summary: dict[str, Any]) -> str:
    """A real-time run's health: how late the emulator loop woke, the streams' rates and gaps."""
    rt = summary.get("realtime")
    if not isinstance(rt, dict):
        return ""
    contact = rt.get("contact_s")
    first = "no frame from the onboard program" if contact is None else (
        f"the onboard program's first frame at {_fmt(contact)} s; the run's duration counts from there")
    return (f"<h2>Real time</h2><p class=\"note\">{escape(first)}.</p>"
            + _stat_table({k: v for k, v in rt.items() if isinstance(v, dict)}))


def _stat_table(groups: dict[str, Any]) -> str:
    """Named groups of statistics as one table, a column per group."""
    links = groups
    names = [n for n, v in links.items() if isinstance(v, dict)]
    stats: list[str] = []
    for n in names:
        for key in links[n]:
            if key not in stats:
                stats.append(key)
    head = "".join(f"<th>{escape(n)}</th>" for n in names)
    rows = "".join(
        f"<tr><td>{escape(k)}</td>"
        + "".join(f'<td class="num">{escape(_fmt(links[n].get(k)))}</td>' for n in names)
        + "</tr>"
        for k in stats
    )
    return f"<table><tr><th>statistic</th>{head}</tr>{rows}</table>"


def _events(summary: dict[str, Any]) -> str:
    events = [e for e in summary.get("events") or [] if isinstance(e, dict)]
    if not events:
        return ""
    rows = "".join(
        f'<tr><td class="num">{escape(_fmt(e.get("time_s")))}</td><td>{escape(str(e.get("source", "")))}</td>'
        f"<td>{escape(str(e.get('text', '')))}</td></tr>"
        for e in events
    )
    return f"<h2>Events</h2><table><tr><th>sim time (s)</th><th>source</th><th>what</th></tr>{rows}</table>"
