"""Loading `*.scenario.yaml` files into `Scenario` values, with errors that name file, line and field.

The YAML is composed into nodes (``yaml.compose_all``) so every value keeps its line; the nodes are
then checked against the dataclasses of `hil.scenario.schema` (types, ranges, choices, unknown fields
with a "did you mean" hint) and a few rules across fields (the gap and the start inside the lab, ...).
"""

from __future__ import annotations

import difflib
import math
import re
import types
from collections.abc import Callable, Iterable
from dataclasses import MISSING, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

import yaml
from yaml.constructor import SafeConstructor
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from hil.scenario import schema
from hil.scenario.dispersions import PathError, apply, base_document, value_at
from hil.scenario.expect_fields import EXPECT_FIELDS
from hil.scenario.fault_kinds import FAULT_KINDS, NoParams, ParamSetParams, WindGustParams
from hil.scenario.schema import (
    DISTRIBUTIONS,
    FLIGHT_PHASES,
    MISSION_EVENTS,
    SCENARIO_LIMITS,
    Dispersions,
    Distribution,
    EventTime,
    Expectations,
    Fault,
    GoCriterion,
    RecoveryExpectation,
    Scenario,
)

#: the largest scenario file read (bytes): the shipped ones hold about 1 kB; one of this size loads in
#: about 2 s at worst (a list of 60,000 values)
MAX_FILE_BYTES = 256 * 1024
#: the deepest nesting of values read (the document's mapping is level 1; the schema needs 6): libyaml
#: stops at 1000 levels and PyYAML's pure-Python composer recurses about 3 frames a level
MAX_DEPTH = 50
#: the fields of one entry of ``faults:`` (a window: start_s or start, then end_s or duration_s; an
#: instant: at_s or at)
FAULT_KEYS = ("kind", "start_s", "end_s", "at_s", "start", "at", "duration_s", "phase", "params")
#: ``expect:`` fields that write another field the other way round (``no_collision``: collision_expected)
EXPECT_ALIASES = ("no_collision",)


class _TooDeep(yaml.YAMLError):
    """A file nested deeper than MAX_DEPTH, at ``problem_mark``."""

    def __init__(self, mark: yaml.Mark) -> None:
        super().__init__()
        self.problem_mark = mark
        self.problem = f"nested deeper than {MAX_DEPTH} levels (the most a scenario file may nest)"


class _PureLoader(yaml.SafeLoader):
    """PyYAML's pure-Python loader, stopping at MAX_DEPTH levels (never at Python's recursion limit)."""

    _depth = 0

    def compose_node(self, parent: Node | None, index: Any) -> Node | None:
        if self._depth >= MAX_DEPTH:
            raise _TooDeep(self.peek_event().start_mark)
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


#: libyaml's parser where PyYAML was built with it (the files under scenarios/ load about 2x faster with it,
#: `hil bench` scenario_load_ms), else the pure-Python one: the same nodes, with their lines
_LOADER = getattr(yaml, "CSafeLoader", _PureLoader)

SUFFIX = ".scenario.yaml"
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_MARKER_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class ScenarioError(ValueError):
    """A scenario file is unreadable or invalid: ``source:line: field: message``."""

    def __init__(self, source: str, line: int, field: str, message: str) -> None:
        super().__init__(f"{source}:{line}: {field}: {message}")
        self.source = source
        self.line = line
        self.field = field
        self.message = message


# --- public API ----------------------------------------------------------------------------------
def load_scenarios(path: str | Path) -> list[Scenario]:
    """All scenarios of one file (one per YAML document), validated; raises ScenarioError."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:  # before reading it
            raise _too_large(str(p), size)
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(str(p), 1, "<file>", f"cannot read: {exc}") from exc
    return loads_scenarios(text, source=str(p))


def loads_scenarios(text: str, source: str = "<string>") -> list[Scenario]:
    """Scenarios from YAML text; ``source`` names it in errors and gives the id's stem."""
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_FILE_BYTES:
        raise _too_large(source, size)
    try:
        documents = _compose(text, _LOADER)
    except yaml.YAMLError as exc:
        raise _not_yaml(text, source, exc) from exc
    documents = [d for d in documents if not _is_empty(d)]
    if not documents:
        raise ScenarioError(source, 1, "<file>", "no scenario in the file (expected at least one document)")
    stem = _stem(source)
    scenarios = []
    seen: dict[str, int] = {}
    for index, node in enumerate(documents):
        default_id = stem if len(documents) == 1 else f"{stem}-{index}"
        scenario = _Builder(source).scenario(node, index, default_id)
        if scenario.id in seen:
            raise ScenarioError(
                source,
                scenario.line,
                "name",
                f"id '{scenario.id}' already used by the document on line {seen[scenario.id]}",
            )
        seen[scenario.id] = scenario.line
        scenarios.append(scenario)
    return scenarios


