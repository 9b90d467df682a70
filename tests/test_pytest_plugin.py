"""The pytest plugin: scenario files collected as tests (one per document), failures showing the failed
checks and the report, markers from YAML, bad files as collection errors, JUnit XML, xdist."""

from __future__ import annotations

import json
import subprocess
import sys
import xml.etree.ElementTree as ET

FAILSAFE = """
name: {name}
description: the command link drops during the climb; the FC must fail safe
gap: {{roll_deg: 0}}
faults:
  - {{kind: command_link_down, start_s: 0.8}}
duration_s: 2.2
markers: [faults]
expect: {{crosses_gap: false, recovery: false, failsafe_expected: {fs}}}
"""


def pytest_run(args: list[str], cwd) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_scenarios_collected_run_and_reported(tmp_path):
    (tmp_path / "two.scenario.yaml").write_text(
        FAILSAFE.format(name="good", fs="hover") + "---\n" + FAILSAFE.format(name="wrong", fs="false")
    )
    (tmp_path / "skipped.scenario.yaml").write_text("description: not run\nskip: shows skip\n")
    xml = tmp_path / "junit.xml"
    p = pytest_run(
        [
            str(tmp_path),
            "-n",
            "2",
            "--hil-in-process",
            "--hil-out",
            str(tmp_path / "out"),
            f"--junitxml={xml}",
            "-m",
            "faults or not faults",
        ],
        tmp_path,
    )
    out = p.stdout
    assert p.returncode == 1, out
    assert "1 failed, 1 passed, 1 skipped" in out
    assert "failsafe: expected no failsafe; observed failsafe_hover (t = 1.7" in out
    assert str(tmp_path / "out" / "wrong" / "report.html") in out
    cases = {c.get("name"): c for c in ET.parse(xml).getroot().iter("testcase")}
    assert set(cases) == {"good", "wrong", "skipped"}
    assert cases["wrong"].find("failure") is not None and cases["good"].find("failure") is None
    p = pytest_run([str(tmp_path), "--collect-only", "-q", "-m", "not faults"], tmp_path)
    assert "good" not in p.stdout and "skipped" in p.stdout  # markers come from the YAML


def test_a_bad_file_is_a_collection_error_naming_file_line_field(tmp_path):
    (tmp_path / "bad.scenario.yaml").write_text("description: x\ngap:\n  roll_deg: sixty\n")
    p = pytest_run([str(tmp_path), "--collect-only"], tmp_path)
    assert p.returncode != 0
    assert "bad.scenario.yaml:3" in p.stdout and "gap.roll_deg" in p.stdout


def test_an_unknown_pilot_is_a_usage_error_naming_the_pilots(tmp_path):
    """As a vehicle that does not load: once, at start-up, not a traceback in every scenario."""
    (tmp_path / "one.scenario.yaml").write_text(FAILSAFE.format(name="one", fs="hover"))
    p = pytest_run([str(tmp_path), "--hil-in-process", "--pilot", "imitation"], tmp_path)
    assert p.returncode == 4, p.stdout + p.stderr  # pytest's usage error
    assert "--pilot imitation: unknown pilot; one of " in p.stderr and "traditional" in p.stderr, p.stderr
    assert "Traceback" not in p.stdout + p.stderr


def test_protocol_option_flies_the_scenario_over_djis_open_protocol(tmp_path):
    (tmp_path / "one.scenario.yaml").write_text(FAILSAFE.format(name="one", fs="hover"))
    out = tmp_path / "out"
    p = pytest_run([str(tmp_path), "--hil-in-process", "--hil-protocol", "dji_open", "--hil-out", str(out)],
                   tmp_path)
    assert p.returncode == 0, p.stdout
    capture = (out / "one" / "run.tlog").read_bytes()
    assert capture[8] == 0xAA  # after the first stamp: an OPEN-protocol frame, not MAVLink's 0xFD
    p = pytest_run([str(tmp_path), "--hil-protocol", "dji"], tmp_path)
    assert p.returncode != 0 and "invalid choice: 'dji'" in p.stderr


def test_scenarios_fly_warm_over_ptys_by_default_and_cold_on_request(tmp_path):
    (tmp_path / "two.scenario.yaml").write_text(
        FAILSAFE.format(name="a", fs="hover") + "---\n" + FAILSAFE.format(name="b", fs="hover")
    )
    for flag, start in (([], "warm"), (["--hil-cold-start"], "cold")):
        out = tmp_path / start
        p = pytest_run([str(tmp_path / "two.scenario.yaml"), "-n", "2", "--hil-out", str(out), *flag],
                       tmp_path)
        assert p.returncode == 0, p.stdout
        for name in ("a", "b"):
            summary = json.loads((out / name / "summary.json").read_text())
            assert summary["mode"]["onboard_start"] == start
            assert summary["mode"]["in_process"] is False
