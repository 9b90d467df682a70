"""The key both sides keep a numba kernel's compiled forms by (`emulator.kernel_cache.entry`,
`policies.compiling.Kernel.entry`): the argument types of an example call, from numba's own fingerprints
of the values. Here because the two sides share no module but the link layer; it loads no numba itself
(the caller hands in numba's fingerprint function)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def types_key(args: tuple[Any, ...], fingerprint: Callable[[Any], bytes] | None) -> tuple[bytes, ...] | None:
    """``fingerprint`` (numba's ``compute_fingerprint``, what its dispatcher keys its type cache on: a
    fraction of a microsecond where ``numba.typeof`` takes 2-20) of each of ``args``, or None where
    that does not fix the numba type: a value numba has no fingerprint for, an int beyond int64 (an
    int's type depends on its value), an array that is not a plain aligned native-order ndarray, or
    no ``fingerprint`` at all (a numba without it: the caller then asks numba each time)."""
    if fingerprint is None:
        return None
    try:
        key = tuple(map(fingerprint, args))
    except (NotImplementedError, ValueError, TypeError):
        return None
    for k, a in zip(key, args, strict=True):
        if k[:1] == b"A":  # (an array: numba types an unaligned, byte-swapped or subclassed one apart)
            if not (a.__class__ is np.ndarray and a.flags.aligned and a.dtype.isnative):
                return None
        elif b"i" in k and not (k == b"i" and -(1 << 63) <= a < 1 << 63):
            return None
    return key
