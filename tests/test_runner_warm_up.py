"""What a suite loads before its runs: on a cold kernel cache, the families of kernels only some runs use
compile in child processes beside the warm-up, and a run of such a family waits for its child instead of
compiling the same kernels a second time."""

from __future__ import annotations

import os
import signal
import time

from emulator import kernel_cache
from hil.runner import RunOptions
from hil.runner.warm_up import Compiling, families_of
from hil.scenario import loads_scenarios

PLAIN = loads_scenarios("description: a plain flight\nduration_s: 1\n")[0]
ESC = loads_scenarios("description: motors on a bus\nduration_s: 1\nlinks:\n  esc_bus: {}\n")[0]


def test_a_family_is_cold_until_one_of_its_kernels_is_in_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_CACHE_DIR", str(tmp_path))
    folder = kernel_cache.cache_root() / kernel_cache.sources_digest()
    (folder / "fc_0123").mkdir(parents=True)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(folder))
    assert kernel_cache.cold() == folder and kernel_cache.cold("emulator.esc.kernels") == folder
    (folder / "fc_0123" / "inner_loop.control-86.py311.nbi").write_bytes(b"")
    assert kernel_cache.cold() is None  # some kernels cached: not cold as a whole
    assert kernel_cache.cold("emulator.esc.kernels") == folder  # but the ESC bus's are not
    (folder / "physics_0123").mkdir()
    (folder / "physics_0123" / "kernels.step_vehicle-40.py311.nbi").write_bytes(b"")  # another `kernels`
    assert kernel_cache.cold("emulator.esc.kernels") == folder
    (folder / "esc_4567").mkdir()
    (folder / "esc_4567" / "kernels.run-40.py311.nbi").write_bytes(b"")
    assert kernel_cache.cold("emulator.esc.kernels") is None
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))  # the user's own folder: never cold
    assert kernel_cache.cold("emulator.world.box_kernel") is None


def test_only_runs_with_an_esc_bus_use_the_esc_bus_family():
    assert families_of([PLAIN]) == []
    assert families_of([PLAIN, ESC]) == ["esc_bus"]


def test_a_run_of_a_family_waits_for_its_compiling_child_and_no_other_run_does():
    compiling = Compiling()
    compiling.start("esc_bus", RunOptions())
    child = compiling.procs[0]
    os.kill(child.pid, signal.SIGSTOP)  # held mid-way, whatever it has done
    try:
        t0 = time.monotonic()
        compiling.wait_for(PLAIN)  # not of the family: at once (a wait would last the 300 s timeout)
        assert time.monotonic() - t0 < 60.0
        t0 = time.monotonic()
        compiling.wait_for(ESC, timeout_s=0.2)  # of the family: waits, here until its timeout
        assert time.monotonic() - t0 >= 0.2 and child.is_alive()
    finally:
        os.kill(child.pid, signal.SIGCONT)
    compiling.wait_for(ESC)  # until the child has flown its flight
    child.join(timeout=60)
    assert child.exitcode == 0
    assert kernel_cache.cold("emulator.esc.kernels") is None  # which left the family's kernels in the cache
    compiling.join()


def test_a_run_does_not_wait_on_a_child_that_died():
    compiling = Compiling()
    compiling.start("esc_bus", RunOptions())
    os.kill(compiling.procs[0].pid, signal.SIGKILL)
    t0 = time.monotonic()
    compiling.wait_for(ESC)  # the pipe's end shows the child gone: no 300 s wait
    assert time.monotonic() - t0 < 60.0
    compiling.join()
    assert compiling.procs[0].exitcode == -signal.SIGKILL
