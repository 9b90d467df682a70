"""Scenario files: defaults, line-numbered errors for bad files, round trips and the examples."""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path

import pytest
import yaml

from hil.scenario import (
    Expectations,
    Scenario,
    ScenarioError,
    load_all,
    load_scenarios,
    loads_scenarios,
    schema,
)
from hil.scenario.fault_kinds import FAULT_KINDS, CorruptBytesParams, NoParams, ParamSetParams, WindGustParams
from hil.scenario.loader import EXPECT_ALIASES, FAULT_KEYS

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "scenarios" / "examples"


def write(tmp_path: Path, text: str, name: str = "x.scenario.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def error_of(path: Path) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        load_scenarios(path)
    return info.value


# --- a minimal file ------------------------------------------------------------------------------
MINIMAL = """\
description: cross a 60 deg gap at 2.5 m/s
gap:
  roll_deg: 60
approach:
  speed_m_s: 2.5
"""


def test_minimal_five_line_file_loads_with_the_documented_defaults(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL, "roll60.scenario.yaml")
    assert len(path.read_text().splitlines()) <= 5
    [s] = load_scenarios(path)
    assert s.id == "roll60" and s.source == str(path) and s.line == 1
    assert s.description == "cross a 60 deg gap at 2.5 m/s"
    assert s.gap.roll_deg == 60.0 and s.gap.roll_rad == pytest.approx(1.0471975512)
    assert s.approach.speed_m_s == 2.5 and s.approach.duration_s == 2.6
    assert (s.vehicle, s.physics, s.pilot) == ("n3_tx2", "native", "traditional")
    assert s.links.command.transport == "pty" and s.links.mocap.rate_hz > 0
    assert s.faults == () and s.skip is None and s.markers == () and s.realtime is False
    e = s.expect
    assert e.crosses_gap and not e.collision_expected and e.stays_in_lab
    assert e.recovery is not None and e.recovery.radius_m > 0 and e.recovery.time_s > 0
    assert e.failsafe_expected is False and e.onboard_abort_expected is False


# --- errors name the file, the line and the field ------------------------------------------------
def test_wrong_type_gives_file_line_field_and_what_was_expected(tmp_path: Path) -> None:
    path = write(tmp_path, "description: tilted\nseed: 3\ngap:\n  centre_m: [0, 0.5, 2]\n  roll_deg: sixty\n")
    err = error_of(path)
    assert str(err) == f"{path}:5: gap.roll_deg: expected a number between -90 and 90, got 'sixty'"
    assert (err.source, err.line, err.field) == (str(path), 5, "gap.roll_deg")


def test_value_out_of_range(tmp_path: Path) -> None:
    path = write(tmp_path, "description: d\nlinks:\n  mocap:\n    loss: 1.5\n")
    assert str(error_of(path)) == f"{path}:4: links.mocap.loss: expected a number between 0 and 1, got 1.5"
    path = write(tmp_path, "description: d\napproach: {speed_m_s: 0.5}\n")
    assert str(error_of(path)) == f"{path}:2: approach.speed_m_s: expected a number between 1 and 5, got 0.5"
    path = write(tmp_path, "description: d\n\n\nduration_s: 0\n")
    assert str(error_of(path)) == f"{path}:4: duration_s: expected a number > 0 and <= 3600, got 0"


def test_speeds_to_5_m_s_and_tilts_to_the_vehicles_limit(tmp_path: Path) -> None:
    """Past the paper's 60 deg and 3 m/s: 70 deg at 4-5 m/s loads; a tilt past the profile's limit (75 deg
    for n3_tx2, from roll and pitch together) is refused, naming the limit."""
    (s,) = loads_scenarios("description: d\ngap: {roll_deg: -70}\napproach: {speed_m_s: 4.0}\n")
    assert (s.gap.roll_deg, s.approach.speed_m_s) == (-70.0, 4.0)
    (s,) = loads_scenarios("description: d\napproach: {speed_m_s: 5}\n")
    assert s.approach.speed_m_s == 5.0
    path = write(tmp_path, "description: d\ngap:\n  roll_deg: 60\n  pitch_deg: 60\n")
    assert str(error_of(path)) == (f"{path}:3: gap.roll_deg: expected a gap tilt within the vehicle's tilt "
                                   "limit (75 deg for n3_tx2), got 75.5 deg")
    path = write(tmp_path, "description: d\nvehicle: f450\ngap: {roll_deg: 80}\n")
    assert "gap.roll_deg: expected a gap tilt within the vehicle's tilt limit" in str(error_of(path))


def test_unknown_field_with_did_you_mean(tmp_path: Path) -> None:
    path = write(tmp_path, "description: d\ngap:\n  rol_deg: 60\n")
    err = error_of(path)
    assert str(err).startswith(f"{path}:3: gap.rol_deg: unknown field (did you mean 'roll_deg'?)")
    path = write(tmp_path, "description: d\nexpectations:\n  crosses_gap: true\n")
    err = error_of(path)
    assert err.line == 2 and err.field == "expectations" and "did you mean 'expect'" in str(err)
    path = write(tmp_path, "description: d\nzzz: 1\n")
    assert "did you mean" not in str(error_of(path)) and "allowed here:" in str(error_of(path))


def test_missing_description(tmp_path: Path) -> None:
    path = write(tmp_path, "gap:\n  roll_deg: 30\n")
    err = error_of(path)
    assert (err.line, err.field) == (1, "description")
    assert str(err).startswith(f"{path}:1: description: required field missing")
    # in the second document of a file, the line is that document's
    path = write(tmp_path, "description: ok\n---\ngap: {roll_deg: 30}\n")
    assert error_of(path).line == 3


def test_bad_yaml(tmp_path: Path) -> None:
    path = write(tmp_path, "description: d\ngap:\n  roll_deg: [60\n  width_m: 1\n")
    err = error_of(path)
    assert err.field == "<yaml>" and err.line in (4, 5) and str(err).startswith(f"{path}:{err.line}: <yaml>:")
    path = write(tmp_path, "description: d\n  bad indent: 1\n")
    assert error_of(path).line == 2


def test_other_errors_point_at_the_right_line(tmp_path: Path) -> None:
    cases = {
        "description: d\ngap: {roll_deg: 1}\ngap: {roll_deg: 2}\n": (3, "gap", "given twice"),
        "description: d\nvehicle: n3tx2\n": (2, "vehicle", "did you mean 'n3_tx2'"),
        "description: d\nphysics: bullet\n": (2, "physics", "expected one of"),
        "description: d\npilot: magic\n": (2, "pilot", "traditional"),
        "description: d\nseed: 1.5\n": (2, "seed", "whole number"),
        "description: d\nrealtime: 1\n": (2, "realtime", "true or false"),
        "description: d\ngap:\n  centre_m: [0, 1]\n": (3, "gap.centre_m", "a list of 3 numbers"),
        "description: d\ngap:\n  centre_m: [0, 9, 2]\n": (3, "gap.centre_m", "inside the lab"),
        "description: d\nlab:\n  min_m: [0, 0, 0]\n  max_m: [1, -1, 3]\n": (
            4, "lab.max_m", "above lab.min_m"),
        "description: d\ngap: {width_m: 0.3, height_m: 0.5}\n": (2, "gap.height_m", "at most width_m"),
        "description: d\ninitial:\n  on_ground: true\n  vel_m_s: [1, 0, 0]\n": (4, "initial.vel_m_s", "zero"),
        "description: d\nmarkers: [slow, 'not a name']\n": (2, "markers[1]", "marker name"),
        "description: d\nexpect:\n  failsafe_expected: maybe\n": (3, "expect.failsafe_expected", "hover"),
        "description: d\nexpect:\n  no_collision: false\n  collision_expected: false\n": (
            3, "expect.no_collision", "contradicts"),
        "description: d\nfaults:\n  - kind: wind_gust\n    start_s: 1\n": (3, "faults[0].params", "required"),
        "description: d\nfaults:\n  - kind: hail\n    start_s: 1\n": (3, "faults[0].kind", "wind_gust"),
        "description: d\nfaults:\n  - kind: mocap_frozen\n    start_s: 2\n    end_s: 1\n": (
            5, "faults[0].end_s", "> 2"),
        "description: d\nfaults:\n  - kind: onboard_killed\n    start_s: 2\n": (
            4, "faults[0].start_s", "at_s"),
        "description: d\nduration_s: 5\nfaults:\n  - {kind: onboard_killed, at_s: 6}\n": (
            4, "faults[0].at_s", "before duration_s"),
        "description: d\nfaults:\n- kind: wind_gust\n  start_s: 1\n  params:\n    force_n: 2\n"
        "    speed_m_s: 3\n    direction: [0, 1, 0]\n": (
            6, "faults[0].params", "exactly one of force_n and speed_m_s"),
        "description: d\nfaults:\n- kind: corrupt_bytes\n  start_s: 1\n"
        "  params: {link: radio, fraction: 0.1}\n": (
            5, "faults[0].params.link", "command, mocap"),
        "description: d\nfaults:\n- kind: mocap_dropped\n  start_s: 1\n  params: {fraction: 0.1}\n": (
            5, "faults[0].params.fraction", "unknown field"),
    }  # fmt: skip
    for text, (line, field, words) in cases.items():
        path = write(tmp_path, text)
        err = error_of(path)
        assert (err.line, err.field) == (line, field), (text, str(err))
        assert str(err).startswith(f"{path}:{line}: {field}: ") and words in str(err), str(err)


def test_empty_and_unreadable_files(tmp_path: Path) -> None:
    assert error_of(write(tmp_path, "# nothing\n")).field == "<file>"
    assert error_of(write(tmp_path, "- just\n- a list\n")).field == "<document>"
    missing = tmp_path / "missing.scenario.yaml"
    assert str(error_of(missing)).startswith(f"{missing}:1: <file>: cannot read")


# --- values ------------------------------------------------------------------------------------
def test_faults_are_typed_and_timed(tmp_path: Path) -> None:
    text = """\
description: faults
faults:
  - {kind: wind_gust, start_s: 1, end_s: 2, params: {force_n: 2, direction: [3, 4, 0]}}
  - {kind: corrupt_bytes, start_s: 0.5, params: {link: command, fraction: 0.01}}
  - {kind: onboard_killed, at_s: 4}
  - {kind: mocap_frozen, start_s: 2, end_s: 3, params: {}}
"""
    wind, corrupt, killed, frozen = load_scenarios(write(tmp_path, text))[0].faults
    assert isinstance(wind.params, WindGustParams) and wind.params.direction == pytest.approx((0.6, 0.8, 0.0))
    assert wind.active(1.0) and wind.active(1.99) and not wind.active(2.0) and not wind.active(0.5)
    assert corrupt.params == CorruptBytesParams(link="command", fraction=0.01) and corrupt.end_s is None
    assert corrupt.active(1e6)
    assert (killed.kind, killed.start_s, killed.end_s) == ("onboard_killed", 4.0, None)
    assert frozen.params == NoParams()


def test_aliases_and_switches(tmp_path: Path) -> None:
    text = "description: d\nexpect:\n  no_collision: false\n  recovery: false\n  failsafe_expected: true\n"
    e = load_scenarios(write(tmp_path, text))[0].expect
    assert e.collision_expected is True and e.recovery is None and e.failsafe_expected is True
    e = load_scenarios(write(tmp_path, "description: d\nexpect: {recovery: {radius_m: 1.0}}\n"))[0].expect
    assert e.recovery is not None and (e.recovery.radius_m, e.recovery.time_s) == (1.0, 4.0)


def test_ids_from_stem_index_and_name(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "description: a\n---\nname: b_named\ndescription: b\n---\ndescription: c\n",
        "set.scenario.yaml",
    )
    scenarios = load_scenarios(path)
    assert [s.id for s in scenarios] == ["set-0", "b_named", "set-2"]
    assert [s.line for s in scenarios] == [1, 3, 6] and [s.index for s in scenarios] == [0, 1, 2]
    dup = write(tmp_path, "name: a\ndescription: a\n---\nname: a\ndescription: b\n")
    assert error_of(dup).line == 4 and "already used" in str(error_of(dup))


# --- round trip and the shipped examples ---------------------------------------------------------
def _leaves(d: object, prefix: str = "") -> dict[str, object]:
    if isinstance(d, dict):
        out: dict[str, object] = {}
        for k, v in d.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else k))
        return out
    return {prefix: d}


