"""The onboard side of a run: the onboard program in this process (stepped on the ticks it reads from
its own link) or as a separate process on the other ends of two pseudo-terminals (the real path).

Both present the same small interface to the runner: `service()` (let it act on what was sent), `kill()`,
`pause()` / `resume()`, `alive`, `events()` (its mission events as dicts, the program's closing "summary"
of counters last once `close()` has run), `close()` (returns the program's exit code).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import IO, Any, Protocol

from hil.link.transport import Transport
from hil.scenario.loader import onboard_vehicle
from hil.scenario.schema import Scenario
from policies.onboard import EventLog, OnboardProgram, ProgramConfig, forkserver
from policies.onboard.cli import add_arguments, config_from_args
from policies.onboard.command_links import COMMAND_LINKS

DEFAULT_APPROACH_SPEED_M_S = 2.0  # when the scenario leaves the speed to the pilot


class OnboardSide(Protocol):
    alive: bool

    def service(self) -> None: ...
    def kill(self) -> None: ...
    def pause(self) -> None: ...
    def resume(self) -> None: ...
    def exited(self) -> bool: ...
    def events(self) -> list[dict[str, Any]]: ...
    def new_events(self, up_to_s: float) -> list[dict[str, Any]]: ...
    def close(self) -> int | None: ...


class _EventCursor:
    """Hands out each event once, in order, up to a sim time; later ones wait for a later call."""

    def __init__(self) -> None:
        self._held: list[dict[str, Any]] = []

    def take(self, fresh: list[dict[str, Any]], up_to_s: float) -> list[dict[str, Any]]:
        held = self._held
        held += fresh
        n = 0
        while n < len(held) and _event_time(held[n]) <= up_to_s + 1e-9:
            n += 1
        out, self._held = held[:n], held[n:]
        return out


def _event_time(ev: dict[str, Any]) -> float:
    t = ev.get("t_s")
    return float(t) if isinstance(t, int | float) else -1.0


class InProcessOnboard:
    """`OnboardProgram` over in-memory links, run when `service()` is called (lockstep)."""

    def __init__(
        self,
        command: Transport,
        mocap: Transport,
        config: ProgramConfig,
        log_path: Path | None = None,
        lockstep: bool = True,
    ) -> None:
        self.program = OnboardProgram(
            command, mocap, config, events=EventLog(path=None if log_path is None else str(log_path))
        )
        self.program.link.lockstep = lockstep  # as `python -m policies.onboard --lockstep` runs
        self._poll = self.program.lockstep_poll
        self.alive = True
        self.paused = False
        self._cursor = _EventCursor()
        self._seen = 0

    def service(self) -> None:
        """Read what arrived; act on each lockstep tick in it (as `run_lockstep` does, without waiting)."""
        if self.alive and not self.paused:
            self._poll()  # (it does nothing once the program has finished)

    def step_realtime(self, now_s: float) -> None:
        if self.alive and not self.paused and not self.program.finished:
            self.program.step(now_s)

    def kill(self) -> None:
        self.alive = False

    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    def exited(self) -> bool:
        return self.program.finished

    def events(self) -> list[dict[str, Any]]:
        return list(self.program.events.events)

    def new_events(self, up_to_s: float) -> list[dict[str, Any]]:
        """The events not handed out before, stamped up to ``up_to_s`` (sim s)."""
        log = self.program.events.events
        fresh, self._seen = log[self._seen :], len(log)
        return self._cursor.take(fresh, up_to_s)

    def close(self) -> int | None:
        """Log the program's summary (unless killed: a killed process writes none) and close its log;
        returns its exit code."""
        if self.alive:
            self.program.log_summary()
        self.program.events.close()
        return self.program.exit_code


def program_env() -> dict[str, str]:
    """The onboard program's environment: this one, with a fixed hash seed (the same run, the same bytes)."""
    env = dict(os.environ)
    env.setdefault("PYTHONHASHSEED", "0")
    return env


