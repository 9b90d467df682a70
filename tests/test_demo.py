"""`hil demo`: flies the open-loop sequence and writes its plot and summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli import main


def test_demo_writes_plot_and_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--out", str(tmp_path / "out"), "--profile", "n3_tx2"]) == 0
    printed = capsys.readouterr().out
    png, js = tmp_path / "out" / "demo.png", tmp_path / "out" / "demo.json"
    assert f"wrote {png}" in printed and f"wrote {js}" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads(js.read_text())
    assert summary["sim_time_s"] == pytest.approx(5.0)
    assert summary["max_height_m"] > 0.5  # it took off and climbed
    assert abs(summary["final_state"]["rpy_deg"][0]) < 2.0  # the 1-2-1 doublet ends level


def test_demo_rejects_an_unknown_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--out", str(tmp_path), "--profile", "no_such_vehicle"]) == 2
    assert "no built-in profile" in capsys.readouterr().err