EVERY_FIELD = """\
name: every_field_wind_jsbsim
description: a 45 deg gap flown on the JSBSim backend through lossy links, with a gust and faults
vehicle: n3_tx2
physics: jsbsim
gap:
  centre_m: [0.5, 0.0, 1.8]
  roll_deg: 45
  pitch_deg: 5
  yaw_deg: 10
  width_m: 0.9
  height_m: 0.4
  wall_thickness_m: 0.08
lab:
  min_m: [-6, -4, 0]
  max_m: [6, 4, 3.5]
initial:
  pos_m: [-2.5, 0.5, 1.0]
  vel_m_s: [0.1, 0, 0]
  yaw_deg: 5
  on_ground: false
pilot: planner_net
approach:
  speed_m_s: 2.0
  duration_s: 3.0
links:
  command:
    transport: udp
    baud: 230400
    latency_ms: 2.0
    jitter_ms: 0.5
    loss: 0.01
    burst: {p_gb: 0.002, p_bg: 0.3}
    protocol: dji_open
  mocap:
    transport: memory
    baud: 460800
    latency_ms: 6.0
    jitter_ms: 1.5
    loss: 0.02
    burst: {p_gb: 0.001, p_bg: 0.5}
    rate_hz: 200
  esc_bus: {bitrate_bps: 500000, command_rate_hz: 250, status_rate_hz: 20, loss: 0.001, corruption: 0.001}
faults:
  - kind: wind_gust
    start_s: 2.0
    end_s: 2.5
    params: {force_n: 1.5, direction: [0, 1, 0], yaw_moment_nm: 0.02}
  - {kind: wind_gust, start_s: 6.0, params: {speed_m_s: 3.0, direction: [1, 1, 0]}}
  - {kind: corrupt_bytes, start_s: 1.0, end_s: 1.5, params: {link: mocap, fraction: 0.001}}
  - {kind: mocap_frozen, start_s: 6.5, end_s: 6.6}
  - {kind: mocap_dropped, start_s: 6.7, end_s: 6.8}
  - {kind: command_link_down, start_s: 7.0, end_s: 7.2}
  - {kind: onboard_stalled, start_s: 7.5, end_s: 7.6}
  - {kind: onboard_killed, at_s: 8.5}
  - {kind: param_set, start_s: 3.0, end_s: 5.0, params: {name: COM_OF_LOSS_T, value: 0.5}}
  - {kind: esc_silent, start_s: 7.7, params: {esc: 3}}
  - {kind: can_frame_loss, start_s: 2.0, end_s: 2.5, params: {fraction: 0.1}}
  - {kind: can_bus_off, start_s: 4.0, end_s: 4.05}
params: {MPC_TILTMAX_AIR: 25, COM_OBL_RC_ACT: 4}
seed: 1234
duration_s: 9.0
onboard_compute_ms: 4.5
realtime: true
skip: shows every field; the lossy links and the kill at 8.5 s make its expectations illustrative
markers: [slow, jsbsim]
expect:
  crosses_gap: true
  min_clearance_m: 0.02
  collision_expected: false
  max_attitude_error_deg: 12
  recovery: {radius_m: 0.6, time_s: 3.5}
  stays_in_lab: true
  failsafe_expected: hover
  onboard_abort_expected: false
  link:
    mocap_delivered_fraction_min: 0.9
    command_delivered_fraction_min: 0.95
    mocap_rate_hz_min: 150
    command_rate_hz_min: 40
  realtime_max_late_ms: 15
  quality:
    heading_error_deg: {held: 2, commanded: 10}
    attitude_tracking_deg: 10
    position_error_m: {approach: 0.2, traverse: 0.15, recovery: 0.2}
    thrust_saturation_s: 0.1
    settling_time_s: 0.4
    expected_failures: [settling_time_s]
mocap_bias: {gap_pos_m: [0.01, -0.02, 0.005], gap_roll_deg: 1.5, gap_yaw_deg: -2}
airframe: {mass_scale: 1.1, thrust_scale: 0.95}
dispersions:
  runs: 50
  seed: 9
  go: {min_success: 0.9, confidence: 0.9}
  envelope: [approach.speed_m_s, gap.roll_deg]
  bins: 4
  vary:
    gap.roll_deg: {uniform: [40, 50]}
    approach.speed_m_s: {normal: [2.0, 0.1], clip: [1.8, 2.2]}
    links.command.baud: {choice: [115200, 921600]}
    initial.pos_m: {normal: [0, 0.02], offset: true}
"""


