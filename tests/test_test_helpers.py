"""The tests' own helpers: a wall-clock test on a host that fell behind says so (tests/lateness.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

INNER = """
import pytest
import lateness

lateness.LATE_LIMIT_MS = -1.0  # every host falls behind this

@pytest.mark.realtime
def test_on_the_wall_clock(tmp_path):
    raise AssertionError("ran on a host that had fallen behind")

def test_off_the_wall_clock():
    pass
"""


def test_a_realtime_test_on_a_host_that_fell_behind_fails_saying_so_before_it_runs(tmp_path):
    (tmp_path / "test_inner.py").write_text(INNER)
    tests = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tests), str(tests.parent)])}
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0", "-p",
                        "lateness", str(tmp_path / "test_inner.py")],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 1 and "1 failed, 1 passed" in p.stdout, p.stdout + p.stderr
    assert "host fell behind: a loop of 3 ms of work every 10 ms ran" in p.stdout, p.stdout
    assert "before the test" in p.stdout, p.stdout
    assert "ran on a host that had fallen behind" not in p.stdout, p.stdout
