"""Where numba keeps the compiled kernels: a folder named by a digest of the emulator's sources.

numba checks a cached kernel against the timestamp of its own source file only, but the kernels here are
compiled with functions and constants of other modules inlined (the FC's fused loop calls the mixer, the
physics and the world check). After a change to one of those alone (a `git pull` that touches the mixer),
numba's own cache would go on flying the old code, silently. So the cache lives in a folder named by a
digest of every source file of the package (and of the modules outside it that have kernels or feed
them, `_OTHER_SOURCES`): any change compiles afresh, once (about 10 s), and runs of one checkout share
it. Folders of other digests that
have not been used for a day are removed, beyond the few most recent.

``NUMBA_CACHE_DIR``, when set, is used as it is: the user's choice.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import time
import weakref
from pathlib import Path
from typing import Any

from hil.link.kernel_types import types_key

#: folders of other digests kept whatever their age (other checkouts, a branch switched back to)
KEEP_OTHERS = 4
STALE_AFTER_S = 86400.0

_ROOT = Path(__file__).resolve().parent
#: modules outside the package with kernels, or with plain functions compiled into kernels elsewhere
_OTHER_SOURCES = tuple(_ROOT.parent / f for f in (
    "hil/runner/recorder.py", "hil/rl/observe.py", "hil/rl/reward.py", "hil/rl/targets.py",
    "hil/link/mavlink.py", "policies/learning/learned_pilots.py", "hil/rl/link_observe.py",
    "hil/link/channel.py", "policies/onboard/estimator.py", "hil/link/linktrack.py"))


def sources_digest() -> str:
    """sha256 (12 hex digits) of the package's .py files and the recorder's, by relative path."""
    h = hashlib.sha256()
    files = sorted(_ROOT.rglob("*.py")) + [p for p in _OTHER_SOURCES if p.is_file()]
    for path in files:
        h.update(str(path.relative_to(_ROOT.parent)).encode())
        h.update(b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def cache_root() -> Path:
    """The folder that holds one folder per digest: ``numba`` in the project's cache ($HIL_CACHE_DIR,
    else crossgap-hil under $XDG_CACHE_HOME or ~/.cache, as the learning data's)."""
    env = os.environ.get("HIL_CACHE_DIR")
    if env:
        return Path(env) / "numba"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "crossgap-hil" / "numba"


def configure() -> Path | None:
    """Point numba's cache at this digest's folder (unless NUMBA_CACHE_DIR is set); returns it, or
    None when the user's setting stands or no folder can be made (numba then caches as it would)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    folder = cache_root() / sources_digest()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)  # (used now: kept by the clean-up of other checkouts)
    except OSError:
        return None
    os.environ["NUMBA_CACHE_DIR"] = str(folder)  # (for a numba imported later, and child processes)
    from numba.core import config

    config.CACHE_DIR = str(folder)  # (for a numba imported already)
    _remove_stale(folder)
    return folder


def cold(module: str = "") -> Path | None:
    """This digest's folder when no kernel (of ``module``, a dotted name such as ``emulator.esc.kernels``,
    if named) is cached in it yet (the first use after an install or a change compiles them, about 10-20 s
    on two cores), else None; None too when ``NUMBA_CACHE_DIR`` is the user's own."""
    folder = os.environ.get("NUMBA_CACHE_DIR")
    if not folder or Path(folder) != cache_root() / sources_digest():
        return None
    # numba files a module's kernels under a folder named by the module's own folder (and a hash of its
    # path), each named by the module file's stem: ``esc_<hash>/kernels.run-40.py311.nbi``
    package, _, stem = module.rpartition(".")
    pattern = f"{package.rpartition('.')[2]}_*/{stem}.*.nbi" if module else "*.nbi"
    return Path(folder) if next(Path(folder).rglob(pattern), None) is None else None


def entry(kernel: Any, *args: Any) -> Any:
    """The compiled form of ``kernel`` (a numba dispatcher) for the numba types of ``args`` (an example
    call's arguments; compiled or loaded from the cache now if need be), called without numba's per-call
    dispatch on the argument types: for a per-tick caller whose arguments always have these types (its
    own float64 arrays, bound once, and floats and ints). An int or a numpy float where a float goes is
    converted as `float` converts it; an array is not checked (its dtype, dimensions, layout and
    writability must be the example's). Each kernel's forms are kept by the argument types' key
    (`hil.link.kernel_types.types_key`): a second run of a process asks numba nothing."""
    from numba import typeof  # (numba is configured by `configure` before its first import)
    try:  # (numba's own type key; a private name, so a numba without it is served uncached)
        from numba._dispatcher import compute_fingerprint
    except ImportError:
        compute_fingerprint = None

    key = types_key(args, compute_fingerprint)
    forms = _entries.setdefault(kernel, {})
    form = forms.get(key) if key is not None else None
    if form is None:
        form = kernel.compile(tuple(typeof(a) for a in args))
        if key is not None:
            forms[key] = form
    return form


#: the compiled forms `entry` handed out, by kernel and argument types' key
_entries: weakref.WeakKeyDictionary[Any, dict[tuple[bytes, ...], Any]] = weakref.WeakKeyDictionary()


def _remove_stale(current: Path) -> None:
    others = []
    for p in current.parent.iterdir():
        if p != current and p.is_dir():
            with contextlib.suppress(OSError):
                others.append((p.stat().st_mtime, p))
    others.sort(reverse=True)
    now = time.time()
    for mtime, p in others[KEEP_OTHERS:]:
        if now - mtime > STALE_AFTER_S:
            shutil.rmtree(p, ignore_errors=True)