def test_a_file_with_every_field_round_trips(tmp_path: Path) -> None:
    [s] = load_scenarios(write(tmp_path, EVERY_FIELD, "every.scenario.yaml"))
    # the file really sets every field: no leaf keeps its default
    defaults = _leaves(Scenario(id="x", description="").to_dict(include_meta=False))
    given = _leaves(s.to_dict(include_meta=False))
    same = sorted(k for k in defaults if k in given and given[k] == defaults[k])
    assert same == ["expect.collision_expected", "expect.crosses_gap", "expect.onboard_abort_expected",
                    "expect.refused", "expect.stays_in_lab", "initial.on_ground", "vehicle"]  # fmt: skip
    assert {f.kind for f in s.faults} == set(FAULT_KINDS)
    # to_dict -> YAML -> load gives the same scenario
    text = yaml.safe_dump(s.to_dict(include_meta=False), sort_keys=False)
    [again] = load_scenarios(write(tmp_path, text, "again.scenario.yaml"))
    assert dataclasses.replace(again, source=s.source, line=s.line) == s
    # and the dict is JSON-ready (plain types only)
    import json

    assert json.loads(json.dumps(s.to_dict()))["gap"]["roll_deg"] == 45.0


def test_shipped_examples_load() -> None:
    scenarios = load_all([EXAMPLES])
    assert len(scenarios) >= 3
    assert len({s.id for s in scenarios}) == len(scenarios)


