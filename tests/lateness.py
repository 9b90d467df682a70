"""How far behind this host lets a real-time loop fall: a probe process (``python tests/lateness.py``)
runs a loop as a real-time run's are, ``WORK_S`` of CPU time every ``PERIOD_S``, and measures how late
each period's work ends against its deadline (a host that wakes it late, or gives it less than its share
of a CPU, makes it later and later) until its stdin closes; then it prints the worst (ms) and the
periods it ran. A separate process, so that the test's own Python (which holds its interpreter's lock)
does not enter the figure: the host's scheduling does.

For pytest (tests/conftest.py takes its hooks): a test marked ``realtime`` (it depends on the wall
clock) first checks the host for ``CHECK_S`` and fails at once with "host fell behind: ..." when a
wake-up was later than ``LATE_LIMIT_MS``; a probe then runs beside the test, and a failure while the
host fell behind says so first ("host fell behind: ..., and then: the test's own failure")."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hil.scenario.schema import REALTIME_MAX_LATE_MS

PERIOD_S = 0.01
WORK_S = 0.003  # CPU time (s) a period: a share of a CPU a real-time run's loops need at least
CHECK_S = 0.3
#: a wake-up later than this is a host too busy for a real-time test: the lateness a real-time run's
#: loop may show at worst (its own check, the scenario's realtime_max_late_ms default)
LATE_LIMIT_MS = REALTIME_MAX_LATE_MS


class Probe:
    """A probe process running from construction to `stop`."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__))], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        self.proc.stdout.readline()  # measuring from here (its start-up is not the host's lateness)

    def stop(self) -> tuple[float, int]:
        """The worst lateness (ms) and the number of wake-ups measured."""
        out, _ = self.proc.communicate(timeout=30)
        data = json.loads(out.strip() or "{}")
        return float(data.get("worst_ms", 0.0)), int(data.get("wakeups", 0))


def fell_behind(worst_ms: float, wakeups: int, when: str) -> str | None:
    """The "host fell behind" sentence when ``worst_ms`` is past the limit, else None."""
    if worst_ms <= LATE_LIMIT_MS:
        return None
    return (f"host fell behind: a loop of {WORK_S * 1e3:g} ms of work every {PERIOD_S * 1e3:g} ms ran "
            f"{worst_ms:.0f} ms late at worst ({wakeups} periods {when}; a real-time test needs under "
            f"{LATE_LIMIT_MS:g} ms)")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):  # type: ignore[no-untyped-def]
    if item.get_closest_marker("realtime") is None:
        yield
        return
    check = Probe()
    time.sleep(CHECK_S)
    before = fell_behind(*check.stop(), f"in {CHECK_S:g} s before the test")
    if before is not None:
        pytest.fail(before, pytrace=False)
    probe = Probe()
    outcome = yield
    worst, wakeups = probe.stop()
    during = fell_behind(worst, wakeups, "while the test ran")
    if during is not None and outcome.excinfo is not None:
        item.user_properties.append(("host_fell_behind", during))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):  # type: ignore[no-untyped-def]
    outcome = yield
    report = outcome.get_result()
    behind = dict(item.user_properties).get("host_fell_behind")
    if behind is not None and call.when == "call" and report.failed:
        report.longrepr = f"{behind}, and then:\n{report.longrepr}"


def _measure() -> None:
    worst, periods = 0.0, 0
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    print("measuring", flush=True)
    deadline = time.monotonic() + PERIOD_S
    while not done.is_set():
        cpu0 = time.process_time()
        while time.process_time() - cpu0 < WORK_S:
            pass
        now = time.monotonic()
        worst = max(worst, (now - deadline) * 1e3)
        if now < deadline:
            time.sleep(deadline - now)
        deadline += PERIOD_S  # (a loop that fell behind stays behind: as a real-time run's)
        periods += 1
    print(json.dumps({"worst_ms": round(worst, 3), "wakeups": periods}))


if __name__ == "__main__":
    _measure()
