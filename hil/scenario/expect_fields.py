"""The ``expect:`` fields a registered check adds to the scenario schema (`ExpectField`: its name, type,
default, range and meaning), by name in `EXPECT_FIELDS`. The project's own checks read the fields of
`hil.scenario.schema.Expectations`; a check registered later (`hil.runner.checks.register_check`, a
test or a plugin) brings its fields here, and the loader accepts and validates them in ``expect:`` like
the project's, with the same line-aware errors (docs/extending.md, "A check")."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class ExpectField:
    """One ``expect:`` field owned by a check: ``type`` is one the loader reads (bool, int, float, str, a
    tuple of them, any of them ``| None``); ``lo``/``hi`` (inclusive unless ``*_open``) and ``choices``
    bound it as `hil.scenario.spec.spec` does; ``doc`` is its meaning (the format document's table)."""

    name: str
    type: Any
    default: Any
    doc: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: Collection[str] = ()

    @property
    def meta(self) -> dict[str, Any]:
        """Its limits as a `spec` field's metadata (what the loader validates against)."""
        return {"lo": self.lo, "hi": self.hi, "lo_open": self.lo_open, "hi_open": self.hi_open,
                "choices": self.choices, "doc": self.doc}


#: field name -> the field, in the order the checks that own them were registered
EXPECT_FIELDS: dict[str, ExpectField] = {}


def add_expect_field(f: ExpectField, taken: Collection[str]) -> None:
    """Add ``f`` to `EXPECT_FIELDS`; ValueError when its name is taken (registered, or in ``taken``: the
    project's own fields)."""
    if f.name in EXPECT_FIELDS or f.name in taken:
        raise ValueError(f"expect field {f.name!r} exists already")
    EXPECT_FIELDS[f.name] = f