def test_strings_parse_like_files() -> None:
    [s] = loads_scenarios(MINIMAL, source="inline.scenario.yaml")
    assert s.id == "inline" and s.gap.roll_deg == 60


def schema_classes() -> set[type]:
    """Every dataclass a scenario file can hold: those reached from `Scenario`'s fields (through
    optional, union and tuple types) and each registered fault kind's parameters."""
    found: set[type] = set()
    todo: list[object] = [Scenario, *(kind.params for kind in FAULT_KINDS.values())]
    while todo:
        t = todo.pop()
        if dataclasses.is_dataclass(t) and isinstance(t, type):
            if t not in found:
                found.add(t)
                todo += typing.get_type_hints(t).values()
        else:
            todo += typing.get_args(t)
    return found


def test_the_schema_walk_reaches_the_nested_blocks() -> None:
    classes = schema_classes()
    assert {schema.EventTime, schema.Distribution, schema.HeadingErrorLimits, CorruptBytesParams} <= classes
    assert len(classes) >= 26


def test_the_format_document_names_every_field() -> None:
    doc = (ROOT / "docs" / "scenario-format.md").read_text()
    names: set[str] = set()
    for cls in schema_classes():
        names.update(f.name for f in dataclasses.fields(cls))
    names -= {*Scenario.META_FIELDS, *Expectations.INTERNAL_FIELDS}
    names |= {*FAULT_KEYS, *EXPECT_ALIASES, *FAULT_KINDS, *schema.MISSION_EVENTS, *schema.FLIGHT_PHASES}
    missing = sorted(n for n in names if not re.search(rf"`{re.escape(n)}`", doc))
    assert missing == []


