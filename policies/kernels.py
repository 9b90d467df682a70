"""The onboard computer's float chains compiled by numba: one call a control step or a pose instead of
a few hundred interpreted float operations.

Each kernel is numba's compilation of a plain-Python function of the module that owns the computation
(`policies.controller.expert_law`, `policies.gap_planning.plan_reference`, the traditional pilot's
`traditional_command`, the estimator's `take_pose` and `predicted_state`): that function is the only
definition, run compiled; the classes' methods (`ExpertController.command`, `MissionPlan.reference_tuples`,
`PoseEstimator.take`, ...) are views of it. A function a kernel calls (`_poly_state`, `filter_update`,
...) is compiled too and bound in the kernel's copy of its module's globals (`_compiled`), so the
interpreted code and the compiled code read the same source. numba's IEEE +, -, *, / and sqrt and its
libm calls give the numbers the interpreter gives, and no fast-math or contraction is asked for.

numba checks a cached kernel against its own file only, while these inline functions of other files:
their cache lives in a folder named by a digest of every source they compile (`SOURCES`), under
``NUMBA_CACHE_DIR`` when set (the harness sets it), else in this package's ``__pycache__``. `warm`
compiles or loads them all (the fork server calls it before it forks, so no run pays for it).
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

import numpy as np
from numba import njit
from numba.core import config

from policies import controller, frames, gap_planning, primitives
from policies.onboard import estimator
from policies.onboard.pilots import traditional

#: every source file whose code or constants the kernels compile (the cache folder's digest)
SOURCES = tuple(Path(str(m.__file__))
                for m in (controller, frames, gap_planning, primitives, estimator, traditional))


def cache_folder(sources: tuple[Path, ...] = (Path(__file__), *SOURCES)) -> str:
    """The kernels' cache folder: ``policies-`` and a digest (sha256, 12 hex digits) of ``sources``' names
    and bytes, under ``NUMBA_CACHE_DIR`` if set, else under this package's ``__pycache__``."""
    h = hashlib.sha256()
    for path in sources:
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    base = os.environ.get("NUMBA_CACHE_DIR") or str(Path(__file__).resolve().parent / "__pycache__")
    return os.path.join(base, f"policies-{h.hexdigest()[:12]}")


@contextlib.contextmanager
def _caching_in(folder: str) -> Iterator[None]:
    """numba's cache folder while kernels are defined (numba fixes a kernel's folder then)."""
    before = config.CACHE_DIR
    config.CACHE_DIR = folder
    try:
        yield
    finally:
        config.CACHE_DIR = before


_FOLDER = cache_folder()


def _compiled(fn: Callable[..., Any], **callees: Any) -> Any:
    """numba's compilation of the plain function ``fn`` (its code object, its file's cache entry), with
    the functions it calls named in ``callees`` bound to their compiled forms."""
    scope = dict(fn.__globals__)
    scope.update(callees)
    copy = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__qualname__, copy.__module__, copy.__doc__ = fn.__qualname__, fn.__module__, fn.__doc__
    with _caching_in(_FOLDER):
        return njit(cache=True, error_model="numpy")(copy)


_poly_state = _compiled(primitives._poly_state)
_ballistic_state = _compiled(gap_planning.ballistic_state)
_segment_index = _compiled(gap_planning.segment_index)
_poly_axes = _compiled(gap_planning._poly_axes, _poly_state=_poly_state)
_clip = _compiled(controller._clip)

#: roll, pitch (rad), thrust (N) of the expert law: `policies.controller.expert_law`
expert_law = _compiled(controller.expert_law, _clip=_clip)
#: `expert_law` row by row: `policies.controller.expert_law_rows`
expert_law_rows = _compiled(controller.expert_law_rows, expert_law=expert_law)
#: the plan's reference: `policies.gap_planning.plan_reference`
plan_reference = _compiled(gap_planning.plan_reference, segment_index=_segment_index, _poly_axes=_poly_axes,
                           ballistic_state=_ballistic_state)
#: the traditional pilot's command: `policies.onboard.pilots.traditional.traditional_command`
traditional_command = _compiled(traditional.traditional_command, plan_reference=plan_reference,
                                expert_law=expert_law)

_filter_update = _compiled(estimator.filter_update)
_predicted = _compiled(estimator.predicted)
_plausible_jump_m = _compiled(estimator.plausible_jump_m)
_prediction_horizon_s = _compiled(estimator.prediction_horizon_s)
#: one pose into the estimator's state: `policies.onboard.estimator.take_pose`
take_pose = _compiled(estimator.take_pose, filter_update=_filter_update, predicted=_predicted,
                      plausible_jump_m=_plausible_jump_m)
#: the estimator's state predicted: `policies.onboard.estimator.predicted_state`
predicted_state = _compiled(estimator.predicted_state, prediction_horizon_s=_prediction_horizon_s,
                            predicted=_predicted)

#: the expert law on a packed trajectory: `policies.onboard.pilots.traditional.tracking_command`
tracking_command = _compiled(traditional.tracking_command, _poly_axes=_poly_axes, expert_law=expert_law)


@functools.cache
def warm() -> None:
    """Compile (or load from the cache) every kernel for the argument types the program passes; once a
    process (a process forked after it has them)."""
    g = controller.gains_array(controller.ExpertGains())
    expert_law(*(0.0,) * 16, 0.9, g)
    one = np.zeros((1, 3))
    expert_law_rows(one, one, one, one, one, np.zeros(1), 0.9, g, np.empty((1, 3)))
    plan = np.zeros(gap_planning.PLAN_FLOATS)
    plan[[gap_planning._PLAN_APPROACH, gap_planning._PLAN_RECOVERY]] = 6.0
    plan.flags.writeable = False  # (as `MissionPlan.packed`: numba compiles a read-only array apart)
    for t in (-1.0, 0.0, 1.0):
        plan_reference(plan, t)
        traditional_command(plan, t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.9, g)
        tracking_command(plan[gap_planning._PLAN_APPROACH:gap_planning._PLAN_RECOVERY].copy(), t, 0.0, 0.0,
                         0.0, 0.0, 0.0, 0.0, 0.0, 0.9, g)
    est = estimator.PoseEstimator(max_accel_m_s2=30.0)  # (its arrays: the program's argument types)
    for k in range(3):
        est.take(k * 0.01, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), k * 0.01 + 0.03)
    est.state_tuples(0.05)
