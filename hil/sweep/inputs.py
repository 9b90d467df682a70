"""What decides the outcome of a sweep's runs, by content: the scenario and its dispersions as the
plan reads them, each file the scenario names (a vehicle profile file and the onboard configuration
beside it), the project's own files (its code, built-in vehicles and network weights) and its version.
A sweep resumes results only while every one of them is as it was when they were flown."""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.util
import json
from pathlib import Path
from typing import Any

from hil.scenario.dispersions import base_document
from hil.scenario.loader import onboard_vehicle
from hil.scenario.schema import Dispersions, Scenario

#: the packages whose files decide a run (the harness, the flight controller's side, the onboard side)
PROJECT_PACKAGES = ("hil", "emulator", "policies")
DISTRIBUTION = "crossgap-hil"
SCENARIO = "the scenario and its dispersions"
PROJECT = "the project's files"
VERSION = "the project's version"


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def tree_digest(roots: dict[str, Path]) -> str:
    """One digest of every file under each root (by name and content; compiled-bytecode caches left out)."""
    h = hashlib.sha256()
    for name, root in sorted(roots.items()):
        for p in sorted(root.rglob("*")):
            if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
                h.update(f"{name}/{p.relative_to(root).as_posix()}\0".encode())
                h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()[:16]


@functools.cache
def project_digest() -> str:
    """The digest of the project's packages as this process imports them (read once per process)."""
    roots = {}
    for name in PROJECT_PACKAGES:
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.submodule_search_locations, name  # this module is one of them
        roots[name] = Path(next(iter(spec.submodule_search_locations)))
    return tree_digest(roots)


def project_version() -> str:
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def named_files(scenario: Scenario) -> dict[str, Path]:
    """The files outside the project that ``scenario`` flies with, by what they are (a built-in vehicle
    is among the project's files)."""
    if not scenario.vehicle.endswith((".yaml", ".yml")):
        return {}
    return {f"the vehicle profile {scenario.vehicle}": Path(scenario.vehicle),
            f"the onboard configuration {onboard_vehicle(scenario.vehicle)}":
                Path(onboard_vehicle(scenario.vehicle))}


def run_inputs(scenario: Scenario, dispersions: Dispersions) -> dict[str, str]:
    """What decides the sweep's runs, each by a digest of its content (a missing file: "missing")."""
    doc = json.dumps({"scenario": base_document(scenario), "dispersions": dispersions.to_dict()},
                     sort_keys=True, default=str)
    out = {SCENARIO: _sha(doc.encode())}
    for what, path in named_files(scenario).items():
        out[what] = _sha(path.read_bytes()) if path.is_file() else "missing"
    out[PROJECT] = project_digest()
    out[VERSION] = project_version()
    return out


def fingerprint(inputs: dict[str, str]) -> str:
    return _sha(json.dumps(inputs, sort_keys=True).encode())


def changed(then: Any, now: dict[str, str]) -> str:
    """Why results flown with ``then`` (a plan file's ``inputs``) are not this plan's: what changed."""
    if not isinstance(then, dict):
        return "they were flown by a version that did not record what decided them"
    what = [k for k in now if then.get(k) != now[k]] + [k for k in then if k not in now]
    if VERSION in what:
        what[what.index(VERSION)] = f"{VERSION} ({then.get(VERSION)} -> {now.get(VERSION)})"
    return ", ".join(what) + (" changed" if what else "")
