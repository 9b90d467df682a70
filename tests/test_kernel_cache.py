"""The compiled kernels' cache: one folder per digest of the emulator's sources, so a change to a module
whose code a kernel inlines (the mixer, in the FC's fused loop) compiles afresh instead of flying the
old code from numba's cache."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from emulator import kernel_cache

ROOT = Path(__file__).resolve().parents[1]


def test_a_change_to_any_source_the_kernels_inline_names_another_folder(tmp_path, monkeypatch):
    shutil.copytree(ROOT / "emulator", tmp_path / "emulator", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "hil" / "runner").mkdir(parents=True)
    shutil.copy(ROOT / "hil" / "runner" / "recorder.py", tmp_path / "hil" / "runner" / "recorder.py")
    monkeypatch.setattr(kernel_cache, "_ROOT", tmp_path / "emulator")
    monkeypatch.setattr(kernel_cache, "_OTHER_SOURCES", (tmp_path / "hil" / "runner" / "recorder.py",))
    before = kernel_cache.sources_digest()
    assert before == kernel_cache.sources_digest()  # the same sources, the same folder
    mixer = tmp_path / "emulator" / "fc" / "inner_loop.py"
    mixer.write_text(mixer.read_text() + "\n# a change to the mixer alone\n")
    changed = kernel_cache.sources_digest()
    assert changed != before
    recorder = tmp_path / "hil" / "runner" / "recorder.py"
    recorder.write_text(recorder.read_text() + "\n")
    assert kernel_cache.sources_digest() not in (before, changed)


def test_numba_caches_in_the_digest_folder_and_the_users_setting_stands(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "HIL_CACHE_DIR")}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    probe = ("import emulator, emulator.kernel_cache as k; from numba.core import config; "
             "print(config.CACHE_DIR); print(k.sources_digest())")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout.split()
    assert out[0] == str(tmp_path / "cache" / "crossgap-hil" / "numba" / out[1])
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout.split()
    assert out[0] == str(tmp_path / "mine")


def test_folders_of_other_digests_unused_for_a_day_go_beyond_the_few_most_recent(tmp_path, monkeypatch):
    from numba.core import config

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("HIL_CACHE_DIR", raising=False)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)  # (both restored after the test: the rest of
    monkeypatch.setattr(config, "CACHE_DIR", config.CACHE_DIR)  # this process caches where it did)
    root = kernel_cache.cache_root()
    old = time.time() - 2 * kernel_cache.STALE_AFTER_S
    for i in range(kernel_cache.KEEP_OTHERS + 3):
        d = root / f"old{i}"
        d.mkdir(parents=True)
        os.utime(d, (old - i, old - i))
    (root / "fresh").mkdir()
    current = kernel_cache.configure()
    kept = {p.name for p in root.iterdir()}
    assert current is not None and current.name in kept and "fresh" in kept
    assert kept - {current.name, "fresh"} == {f"old{i}" for i in range(kernel_cache.KEEP_OTHERS - 1)}


def test_a_kernels_entry_gives_the_kernels_numbers_and_takes_ints_where_floats_go():
    """The compiled form a per-tick caller binds (no type dispatch) flies what the kernel flies: accepted,
    tilt-limited and refused setpoints alike; an int where a float goes is taken as that float."""
    from emulator.fc.n3 import ATTITUDE_THRUST_YAW_RATE, attitude_thrust_values

    fast = kernel_cache.entry(attitude_thrust_values, 0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0)
    flag = ATTITUDE_THRUST_YAW_RATE
    for args in [(flag, 12.5, -20.0, 55.0, 30.0, 35.0, 150.0), (flag, 80.0, 70.0, 55.0, 400.0, 35.0, 150.0),
                 (flag, 10.0, 0.0, 120.0, 0.0, 35.0, 150.0), (flag, 95.0, 0.0, 50.0, 0.0, 35.0, 150.0)]:
        assert fast(*args) == attitude_thrust_values(*args)
    assert fast(flag, 12, -20, 55, 30, 35, 150) == attitude_thrust_values(flag, 12.0, -20.0, 55.0, 30.0, 35.0,
                                                                        150.0)


def test_a_kernels_entry_is_kept_by_its_argument_types_and_never_mixes_two_types():
    """A run asks for the same compiled forms as the run before it: the second ask is answered from what
    the first made, and arguments of other numba types (a read-only array, an int beyond int64, a
    float32 array) get their own form, never one compiled for another type."""
    import numba
    import numpy as np

    @numba.njit
    def first(a, k):
        return a[0] + k

    row, frozen = np.arange(3.0), np.arange(3.0)
    frozen.flags.writeable = False
    one = kernel_cache.entry(first, row, 1)
    assert kernel_cache.entry(first, np.zeros(5), 7) is one  # the same types: the same form, kept
    forms = {one, kernel_cache.entry(first, frozen, 1), kernel_cache.entry(first, row, 1 << 63),
             kernel_cache.entry(first, row.astype(np.float32), 1), kernel_cache.entry(first, row, 1.0)}
    assert len(forms) == 5
    assert kernel_cache.entry(first, row, 1 << 63)(row, 1 << 63) == float(1 << 63)  # (uint64, not int64)


def test_a_numba_without_its_fingerprint_function_still_gives_each_kernels_form(monkeypatch):
    """numba's type key is a private name of its dispatcher: where a numba has none, an entry is asked of
    numba each time (slower) and still gives the form compiled for the arguments' types."""
    import numba
    import numba._dispatcher
    import numpy as np

    @numba.njit
    def second(a, k):
        return a[0] * k

    monkeypatch.delattr(numba._dispatcher, "compute_fingerprint")
    row = np.arange(1.0, 4.0)
    one = kernel_cache.entry(second, row, 3)
    assert one(row, 3) == 3.0
    assert kernel_cache.entry(second, row.astype(np.float32), 2.5)(row.astype(np.float32), 2.5) == 2.5