def _too_large(source: str, size: int) -> ScenarioError:
    return ScenarioError(source, 1, "<file>", f"{size} bytes, more than a scenario file may hold "
                         f"({MAX_FILE_BYTES} bytes)")


def _compose(text: str, loader: type) -> list[Node | None]:
    """The documents' nodes of ``text``, none nested deeper than MAX_DEPTH (else _TooDeep)."""
    documents = list(yaml.compose_all(text, Loader=loader))
    for root in documents:
        _check_depth(root)
    return documents


def _check_depth(root: Node | None) -> None:
    """_TooDeep at the first node below MAX_DEPTH levels (an alias's node may sit in several places, or
    inside itself: each is walked again only when met deeper than before)."""
    deepest: dict[int, int] = {}
    stack: list[tuple[Node, int]] = [(root, 1)] if isinstance(root, SequenceNode | MappingNode) else []
    while stack:
        node, depth = stack.pop()
        if deepest.get(id(node), 0) >= depth:
            continue
        deepest[id(node)] = depth
        children = node.value if isinstance(node, SequenceNode) else [c for pair in node.value for c in pair]
        if children and depth >= MAX_DEPTH:
            raise _TooDeep(children[0].start_mark)
        stack.extend((c, depth + 1) for c in children if not isinstance(c, ScalarNode))


def _not_yaml(text: str, source: str, exc: yaml.YAMLError) -> ScenarioError:
    """The ScenarioError of ``text`` that is not valid YAML, at the line of the problem, in the words of
    PyYAML's pure-Python parser whichever parser found it (libyaml's differ)."""
    if not isinstance(exc, _TooDeep) and _LOADER is not _PureLoader:
        try:
            _compose(text, _PureLoader)
        except yaml.YAMLError as pure:
            exc = pure
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    line = mark.line + 1 if mark is not None else 1
    problem = getattr(exc, "problem", None) or str(exc)
    what = problem if isinstance(exc, _TooDeep) else f"not valid YAML: {problem}"
    return ScenarioError(source, line, "<yaml>", what)


def find_scenario_files(root: str | Path) -> list[Path]:
    """Every ``*.scenario.yaml`` under ``root`` (or ``root`` itself if it is a file), sorted."""
    r = Path(root)
    if r.is_file():
        return [r]
    return sorted(p for p in r.rglob(f"*{SUFFIX}") if p.is_file())


def load_all(paths: Iterable[str | Path]) -> list[Scenario]:
    """Scenarios of every file found under ``paths``; ids must be unique across them."""
    out: list[Scenario] = []
    ids: dict[str, Scenario] = {}
    for root in paths:
        for path in find_scenario_files(root):
            for s in load_scenarios(path):
                if s.id in ids:
                    other = ids[s.id]
                    raise ScenarioError(
                        s.source, s.line, "name", f"id '{s.id}' also used at {other.source}:{other.line}"
                    )
                ids[s.id] = s
                out.append(s)
    return out


def dispersed(scenario: Scenario, values: dict[str, Any], seed: int, name: str) -> Scenario:
    """``scenario`` with dispersed ``values`` applied (`hil.scenario.dispersions`) and ``seed``, named
    ``name``, validated as a file is (ScenarioError, naming the field, for a draw out of its range)."""
    doc = apply(base_document(scenario), values)
    doc["seed"], doc["name"] = seed, name
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)  # (libyaml's, where PyYAML has it: faster)
    text = yaml.dump(doc, Dumper=dumper, sort_keys=False)
    [s] = loads_scenarios(text, source=f"{scenario.source} ({name})")
    return s


