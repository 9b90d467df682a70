"""The onboard program's command line (shared by `python -m policies.onboard` and `hil onboard`)."""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import signal
import sys
from types import FrameType
from typing import NoReturn

from hil.link.endpoint import open_link
from hil.link.transport import LinkError
from policies.onboard.command_links import COMMAND_LINKS
from policies.onboard.estimator import EstimatorConfig
from policies.onboard.pilots import PILOTS
from policies.onboard.program import (
    EXIT_ERROR,
    MIN_RATE_HZ,
    EventLog,
    OnboardProgram,
    ProgramConfig,
    warm_kernels,
)
from policies.vehicle import DEFAULT_VEHICLE, load_vehicle, vehicle_names


def _triple(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (m), got {text!r}")
    try:
        x, y, z = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}") from None
    return x, y, z


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The program's options (units in the help)."""
    d = ProgramConfig()
    p.add_argument("--command-link", required=True, metavar="SPEC",
                   help="link to the FC (MAVLink, or DJI OPEN with --fc-protocol dji-open), e.g. "
                        "serial:/dev/pts/5:921600 or udpout:127.0.0.1:14550")
    aliases = [n.replace("_", "-") for n in COMMAND_LINKS if "_" in n]  # dji-open as well as dji_open
    p.add_argument("--fc-protocol", default=d.fc_protocol, choices=[*COMMAND_LINKS, *aliases],
                   help="what the FC speaks on the command link: MAVLink 2 (default) or DJI's OPEN protocol")
    p.add_argument("--mocap-link", required=True, metavar="SPEC",
                   help="mocap (LinkTrack) link, e.g. serial:/dev/pts/6:921600 or udp:127.0.0.1:14660")
    p.add_argument("--pilot", default=d.pilot, help=f"pilot by name: {', '.join(PILOTS.names())}")
    p.add_argument("--rate-hz", type=float, default=d.rate_hz,
                   help=f"control rate (Hz, >= {MIN_RATE_HZ:g}, the N3's minimum; default {d.rate_hz:g})")
    p.add_argument("--approach-speed", type=float, default=d.approach_speed_m_s, metavar="M_S",
                   help=f"speed through the gap centre (m/s, default {d.approach_speed_m_s:g})")
    p.add_argument("--approach-duration", type=float, default=d.approach_duration_s, metavar="S",
                   help=f"approach primitive duration (s, default {d.approach_duration_s:g})")
    p.add_argument("--traverse-lead", type=float, default=None, metavar="M",
                   help="min. traverse start distance before the gap (m), instead of the vehicle's")
    p.add_argument("--stale-mocap-ms", type=float, default=d.stale_mocap_s * 1e3, metavar="MS",
                   help=f"safe hover when the pose is older (ms, default {d.stale_mocap_s * 1e3:g})")
    p.add_argument("--mocap-latency-ms", type=float, default=EstimatorConfig().latency_s * 1e3, metavar="MS",
                   help="exposure-to-arrival latency the state estimate is predicted over (ms, default 25)")
    p.add_argument("--vehicle", default=DEFAULT_VEHICLE, metavar="NAME|PATH",
                   help="the vehicle's onboard configuration: mass, full thrust, tilt limit, control lead "
                        f"(built-in: {', '.join(vehicle_names())}, or a YAML file; "
                        f"default {DEFAULT_VEHICLE})")
    p.add_argument("--mass", type=float, default=None, metavar="KG",
                   help="mass (kg), instead of the vehicle's")
    p.add_argument("--full-thrust", type=float, default=None, metavar="N",
                   help="total thrust at N3 100 %% (N), instead of the vehicle's")
    p.add_argument("--max-tilt", type=float, default=None, metavar="DEG",
                   help="the expert's tilt limit (deg), instead of the vehicle's")
    p.add_argument("--control-lead-ms", type=float, default=None, metavar="MS",
                   help="compute commands this far ahead, the FC's attitude lag (ms), instead of the "
                        "vehicle's")
    p.add_argument("--gap-size", type=float, nargs=2, default=(d.gap_width_m, d.gap_height_m),
                   metavar=("WIDTH", "HEIGHT"), help="opening's long and short side (m, default 0.8 0.35)")
    p.add_argument("--lab-min", type=_triple, default=d.lab_min_m, metavar="X,Y,Z",
                   help="lab lower corner (m)")
    p.add_argument("--lab-max", type=_triple, default=d.lab_max_m, metavar="X,Y,Z",
                   help="lab upper corner (m)")
    p.add_argument("--body-box", type=float, nargs=3, default=None, metavar=("L", "W", "H"),
                   help="the vehicle's collision box, length width height (m), instead of the vehicle's")
    p.add_argument("--clearance-margin", type=float, default=d.clearance_margin_m, metavar="M",
                   help="room the plan keeps beyond the body box's reach from the floor, the lab and the "
                        f"wall (m, default {d.clearance_margin_m:g})")
    p.add_argument("--takeoff-height", type=float, default=d.takeoff_height_m, metavar="M",
                   help="climb at least to this height before the mission (m, default 0.5)")
    p.add_argument("--hover-time", type=float, default=d.hover_s, metavar="S",
                   help="hover at the end point this long before handing back to the FC (s, default 2)")
    p.add_argument("--lockstep", action="store_true",
                   help="take time from the FC's TIMESYNC ticks and answer each one (simulated time)")
    p.add_argument("--lockstep-spin-us", type=float, default=d.lockstep_spin_s * 1e6, metavar="US",
                   help="with --lockstep: poll this long for the next tick before sleeping (us, default "
                        f"{d.lockstep_spin_s * 1e6:g}; 0: sleep at once)")
    p.add_argument("--max-duration", type=float, default=None, metavar="S",
                   help="give up after S seconds of wall time (real-time mode)")
    p.add_argument("--log-json", default=None, metavar="PATH", help="also write the JSON event lines to PATH")
    p.add_argument("--quiet", action="store_true", help="do not print events on stdout")


