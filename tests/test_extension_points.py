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
import yaml

from hil.runner import RunOptions, run_scenario
from hil.runner.checks import CHECK_KINDS, Check, Observations, check_registered
from hil.scenario import ScenarioError, loads_scenarios
from hil.scenario.expect_fields import EXPECT_FIELDS, ExpectField
from hil.scenario.fault_kinds import FAULT_KINDS, FaultKind, FaultTarget, fault_kind_registered
from hil.scenario.loader import EXPECT_ALIASES
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


# docs/extending.md, "A check": the `expect:` field it brings, and a function from the expectations and
# the observations to its verdicts

MIN_CLIMB = ExpectField("toy_min_climb_m_s", float | None, 0.3, lo=0.0, hi=10.0, lo_open=True,
                        doc="the vehicle rises faster than this at some moment; null: not checked")


def climbed(e: Expectations, obs: Observations) -> list[Check]:
    """The vehicle rose faster than ``expect.toy_min_climb_m_s`` at some moment of the run (the updraft
    pushed it)."""
    if e.toy_min_climb_m_s is None:
        return []
    vz = float(np.max(obs.columns["vel_m_s_z"]))
    return [Check("toy_climbed", vz > e.toy_min_climb_m_s, f"rises faster than {e.toy_min_climb_m_s:g} m/s",
                  f"{vz:.2f} m/s at most")]


HOVER = """
description: hovering before the gap; {extra}
gap: {{roll_deg: 0}}
initial: {{pos_m: [-2, -1, 1.5]}}
duration_s: 2.5
expect: {{crosses_gap: false, recovery: false}}
"""
UPDRAFT = "faults:\n  - {kind: toy_updraft, start_s: 0.5, end_s: 1.5, params: {force_n: 8}}\n"


def test_a_toy_fault_and_a_toy_check_fly_in_a_scenario(tmp_path: Path) -> None:
    with fault_kind_registered(Updraft), check_registered("toy_climbed", climbed, expect=MIN_CLIMB,
                                                          doc="a climb"):
        [pushed] = loads_scenarios(HOVER.format(extra="an updraft") + UPDRAFT)
        [calm] = loads_scenarios(HOVER.format(extra="calm"))
        [slow] = loads_scenarios(HOVER.format(extra="a slow climb expected").replace(
            "recovery: false", "recovery: false, toy_min_climb_m_s: 0.05") + UPDRAFT)
        [unchecked] = loads_scenarios(HOVER.format(extra="x").replace(
            "recovery: false", "recovery: false, toy_min_climb_m_s: null"))
        r = run_scenario(pushed, tmp_path / "pushed", RunOptions(in_process=True))
        c = run_scenario(calm, tmp_path / "calm", RunOptions(in_process=True))
        assert pushed.to_dict()["faults"][0]["params"] == {"force_n": 8.0}
        assert pushed.expect.toy_min_climb_m_s == 0.3 and slow.expect.toy_min_climb_m_s == 0.05
        assert unchecked.expect.toy_min_climb_m_s is None
        assert slow.to_dict()["expect"]["toy_min_climb_m_s"] == 0.05  # in summary.json as written
        assert loads_scenarios(yaml.safe_dump(slow.to_dict(include_meta=False)))[0].expect == slow.expect
    verdict = {ch.name: ch for ch in r.checks}["toy_climbed"]
    assert verdict.passed and verdict.expected == "rises faster than 0.3 m/s", verdict
    assert not {ch.name: ch for ch in c.checks}["toy_climbed"].passed  # the climb is the fault's
    assert r.summary["scenario"]["expect"]["toy_min_climb_m_s"] == 0.3
    assert r.summary["faults"][0]["kind"] == "toy_updraft"
    assert [e["text"] for e in r.summary["events"] if e["source"] == "fault"] == [
        "toy_updraft starts", "toy_updraft ends"]
    # unregistered again: the project's registries and the schema as they were
    assert "toy_updraft" not in FAULT_KINDS and "toy_climbed" not in CHECK_KINDS and not EXPECT_FIELDS
    with pytest.raises(ScenarioError, match=re.escape("faults[0].kind: ") + ".*toy_updraft"):
        loads_scenarios(HOVER.format(extra="x") + UPDRAFT)
    with pytest.raises(ScenarioError, match=re.escape("expect.toy_min_climb_m_s: unknown field")):
        loads_scenarios(HOVER.format(extra="x").replace("recovery: false", "toy_min_climb_m_s: 1"))


