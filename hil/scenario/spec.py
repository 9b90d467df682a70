"""`spec`: a dataclass field of a scenario file with its validation limits (range, choices, meaning),
which the loader validates against and the format document is checked against."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import MISSING, field
from typing import Any

Vec3 = tuple[float, float, float]


def spec(
    default: Any = MISSING,
    *,
    factory: Any = MISSING,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    choices: Collection[str] = (),
    doc: str = "",
) -> Any:
    """A dataclass field carrying its validation limits (``lo``/``hi`` inclusive unless ``*_open``)."""
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "choices": choices, "doc": doc}
    if factory is not MISSING:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)

