"""`hil fc`: the N3-style flight-controller emulator standalone, in real time, behind a MAVLink link or,
with ``--protocol dji-open``, DJI's OPEN protocol (docs/dji-open-link.md)."""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np

from emulator.assembly import assemble, warm_up
from emulator.esc.bus import Bridge, EscBusConfig, EscBusStepper, attach, parse_bus_spec
from emulator.fc import FcConfig
from emulator.fc.tuning import fc_gains
from emulator.loops.realtime_runner import RealtimeRunner
from emulator.mocap import MocapConfig
from emulator.params import describe, param_def, read_param_file
from emulator.physics import backend_names
from emulator.profile import ProfileError, load_profile
from emulator.servers.dji_open_server import DjiOpenServer, DjiServerConfig
from emulator.servers.mavlink_server import ServerConfig
from emulator.servers.registry import FC_SERVERS
from emulator.standalone import GAPS, loop_links
from emulator.uwb import UwbConfig
from emulator.vehicle import resting_state
from hil.commands import port_number, say_if_compiling
from hil.link.clock import WallClock
from hil.link.endpoint import open_link, parse_endpoint
from hil.link.mavlink import parse_signing_key
from hil.link.tlog import TlogWriter
from hil.runner.realtime import WireWatch


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
        config = FcConfig()
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
        budget_bytes_s = 0.0 if args.link_budget_bytes_s is None else args.link_budget_bytes_s
        if args.link_budget_bytes_s is not None and args.protocol == "mavlink":  # (the flag wins too)
            params["MAV_0_RATE"] = param_def("MAV_0_RATE").check(budget_bytes_s)
        key = parse_signing_key(args.signing_key) if args.signing_key else None
        protocol = args.protocol.replace("-", "_")
        if key is not None and protocol != "mavlink":
            raise ValueError("--signing-key signs MAVLink: the OPEN protocol has no signing")
        dji_config = DjiServerConfig(activation_code=args.activation_code, rc_mode=args.rc_mode,
                                     budget_bytes_s=budget_bytes_s)
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
        mocap_cfg = MocapConfig(rate_hz=args.mocap_rate)
        uwb_cfg = UwbConfig(
            latency_s=args.uwb_latency_ms / 1000.0,
            jitter_s=args.uwb_jitter_ms / 1000.0,
            loss_prob=args.uwb_loss,
        )
    except ValueError as exc:
        return fail(str(exc))
    try:
        spec = parse_endpoint(args.link)
        # a serial line carries baud / 10 bytes a second: the FC writes at that pace, within its budget
        link_baud = spec.baud if spec.kind == "serial" else None
        link = open_link(spec, "fc", uart_baud=link_baud)
    except (ValueError, OSError) as exc:
        return fail(str(exc))
    mocap_link = None
    if args.mocap_link != "none":
        try:
            mocap_link = open_link(args.mocap_link, "fc")
        except (ValueError, OSError) as exc:
            link.close()
            return fail(f"--mocap-link: {exc}")
    esc_stepper: EscBusStepper | None = None
    tlog = None
    view = None
    if args.tlog:
        try:
            tlog = TlogWriter(args.tlog)
        except OSError as exc:
            link.close()
            return fail(str(exc))
    try:
        gap, start_xy = GAPS.get(args.gap, (None, (0.0, 0.0)))
        start = resting_state(profile, *start_xy, yaw_rad=0.0)  # facing world +x, the paper's reference yaw
        say_if_compiling("hil fc")
        warm_up(profile)  # before the clock starts
        if args.esc_bus is not None:
            import dronecan  # noqa: F401 (its message types load here, not on the clock)
        clock, epoch_unix_s = WallClock(), time.time()  # clock zero in Unix time, for tlog and signing
        if tlog is not None:
            tlog.epoch_unix_s = epoch_unix_s
        emu = assemble(
            profile, link, clock, initial_state=start, backend=args.physics, fc_config=config, gap=gap,
            mocap_link=mocap_link, mocap_rng=np.random.default_rng(args.seed), mocap_config=mocap_cfg,
            uwb_config=uwb_cfg, system_id=args.system_id, tlog=tlog, signing_key=key,
            signing_epoch_unix_s=epoch_unix_s,
            server_config=ServerConfig(param_file=args.params, link_baud=link_baud),
            protocol=protocol, dji_config=replace(dji_config, link_baud=link_baud),
        )
        try:
            emu.server.params.set_many(params)
        except ValueError as exc:
            return fail(str(exc))
        if args.esc_bus is not None:
            try:
                esc_stepper = _esc_bus(args, emu)
            except (ValueError, OSError) as exc:
                return fail(f"--esc-bus: {exc}")
        vehicle, codec, server, mocap = emu.vehicle, emu.codec, emu.server, emu.mocap
        if isinstance(server, DjiOpenServer):  # (MAVLink says it in a STATUSTEXT)
            server.on_capped = _say_capped
        links = loop_links(emu, gap)
        endpoints = {"command_link": link.endpoint, "protocol": protocol}
        if mocap is not None and mocap_link is not None:
            endpoints["mocap_link"] = mocap_link.endpoint
        fds = [link.fileno()] if _has_fileno(link) else []
        wire = WireWatch(server, mocap)
        links.append(wire)
        runner = RealtimeRunner(vehicle, links, clock=clock, duration_s=args.duration, wait_fds=fds)
        _stop_on_signals(runner)
        if args.view:
            from hil.view import LiveSource, ViewServer  # (the view server's imports only with --view)

            try:
                view = ViewServer(port=args.view_port)
            except OSError as exc:
                return fail(f"--view: cannot serve on 127.0.0.1:{args.view_port}: {exc}")
            uwb = {"latency_ms": args.uwb_latency_ms, "loss": args.uwb_loss}
            view.live(LiveSource(vehicle, server, mocap, emu.world, title=f"hil fc ({profile.name})",
                                 lock=runner.lock, links={"mocap": uwb} if mocap is not None else {}))
            endpoints["view"] = view.url
        print(json.dumps(endpoints), flush=True)
        runner.run()
        count_drops = getattr(link, "count_drops", None)  # (UDP: the kernel's drops until now)
        if count_drops is not None:
            count_drops()
        summary = {
            "sim_time_s": round(vehicle.time_s, 3),
            "state": vehicle.fc.state.value,
            "events": [
                {"time_s": round(e.time_s, 4), "to": e.to_state.value, "reason": e.reason}
                for e in vehicle.fc.events
            ],
            "link": codec.stats.as_dict(),
            "transport": asdict(link.stats),
            "server": server.stats.as_dict(),
            "realtime": {"loop": runner.pacing.as_dict(), **wire.as_dict(), "serial": _serial_stats(link)},
        }
        budget = getattr(server, "budget", None)
        if budget is not None:
            summary["link_budget"] = budget.summary(link, clock.now_s())
        if esc_stepper is not None:
            summary["esc_bus"] = esc_stepper.summary(clock.now_s())
        if mocap is not None:
            st = mocap.stats
            summary["mocap"] = {
                "frames_written": st.frames_written,
                "radio_sent": st.radio.sent,
                "radio_delivered": st.radio.delivered,
                "radio_lost": st.radio.lost,
            }
        print(json.dumps(summary), flush=True)
        return 0
    finally:
        if esc_stepper is not None:
            esc_stepper.esc.close()
        if view is not None:
            view.finish(None)
            view.close()
        if tlog is not None:
            tlog.close()
        link.close()
        if mocap_link is not None:
            mocap_link.close()


def _say_capped(text: str) -> None:
    print(f"hil fc: link budget: {text} (the OPEN ACK says success: it has no room for a reason)",
          file=sys.stderr, flush=True)


def _esc_bus(args: argparse.Namespace, emu: Any) -> EscBusStepper:
    """The ESC bus ``--esc-bus`` names, with the FC's ESC parameters; ValueError or OSError say why not."""
    spec = parse_bus_spec(args.esc_bus)
    if spec == "sim" and args.external_esc:
        raise ValueError("--external-esc needs a bus other processes reach (mcast, udp_multicast, socketcan)")
    config = EscBusConfig(external=tuple(args.external_esc), **emu.server.params.esc_settings())
    bridge = None if spec == "sim" else Bridge(spec, config.bitrate_bps)
    return attach(emu.vehicle, emu.server, config, np.random.default_rng(args.seed), bridge)


def _has_fileno(link: object) -> bool:
    try:
        link.fileno()  # type: ignore[attr-defined]
    except (NotImplementedError, ValueError, OSError):
        return False
    return True


def _stop_on_signals(runner: RealtimeRunner) -> None:
    def handler(signum: int, frame: FrameType | None) -> None:
        runner.stop(timeout_s=0)

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
