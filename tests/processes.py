"""The processes a test started, read from /proc: those of a session (a process started with
start_new_session=True leads one, and its children stay in it) or below a process, and how to end them
all, stopped ones too (continued first: a stopped process never notices its links closing).

As a pytest plugin (tests/conftest.py takes its hook; ``pytest -p processes`` elsewhere) it ends, when
the session ends, every process the tests started and left behind, and names them."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path

import pytest

from policies.onboard import forkserver


def _processes() -> list[tuple[int, str, int, int, str]]:
    """Every live process: (pid, state, parent pid, session id, command name); zombies left out."""
    out = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        name_end = stat.rindex(")")
        fields = stat[name_end + 2:].split()
        if fields[0] != "Z":
            out.append((int(proc.name), fields[0], int(fields[1]), int(fields[3]),
                        stat[stat.index("(") + 1:name_end]))
    return out


def processes_of_session(sid: int) -> list[str]:
    """The live processes of session ``sid``: "pid state command" each."""
    return sorted(f"{pid} {state} {name}" for pid, state, _, session, name in _processes() if session == sid)


def descendants(pid: int) -> list[str]:
    """The live processes below ``pid`` (children, theirs, ...): "pid state command" each."""
    procs = _processes()
    below, found = {pid}, True
    while found:
        found = False
        for p, _, parent, _, _ in procs:
            if parent in below and p not in below:
                below.add(p)
                found = True
    return sorted(f"{p} {state} {name}" for p, state, _, _, name in procs if p in below and p != pid)


def end_all(listed: list[str], timeout_s: float = 5.0) -> None:
    """Continue, then kill, the processes ``listed`` ("pid ..." each); waits up to ``timeout_s``."""
    pids = [int(line.split()[0]) for line in listed]
    for sig in (signal.SIGCONT, signal.SIGKILL):
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and any(_state(pid) != "Z" for pid in pids):
        time.sleep(0.05)


def kill_session(sid: int, timeout_s: float = 5.0) -> None:
    """Continue, then kill, every process of session ``sid``."""
    end_all(processes_of_session(sid), timeout_s)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


def pytest_sessionfinish(session: pytest.Session) -> None:
    """End what the tests of this process left running (an xdist controller's own children are its
    workers: each of them ends its own)."""
    config = session.config
    if not hasattr(config, "workerinput") and config.getoption("dist", "no") != "no":
        return
    forkserver.close_shared()  # (kept for all the session's runs: not a process left behind)
    left = descendants(os.getpid())
    if left:
        print(f"\nending {len(left)} processes the tests left: {'; '.join(left)}", file=sys.stderr)
        end_all(left)
