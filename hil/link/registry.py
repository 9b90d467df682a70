"""Registries by name: name -> a factory imported only when that name is asked for (python-can's bus
registry). Kept here, beside the links, because it is the one place both sides and the harness may import.

A registry lists its names either explicitly (``{"native": "emulator.physics.native:NativeBackend"}``) or
as the public modules of a package, each module one entry whose factory is the attribute ``attr``
(adding an entry is then adding one file). An unknown name is ``error`` with the known names listed.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Mapping


class Registry:
    """``names()`` and ``load(name)`` (the factory) of one kind of thing, e.g. pilots or benches."""

    def __init__(self, kind: str, *, package: str | None = None, attr: str = "",
                 entries: Mapping[str, str] | None = None, error: type[Exception] = ValueError) -> None:
        if (package is None) == (entries is None) or (package is not None and not attr):
            raise ValueError("a registry takes either a package and an attribute, or explicit entries")
        self.kind, self.package, self.attr, self.error = kind, package, attr, error
        self._entries = dict(entries or {})
        self._names: list[str] | None = None  # a package's, listed on first use

    def names(self) -> list[str]:
        """The known names, sorted. A package's modules are listed once a process (a process forked
        after it, a warm-started program, finds them listed): a module added while it runs is not seen."""
        if self._names is None:
            if self.package is None:
                self._names = sorted(self._entries)
            else:
                path = importlib.import_module(self.package).__path__
                self._names = sorted(m.name for m in pkgutil.iter_modules(path) if not m.name.startswith("_"))
        return list(self._names)

    def check(self, name: str) -> None:
        """``error`` naming the known names unless ``name`` is one."""
        names = self.names()
        if name not in names:
            raise self.error(f"unknown {self.kind} {name!r}; known: {', '.join(names)}")

    def load(self, name: str) -> object:
        """The factory registered as ``name``; ``error`` if there is none. Imports only its module (an
        ImportError there is the caller's: a missing optional dependency of that one entry)."""
        self.check(name)
        if self.package is None:
            module, _, attr = self._entries[name].partition(":")
        else:
            module, attr = f"{self.package}.{name}", self.attr
        return getattr(importlib.import_module(module), attr)
