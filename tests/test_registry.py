"""hil.link.registry: names -> lazily imported factories, as pilots, physics backends, benches and commands
are found."""

from __future__ import annotations

import sys

import pytest

from emulator.physics import BACKENDS, backend_names
from hil.benches import BENCHES
from hil.cli import COMMANDS
from hil.link.registry import Registry
from policies.onboard.pilots import PILOTS, UnknownPilot


def test_each_registry_lists_its_entries_and_names_them_in_the_error_for_an_unknown_one():
    assert {"traditional", "planner_net", "e2e"} <= set(PILOTS.names())
    assert backend_names() == ["jsbsim", "native"]
    assert {"planning", "runner", "physics"} <= set(BENCHES.names()) and "run" in COMMANDS.names()
    with pytest.raises(UnknownPilot, match=r"unknown pilot 'ghost'; known: .*traditional"):
        PILOTS.load("ghost")
    with pytest.raises(ValueError, match="unknown physics backend 'ode'; known: jsbsim, native"):
        BACKENDS.check("ode")


def test_an_entry_is_imported_only_when_asked_for(tmp_path, monkeypatch):
    (tmp_path / "lazy_entry_mod.py").write_text("made = []\ndef factory():\n    return 'built'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    reg = Registry("widget", entries={"lazy": "lazy_entry_mod:factory"})
    assert reg.names() == ["lazy"] and "lazy_entry_mod" not in sys.modules
    assert reg.load("lazy")() == "built" and "lazy_entry_mod" in sys.modules
    with pytest.raises(ValueError, match="either a package"):
        Registry("widget")