def prestart() -> None:
    """Start this process's fork server now (it imports in the background), so that the first warm
    start of a run does not wait for it."""
    with contextlib.suppress(forkserver.ForkServerError):
        forkserver.shared(program_env())


class ProcessOnboard:
    """``python -m policies.onboard`` as a child process on two pty slave paths: forked by this process's
    fork server (``warm``, see `policies.onboard.forkserver`), or a new interpreter (cold)."""

    def __init__(self, argv: list[str], log_path: Path, stderr_path: Path, warm: bool = False) -> None:
        self.argv = argv
        self.log_path = log_path
        self._stderr = open(stderr_path, "wb")  # noqa: SIM115 - closed in close()
        proc: forkserver.ForkedProcess | None = None
        if warm and argv[:3] == program_command():
            pilot = argv[argv.index("--pilot") + 1] if "--pilot" in argv[:-1] else None
            try:
                server = forkserver.shared(program_env())
                if server is not None:
                    proc = server.spawn(argv[3:], self._stderr, preload=pilot)
            except forkserver.ForkServerError as exc:  # the run goes on cold, and its folder says why
                self._stderr.write(f"warm start failed ({exc}); started cold\n".encode())
                self._stderr.flush()
        self.warm = proc is not None
        self.proc: subprocess.Popen[bytes] | forkserver.ForkedProcess = proc or subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._stderr, env=program_env(),
            process_group=0,  # a Ctrl-C at the terminal is the harness's to handle, not the program's
        )
        self.alive = True
        self.paused = False
        self._cursor = _EventCursor()
        self._log_offset = 0  # bytes of the event log read by `new_events`
        self._log: IO[bytes] | None = None  # the event log, open for `new_events`
        #: real time: the harness's time zero on the monotonic clock (s); the program's events, stamped
        #: on its own clock, are put on the harness's time line with it (see `_on_harness_time`)
        self.harness_zero_monotonic_s: float | None = None
        self._offset_s: float | None = None  # program clock -> harness clock (s), once known

    def service(self) -> None:
        return  # it runs on its own

    def exited(self) -> bool:
        return self.proc.poll() is not None

    @property
    def cpu_s(self) -> float | None:
        """The program's CPU time in all (user + system, s) once it has exited, as its fork server
        reaped it; None while it runs, or when it was started cold."""
        return getattr(self.proc, "cpu_s", None)

    def kill(self) -> None:
        if self.proc.poll() is None:
            for sig in (signal.SIGCONT, signal.SIGKILL):  # (a stopped process is continued first)
                with contextlib.suppress(ProcessLookupError):
                    self.proc.send_signal(sig)
            self.proc.wait()
        self.alive = False

    def pause(self) -> None:
        if self.proc.poll() is None and not self.paused:
            self.proc.send_signal(signal.SIGSTOP)
        self.paused = True

    def resume(self) -> None:
        if self.proc.poll() is None and self.paused:
            self.proc.send_signal(signal.SIGCONT)
        self.paused = False

    def events(self) -> list[dict[str, Any]]:
        with contextlib.suppress(OSError):
            return self._on_harness_time(_parse_events(self.log_path.read_bytes()))
        return []

    def _on_harness_time(self, events: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """``events`` with their times moved from the program's clock to the harness's, in real time
        (the program's clock starts with it, the harness's before it); as they are in lockstep."""
        zero = self.harness_zero_monotonic_s
        if zero is None:
            return events
        if self._offset_s is None:
            start = next((e for e in events if e.get("event") == "start"), None)
            own = None if start is None else start.get("clock_zero_monotonic_s")
            if not isinstance(own, int | float):
                return events  # (not known yet: a later call has the start event)
            self._offset_s = float(own) - zero
        for ev in events:
            if isinstance(ev.get("t_s"), int | float):
                ev["t_s"] = round(ev["t_s"] + self._offset_s, 4)
        return events

    def new_events(self, up_to_s: float) -> list[dict[str, Any]]:
        """The events not handed out before, stamped up to ``up_to_s`` (sim s): the program writes each
        line before it answers the tick it happened at, so the log holds every event up to a tick
        answered; a line still being written waits for the next call."""
        data = b""
        with contextlib.suppress(OSError):
            if self._log is None:  # opened once the program has made it, read on from where it was
                self._log = open(self.log_path, "rb")  # noqa: SIM115 - closed in close()
            self._log.seek(self._log_offset)
            data = self._log.read()
        whole = data[: data.rfind(b"\n") + 1]
        self._log_offset += len(whole)
        return self._cursor.take(self._on_harness_time(_parse_events(whole)), up_to_s)

    def close(self, timeout_s: float = 5.0) -> int | None:
        """End the process (SIGTERM, then SIGKILL) and return its exit code."""
        if self._log is not None:
            self._log.close()
            self._log = None
        if self.paused:
            self.resume()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        self._stderr.close()
        return self.proc.returncode


def _parse_events(data: bytes) -> list[dict[str, Any]]:
    """The JSON-object lines of an event log; anything else is skipped."""
    out = []
    for line in data.decode("utf-8", errors="replace").splitlines():
        with contextlib.suppress(ValueError):
            ev = json.loads(line)
            if isinstance(ev, dict):
                out.append(ev)
    return out


def onboard_options(s: Scenario) -> list[str]:
    """The onboard program's options for scenario ``s`` (links not included): the vehicle's mass and
    limits come from the onboard side's own configuration of it (`onboard_vehicle`), never from the
    emulator's profile."""
    lab_min, lab_max = (",".join(repr(float(v)) for v in c) for c in (s.lab.min_m, s.lab.max_m))
    return [
        "--fc-protocol",
        s.links.command.protocol,
        "--pilot",
        s.pilot,
        "--approach-speed",
        repr(s.approach.speed_m_s or DEFAULT_APPROACH_SPEED_M_S),
        "--approach-duration",
        repr(s.approach.duration_s),
        "--vehicle",
        onboard_vehicle(s.vehicle),
        "--gap-size",
        repr(s.gap.width_m),
        repr(s.gap.height_m),
        f"--lab-min={lab_min}",
        f"--lab-max={lab_max}",
    ]


@functools.cache
def _options_parser(protocols: tuple[str, ...]) -> argparse.ArgumentParser:
    """The onboard program's options as `program_config` parses them, built once a process for the
    registered command-link protocols ``protocols`` (its ~140 options took most of a run's
    `program_config`; a protocol registered later is a new ``--fc-protocol`` choice: a new parser;
    parsing leaves the parser as it was)."""
    parser = argparse.ArgumentParser(prog="onboard", exit_on_error=False)
    add_arguments(parser)
    return parser


def program_config(options: list[str]) -> ProgramConfig:
    """The ProgramConfig the onboard program's own command line makes of ``options``."""
    try:
        args = _options_parser(tuple(COMMAND_LINKS)).parse_args(
            ["--command-link", "memory", "--mocap-link", "memory", *options])
    except (argparse.ArgumentError, SystemExit) as exc:
        raise ValueError(f"onboard options {options}: {exc}") from None
    return config_from_args(args)


def onboard_argv(
    command_path: str,
    mocap_path: str,
    baud_command: int,
    baud_mocap: int,
    options: list[str],
    log_path: Path,
    lockstep: bool,
) -> list[str]:
    """The onboard program's command line on two serial paths."""
    argv = [
        *program_command(),
        "--command-link",
        f"serial:{command_path}:{baud_command}",
        "--mocap-link",
        f"serial:{mocap_path}:{baud_mocap}",
        *options,
        "--log-json",
        str(log_path),
        "--quiet",
    ]
    if lockstep:
        argv.append("--lockstep")
    return argv


def program_command() -> list[str]:
    """How the onboard program is started cold: ``python -m policies.onboard``."""
    return [sys.executable, "-m", forkserver.MODULE]
