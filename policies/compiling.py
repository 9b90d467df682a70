"""The onboard computer's float chains compiled by numba, each on its first use: one call a control step
or a pose instead of a few hundred interpreted float operations.

A `Kernel` is numba's compilation of a plain-Python function of the module that owns the computation
(`policies.controller.expert_law`, `policies.gap_planning.plan_reference`, the traditional pilot's
`traditional_command` and the program's control steps `traditional_step` and `takeoff_step`, the
estimator's `take_pose` and `predicted_state`, the command links' setpoint numbers `setpoint_wire`
(MAVLink) and `setpoint_angles` (OPEN) and the mocap intake's
`intake_frames`): that function is
the only definition, run compiled; the classes' methods (`ExpertController.command`,
`MissionPlan.reference_tuples`, `PoseEstimator.take`, ...) are views of it. A function a kernel calls
(`_poly_state`, `filter_update`, ...) is compiled too and bound in the kernel's copy of its module's
globals, so the interpreted code and the compiled code read the same source. numba's IEEE +, -, *, /
and sqrt and its libm calls give the numbers the interpreter gives, and no fast-math or contraction is
asked for. Each module declares its kernels beside their functions; nothing here imports them, so the
modules and their kernels form no import circle, and numba is loaded only when a kernel is first asked
for (importing the onboard side stays light; the program asks for all of them before it opens its
links, the fork server before it forks).

numba checks a cached kernel against its own file only, while these inline functions of other files:
their cache lives in a folder named by a digest of every source they compile (`SOURCES`), under
``NUMBA_CACHE_DIR`` when set (the harness sets it), else in this package's ``__pycache__``.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from hil.link.kernel_types import types_key

_ROOT = Path(__file__).resolve().parent
#: every source file whose code or constants the kernels compile (the cache folder's digest)
SOURCES = tuple(_ROOT / f for f in (
    "compiling.py", "controller.py", "frames.py", "gap_planning.py", "primitives.py", "onboard/estimator.py",
    "onboard/pilots/traditional.py", "onboard/command_link.py", "onboard/dji_command_link.py",
    "onboard/mocap_intake.py", "mocap_reader.py", "../hil/link/mavlink.py", "../hil/link/linktrack.py"))


def cache_folder(sources: tuple[Path, ...] = SOURCES) -> str:
    """The kernels' cache folder: ``policies-`` and a digest (sha256, 12 hex digits) of ``sources``' names
    and bytes, under ``NUMBA_CACHE_DIR`` if set, else under this package's ``__pycache__``."""
    h = hashlib.sha256()
    for path in sources:
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    base = os.environ.get("NUMBA_CACHE_DIR") or str(_ROOT / "__pycache__")
    return os.path.join(base, f"policies-{h.hexdigest()[:12]}")


@functools.cache
def _folder() -> str:
    return cache_folder()


@contextlib.contextmanager
def _caching_in(folder: str) -> Iterator[None]:
    """numba's cache folder while a kernel is defined (numba fixes a kernel's folder then)."""
    from numba.core import config  # (numba loaded with the first kernel: see the module's docstring)

    before = config.CACHE_DIR
    config.CACHE_DIR = folder
    try:
        yield
    finally:
        config.CACHE_DIR = before


class Kernel:
    """numba's compilation of the plain function ``fn``, made (or loaded from the cache) on the first
    `get`, with the functions it calls named in ``callees`` bound to their own kernels."""

    def __init__(self, fn: Callable[..., Any], **callees: Kernel) -> None:
        self.fn = fn
        self.callees = callees
        self._compiled: Any = None
        self._entries: dict[tuple[bytes, ...], Any] = {}  # (`entry`'s forms, by argument types' key)

    def get(self) -> Any:
        """The compiled function (numba's dispatcher: it compiles or loads each argument type's form on
        its first call with them)."""
        if self._compiled is None:
            from numba import njit  # (numba loaded with the first kernel: see the module's docstring)

            fn = self.fn
            scope = dict(fn.__globals__)
            scope.update({name: k.get() for name, k in self.callees.items()})
            copy = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
            copy.__qualname__, copy.__module__, copy.__doc__ = fn.__qualname__, fn.__module__, fn.__doc__
            with _caching_in(_folder()):
                self._compiled = njit(cache=True, error_model="numpy")(copy)
        return self._compiled

    def entry(self, *args: Any) -> Any:
        """The compiled form for the numba types of ``args`` (an example call's arguments; compiled or
        loaded from the cache now if need be), called without numba's per-call dispatch on the argument
        types (about half a call's cost): for a caller whose arguments always have these types, its own
        arrays (float64, the same layout and flags) and floats. An int or a numpy float where a float
        goes is converted as `float` converts it; an array is not checked. The forms are kept by the
        argument types' key (`hil.link.kernel_types.types_key`): a program forked from a process that
        made them asks numba nothing."""
        from numba import typeof  # (numba loaded with the first kernel: see the module's docstring)
        try:  # (numba's own type key; a private name, so a numba without it is served uncached)
            from numba._dispatcher import compute_fingerprint
        except ImportError:
            compute_fingerprint = None

        key = types_key(args, compute_fingerprint)
        form = self._entries.get(key) if key is not None else None
        if form is None:
            form = self.get().compile(tuple(typeof(a) for a in args))
            if key is not None:
                self._entries[key] = form
        return form
