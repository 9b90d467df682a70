"""Run results: summary.json, timeseries.npz and a self-contained report.html for a made-up 60 deg run."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from hil.report import read_summary, read_timeseries, write_report_html, write_summary, write_timeseries
from hil.report.synthetic import DEMO_SCENARIO, synthetic_run
from hil.scenario import Scenario, loads_scenarios


class Tags(HTMLParser):
    """Collects start tags (with attributes), text, and checks that svg/table/section elements close."""

    def __init__(self) -> None:
        super().__init__()
        self.starts: list[tuple[str, dict[str, str | None]]] = []
        self.text: list[str] = []
        self.open: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.starts.append((tag, dict(attrs)))
        if tag in ("svg", "table", "section", "main", "html"):
            self.open.append(tag)

    def handle_endtag(self, tag: str) -> None:
        if tag in ("svg", "table", "section", "main", "html"):
            assert self.open and self.open[-1] == tag, f"</{tag}> closes {self.open[-1:]}"
            self.open.pop()

    def handle_data(self, data: str) -> None:
        self.text.append(data)

    def count(self, tag: str, cls: str | None = None) -> int:
        return sum(
            1 for t, a in self.starts if t == tag and (cls is None or cls in (a.get("class") or "").split())
        )


def parse(html: str) -> Tags:
    tags = Tags()
    tags.feed(html)
    tags.close()
    assert tags.open == [], f"unclosed: {tags.open}"
    return tags


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    [s] = loads_scenarios(DEMO_SCENARIO, source="roll60.scenario.yaml")
    assert s.gap.roll_deg == -60.0
    return s


@pytest.fixture(scope="module")
def run(scenario: Scenario) -> tuple[dict, dict[str, np.ndarray]]:
    return synthetic_run(scenario, np.random.default_rng(7))


def assert_self_contained(html: str) -> None:
    lowered = html.lower()
    for needle in ("http://", "https://", "<script", "<link", " src=", "url(", "@import", "//cdn"):
        assert needle not in lowered, needle


def test_report_of_a_60_deg_crossing_is_one_self_contained_page(
    tmp_path: Path, scenario: Scenario, run
) -> None:
    summary, columns = run
    write_summary(tmp_path, summary)
    write_timeseries(tmp_path, columns)
    path = write_report_html(tmp_path, summary, columns, scenario)
    assert path == tmp_path / "report.html"
    html = path.read_text()
    assert_self_contained(html)
    tags = parse(html)
    # verdict first: the banner precedes every chart and names the scenario
    assert html.index("PASSED") < html.index("<svg")
    assert tags.count("section", "verdict") == 1 and tags.count("section", "pass") == 1
    assert scenario.id in html and scenario.description in html
    # every check is a row with its name, expected and observed values
    for check in summary["checks"]:
        assert f"<td>{check['name']}</td>" in html
    assert tags.count("td", "ok") == len(summary["checks"]) and tags.count("td", "bad") == 0
    # two 3D views (wall with the opening, coloured trajectory, start/end/crossing) and the charts
    assert tags.count("svg", "scene") == 2
    assert tags.count("path", "wall") == 2 and tags.count("polygon", "gapedge") == 2
    assert tags.count("line", "traj") > 100
    assert tags.count("circle", "start") == 2 and tags.count("rect", "end") == 2
    assert tags.count("polygon", "cross") == 2
    titles = " ".join(tags.text)
    for title in ("Roll", "Pitch", "Yaw", "Thrust command", "Clearance to the gap's edges", "Link rates"):
        assert title in titles
    assert tags.count("svg", "chart") >= 8
    # the roll chart shows measured and commanded, and the gap's roll as a reference line
    assert "gap roll" in html and "commanded" in html
    # the fault window is shaded, the link table has both links
    assert tags.count("rect", "band") >= 1
    assert "<th>command</th><th>mocap</th>" in html


def test_summary_and_timeseries_files_round_trip(tmp_path: Path, run) -> None:
    summary, columns = run
    spath = write_summary(
        tmp_path, {**summary, "extra": np.float32(0.5), "nan": float("nan"), "arr": np.arange(3)}
    )
    data = json.loads(spath.read_text())
    assert data == read_summary(tmp_path)
    assert data["passed"] is True and len(data["checks"]) == len(summary["checks"])
    assert data["extra"] == 0.5 and data["nan"] is None and data["arr"] == [0, 1, 2]
    assert data["scenario"]["gap"]["roll_deg"] == -60.0
    tpath = write_timeseries(tmp_path, columns)
    back = read_timeseries(tpath)
    assert sorted(back) == sorted(columns)
    for name, values in columns.items():
        np.testing.assert_array_equal(back[name], values)


def test_failed_run_says_failed_and_marks_the_failed_check(tmp_path: Path, scenario: Scenario, run) -> None:
    summary, columns = run
    checks = [dict(c) for c in summary["checks"]]
    checks[2] = {**checks[2], "passed": False, "observed": -0.031}
    bad = {**summary, "passed": False, "checks": checks}
    html = write_report_html(tmp_path, bad, columns, scenario).read_text()
    tags = parse(html)
    assert tags.count("section", "fail") == 1 and "FAILED" in html and "PASSED" not in html
    assert tags.count("tr", "failed") == 1 and tags.count("td", "bad") == 1
    assert "-0.031" in html and f"{len(checks) - 1} of {len(checks)} checks passed" in html


def test_crossing_is_found_from_the_trajectory_when_the_summary_has_none(scenario: Scenario, run) -> None:
    summary, columns = run
    from hil.report import render_report_html

    html = render_report_html({**summary, "crossing": None}, columns, scenario)
    m = re.search(r"Crossing \(star\) at ([0-9.]+) s", html)
    assert m is not None
    t_cross = 1.0 + scenario.approach.duration_s  # the made-up run passes the centre after hover + approach
    assert float(m.group(1)) == pytest.approx(t_cross, abs=0.01)


def test_sparse_or_hostile_inputs_still_render(tmp_path: Path, scenario: Scenario) -> None:
    t = np.linspace(0, 1, 5)
    html = write_report_html(tmp_path, {"passed": True}, {"t_s": t}, scenario).read_text()
    assert "No position columns" in html and "no checks recorded" in html
    parse(html)
    pos = np.full(5, np.nan)
    columns = {"t_s": t, "pos_m_x": pos, "pos_m_y": pos, "pos_m_z": pos, "roll_deg": pos}
    summary = {"passed": False, "checks": [{"name": "<script>alert(1)</script>", "passed": False}]}
    html = write_report_html(tmp_path, summary, columns, scenario).read_text()
    assert_self_contained(html)
    assert "&lt;script&gt;" in html
    parse(html)


@pytest.mark.parametrize(("cpu", "shown"), [
    ({"harness": 0.291, "onboard": 0.224}, "harness 0.29 s, onboard 0.22 s"),
    ({"harness": 0.5, "onboard": None}, "harness 0.50 s"),
    ({"harness": "x", "onboard": float("nan")}, None),
    ({"harness": True, "onboard": -0.2}, None),  # a bool and a negative figure are not times either
    ({"harness": float("inf"), "onboard": 0.1}, "onboard 0.10 s"),
    ("0.3", None),
])
def test_the_verdict_line_gives_each_side_s_cpu_time_that_is_known(tmp_path: Path, scenario: Scenario,
                                                                  cpu, shown) -> None:
    html = write_report_html(tmp_path, {"passed": True, "cpu_s": cpu}, {"t_s": np.linspace(0, 1, 5)},
                             scenario).read_text()
    parse(html)
    if shown is None:
        assert "CPU time" not in html
    else:
        assert f"<b>CPU time</b> {shown}</span>" in html


def test_timeseries_columns_are_checked(tmp_path: Path) -> None:
    t = np.arange(4.0)
    bad = [
        ({"pos_m_x": t}, "t_s"),
        ({"t_s": t, "x": np.arange(3.0)}, "3 rows"),
        ({"t_s": t, "x": np.zeros((4, 2))}, "1-D"),
        ({"t_s": t[::-1]}, "non-decreasing"),
        ({"t_s": t, "bad name": t}, "identifier"),
        ({"t_s": t, "s": np.array(["a"] * 4)}, "numbers"),
    ]
    for columns, words in bad:
        with pytest.raises(ValueError, match=words):
            write_timeseries(tmp_path, columns)
    assert not (tmp_path / "timeseries.npz").exists()


def test_a_chart_line_lifts_the_pen_at_each_sample_that_is_not_finite() -> None:
    """A NaN or an infinity in a series breaks its line there (a new 'M'), the finite stretches drawn as
    lines, a single point as a move only; a series with nothing finite draws no path."""
    from hil.report.svg import Chart, Series, line_chart

    t = np.arange(9.0)
    y = np.array([0.0, 1.0, np.nan, 3.0, 4.0, np.inf, 6.0, -np.inf, 8.0])
    series = [Series("a", y, "#000000"), Series("b", np.full(9, np.nan), "#111111")]
    svg = line_chart(Chart("x", "m", t, series))
    paths = re.findall(r'<path d="([^"]*)"', svg)
    assert len(paths) == 1  # the all-NaN series draws nothing
    runs = re.findall(r"M[^M]*", paths[0])
    assert [r.count("L") for r in runs] == [1, 1, 0, 0]  # (0, 1), (3, 4), (6), (8)
    assert all(re.fullmatch(r"M-?\d+\.\d,-?\d+\.\d(L-?\d+\.\d,-?\d+\.\d)*", r) for r in runs)


def test_the_drawings_coordinates_read_as_one_decimal_formatting_writes_them() -> None:
    """Every coordinate a chart or a scene draws is the text ``'%.1f'`` gives: random values across the
    table's range and beyond, ties of the binary value (x.25, x.75: to even) and values a hair either
    side of a printed half (0.05, 0.15, ...), negative zero and values that round to it, and values not
    finite or too large for the table."""
    from hil.report.svg import _points

    rng = np.random.default_rng(7)
    halves = np.arange(-20000, 20000) / 20 + 0.05  # (x.x5 as written: each a hair above or below)
    values = np.concatenate([
        rng.uniform(-1200.0, 1200.0, 20000), np.arange(-40000, 40000) / 40, halves,
        [0.0, -0.0, 0.04, -0.04, -0.05, 5e-324, -5e-324, 999.85, 999.899, 999.95, 1e13 + 0.25]])
    values = np.concatenate([values, np.nextafter(values, np.inf), np.nextafter(values, -np.inf)])
    for chunk in (values[np.abs(values) < 999.0], values, np.array([1.0, np.nan, np.inf, -np.inf])):
        xy = np.column_stack((chunk, chunk[::-1]))
        assert _points(xy, " ").split(" ") == [f"{x:.1f},{y:.1f}" for x, y in xy.tolist()]