def test_a_pilot_added_as_one_module_is_accepted_by_scenario_files(tmp_path, monkeypatch):
    import policies.onboard.pilots as pilots

    extra = tmp_path / "pilots"
    extra.mkdir()
    (extra / "hover_only.py").write_text("def make_pilot(context):\n    raise NotImplementedError\n")
    monkeypatch.setattr(pilots, "__path__", [*pilots.__path__, str(extra)])
    (s,) = load_scenarios(write(tmp_path, MINIMAL + "pilot: hover_only\n"))
    assert s.pilot == "hover_only"
    assert "hover_only" in str(error_of(write(tmp_path, MINIMAL + "pilot: magic\n", "y.scenario.yaml")))


def test_fc_parameters_are_checked_against_the_fc_table(tmp_path: Path) -> None:
    [s] = loads_scenarios(MINIMAL + "params: {COM_OF_LOSS_T: 0.5}\nfaults:\n"
                          "  - {kind: param_set, start_s: 1, params: {name: COM_OBL_RC_ACT, value: 4}}\n")
    assert s.params == (("COM_OF_LOSS_T", 0.5),)
    assert s.faults[0].params == ParamSetParams("COM_OBL_RC_ACT", 4.0)
    for extra, where, why in (
        ("params: {COM_OF_LOS_T: 0.5}", "params.COM_OF_LOS_T", "did you mean COM_OF_LOSS_T?"),
        ("params: {COM_OF_LOSS_T: 99}", "params.COM_OF_LOSS_T", "99 outside 0.1..60 s"),
        ("params: {COM_OBL_RC_ACT: 4.5}", "params.COM_OBL_RC_ACT", "expected an integer"),
        ("params: {COM_OF_LOSS_T: fast}", "params.COM_OF_LOSS_T", "expected a number"),
        ("params: [COM_OF_LOSS_T]", "params", "expected a mapping"),
        ("faults:\n  - {kind: param_set, start_s: 1, params: {name: NOPE, value: 1}}", "faults[0].params",
         "unknown parameter 'NOPE'"),
        ("faults:\n  - {kind: param_set, start_s: 1, params: {name: COM_OF_LOSS_T}}",
         "faults[0].params.value", "required field missing"),
    ):
        with pytest.raises(ScenarioError, match=re.escape(f"{where}: ")) as info:
            loads_scenarios(MINIMAL + extra + "\n", source="x.scenario.yaml")
        assert why in str(info.value), (extra, str(info.value))


