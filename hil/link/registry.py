"""Registries by name: name -> a factory imported only when that name is asked for (python-can's bus
registry). Kept here, beside the links, because it is the one place both sides and the harness may import.

A registry lists its names either explicitly (``{"native": "emulator.physics.native:NativeBackend"}``) or
as the public modules of a package, each module one entry whose factory is the attribute ``attr``
(adding an entry is then adding one file). An unknown name is ``error`` with the known names listed.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
from collections.abc import Mapping


def _mtime_ns(folder: str) -> int:
    """A folder's modification time (ns; -1 if it cannot be read): it changes when a file is added."""
    try:
        return os.stat(folder).st_mtime_ns
    except OSError:
        return -1


class Registry:
    """``names()`` and ``load(name)`` (the factory) of one kind of thing, e.g. pilots or benches."""

    def __init__(self, kind: str, *, package: str | None = None, attr: str = "",
                 entries: Mapping[str, str] | None = None, error: type[Exception] = ValueError) -> None:
        if (package is None) == (entries is None) or (package is not None and not attr):
            raise ValueError("a registry takes either a package and an attribute, or explicit entries")
        self.kind, self.package, self.attr, self.error = kind, package, attr, error
        self._entries = dict(entries or {})
        self._listed: tuple[tuple[tuple[str, int], ...], list[str]] | None = None  # (where, names)

    def names(self) -> list[str]:
        """The known names, sorted. A package's modules are listed again only when its folders (or their
        modification times) change: a module added while a process runs is seen, and a process forked
        after the listing (a warm-started program) stats the folders instead of reading them."""
        if self.package is None:
            return sorted(self._entries)
        path = importlib.import_module(self.package).__path__
        where = tuple((p, _mtime_ns(p)) for p in path)
        if self._listed is None or self._listed[0] != where:
            found = sorted(m.name for m in pkgutil.iter_modules(path) if not m.name.startswith("_"))
            self._listed = (where, found)
        return list(self._listed[1])

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
