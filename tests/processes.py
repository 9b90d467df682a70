"""The processes a test started: those of a session (a process started with start_new_session=True
leads one, and its children stay in it), read from /proc, and how to end them all, stopped ones too."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path


def processes_of_session(sid: int) -> list[str]:
    """The live processes of session ``sid``: "pid state command" each (zombies left out)."""
    out = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        comm_end = stat.rindex(")")
        fields = stat[comm_end + 2:].split()
        state, session = fields[0], int(fields[3])
        if session == sid and state != "Z":
            out.append(f"{proc.name} {state} {stat[stat.index('(') + 1:comm_end]}")
    return sorted(out)


def kill_session(sid: int, timeout_s: float = 5.0) -> None:
    """Continue, then kill, every process of session ``sid``; waits up to ``timeout_s`` for them to go."""
    for sig in (signal.SIGCONT, signal.SIGKILL):
        for line in processes_of_session(sid):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(int(line.split()[0]), sig)
    end = time.monotonic() + timeout_s
    while processes_of_session(sid) and time.monotonic() < end:
        time.sleep(0.05)
