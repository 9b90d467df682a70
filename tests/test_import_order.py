"""Every module a user or a tool imports first loads on its own in a fresh interpreter: no import cycle
that only works when another module happened to be imported before (the ESC bus model once failed
`import emulator.esc.bus` alone: its kernels load the FC, whose parameters named the bus's settings)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIRST_IMPORTS = (
    "emulator.esc.bus", "emulator.esc.kernels", "emulator.esc.config", "emulator.fc",
    "emulator.params", "emulator.fc.n3", "emulator.loops.batched_steps", "emulator.physics.native",
    "emulator.world", "hil.rl.env", "hil.rl.observe", "hil.rl.targets", "hil.link.mavlink", "hil.runner",
    "hil.cli", "policies.onboard.cli", "policies.learning.learned_pilots",
)


def test_each_module_imports_first_in_a_fresh_interpreter():
    procs = {m: subprocess.Popen([sys.executable, "-c", f"import {m}"], cwd=ROOT, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True) for m in FIRST_IMPORTS}
    failed = {}
    for m, p in procs.items():
        _, err = p.communicate(timeout=300)
        if p.returncode != 0:
            failed[m] = err.strip().splitlines()[-1] if err.strip() else f"exit {p.returncode}"
    assert not failed, failed


@pytest.mark.parametrize("module", ["policies.onboard.cli", "policies.learning.learned_pilots"])
def test_the_onboard_side_loads_no_compiler(module):
    # (the onboard computer runs the pilot's plain arithmetic as it is; the RL environment compiles it)
    code = f"import sys, {module}; assert 'numba' not in sys.modules, 'numba loaded'"
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
