"""`hil run` as a user calls it: exit 0 when every check passes, 1 when one fails (the harness reports
a collision it was not told to expect), 2 for bad files, each with a message naming file, line, field."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from processes import kill_session, processes_of_session

HIL = [sys.executable, "-m", "hil.cli"]

PASSING = """
description: command link lost during the climb; the FC must fail safe to a hover
gap: {roll_deg: 0}
faults:
  - {kind: command_link_down, start_s: 1.0}
duration_s: 2.5
expect: {crosses_gap: false, recovery: false, failsafe_expected: hover}
"""
FAILING = PASSING.replace("failsafe_expected: hover", "failsafe_expected: false")
CROSSING_20S = """
description: the 60 deg gap at 2.5 m/s, then hovering to 20 s
gap: {roll_deg: -60}
approach: {speed_m_s: 2.5}
duration_s: 20
"""


def _a_run_flying(out: Path, besides: str, timeout_s: float = 60.0) -> str:
    """The id of a run under ``out`` (not ``besides``) whose onboard program has started (its event log
    has a line) and which has not finished (no summary yet)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for run_dir in out.iterdir() if out.is_dir() else ():
            log = run_dir / "onboard_events.jsonl"
            if (run_dir.name != besides and log.exists() and log.stat().st_size > 0
                    and not (run_dir / "summary.json").exists()):
                return run_dir.name
        time.sleep(0.002)
    raise AssertionError(f"no run was seen flying under {out} within {timeout_s} s")


def run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(HIL + args, cwd=cwd, capture_output=True, text=True, timeout=120)


