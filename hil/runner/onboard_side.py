"""The onboard side of a run: the onboard program in this process (stepped on the ticks it reads from
its own link) or as a separate process on the other ends of two pseudo-terminals (the real path).

Both present the same small interface to the runner: `service()` (let it act on what was sent), `kill()`,
`pause()` / `resume()`, `alive`, `events()` (its mission events as dicts), `close()`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any, Protocol

from emulator.profile import VehicleProfile
from hil.link.transport import Transport
from hil.scenario.schema import Scenario
from policies.onboard import EventLog, OnboardProgram, ProgramConfig
from policies.onboard.cli import add_arguments, config_from_args

DEFAULT_APPROACH_SPEED_M_S = 2.0  # when the scenario leaves the speed to the pilot


class OnboardSide(Protocol):
    alive: bool

    def service(self) -> None: ...
    def kill(self) -> None: ...
    def pause(self) -> None: ...
    def resume(self) -> None: ...
    def exited(self) -> bool: ...
    def events(self) -> list[dict[str, Any]]: ...
    def close(self) -> None: ...


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
        self.alive = True
        self.paused = False

    def service(self) -> None:
        """Read what arrived; act on each lockstep tick in it (as `run_lockstep` does, without waiting)."""
        p = self.program
        if self.alive and not self.paused and not p.finished:
            p.lockstep_poll()

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

    def close(self) -> None:
        self.program.events.close()


class ProcessOnboard:
    """``python -m policies.onboard`` as a child process on two pty slave paths."""

    def __init__(self, argv: list[str], log_path: Path, stderr_path: Path) -> None:
        self.argv = argv
        self.log_path = log_path
        self._stderr = open(stderr_path, "wb")  # noqa: SIM115 - closed in close()
        env = dict(os.environ)
        env.setdefault("PYTHONHASHSEED", "0")
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._stderr, env=env
        )
        self.alive = True
        self.paused = False

    def service(self) -> None:
        return  # it runs on its own

    def exited(self) -> bool:
        return self.proc.poll() is not None

    def kill(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGKILL)
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
        out = []
        with contextlib.suppress(OSError):
            for line in self.log_path.read_text(encoding="utf-8").splitlines():
                with contextlib.suppress(ValueError):
                    ev = json.loads(line)
                    if isinstance(ev, dict):
                        out.append(ev)
        return out

    def close(self, timeout_s: float = 5.0) -> int | None:
        """End the process (SIGTERM, then SIGKILL) and return its exit code."""
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


def onboard_options(s: Scenario, profile: VehicleProfile) -> list[str]:
    """The onboard program's options for scenario ``s`` on vehicle ``profile`` (links not included)."""
    lab_min, lab_max = (",".join(repr(float(v)) for v in c) for c in (s.lab.min_m, s.lab.max_m))
    return [
        "--pilot",
        s.pilot,
        "--approach-speed",
        repr(s.approach.speed_m_s or DEFAULT_APPROACH_SPEED_M_S),
        "--approach-duration",
        repr(s.approach.duration_s),
        "--mass",
        repr(profile.mass_kg),
        "--full-thrust",
        repr(profile.n3_full_thrust_n),
        "--gap-size",
        repr(s.gap.width_m),
        repr(s.gap.height_m),
        f"--lab-min={lab_min}",
        f"--lab-max={lab_max}",
        "--body-box",
        *(repr(float(v)) for v in profile.body_box_m),
    ]


def program_config(options: list[str]) -> ProgramConfig:
    """The ProgramConfig the onboard program's own command line makes of ``options``."""
    parser = argparse.ArgumentParser(prog="onboard", exit_on_error=False)
    add_arguments(parser)
    try:
        args = parser.parse_args(["--command-link", "memory", "--mocap-link", "memory", *options])
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
        sys.executable,
        "-m",
        "policies.onboard",
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