def config_from_args(args: argparse.Namespace) -> ProgramConfig:
    """A ProgramConfig from parsed options; ValueError with the reason when one is out of range."""
    v = load_vehicle(args.vehicle)
    lead_s = v.control_lead_s if args.control_lead_ms is None else args.control_lead_ms / 1e3
    traverse_lead_m = v.traverse_lead_m if args.traverse_lead is None else args.traverse_lead
    return ProgramConfig(
        pilot=args.pilot, fc_protocol=args.fc_protocol.replace("-", "_"), rate_hz=args.rate_hz,
        approach_speed_m_s=args.approach_speed,
        approach_duration_s=args.approach_duration, traverse_lead_m=traverse_lead_m,
        stale_mocap_s=args.stale_mocap_ms / 1e3,
        mass_kg=v.mass_kg if args.mass is None else args.mass,
        full_thrust_n=v.full_thrust_n if args.full_thrust is None else args.full_thrust,
        max_tilt_deg=v.max_tilt_deg if args.max_tilt is None else args.max_tilt, control_lead_s=lead_s,
        gap_width_m=args.gap_size[0], gap_height_m=args.gap_size[1], lab_min_m=args.lab_min,
        lab_max_m=args.lab_max, takeoff_height_m=args.takeoff_height, hover_s=args.hover_time,
        body_box_m=v.body_box_m if args.body_box is None else tuple(args.body_box),
        max_body_rate_rad_s=v.max_body_rate_rad_s,
        clearance_margin_m=args.clearance_margin,
        estimator=EstimatorConfig(latency_s=args.mocap_latency_ms / 1e3),
        lockstep_spin_s=args.lockstep_spin_us * 1e-6,
    )


