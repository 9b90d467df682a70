"""`hil fc`: the N3-style flight-controller emulator standalone, in real time, behind a MAVLink link or,
with ``--protocol dji-open``, DJI's OPEN protocol (docs/dji-open-link.md)."""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
from pathlib import Path
from types import FrameType

from emulator.fc.tuning import fc_gains
from emulator.loops.realtime_runner import RealtimeRunner
from emulator.mocap import MocapConfig
from emulator.params import describe, param_def, read_param_file
from emulator.physics import backend_names
from emulator.profile import ProfileError, load_profile
from emulator.servers.registry import FC_SERVERS, server_config
from emulator.standalone import GAPS, SetupError, StandaloneConfig, StandaloneFc
from emulator.uwb import UwbConfig
from hil.commands import port_number, say_if_compiling
from hil.link.mavlink import parse_signing_key


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fc", help="run the N3-style FC emulator in real time behind a MAVLink link")
    p.add_argument("--profile", default="n3_tx2", help="vehicle profile name or YAML path (default n3_tx2)")
    p.add_argument("--physics", default="native", choices=backend_names(), help="physics backend")
    p.add_argument("--gap", default="paper", choices=[*GAPS, "none"], help="gap to watch for crossings")
    p.add_argument(
        "--link",
        "--command-link",
        dest="link",
        default="pty",
        metavar="SPEC",
        help="MAVLink command link: pty (default), serial:DEVICE:BAUD, udp:HOST:PORT, tcp:HOST:PORT",
    )
    p.add_argument(
        "--mocap-link",
        default="pty",
        metavar="SPEC",
        help="mocap-over-UWB link: pty (default), serial:DEVICE:BAUD, udp:HOST:PORT, none",
    )
    p.add_argument("--mocap-rate", type=float, default=120.0, metavar="HZ", help="mocap frame rate (100-360)")
    p.add_argument("--uwb-latency-ms", type=float, default=20.0, metavar="MS", help="UWB latency (20)")
    p.add_argument("--uwb-jitter-ms", type=float, default=5.0, metavar="MS", help="UWB latency jitter (5)")
    p.add_argument("--uwb-loss", type=float, default=0.0, metavar="P", help="UWB independent loss 0..1 (0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the mocap noise and the radio (default 0)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--tlog", default=None, metavar="PATH",
                   help="record every frame of the command link, both ways and timestamped, to PATH "
                        "(a .tlog; `hil decode PATH` prints it)")
    p.add_argument(
        "--failsafe-timeout", type=float, default=None, metavar="S",
        help="setpoint loss before failsafe (parameter COM_OF_LOSS_T; default 1.0)",
    )
    p.add_argument(
        "--params", default=None, metavar="FILE",
        help="FC parameters to load (NAME VALUE lines, MAVProxy's or QGroundControl's files); "
        "MAV_CMD_PREFLIGHT_STORAGE writes the values in force back to it",
    )
    p.add_argument("--protocol", default="mavlink", choices=[n.replace("_", "-") for n in FC_SERVERS],
                   help="what the command link speaks: MAVLink 2 (default) or DJI's OPEN protocol (as an N3)")
    p.add_argument("--activation-code", type=int, default=0, metavar="CODE",
                   help="dji-open: answer every activation with this documented code (0 accepts, default; "
                        "1-8 refuse)")
    p.add_argument("--rc-mode", default="F", choices=("P", "A", "F"),
                   help="dji-open: the RC's mode switch; only F lets the onboard device obtain control")
    p.add_argument("--link-budget-bytes-s", type=float, default=None, metavar="B_S",
                   help="the telemetry's data-rate budget on the command link (bytes/s; 0: half a serial "
                   "line, none on other links; default 0): MAVLink's MAV_0_RATE, the OPEN protocol's pushes")
    p.add_argument("--signing-key", default=None, metavar="HEX", help="MAVLink 2 signing key (64 hex digits)")
    p.add_argument(
        "--esc-bus", default=None, metavar="SPEC",
        help="the motors behind DroneCAN ESCs on a CAN bus: sim (the model alone), virtual:CHANNEL, "
        "socketcan:IFACE, and the cross-process buses mcast[:N] (dronecan's multicast) and "
        "udp_multicast[:GROUP] (python-can's), which stay on this machine (loopback interface); add @ADDR, "
        "an interface's IPv4 address, to put them on a lab network (mcast:0@192.168.1.20); default: off",
    )
    p.add_argument("--external-esc", type=int, action="append", default=[], metavar="NODE_ID",
                   help="an ESC node served by another node on the bus (20-23: ESC 0-3); repeatable")
    p.add_argument("--list-params", action="store_true", help="print the FC's parameter table and exit")
    p.add_argument("--system-id", type=int, default=1, help="MAVLink system id (default 1)")
    p.add_argument("--view", action="store_true",
                   help="serve a live view on 127.0.0.1 (its URL in the endpoints line, as \"view\")")
    p.add_argument("--view-port", type=port_number, default=0, metavar="PORT",
                   help="the view's port (default: free)")
    p.set_defaults(func=main)