def test_esc_faults_need_the_esc_bus() -> None:
    with pytest.raises(ScenarioError, match=re.escape("faults[0].kind: esc_silent needs the motors on an")):
        loads_scenarios(MINIMAL + "faults:\n  - {kind: esc_silent, start_s: 1, params: {esc: 1}}\n")
    with pytest.raises(ScenarioError, match=re.escape("faults[0].params.esc: expected a whole number")):
        loads_scenarios(MINIMAL + "links: {esc_bus: {}}\nfaults:\n"
                        "  - {kind: esc_silent, start_s: 1, params: {esc: 4}}\n")
    [s] = loads_scenarios(MINIMAL + "links: {esc_bus: {}}\n")
    assert s.links.esc_bus == schema.EscBusSpec()



def test_either_yaml_parser_reads_files_and_reports_errors_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    """libyaml's parser (used where PyYAML has it) and the pure-Python one read every shipped file the same,
    dispersions included, and report a file that is not YAML in the same words at the same line."""
    import hil.scenario.loader as loader

    files = sorted((ROOT / "scenarios").rglob("*.scenario.yaml"))
    assert len(files) >= 35
    broken = "description: x\ngap: {roll_deg: 30\nduration_s: 5\n"
    parsers = {"pure": yaml.SafeLoader, "libyaml": getattr(yaml, "CSafeLoader", None), "used": loader._LOADER}
    read: dict[str, list[object]] = {}
    for name, parser in parsers.items():
        if parser is None:  # a PyYAML built without libyaml: the pure-Python parser is the one used
            continue
        monkeypatch.setattr(loader, "_LOADER", parser)
        with pytest.raises(ScenarioError) as info:
            loads_scenarios(broken, source="broken.scenario.yaml")
        assert str(info.value).startswith("broken.scenario.yaml:3: <yaml>: not valid YAML: expected ','")
        read[name] = [[s.to_dict() for s in load_scenarios(f)] for f in files] + [str(info.value)]
    assert all(r == read["pure"] for r in read.values())


