"""`hil bench`'s tick CPU rows read from the summaries of runs flown through ptys."""

from __future__ import annotations

from pathlib import Path

from hil.benches.runner import suite_cpu_rows, tick_cpu_rows
from hil.runner import RunOptions, run_scenario
from hil.scenario.loader import load_scenarios

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def test_tick_cpu_rows_are_each_sides_cpu_per_tick_of_the_flown_runs(tmp_path: Path) -> None:
    flown = load_scenarios(SCENARIOS / "command_link_down.scenario.yaml")[0]
    refused = load_scenarios(SCENARIOS / "narrow_gap_refused.scenario.yaml")[0]
    summaries = [run_scenario(s, tmp_path / s.id, RunOptions(html_report=False)).summary
                 for s in (flown, refused)]
    sm = summaries[0]
    assert sm["ticks"] > 0 and not summaries[1].get("ticks")  # the refused run flies no tick
    rows = {r.name: r for r in tick_cpu_rows(summaries)}
    assert set(rows) == {"tick_cpu_us_emulator", "tick_cpu_us_onboard"}
    assert rows["tick_cpu_us_emulator"].value == 1e6 * sm["cpu_s"]["harness"] / sm["ticks"]
    assert rows["tick_cpu_us_onboard"].value == 1e6 * sm["cpu_s"]["onboard"] / sm["ticks"]
    assert all(r.unit == "us" and "over 1 runs" in r.note for r in rows.values())
    # the suite's rows skip the refused run too (it has no onboard program to time)
    suite = {r.name: r.value for r in suite_cpu_rows(summaries, sm["sim_time_s"])}
    assert suite["onboard_startup_ms"] == 1e3 * sm["onboard_startup_s"]
    assert suite["tick_cpu_us_emulator"] == rows["tick_cpu_us_emulator"].value
    cpu_s = sm["cpu_s"]["harness"] + sm["cpu_s"]["onboard"]
    assert suite["suite_cpu_ms_per_sim_s"] == 1e3 * cpu_s / sm["sim_time_s"]