def test_a_checks_own_expect_field_is_validated_like_the_projects() -> None:
    with check_registered("toy_climbed", climbed, expect=MIN_CLIMB):
        for value, why in (("0", "expected a number > 0 and <= 10, got 0"),
                           ("fast", "expected a number > 0 and <= 10, got 'fast'"),
                           ("[1]", "expected a number > 0 and <= 10, got a list")):
            text = HOVER.format(extra="x").replace("recovery: false}", "recovery: false,\n"
                                                   f"  toy_min_climb_m_s: {value}}}")
            with pytest.raises(ScenarioError) as info:
                loads_scenarios(text, source="t.scenario.yaml")
            error = str(info.value)
            assert error.startswith("t.scenario.yaml:7: expect.toy_min_climb_m_s: ") and why in error, error
        with pytest.raises(ScenarioError, match="did you mean 'toy_min_climb_m_s'"):
            loads_scenarios(HOVER.format(extra="x").replace("recovery: false", "toy_min_clim_m_s: 1"))
    for expect, why in ((ExpectField("crosses_gap", bool, True, "?"), "'crosses_gap' exists already"),
                        ("crosses_gap", "'crosses_gap' is set by another check"),
                        ("toy_field", "'toy_field' is no field of expect")):
        with pytest.raises(ValueError, match=re.escape(why)), check_registered("toy", climbed, expect=expect):
            pass
        assert "toy" not in CHECK_KINDS and not EXPECT_FIELDS


# docs/extending.md, "A pilot": one module with a `make_pilot(context)` factory, found by its name

TOY_PILOT = """
from policies.onboard.pilots import flown_by
from policies.onboard.pilots.traditional import TraditionalPilot


class ToyPilot(TraditionalPilot):
    \"\"\"The expert on the plan's reference, saying that a toy flew the approach.\"\"\"

    def __init__(self, mass_kg, max_tilt_deg):
        super().__init__(mass_kg, max_tilt_deg)
        self.flies = flown_by(approach="toy pilot")


def make_pilot(context):
    return ToyPilot(context.mass_kg, context.max_tilt_deg)
"""


def test_a_toy_pilot_added_as_one_module_flies_a_scenario(tmp_path: Path, monkeypatch) -> None:
    import policies.onboard.pilots as pilots

    (tmp_path / "pilots").mkdir()
    (tmp_path / "pilots" / "toy_pilot.py").write_text(TOY_PILOT)
    monkeypatch.setattr(pilots, "__path__", [*pilots.__path__, str(tmp_path / "pilots")])
    text = (ROOT / "scenarios" / "gap_roll30_2ms.scenario.yaml").read_text() + "pilot: toy_pilot\n"
    [s] = loads_scenarios(text)
    r = run_scenario(s, tmp_path / "run", RunOptions(in_process=True, html_report=False))
    assert r.passed, [f"{c.name}: {c.observed}" for c in r.failed_checks]
    assert r.summary["mode"]["pilot"] == "toy_pilot"
    assert r.summary["mode"]["pilot_flies"]["approach"] == "toy pilot"  # the program flew the toy


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


def _range_cell(meta: dict[str, Any]) -> str:
    """A field's range as the format document's tables write it (``-1..1``, ``> 0, <= 180``)."""
    lo, hi, lo_open, hi_open = (meta.get(k) for k in ("lo", "hi", "lo_open", "hi_open"))
    if lo is not None and hi is not None and not lo_open and not hi_open:
        return f"{lo:g}..{hi:g}"
    parts = [] if lo is None else [f"{'>' if lo_open else '>='} {lo:g}"]
    return ", ".join(parts + ([] if hi is None else [f"{'<' if hi_open else '<='} {hi:g}"]))


def test_the_format_documents_expect_table_is_the_schema() -> None:
    """Its rows are `Expectations`' own fields (and ``no_collision``, written the other way round), each
    with its range and choices as the schema bounds it."""
    doc = (ROOT / "docs" / "scenario-format.md").read_text()
    section = doc[doc.index("## `expect`: what must hold"):]
    cells = [[c.strip() for c in row.split("|")[1:-1]]
             for row in _table(section, "| field | type | default | range | meaning |")]
    rows = {c[0].strip("`"): c for c in cells}
    assert sorted(rows) == sorted([*Expectations.own_fields(), *EXPECT_ALIASES])
    for f in fields(Expectations):
        if f.name in rows:
            assert rows[f.name][3] == _range_cell(dict(f.metadata)), f.name
            assert all(f"`{c}`" in rows[f.name][1] for c in f.metadata["choices"]), f.name


def test_every_expect_field_is_owned_by_one_registered_check() -> None:
    owned = [name for k in CHECK_KINDS.values() for name in k.expect]
    assert sorted(owned) == sorted(Expectations.own_fields())
    with check_registered("toy_climbed", climbed, expect=MIN_CLIMB) as kind:
        assert kind.expect == ("toy_min_climb_m_s",) and EXPECT_FIELDS == {"toy_min_climb_m_s": MIN_CLIMB}
        assert Expectations().toy_min_climb_m_s == 0.3  # the default, also where no file gave it