# --- hostile values and structures ---------------------------------------------------------------
@pytest.mark.parametrize("parser", ["pure", "libyaml"])
def test_nesting_past_the_limit_is_an_error_at_its_line_with_either_parser(
    parser: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Deep flow and block nesting, closed or not, and an alias that holds itself: the line where the
    nesting passes the stated limit, never Python's recursion limit."""
    import hil.scenario.loader as loader

    if parser == "libyaml":
        if not hasattr(yaml, "CSafeLoader"):
            pytest.fail("PyYAML without libyaml: the libyaml case cannot be checked here")
        monkeypatch.setattr(loader, "_LOADER", yaml.CSafeLoader)
    else:
        monkeypatch.setattr(loader, "_LOADER", loader._PureLoader)
    deep = loader.MAX_DEPTH - 1  # the levels below the document's own mapping
    texts = {
        "description: d\ngap: " + "[" * 490 + "\n": 2,
        "description: d\ngap: " + "{a: " * 3000 + "}" * 3000 + "\n": 2,
        "description: d\ngap:\n" + "".join(" " * i + "-\n" for i in range(1, 600)): loader.MAX_DEPTH + 2,
        "description: d\ngap:\n" + "".join(" " * i + f"k{i}:\n" for i in range(1, 400)): loader.MAX_DEPTH + 1,
        "description: d\ngap: &a [*a]\n": 2,
    }
    for text, line in texts.items():
        with pytest.raises(ScenarioError) as info:
            loads_scenarios(text, source="deep.scenario.yaml")
        assert str(info.value) == (f"deep.scenario.yaml:{line}: <yaml>: nested deeper than "
                                   f"{loader.MAX_DEPTH} levels (the most a scenario file may nest)")
    # the limit itself is allowed: the error is the schema's, not the depth's
    with pytest.raises(ScenarioError, match="gap: expected a mapping"):
        loads_scenarios("description: d\ngap: " + "[" * deep + "]" * deep + "\n")


def test_values_no_python_type_holds_are_errors_naming_the_field(tmp_path: Path) -> None:
    cases = {
        "description: d\nduration_s: 1" + "0" * 309 + "\n": (2, "duration_s", "about 310 digits"),
        "description: d\ngap: {roll_deg: -1" + "0" * 400 + "}\n": (2, "gap.roll_deg", "about 401 digits"),
        "description: d\nseed: 1" + "0" * 30 + "\n": (2, "seed", "about 31 digits"),
        "description: d\nseed: 1" + "0" * 5000 + "\n": (2, "<yaml>", "cannot read value '1000"),
        "description: d\nparams: {COM_OF_LOSS_T: 1" + "0" * 400 + "}\n": (
            2, "params.COM_OF_LOSS_T", "about 401 digits"),
        "description: d\nduration_s: !!int abc\n": (2, "<yaml>", "cannot read value 'abc'"),
        "description: d\nrealtime: !!bool maybe\n": (2, "<yaml>", "cannot read value 'maybe'"),
        "description: d\nskip: !!timestamp nope\n": (2, "<yaml>", "cannot read value 'nope'"),
        "description: d\nduration_s: !!float x\n": (2, "<yaml>", "cannot read value 'x'"),
    }  # fmt: skip
    for text, (line, field, words) in cases.items():
        err = error_of(write(tmp_path, text))
        assert (err.line, err.field) == (line, field), str(err)
        assert words in err.message and len(str(err)) < 400, str(err)


def test_a_file_past_the_size_limit_is_refused_before_it_is_read(tmp_path: Path) -> None:
    from hil.scenario.loader import MAX_FILE_BYTES

    big = tmp_path / "big.scenario.yaml"
    with big.open("w") as f:
        f.write("description: d\n")
        f.truncate(10_000_000)  # 10 MB, sparse
    assert str(error_of(big)) == (f"{big}:1: <file>: 10000000 bytes, more than a scenario file may hold "
                                  f"({MAX_FILE_BYTES} bytes)")
    with pytest.raises(ScenarioError, match=r"^<string>:1: <file>: "):
        loads_scenarios("description: d\n# " + "x" * MAX_FILE_BYTES)


def test_the_format_document_states_the_limits() -> None:
    from hil.scenario.loader import MAX_DEPTH, MAX_FILE_BYTES

    doc = " ".join((ROOT / "docs" / "scenario-format.md").read_text().split())
    assert f"at most {MAX_FILE_BYTES // 1024} KiB ({MAX_FILE_BYTES:,} bytes" in doc
    assert f"nested at most {MAX_DEPTH} levels deep" in doc


@pytest.mark.parametrize(("written", "field"), [
    ("1e3", "duration_s"), ("1.0e3", "duration_s"), ("'2.5'", "duration_s"), ('"7"', "seed"),
    ("1e1", "gap.roll_deg"), ("25e-2", "approach.duration_s"),
])
def test_a_number_read_as_text_gets_a_hint_in_a_form_that_loads(written: str, field: str) -> None:
    """YAML 1.1 reads 1e3 and 1.0e3 as text (an exponent needs a dot and a sign): the hint's form loads."""
    head, _, key = field.rpartition(".")
    doc = (lambda v: f"description: d\n{head}: {{{key}: {v}}}\n") if head else (
        lambda v: f"description: d\n{key}: {v}\n")
    with pytest.raises(ScenarioError) as info:
        loads_scenarios(doc(written))
    hint = re.search(r"the number is written (\S+)\)$", info.value.message)
    assert hint is not None and info.value.field == field, info.value.message
    [s] = loads_scenarios(doc(hint.group(1)))
    value = s.to_dict()
    for part in field.split("."):
        value = value[part]
    assert value == float(written.strip("'\""))