def run(args: argparse.Namespace, prog_name: str = "onboard") -> int:
    """Open the links, run the program (its last event line is the "summary" of its counters); returns
    the exit code (0 done, 1 error, 2 bad options, 3 aborted to a safe hover, 143 ended by SIGTERM)."""
    try:
        config = config_from_args(args)
        PILOTS.check(config.pilot)
    except ValueError as exc:
        print(f"{prog_name}: {exc}", file=sys.stderr)
        return 2
    # the compiled kernels loaded (or compiled, on a cold cache: many seconds) before the links open, so
    # that no mocap stream piles up unread on a port meanwhile
    warm_kernels()
    try:
        command = open_link(args.command_link, "onboard")
    except (ValueError, OSError) as exc:
        print(f"{prog_name}: command link: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError) else EXIT_ERROR
    try:
        mocap = open_link(args.mocap_link, "onboard")
    except (ValueError, OSError) as exc:
        command.close()
        print(f"{prog_name}: mocap link: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError) else EXIT_ERROR
    events = EventLog(None if args.quiet else sys.stdout, args.log_json)
    program = OnboardProgram(command, mocap, config, events=events)
    program.link.lockstep = bool(args.lockstep)  # a tick's frames go out with its answer, in one write
    previous = _on_sigterm(_terminate)  # a harness ending the run gets the closing summary too
    try:
        code = program.run_lockstep() if args.lockstep else program.run_realtime(args.max_duration)
    except KeyboardInterrupt:
        code = 130
    except _Terminated:
        code = EXIT_TERMINATED
    except LinkError as exc:
        print(f"{prog_name}: link lost: {exc}", file=sys.stderr)
        code = EXIT_ERROR
    finally:
        _on_sigterm(signal.SIG_DFL)  # a second SIGTERM while closing ends the process at once
        program.close()  # logs the summary event
        _on_sigterm(previous)
    return code


EXIT_TERMINATED = 128 + signal.SIGTERM  # the shell's code for a process ended by SIGTERM


class _Terminated(Exception):
    """SIGTERM arrived: the program stops, closes its links and logs its summary."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise _Terminated


def _on_sigterm(handler: object) -> object:
    """Install ``handler`` for SIGTERM; returns the one it replaces (None outside the main thread, where
    Python cannot install handlers: SIGTERM then keeps its effect)."""
    with contextlib.suppress(ValueError, TypeError):
        return signal.signal(signal.SIGTERM, handler)  # type: ignore[arg-type]
    return None


#: a command line with an option of each arity the parser has (0, 1, 2 and 3 values): argparse compiles a
#: regular expression per arity on its first parse (kept in `re`'s cache), which `parser` makes then
_ARITIES = ["--command-link", "memory", "--mocap-link", "memory", "--gap-size", "1", "1",
            "--body-box", "1", "1", "1", "--lockstep"]


def parser() -> argparse.ArgumentParser:
    """``python -m policies.onboard``'s parser, built once a process with what its first parse compiles
    (a program forked warm finds both made: about 2 ms of each run's start) and again when a command-link
    protocol has been registered since (its name a new ``--fc-protocol`` choice); parsing leaves it as it
    was."""
    return _parser(tuple(COMMAND_LINKS))


@functools.cache
def _parser(protocols: tuple[str, ...]) -> argparse.ArgumentParser:
    """`parser` for the command-link protocols ``protocols`` (the registered ones)."""
    p = argparse.ArgumentParser(prog="python -m policies.onboard",
                                description="the onboard program: fly a pilot through the gap")
    add_arguments(p)
    p.parse_args(_ARITIES)
    return p


def main(argv: list[str] | None = None) -> int:
    return run(parser().parse_args(argv), "policies.onboard")


def main_and_leave(argv: list[str] | None = None) -> NoReturn:
    """`python -m policies.onboard`: `main`, then leave the process at once with its exit code, without
    the interpreter's teardown of the numerical libraries (~50-100 ms), which a harness in lockstep would
    otherwise wait out tick by tick (the program has closed its links and its event log by then)."""
    code = main(argv)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