def _serial_stats(link: object) -> dict[str, int] | None:
    """A serial link's unplugs and replugs (None for other links)."""
    link = getattr(link, "inner", link)  # (under its UART pacing)
    if not hasattr(link, "disconnects"):
        return None
    return {"disconnects": link.disconnects, "reconnects": link.reconnects}  # type: ignore[attr-defined]


def main(args: argparse.Namespace) -> int:
    def fail(msg: str) -> int:
        print(f"hil fc: {msg}", file=sys.stderr)
        return 2

    if args.list_params:
        print("\n".join(describe()))
        return 0
    try:
        profile = load_profile(args.profile)
        fc_gains(profile)  # a vehicle the FC cannot stabilise is refused with the reason
        params: dict[str, float | int] = {}
        if args.params is not None and Path(args.params).exists():
            params = read_param_file(args.params)
        elif args.params is not None:  # a file to write later: said, so that a mistyped name is noticed
            if not Path(args.params).resolve().parent.is_dir():
                return fail(f"--params {args.params}: no such file, nor a folder to write it in")
            print(f"hil fc: --params {args.params} does not exist yet: the defaults, written there on "
                  "MAV_CMD_PREFLIGHT_STORAGE", file=sys.stderr)
        if args.failsafe_timeout is not None:  # the flag wins over the file
            params["COM_OF_LOSS_T"] = param_def("COM_OF_LOSS_T").check(args.failsafe_timeout)
        key = parse_signing_key(args.signing_key) if args.signing_key else None
        protocol = args.protocol.replace("-", "_")
        settings = {"activation_code": args.activation_code, "rc_mode": args.rc_mode}
        server_config(protocol, **settings)  # (its settings checked before any link is opened)
    except (ProfileError, ValueError, OSError) as exc:
        return fail(str(exc))
    if args.external_esc and args.esc_bus is None:
        return fail("--external-esc needs --esc-bus")
    if args.esc_bus is not None and protocol != "mavlink":
        return fail("--esc-bus: the FC reports its ESCs over MAVLink; use --protocol mavlink")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        return fail(f"--duration must be a positive number of seconds, got {args.duration}")
    if not 1 <= args.system_id <= 255:
        return fail(f"--system-id must be 1..255, got {args.system_id}")
    try:
        config = StandaloneConfig(
            profile, command_link=args.link,
            mocap_link=None if args.mocap_link == "none" else args.mocap_link, backend=args.physics,
            gap=None if args.gap == "none" else args.gap, protocol=protocol, protocol_settings=settings,
            params=params, param_file=args.params, link_budget_bytes_s=args.link_budget_bytes_s,
            signing_key=key, system_id=args.system_id, seed=args.seed, duration_s=args.duration,
            tlog_path=args.tlog, mocap=MocapConfig(rate_hz=args.mocap_rate),
            uwb=UwbConfig(latency_s=args.uwb_latency_ms / 1000.0, jitter_s=args.uwb_jitter_ms / 1000.0,
                          loss_prob=args.uwb_loss),
            esc_bus=args.esc_bus, external_esc=tuple(args.external_esc),
        )
    except ValueError as exc:
        return fail(str(exc))
    say_if_compiling("hil fc")
    try:
        fc = StandaloneFc(config)
    except SetupError as exc:
        flag = {"mocap_link": "--mocap-link: ", "esc_bus": "--esc-bus: "}.get(exc.part, "")
        return fail(f"{flag}{exc}")
    view = None
    try:
        emu = fc.emulator
        emu.server.on_untold = _say
        _stop_on_signals(fc.runner)
        endpoints = fc.endpoints()
        if args.view:
            from hil.view import LiveSource, ViewServer  # (the view server's imports only with --view)

            try:
                view = ViewServer(port=args.view_port)
            except OSError as exc:
                return fail(f"--view: cannot serve on 127.0.0.1:{args.view_port}: {exc}")
            uwb = {"latency_ms": args.uwb_latency_ms, "loss": args.uwb_loss}
            view.live(LiveSource(emu.vehicle, emu.server, emu.mocap, emu.world,
                                 title=f"hil fc ({profile.name})", lock=fc.runner.lock,
                                 links={"mocap": uwb} if emu.mocap is not None else {}))
            endpoints["view"] = view.url
        print(json.dumps(endpoints), flush=True)
        fc.run()
        print(json.dumps(fc.summary()), flush=True)
        return 0
    finally:
        if view is not None:
            view.finish(None)
            view.close()
        fc.close()


def _say(text: str) -> None:
    print(f"hil fc: {text}", file=sys.stderr, flush=True)


def _stop_on_signals(runner: RealtimeRunner) -> None:
    def handler(signum: int, frame: FrameType | None) -> None:
        runner.stop(timeout_s=0)

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