def test_exit_0_when_the_checks_pass_and_1_when_one_fails(tmp_path):
    ok = tmp_path / "ok.scenario.yaml"
    ok.write_text(PASSING)
    p = run(["run", str(ok), "--in-process", "--out", str(tmp_path / "ok")], tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "PASSED ok" in p.stdout and str(tmp_path / "ok" / "report.html") in p.stdout
    summary = json.loads((tmp_path / "ok" / "summary.json").read_text())
    assert summary["passed"] is True and summary["failsafe_events"]
    bad = tmp_path / "bad.scenario.yaml"
    bad.write_text(FAILING)
    p = run(["run", str(bad), "--in-process", "--out", str(tmp_path / "bad")], tmp_path)
    assert p.returncode == 1, p.stdout + p.stderr
    assert "failed failsafe: expected no failsafe, observed failsafe_hover" in p.stdout


@pytest.mark.parametrize(
    ("text", "line", "what"),
    [
        ("description: x\ngap: {roll_deg: 30\n", 2, "not valid YAML: expected ','"),  # the unclosed {
        ("description: x\ngap:\n  rol_deg: 30\n", 3, "gap.rol_deg"),  # unknown field
        ("description: x\nduration_s: 8\ngap:\n  roll_deg: 120\n", 4, "gap.roll_deg"),  # out of range
    ],
    ids=["bad_yaml", "unknown_field", "out_of_range"],
)
def test_broken_files_exit_2_naming_file_line_and_field(tmp_path, text, line, what):
    f = tmp_path / "broken.scenario.yaml"
    f.write_text(text)
    p = run(["run", str(f), "--in-process"], tmp_path)
    assert p.returncode == 2
    assert f"broken.scenario.yaml:{line}" in p.stderr or f"broken.scenario.yaml:{line + 1}" in p.stderr, (
        p.stderr
    )
    assert what in p.stderr


@pytest.mark.parametrize(
    ("text", "line", "field"),
    [
        ("description: x\nduration_s: 1" + "0" * 309 + "\n", 2, "duration_s"),  # no float holds it
        ("description: x\nseed: 1" + "0" * 5000 + "\n", 2, "<yaml>"),  # past Python's 4300 digits
        ("description: x\ngap: " + "[" * 490 + "\n", 2, "<yaml>"),  # deep and unclosed
        ("description: x\ngap: " + "[" * 1200 + "]" * 1200 + "\n", 2, "<yaml>"),  # past libyaml's 1000
        ("description: x\ngap:\n" + "".join(" " * i + "-\n" for i in range(1, 300)), 52, "<yaml>"),  # block
        ("description: x\n# " + "x" * 10_000_000 + "\n", 1, "<file>"),  # 10 MB
    ],
    ids=["huge_integer", "huge_integer_text", "deep_flow_unclosed", "deep_flow", "deep_block", "10_MB"],
)
def test_files_that_crashed_the_loader_exit_2_naming_file_line_and_field(tmp_path, text, line, field):
    """Values and structures past what Python's float, int and recursion hold: a usage error, no traceback."""
    f = tmp_path / "hostile.scenario.yaml"
    f.write_text(text)
    p = run(["run", str(f), "--in-process"], tmp_path)
    assert p.returncode == 2, p.stderr[-2000:]
    assert f"{f}:{line}: {field}: " in p.stderr and "Traceback" not in p.stderr, p.stderr[-2000:]


def test_bad_options_exit_2(tmp_path):
    f = tmp_path / "ok.scenario.yaml"
    f.write_text(PASSING)
    p = run(["run", str(f), "--in-process", "--pilot", "nobody"], tmp_path)
    assert p.returncode == 2 and "unknown pilot 'nobody'" in p.stderr
    p = run(["run", str(tmp_path / "missing.scenario.yaml")], tmp_path)
    assert p.returncode == 2 and "cannot read" in p.stderr


@pytest.mark.parametrize("command", ["run", "suite", "compare", "dryrun"])
def test_an_output_folder_that_cannot_be_made_exits_2_before_any_flight(tmp_path, command):
    f = tmp_path / "ok.scenario.yaml"
    f.write_text(PASSING + "dispersions: {runs: 2, vary: {gap.roll_deg: {uniform: [-5, 5]}}}\n")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    out = blocker / "reports"  # under a regular file: no folder can be made there
    target = str(tmp_path) if command == "suite" else str(f)
    p = run([command, target, "--out", str(out)], tmp_path)
    assert p.returncode == 2, p.stdout + p.stderr
    assert f"hil {command}: cannot make the output folder {out}" in p.stderr
    assert "Traceback" not in p.stderr and "PASSED" not in p.stdout  # said once, nothing flown


@pytest.mark.parametrize(("args", "said"), [
    (["view", ".", "--port", "99999"], "argument --port: a port is 0 (any free one) to 65535, got 99999"),
    (["run", "x.scenario.yaml", "--view-port", "-1"], "argument --view-port: a port is 0"),
    (["fc", "--view-port", "http"], "argument --view-port: a port is a whole number, got 'http'"),
])
def test_a_port_out_of_range_is_refused_by_the_option(tmp_path, args, said):
    p = run(args, tmp_path)
    assert p.returncode == 2 and said in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_the_recovery_point_comes_from_the_scenario_not_the_pilot():
    import math

    import numpy as np

    from emulator.world import Gap
    from hil.runner.run import recovery_point_m

    level = Gap(centre_m=(0.0, 0.5, 2.1))
    # the paper's case: start at (-2, -1), cross along +x, hover 2.5 m past the centre, 1 m up
    assert recovery_point_m(level.axes(), np.array(level.centre_m), np.array([-2.0, -1.0, 0.5])) == (
        2.5,
        0.5,
        1.0,
    )
    # from the other side the vehicle crosses along -x
    p = recovery_point_m(level.axes(), np.array(level.centre_m), np.array([2.0, 0.0, 0.5]))
    assert np.allclose(p, (-2.5, 0.5, 1.0))
    # a gap yawed 90 deg is crossed along +y; its roll does not change the horizontal direction
    yawed = Gap(centre_m=(1.0, 0.0, 2.0), yaw_rad=math.pi / 2, roll_rad=math.radians(60))
    p = recovery_point_m(yawed.axes(), np.array(yawed.centre_m), np.array([1.0, -3.0, 0.5]))
    assert np.allclose(p, (1.0, 2.5, 1.0))


def test_suite_flies_warm_and_cold_start_is_a_flag(tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "a.scenario.yaml").write_text(PASSING)
    (tmp_path / "s" / "b.scenario.yaml").write_text(PASSING)
    for flag, start in (([], "warm"), (["--cold-start"], "cold")):
        out = tmp_path / start
        p = run(["suite", str(tmp_path / "s"), "--out", str(out), "-j", "2", *flag], tmp_path)
        assert p.returncode == 0, p.stdout + p.stderr
        assert "2/2 passed" in p.stdout
        for name in ("a", "b"):
            assert json.loads((out / name / "summary.json").read_text())["mode"]["onboard_start"] == start


def test_suite_starts_the_longest_runs_first_and_lists_them_in_the_suites_order(tmp_path):
    (tmp_path / "s").mkdir()
    for name, duration in (("a", 2.0), ("b", 3.0), ("c", 2.5)):
        (tmp_path / "s" / f"{name}.scenario.yaml").write_text(
            PASSING.replace("duration_s: 2.5", f"duration_s: {duration}"))
    p = run(["suite", str(tmp_path / "s"), "--out", str(tmp_path / "out"), "-j", "1"], tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    printed = [line.split()[1] for line in p.stdout.splitlines() if line.startswith("PASSED")]
    assert printed == ["b", "c", "a"]  # one worker: in the order they started, the longest first
    index = json.loads((tmp_path / "out" / "index.json").read_text())
    assert [r["id"] for r in index["results"]] == ["a", "b", "c"]


def test_a_suite_interrupted_half_way_indexes_what_finished_and_leaves_no_verdict_without_its_report(
        tmp_path):
    """Ctrl-C (SIGINT to the suite's process group) while a run is flying: exit 130, index.html lists
    the finished runs, each with the verdict of a flight the Ctrl-C did not touch (the run in flight
    finishes: its onboard program is not the terminal's to stop), and marks the others interrupted; a
    run folder holds summary.json only beside its report.html; no process of the suite is left."""
    (tmp_path / "s").mkdir()
    # twelve crossings of 20 s each (a fraction of a second of wall clock apiece, seconds on a loaded
    # host): the rest cannot all finish before the Ctrl-C; each passes only if its onboard program flies
    # it to the end (one that dies mid-run leaves the FC to fail safe, a check that fails)
    names = [f"r{k:02d}" for k in range(12)]
    for name in names:
        (tmp_path / "s" / f"{name}.scenario.yaml").write_text(CROSSING_20S)
    out = tmp_path / "out"
    p = subprocess.Popen([*HIL, "suite", str(tmp_path / "s"), "--out", str(out), "-j", "1"], cwd=tmp_path,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert p.stdout is not None
        first = p.stdout.readline()  # the first run's verdict
        assert first.startswith("PASSED"), first + p.stderr.read() if p.stderr else first
        flying = _a_run_flying(out, first.split()[1])
        os.killpg(p.pid, signal.SIGINT)
        rest, err = p.communicate(timeout=120)
    finally:
        leftover = processes_of_session(p.pid)
        kill_session(p.pid)
    assert p.returncode == 130, first + rest + err
    assert "interrupted: " in err and "Traceback" not in err, err
    index = json.loads((out / "index.json").read_text())
    finished = [r["id"] for r in index["results"] if not r.get("interrupted")]
    stopped = [r["id"] for r in index["results"] if r.get("interrupted")]
    assert first.split()[1] in finished and flying in finished, (flying, index)
    assert stopped and len(finished) + len(stopped) == len(names), index
    failed = {r["id"]: r.get("failed") for r in index["results"]
              if not r["passed"] and not r.get("interrupted")}
    assert failed == {}, failed  # (the run that was flying at the Ctrl-C among them, if it was stopped)
    html = (out / "index.html").read_text()
    assert html.count("INTERRUPTED") == len(stopped) and html.count("PASSED") == len(finished)
    for run_dir in out.iterdir():
        if run_dir.is_dir():
            assert (run_dir / "report.html").exists() or not (run_dir / "summary.json").exists(), run_dir
            assert (run_dir / "summary.json").exists() == (run_dir.name in finished), run_dir
    assert leftover == [], leftover
