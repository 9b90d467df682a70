"""The extension points as docs/extending.md describes them: a fault kind and a check registered from
outside the project's files are accepted by scenario files and flown, and the registries are what the
loader, the runner and the format document read."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import MISSING, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.runner import RunOptions, run_scenario
from hil.runner.checks import CHECK_KINDS, Check, Observations, check_registered
from hil.scenario import ScenarioError, loads_scenarios
from hil.scenario.fault_kinds import FAULT_KINDS, FaultKind, FaultTarget, fault_kind_registered
from hil.scenario.schema import Expectations
from hil.scenario.spec import spec

ROOT = Path(__file__).resolve().parents[1]

# docs/extending.md, "A fault": its parameters (a frozen dataclass of `spec` fields) and its kind


@dataclass(frozen=True)
class UpdraftParams:
    force_n: float = spec(MISSING, lo=0.0, hi=20.0, lo_open=True, doc="upward force")


class Updraft(FaultKind):
    """A toy fault: an upward force on the airframe while it acts."""

    name = "toy_updraft"
    params = UpdraftParams
    acts_on = "emulator"
    params_doc = "`force_n`"
    doc = "an upward push on the vehicle"

    def switch(self, faults: Sequence[Any], time_s: float, target: FaultTarget) -> None:
        up = sum(f.params.force_n for f in faults if f.active(time_s))
        target.set_wind(np.array([0.0, 0.0, up]), np.zeros(3))


# docs/extending.md, "A check": a function from the expectations and the observations to its verdicts

def climbed(e: Expectations, obs: Observations) -> list[Check]:
    """The vehicle rose faster than 0.3 m/s at some moment of the run (the updraft pushed it)."""
    vz = float(np.max(obs.columns["vel_m_s_z"]))
    return [Check("toy_climbed", vz > 0.3, "rises faster than 0.3 m/s", f"{vz:.2f} m/s at most")]


HOVER = """
description: hovering before the gap; {extra}
gap: {{roll_deg: 0}}
initial: {{pos_m: [-2, -1, 1.5]}}
duration_s: 2.5
expect: {{crosses_gap: false, recovery: false}}
"""
UPDRAFT = "faults:\n  - {kind: toy_updraft, start_s: 0.5, end_s: 1.5, params: {force_n: 8}}\n"


def test_a_toy_fault_and_a_toy_check_fly_in_a_scenario(tmp_path: Path) -> None:
    with fault_kind_registered(Updraft), check_registered("toy_climbed", climbed, doc="a climb"):
        [pushed] = loads_scenarios(HOVER.format(extra="an updraft") + UPDRAFT)
        [calm] = loads_scenarios(HOVER.format(extra="calm"))
        r = run_scenario(pushed, tmp_path / "pushed", RunOptions(in_process=True))
        c = run_scenario(calm, tmp_path / "calm", RunOptions(in_process=True))
        assert pushed.to_dict()["faults"][0]["params"] == {"force_n": 8.0}
    verdict = {ch.name: ch for ch in r.checks}["toy_climbed"]
    assert verdict.passed, verdict.observed
    assert not {ch.name: ch for ch in c.checks}["toy_climbed"].passed  # the climb is the fault's
    assert r.summary["faults"][0]["kind"] == "toy_updraft"
    assert [e["text"] for e in r.summary["events"] if e["source"] == "fault"] == [
        "toy_updraft starts", "toy_updraft ends"]
    # unregistered again: the project's registries as they were
    assert "toy_updraft" not in FAULT_KINDS and "toy_climbed" not in CHECK_KINDS
    with pytest.raises(ScenarioError, match=re.escape("faults[0].kind: ") + ".*toy_updraft"):
        loads_scenarios(HOVER.format(extra="x") + UPDRAFT)


def test_a_registered_fault_kinds_parameters_are_validated_like_the_projects(tmp_path: Path) -> None:
    with fault_kind_registered(Updraft):
        for fault, where, why in (
            ("params: {force_n: 0}", "faults[0].params.force_n", "> 0 and <= 20, got 0"),
            ("params: {force: 1}", "faults[0].params.force", "did you mean 'force_n'?"),
            ("end_s: 1", "faults[0].params", "required for toy_updraft"),
        ):
            text = HOVER.format(extra="x") + f"faults:\n  - {{kind: toy_updraft, start_s: 0.5, {fault}}}\n"
            with pytest.raises(ScenarioError, match=re.escape(f"{where}: ") + ".*" + re.escape(why)):
                loads_scenarios(text)
        with pytest.raises(ValueError, match="registered already"), fault_kind_registered(Updraft):
            pass


def test_a_kind_that_says_not_where_it_acts_is_refused() -> None:
    class Nowhere(FaultKind):
        name, params, acts_on, doc = "toy_nowhere", UpdraftParams, "airframe", "?"

    with pytest.raises(ValueError, match="acts_on must be one of link, onboard, emulator"), \
            fault_kind_registered(Nowhere):
        pass
    assert "toy_nowhere" not in FAULT_KINDS


def _table(doc: str, header: str) -> set[str]:
    start = doc.index(header)
    rows = doc[start:].split("\n\n", 1)[0].splitlines()[2:]
    return set(rows)


def test_the_format_documents_tables_are_the_registries() -> None:
    doc = (ROOT / "docs" / "scenario-format.md").read_text()
    assert _table(doc, "| `kind` | params | meaning |") == {k.table_row() for k in FAULT_KINDS.values()}
    assert _table(doc, "| check | set by | what it checks |") == {k.table_row() for k in CHECK_KINDS.values()}


def test_every_expectation_sets_a_registered_check() -> None:
    set_by = {k.expect for k in CHECK_KINDS.values()} - {None}
    assert set_by == {f.name for f in fields(Expectations)}