# --- helpers -------------------------------------------------------------------------------------
def _stem(source: str) -> str:
    name = Path(source).name
    for suffix in (SUFFIX, ".yaml", ".yml"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def _is_empty(node: Node | None) -> bool:
    return node is None or (
        isinstance(node, ScalarNode) and node.tag.endswith(":null") and node.value in ("", "~", "null")
    )


def _fmt(x: float) -> str:
    if isinstance(x, int):
        return str(x)
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(float(x))


def _describe(value: Any, node: Node) -> str:
    if isinstance(node, MappingNode):
        return "a mapping"
    if isinstance(node, SequenceNode):
        return f"a list of {len(node.value)}"
    if value is None:
        return "nothing (null)"
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**15:
        return f"a whole number of about {math.ceil(value.bit_length() * math.log10(2))} digits"
    shown = _shorten(repr(value))
    number = _as_yaml_number(value) if isinstance(value, str) else None
    if number is None:
        return shown
    if isinstance(node, ScalarNode) and node.style in ("'", '"'):
        return f"{shown} (text, in quotes; the number is written {number})"
    return f"{shown} (text to YAML; the number is written {number})"


def _shorten(text: str, most: int = 60) -> str:
    return text if len(text) <= most else f"{text[: most - 20]}...{text[-12:]} ({len(text)} characters)"


def _as_yaml_number(text: str) -> str | None:
    """How the number Python reads in ``text`` (``1e3``, ``"2.5"``) is written so that YAML reads a number
    (``1000.0``; an exponent needs a dot and a sign, ``1.0e+20``), or None when ``text`` holds no finite
    number of at most 100 characters. The form given is one this loader reads back as that number."""
    if len(text) > 100:
        return None
    for kind in (int, float):
        try:
            number = kind(text)
        except ValueError:
            continue
        if isinstance(number, float) and not math.isfinite(number):
            return None
        written = yaml.safe_dump(number, default_flow_style=True).splitlines()[0]
        return written if yaml.load(written, Loader=_LOADER) == number else None
    return None


def _finite(x: float) -> bool:
    """Whether ``x`` is a finite float or an integer a float holds (10**309 is not)."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def _range_text(meta: dict[str, Any], what: str) -> str:
    lo, hi = meta.get("lo"), meta.get("hi")
    lo_open, hi_open = meta.get("lo_open", False), meta.get("hi_open", False)
    if lo is not None and hi is not None and not lo_open and not hi_open:
        return f"{what} between {_fmt(lo)} and {_fmt(hi)}"
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {_fmt(lo)}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {_fmt(hi)}")
    return f"{what} {' and '.join(parts)}" if parts else what


def _in_range(x: float, meta: dict[str, Any]) -> bool:
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None and (x < lo or (meta.get("lo_open") and x == lo)):
        return False
    return not (hi is not None and (x > hi or (meta.get("hi_open") and x == hi)))


class _Builder:
    """Turns one document's nodes into a Scenario; remembers each field's line for later checks."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.lines: dict[str, int] = {}
        self._constructor = SafeConstructor()

    # errors and scalars
    def error(self, node: Node | int, field: str, message: str) -> ScenarioError:
        line = node if isinstance(node, int) else node.start_mark.line + 1
        return ScenarioError(self.source, line, field, message)

    def line_of(self, field: str, fallback: int) -> int:
        return self.lines.get(field, fallback)

    def value(self, node: Node) -> Any:
        if isinstance(node, MappingNode | SequenceNode):
            return None
        try:
            return self._constructor.construct_object(node, deep=True)
        # PyYAML's constructors raise plain Python errors on a value its tag cannot hold (`!!int abc`,
        # `!!bool maybe`, `!!timestamp x`, an integer of more than 4300 digits)
        except Exception as exc:
            what = getattr(exc, "problem", None) or str(exc)
            raise self.error(node, "<yaml>", f"cannot read value {_shorten(repr(node.value))}: "
                             f"{_shorten(what, 200)}") from None

    # mappings
    def mapping(self, node: Node, path: str, allowed: Iterable[str]) -> dict[str, Node]:
        """Check ``node`` is a mapping with known, unique string keys; returns key -> value node."""
        where = path or "<document>"
        if not isinstance(node, MappingNode):
            raise self.error(
                node, where, f"expected a mapping of field: value, got {_describe(self.value(node), node)}"
            )
        allowed = list(allowed)
        out: dict[str, Node] = {}
        for key_node, value_node in node.value:
            key = self.value(key_node)
            if not isinstance(key, str):
                raise self.error(key_node, where, f"field names must be text, got {key!r}")
            full = f"{path}.{key}" if path else key
            if key in out:
                raise self.error(key_node, full, "field given twice")
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
                hint = f" (did you mean '{close[0]}'?)" if close else ""
                raise self.error(key_node, full, f"unknown field{hint}; allowed here: {', '.join(allowed)}")
            self.lines[full] = key_node.start_mark.line + 1
            out[key] = value_node
        return out

    def dataclass(
        self,
        cls: type,
        node: Node,
        path: str,
        *,
        custom: dict[str, Callable[[Node, str], Any]] | None = None,
        extra_keys: tuple[str, ...] = (),
        limits: dict[str, dict[str, Any]] | None = None,
        skip: tuple[str, ...] = (),
    ) -> tuple[dict[str, Any], dict[str, Node]]:
        """Validated keyword arguments for ``cls`` from a mapping node (plus the raw key nodes)."""
        custom = custom or {}
        hints = get_type_hints(cls, vars(schema))
        cls_fields = [f for f in fields(cls) if f.init and f.name not in skip]
        items = self.mapping(node, path, [f.name for f in cls_fields] + list(extra_keys))
        kwargs: dict[str, Any] = {}
        for f in cls_fields:
            full = f"{path}.{f.name}" if path else f.name
            if f.name not in items:
                if f.default is MISSING and f.default_factory is MISSING:
                    raise self.error(node, full, "required field missing")
                continue
            sub = items[f.name]
            if f.name in custom:
                kwargs[f.name] = custom[f.name](sub, full)
            else:
                meta = dict(f.metadata) or (limits or {}).get(f.name, {})
                kwargs[f.name] = self.convert(hints[f.name], sub, full, meta)
        return kwargs, items

    # typed values
    def convert(self, tp: Any, node: Node, path: str, meta: dict[str, Any]) -> Any:
        origin = get_origin(tp)
        if origin in (Union, types.UnionType):
            options = get_args(tp)
            if type(None) in options and self.value(node) is None and isinstance(node, ScalarNode):
                return None
            rest = [o for o in options if o is not type(None)]
            if set(rest) == {bool, str}:
                return self.flag_or_choice(node, path, meta)
            return self.convert(rest[0], node, path, meta)
        if origin is tuple:
            args = get_args(tp)
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(
                    self.convert(args[0], n, f"{path}[{i}]", meta)
                    for i, n in enumerate(self.sequence(node, path))
                )
            items = self.sequence(node, path, len(args))
            return tuple(
                self.convert(a, n, f"{path}[{i}]", meta)
                for i, (a, n) in enumerate(zip(args, items, strict=True))
            )
        if is_dataclass(tp):
            kwargs, _ = self.dataclass(tp, node, path)
            return tp(**kwargs)
        value = self.value(node)
        if tp is bool:
            if not isinstance(value, bool):
                raise self.error(node, path, f"expected true or false, got {_describe(value, node)}")
            return value
        if tp is int:
            if isinstance(value, bool) or not isinstance(value, int) or not _in_range(value, meta):
                raise self.error(
                    node,
                    path,
                    f"expected {_range_text(meta, 'a whole number')}, got {_describe(value, node)}",
                )
            return value
        if tp is float:
            ok = isinstance(value, int | float) and not isinstance(value, bool) and _finite(value)
            if not ok or not _in_range(float(value), meta):
                raise self.error(
                    node, path, f"expected {_range_text(meta, 'a number')}, got {_describe(value, node)}"
                )
            return float(value)
        if tp is str:
            choices = meta.get("choices") or ()
            if choices:
                if value not in choices:
                    raise self.error(
                        node, path, f"expected one of {', '.join(choices)}, got {_describe(value, node)}"
                    )
                return value
            if not isinstance(value, str) or not value.strip():
                raise self.error(node, path, f"expected non-empty text, got {_describe(value, node)}")
            return value
        raise TypeError(f"scenario schema: no converter for {tp!r} at {path}")  # a bug in schema.py

    def sequence(self, node: Node, path: str, length: int | None = None) -> list[Node]:
        if not isinstance(node, SequenceNode) or (length is not None and len(node.value) != length):
            want = f"a list of {length} numbers" if length is not None else "a list"
            raise self.error(node, path, f"expected {want}, got {_describe(self.value(node), node)}")
        return list(node.value)

    def flag_or_choice(self, node: Node, path: str, meta: dict[str, Any]) -> bool | str:
        value = self.value(node)
        if isinstance(value, bool) or value in meta.get("choices", ()):
            return value
        choices = ", ".join(("true", "false", *meta.get("choices", ())))
        raise self.error(node, path, f"expected one of {choices}, got {_describe(value, node)}")

    # the document
    def scenario(self, node: Node, index: int, default_id: str) -> Scenario:
        doc_line = node.start_mark.line + 1
        custom = {
            "name": self.name,
            "vehicle": self.vehicle,
            "physics": self.physics,
            "pilot": self.pilot,
            "faults": self.faults,
            "params": self.params,
            "markers": self.markers,
            "expect": self.expectations,
            "dispersions": self.dispersions,
            "skip": lambda n, p: None if self.value(n) is None else self.convert(str, n, p, {}),
        }
        kwargs, _ = self.dataclass(
            Scenario, node, "", custom=custom, limits=SCENARIO_LIMITS, skip=Scenario.META_FIELDS
        )
        if "description" not in kwargs:
            raise self.error(
                node, "description", "required field missing (one line saying what the scenario tests)"
            )
        scenario = Scenario(
            id=kwargs.get("name") or default_id, source=self.source, line=doc_line, index=index, **kwargs
        )
        self.check_across(scenario, doc_line)
        if scenario.dispersions is not None:
            self.check_dispersions(scenario, doc_line)
        return scenario

    def name(self, node: Node, path: str) -> str | None:
        value = self.value(node)
        if value is None and isinstance(node, ScalarNode):
            return None
        if not isinstance(value, str) or not _NAME_RE.match(value):
            raise self.error(
                node,
                path,
                f"expected a name of letters, digits, '_', '-' or '.', got {_describe(value, node)}",
            )
        return value

    def vehicle(self, node: Node, path: str) -> str:
        # (heavy: numba through the emulator, loaded only when a file needs it)
        from emulator.profile import builtin_profiles

        value = self.convert(str, node, path, {})
        if value.endswith((".yaml", ".yml")):
            p = Path(value)
            if not p.is_absolute():
                p = Path(self.source).parent / p
            if not p.is_file():
                raise self.error(
                    node, path, f"expected a built-in profile name or a profile file, no file {p}"
                )
            self.flyable(node, path, str(p))
            return str(p)
        have = builtin_profiles()
        if value not in have:
            close = difflib.get_close_matches(value, have, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise self.error(
                node, path, f"unknown vehicle profile {value!r}{hint}; built-in: {', '.join(have) or 'none'}"
            )
        return value

    def flyable(self, node: Node, path: str, profile_path: str) -> None:
        """A profile file the FC can fly, with the onboard configuration beside it (README, "Bringing
        your own airframe"); the error says why not."""
        # (heavy: numba through the emulator, loaded only when a file names a profile file)
        from emulator.fc.tuning import fc_gains
        from emulator.profile import ProfileError, load_profile

        try:
            fc_gains(load_profile(profile_path))
        except ProfileError as exc:
            raise self.error(node, path, str(exc)) from None
        onboard = onboard_vehicle(profile_path)
        if not Path(onboard).is_file():
            raise self.error(
                node, path, f"no onboard configuration {onboard} beside the profile (mass, tilt limit)"
            )

    def physics(self, node: Node, path: str) -> str:
        # (heavy: numba through the emulator, loaded only when a file needs it)
        from emulator.physics import backend_names

        return self.convert(str, node, path, {"choices": tuple(backend_names())})

    def pilot(self, node: Node, path: str) -> str:
        # (the onboard side, loaded only when a file names a pilot)
        from policies.onboard.pilots import pilot_names

        return self.convert(str, node, path, {"choices": tuple(pilot_names())})

    def markers(self, node: Node, path: str) -> tuple[str, ...]:
        out = []
        for i, n in enumerate(self.sequence(node, path)):
            value = self.value(n)
            if not isinstance(value, str) or not _MARKER_RE.match(value):
                raise self.error(
                    n,
                    f"{path}[{i}]",
                    f"expected a pytest marker name (a Python identifier), got {_describe(value, n)}",
                )
            out.append(value)
        return tuple(out)

    def expectations(self, node: Node, path: str) -> Expectations:
        """The project's own fields, ``no_collision`` and the fields registered checks added."""
        custom = {"recovery": self.recovery}
        kwargs, items = self.dataclass(Expectations, node, path, custom=custom,
                                       extra_keys=(*EXPECT_ALIASES, *EXPECT_FIELDS),
                                       skip=Expectations.INTERNAL_FIELDS)
        kwargs["extra"] = tuple((name, self.convert(f.type, items[name], f"{path}.{name}", f.meta))
                                for name, f in EXPECT_FIELDS.items() if name in items)
        if "no_collision" in items:
            sub = items["no_collision"]
            inverse = not self.convert(bool, sub, f"{path}.no_collision", {})
            if "collision_expected" in kwargs and kwargs["collision_expected"] != inverse:
                raise self.error(
                    sub, f"{path}.no_collision", "contradicts collision_expected; give only one of them"
                )
            kwargs["collision_expected"] = inverse
        return Expectations(**kwargs)

    def recovery(self, node: Node, path: str) -> RecoveryExpectation | None:
        value = self.value(node)
        if isinstance(node, ScalarNode) and (value is None or value is False):
            return None
        if value is True:
            return RecoveryExpectation()
        kwargs, _ = self.dataclass(RecoveryExpectation, node, path)
        return RecoveryExpectation(**kwargs)

    def dispersions(self, node: Node, path: str) -> Dispersions | None:
        if isinstance(node, ScalarNode) and self.value(node) is None:
            return None
        kwargs, items = self.dataclass(Dispersions, node, path, custom={
            "vary": self.vary, "envelope": self.envelope, "go": lambda n, p: GoCriterion(
                **self.dataclass(GoCriterion, n, p)[0])})
        if not kwargs.get("vary"):
            raise self.error(node, f"{path}.vary", "required: at least one field and its distribution")
        d = Dispersions(**kwargs)
        names = [p for p, _ in d.vary]
        if d.envelope is not None:
            for i, p in enumerate(d.envelope):
                if p not in names:
                    raise self.error(items["envelope"], f"{path}.envelope[{i}]",
                                     f"expected a path of vary ({', '.join(names)}), got {p!r}")
        return d

    def vary(self, node: Node, path: str) -> tuple[tuple[str, Distribution], ...]:
        if not isinstance(node, MappingNode):
            raise self.error(node, path, "expected a mapping of field path: distribution "
                             "(gap.roll_deg: {uniform: [50, 62]})")
        out = []
        for key_node, value_node in node.value:
            key = self.value(key_node)
            if not isinstance(key, str):
                raise self.error(key_node, path, f"field paths must be text, got {key!r}")
            full = f"{path}.{key}"
            if key in (p for p, _ in out):
                raise self.error(key_node, full, "field given twice")
            self.lines[full] = key_node.start_mark.line + 1
            out.append((key, self.distribution(value_node, full)))
        return tuple(out)

    def distribution(self, node: Node, path: str) -> Distribution:
        kwargs, items = self.dataclass(Distribution, node, path, custom={"choice": self.choice})
        given = [k for k in DISTRIBUTIONS if kwargs.get(k) is not None]
        if len(given) != 1:
            raise self.error(node, path, f"give exactly one of {', '.join(DISTRIBUTIONS)}, got "
                             f"{', '.join(given) or 'none'}")
        for key in ("uniform", "clip"):
            pair = kwargs.get(key)
            if pair is not None and pair[0] > pair[1]:
                raise self.error(items[key], f"{path}.{key}", f"expected [low, high] with low <= high, got "
                                 f"{list(pair)}")
        if kwargs.get("normal") is not None and kwargs["normal"][1] < 0:
            raise self.error(items["normal"], f"{path}.normal",
                             f"expected [mean, standard deviation >= 0], got {list(kwargs['normal'])}")
        return Distribution(**kwargs)

    def choice(self, node: Node, path: str) -> tuple[Any, ...]:
        items = self.sequence(node, path)
        if not items:
            raise self.error(node, path, "expected a list of at least one value")
        out = []
        for i, n in enumerate(items):
            if not isinstance(n, ScalarNode) or self.value(n) is None:
                raise self.error(n, f"{path}[{i}]", f"expected a value, got {_describe(self.value(n), n)}")
            out.append(self.value(n))
        return tuple(out)

    def envelope(self, node: Node, path: str) -> tuple[str, str] | None:
        if isinstance(node, ScalarNode) and self.value(node) is None:
            return None
        a, b = (self.convert(str, n, f"{path}[{i}]", {}) for i, n in enumerate(self.sequence(node, path, 2)))
        return (a, b)

    def check_dispersions(self, s: Scenario, doc_line: int) -> None:
        """Every path of ``vary`` names a field of this scenario, and the values its distribution reaches
        (a uniform's ends, a normal's mean +- 3 sd, each choice) make a valid scenario."""
        assert s.dispersions is not None
        doc = base_document(s)
        for key, dist in s.dispersions.vary:
            full = f"dispersions.vary.{key}"
            line = self.line_of(full, doc_line)
            try:
                current = value_at(doc, key)
            except PathError as exc:
                raise self.error(line, full, str(exc)) from None
            if isinstance(current, list) and key in (s.dispersions.envelope or ()):
                raise self.error(self.line_of("dispersions.envelope", doc_line), "dispersions.envelope",
                                 f"expected fields with one number each, {key} is a vector: name one of "
                                 f"its components ({key}[0])")
            for value in dist.extremes():
                if isinstance(current, list):
                    drawn: Any = [c + value if dist.offset else value for c in current]
                else:
                    drawn = current + value if dist.offset else value
                try:
                    dispersed(s, {key: drawn}, 0, "check")
                except ScenarioError as exc:
                    raise self.error(line, full, f"a draw of {value!r} makes no valid scenario: "
                                     f"{exc.field}: {exc.message}") from None

    def faults(self, node: Node, path: str) -> tuple[Fault, ...]:
        if isinstance(node, ScalarNode) and self.value(node) is None:
            return ()
        return tuple(self.fault(n, f"{path}[{i}]") for i, n in enumerate(self.sequence(node, path)))

    def fault(self, node: Node, path: str) -> Fault:
        items = self.mapping(node, path, FAULT_KEYS)
        if "kind" not in items:
            raise self.error(node, f"{path}.kind", f"required field missing; one of {', '.join(FAULT_KINDS)}")
        kind = self.convert(str, items["kind"], f"{path}.kind", {"choices": tuple(FAULT_KINDS)})
        time_meta = {"lo": 0.0, "hi": 3600.0}
        # an instant (onboard_killed: at_s or at) or a window (start_s or start, then end_s or duration_s)
        instant = FAULT_KINDS[kind].instant
        abs_key, rel_key = ("at_s", "at") if instant else ("start_s", "start")
        wrong = ("start_s", "start", "end_s", "duration_s") if instant else ("at_s", "at")
        for key in wrong:
            if key in items:
                instants = " or ".join(k for k, c in FAULT_KINDS.items() if c.instant)
                what = f"{kind} is an instant: give at_s or at only" if instant else (
                    f"only {instants} takes at_s or at; use start_s or start")
                raise self.error(items[key], f"{path}.{key}", what)
        if (abs_key in items) == (rel_key in items):
            raise self.error(
                items.get(rel_key, node),
                f"{path}.{abs_key}",
                f"give exactly one of {abs_key} (sim s) and {rel_key} ({{after: EVENT, s: SECONDS}}, after a "
                f"mission event: {', '.join(MISSION_EVENTS)})",
            )
        after: EventTime | None = None
        end: float | None = None
        duration: float | None = None
        if rel_key in items:
            after = self.convert(EventTime, items[rel_key], f"{path}.{rel_key}", {})
            start = math.inf  # when the run sees the event
            if "end_s" in items:
                raise self.error(items["end_s"], f"{path}.end_s",
                                 "a fault timed after an event ends with duration_s, not end_s")
        else:
            start = self.convert(float, items[abs_key], f"{path}.{abs_key}", time_meta)
            if "end_s" in items and "duration_s" in items:
                raise self.error(items["duration_s"], f"{path}.duration_s",
                                 "give end_s or duration_s, not both")
            if "end_s" in items:
                end = self.convert(
                    float | None, items["end_s"], f"{path}.end_s", {**time_meta, "lo": start, "lo_open": True}
                )
        if "duration_s" in items:
            duration = self.convert(float, items["duration_s"], f"{path}.duration_s",
                                    {"lo": 0.0, "hi": 3600.0, "lo_open": True})
            if after is None:
                end = start + duration
        phase = None
        if "phase" in items:
            phase = self.convert(str, items["phase"], f"{path}.phase", {"choices": FLIGHT_PHASES})
        params_cls = FAULT_KINDS[kind].params
        params: Any = NoParams()
        if "params" in items:
            sub = items["params"]
            if params_cls is NoParams:
                if isinstance(sub, ScalarNode) and self.value(sub) is None:
                    pass
                else:
                    self.mapping(sub, f"{path}.params", ())
            else:
                kwargs, _ = self.dataclass(params_cls, sub, f"{path}.params")
                params = params_cls(**kwargs)
        elif params_cls is not NoParams:
            raise self.error(node, f"{path}.params", f"required for {kind}")
        if isinstance(params, WindGustParams):
            params = self.wind(params, items["params"], f"{path}.params")
        if isinstance(params, ParamSetParams):
            sub = self.mapping(items["params"], f"{path}.params", ("name", "value"))
            self.fc_param(params.name, params.value, sub["value"], f"{path}.params")
        return Fault(kind=kind, start_s=start, end_s=end, params=params, after=after,
                     duration_s=duration if after is not None else None, phase=phase)

    def params(self, node: Node, path: str) -> tuple[tuple[str, float], ...]:
        """``params:``, a mapping of FC parameter name: value, each checked against the FC's table."""
        if isinstance(node, ScalarNode) and self.value(node) is None:
            return ()
        if not isinstance(node, MappingNode):
            raise self.error(node, path, "expected a mapping of PARAMETER_NAME: value")
        out: dict[str, float] = {}
        for key_node, value_node in node.value:
            name = self.value(key_node)
            if not isinstance(name, str) or name in out:
                what = "given twice" if name in out else f"expected a parameter name, got {name!r}"
                raise self.error(key_node, path, what)
            value = self.value(value_node)
            out[name] = self.fc_param(name, value, value_node, f"{path}.{name}")
        return tuple(out.items())

    def fc_param(self, name: str, value: Any, node: Node, path: str) -> float:
        """``value`` for the FC parameter ``name``, checked against its table (name, type, range)."""
        # (heavy: numba through the emulator, loaded only when a file needs it)
        from emulator.params import ParamError, param_def

        if isinstance(value, int) and not _finite(value):  # the table compares it as a float
            raise self.error(node, path, f"expected a number, got {_describe(value, node)}")
        try:
            return float(param_def(name).check(value))
        except ParamError as exc:
            raise self.error(node, path, exc.reason) from None

    def wind(self, params: WindGustParams, node: Node, path: str) -> WindGustParams:
        if (params.force_n is None) == (params.speed_m_s is None):
            raise self.error(node, path, "give exactly one of force_n and speed_m_s")
        norm = math.sqrt(sum(c * c for c in params.direction))
        if norm < 1e-9:
            raise self.error(
                self.line_of(f"{path}.direction", node.start_mark.line + 1),
                f"{path}.direction",
                "expected a non-zero direction vector",
            )
        if abs(norm - 1.0) < 1e-12:  # already a unit vector: keep it bit for bit (round trips)
            return params
        unit = (params.direction[0] / norm, params.direction[1] / norm, params.direction[2] / norm)
        return replace(params, direction=unit)

    def check_tilt(self, s: Scenario, doc_line: int) -> None:
        """The gap's tilt within the vehicle profile's tilt limit (the traverse flies at the gap's tilt)."""
        # (heavy: numba through the emulator, loaded only when a file needs it)
        from emulator.profile import ProfileError, load_profile

        try:
            limit = load_profile(s.vehicle).max_tilt_deg
        except (ProfileError, OSError):  # the vehicle field's own check names a bad profile
            return
        if s.gap.tilt_deg > limit:
            key = "gap.roll_deg" if abs(s.gap.roll_deg) >= abs(s.gap.pitch_deg) else "gap.pitch_deg"
            raise self.error(
                self.line_of(key, doc_line),
                key,
                f"expected a gap tilt within the vehicle's tilt limit ({_fmt(limit)} deg for "
                f"{s.vehicle}), got {s.gap.tilt_deg:.1f} deg",
            )

    def check_across(self, s: Scenario, doc_line: int) -> None:
        """Rules that involve several fields; errors point at the field most likely wrong."""
        if s.links.esc_bus is None:
            for i, f in enumerate(s.faults):
                if FAULT_KINDS[f.kind].needs_esc_bus:
                    raise self.error(self.line_of(f"faults[{i}].kind", doc_line), f"faults[{i}].kind",
                                     f"{f.kind} needs the motors on an ESC bus: give links.esc_bus ({{}} "
                                     f"for its defaults)")
        lab = s.lab
        for axis in range(3):
            if lab.max_m[axis] <= lab.min_m[axis]:
                raise self.error(
                    self.line_of("lab.max_m", doc_line),
                    "lab.max_m",
                    f"expected above lab.min_m on every axis, got {list(lab.max_m)} vs {list(lab.min_m)}",
                )

        box = f"{list(lab.min_m)}..{list(lab.max_m)}"

        def inside(p: tuple[float, float, float]) -> bool:
            return all(lab.min_m[i] <= p[i] <= lab.max_m[i] for i in range(3))

        if not inside(s.gap.centre_m):
            raise self.error(
                self.line_of("gap.centre_m", self.line_of("lab", doc_line)),
                "gap.centre_m",
                f"expected a point inside the lab {box}, got {list(s.gap.centre_m)}",
            )
        start = s.initial.pos_m
        if s.initial.on_ground:
            start = (start[0], start[1], max(lab.min_m[2], 0.0))
        if not inside(start):
            raise self.error(
                self.line_of("initial.pos_m", self.line_of("lab", doc_line)),
                "initial.pos_m",
                f"expected a point inside the lab {box}, got {list(start)}",
            )
        if s.initial.on_ground and any(v != 0.0 for v in s.initial.vel_m_s):
            raise self.error(
                self.line_of("initial.vel_m_s", doc_line),
                "initial.vel_m_s",
                f"expected zero when on_ground is true, got {list(s.initial.vel_m_s)}",
            )
        if s.gap.height_m > s.gap.width_m:
            raise self.error(
                self.line_of("gap.height_m", doc_line),
                "gap.height_m",
                f"expected at most width_m ({_fmt(s.gap.width_m)}, the long side) got {_fmt(s.gap.height_m)}",
            )
        self.check_tilt(s, doc_line)
        for i, fault in enumerate(s.faults):
            if fault.after is None and fault.start_s >= s.duration_s:
                key = "at_s" if fault.instant else "start_s"
                raise self.error(
                    self.line_of(f"faults[{i}].{key}", doc_line),
                    f"faults[{i}].{key}",
                    f"expected a time before duration_s ({_fmt(s.duration_s)}), got {_fmt(fault.start_s)}",
                )


def onboard_vehicle(vehicle: str) -> str:
    """The onboard configuration for the scenario's ``vehicle`` (a built-in profile name, or a profile
    file): the built-in of the same name, or ``PROFILE.onboard.yaml`` beside the profile file."""
    if vehicle.endswith((".yaml", ".yml")):
        p = Path(vehicle)
        return str(p.with_name(f"{p.stem}.onboard.yaml"))
    return vehicle
