"""A command-link protocol is one unit: a toy protocol (its codec, its FC server, its onboard link), added
through the three tables from this file alone, flies a shipped scenario in lockstep, in one process and
over ptys (the program's own process registering it on start); its frames are in the run's capture and
`hil decode` reads them; the tables refuse a taken name and name the known ones."""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import pytest

from emulator.fc.modes import FcState
from emulator.fc.n3 import SetpointRejected
from emulator.params import Parameters
from emulator.profile import load_profile
from emulator.servers.registry import FC_SERVERS, ServerOptions, make_server, register_server, server_config
from emulator.vehicle import EmulatedVehicle
from hil.link import dji_open
from hil.link.clock import Clock, SimClock
from hil.link.lockstep import MOCAP_COUNT_MASK, NS_PER_S, Framing, tick_answer_ns
from hil.link.mavlink import euler_from_quat, mav, quat_enu_flu_to_ned_frd_tuple, quat_from_euler_tuple
from hil.link.memory import MemoryTransport
from hil.link.protocols import (
    PROTOCOLS,
    LinkProtocol,
    decode,
    framing,
    register_protocol,
    unregister_protocol,
)
from hil.link.tlog import read_tlog
from hil.link.transport import Transport
from hil.runner import RunOptions, run_scenario
from hil.runner.onboard_side import program_config
from hil.scenario import load_scenarios, loads_scenarios
from policies.onboard.cli import parser
from policies.onboard.command_link import CommandAck, CommandLink
from policies.onboard.command_links import COMMAND_LINKS, register_command_link
from policies.onboard.program import ProgramConfig

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"

# --- the toy protocol's codec: 0x7E, kind, length, payload, sum of kind..payload mod 256 ------------------
SOF = 0x7E
TICK, ANSWER, STATUS, SETPOINT, COMMAND, ACK = b"TASPCK"
MAX_FRAME_BYTES = 3 + 255 + 1
_TICK, _ANSWER, _SETPOINT = struct.Struct("<qI"), struct.Struct("<q"), struct.Struct("<ffff")
#: the toy's commands, and the MAVLink command whose answer each stands for (the program's vocabulary)
OFFBOARD, HOLD, ARM = b"OHR"
ACK_KEYS = {OFFBOARD: mav.MAV_CMD_DO_SET_MODE, HOLD: mav.MAV_CMD_DO_SET_MODE,
            ARM: mav.MAV_CMD_COMPONENT_ARM_DISARM}


def encode(kind: int, payload: bytes = b"") -> bytes:
    body = bytes((kind, len(payload))) + payload
    return bytes((SOF,)) + body + bytes((sum(body) & 0xFF,))


def frame_at(data: bytes, j: int) -> bytes | None:
    if data[j] != SOF or j + 3 > len(data):
        return None
    frame = data[j : j + 4 + data[j + 2]]
    return frame if len(frame) == 4 + frame[2] and sum(frame[1:-1]) & 0xFF == frame[-1] else None


class Splitter:
    """Good frames out of a byte stream; bytes that start none are skipped."""

    def __init__(self) -> None:
        self.buf = b""
        self.skipped = 0

    def feed(self, data: bytes) -> list[bytes]:
        buf, out, i = self.buf + data, [], 0
        while i < len(buf):
            if buf[i] != SOF:
                i, self.skipped = i + 1, self.skipped + 1
                continue
            if i + 3 > len(buf) or i + 4 + buf[i + 2] > len(buf):
                break  # a frame not complete yet
            frame = frame_at(buf, i)
            if frame is None:
                i, self.skipped = i + 1, self.skipped + 1
                continue
            out.append(frame)
            i += len(frame)
        self.buf = buf[i:]
        return out


@dataclass
class ToyStats:
    frames_received: int = 0
    frames_sent: int = 0
    bytes_skipped: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class ToyCodec:
    def __init__(self, transport: Transport, clock: Clock, recorder: object = None) -> None:
        self.transport, self.clock, self.recorder = transport, clock, recorder
        self.stats = ToyStats()
        self._splitter = Splitter()

    def pack(self, kind: int, payload: bytes = b"") -> bytes:
        self.stats.frames_sent += 1
        return encode(kind, payload)

    def send(self, kind: int, payload: bytes = b"") -> None:
        frame = self.pack(kind, payload)
        if self.recorder is not None:
            self.recorder.record(frame, self.clock.now_s())
        self.transport.send(frame)

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        frames = self._splitter.feed(data)
        self.stats.frames_received += len(frames)
        self.stats.bytes_skipped = self._splitter.skipped
        if self.recorder is not None:
            for f in frames:
                self.recorder.record(f, self.clock.now_s())
        return [(f[1], f[3:-1]) for f in frames]


def toy_framing(system_id: int, component_id: int) -> Framing:
    def answered_ns(frame: bytes) -> int | None:
        if len(frame) != 4 + _ANSWER.size or frame[1] != ANSWER:
            return None
        (ns,) = _ANSWER.unpack_from(frame, 3)
        return tick_answer_ns(ns, ns)

    return Framing(
        lambda t, n: encode(TICK, _TICK.pack(round(t * NS_PER_S), n & MOCAP_COUNT_MASK)), answered_ns,
        bytes(MAX_FRAME_BYTES), Splitter, lambda frame: len(frame) > 1 and frame[1] == SETPOINT,
    )


def describe(frame: bytes) -> tuple[str, str, str, dict]:
    kind = chr(frame[1])
    sender = "fc" if frame[1] in (STATUS, ACK, TICK) else "peer"
    return f"TOY_{kind}", sender, f"toy {kind} {frame[3:-1].hex()}", {"payload": frame[3:-1].hex()}


# --- its FC server -------------------------------------------------------------------------------------
@dataclass
class ToyServerStats:
    setpoints_applied: int = 0
    setpoints_rejected: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class ToyServer:
    """The FC over the toy protocol: setpoints (NED degrees, thrust %), three commands, a 50 Hz status."""

    STATUS_PERIOD_S = 0.02

    def __init__(self, vehicle: EmulatedVehicle, codec: ToyCodec) -> None:
        self.vehicle, self.fc, self.codec = vehicle, vehicle.fc, codec
        self.params = Parameters(self.fc, streams=None)
        self.stats = ToyServerStats()
        self.texts: list[str] = []
        self._next_status_s = 0.0

    @property
    def state(self) -> FcState:
        return self.fc.state

    def poll(self, now_s: float) -> None:
        data = self.codec.transport.recv(0.0, 65536)
        for kind, payload in self.codec.feed(data) if data else []:
            self._handle(kind, payload, now_s)
        if now_s >= self._next_status_s:
            self._next_status_s = now_s + self.STATUS_PERIOD_S
            fc = self.fc
            offboard = fc.state is FcState.OFFBOARD or (fc.state is FcState.DISARMED and fc.offboard_selected)
            self.codec.send(STATUS, bytes((fc.state.armed, offboard, fc.state is FcState.HOLD)))

    def _handle(self, kind: int, payload: bytes, now_s: float) -> None:
        fc = self.fc
        if kind == SETPOINT and len(payload) == _SETPOINT.size:
            try:
                fc.set_setpoint_values(dji_open.ATTITUDE_THRUST_YAW_ANGLE, *_SETPOINT.unpack(payload), now_s)
            except SetpointRejected:
                self.stats.setpoints_rejected += 1
                return
            self.stats.setpoints_applied += 1
        elif kind == COMMAND and len(payload) == 1 and payload[0] in ACK_KEYS:
            act = {OFFBOARD: fc.request_offboard, HOLD: fc.request_hold, ARM: fc.arm}[payload[0]]
            self.codec.send(ACK, bytes((payload[0], act(now_s).accepted)))

    def statustext(self, severity: int, text: str, now_s: float, key: str | None = None) -> bool:
        self.texts.append(text)
        return True


def toy_server(vehicle: EmulatedVehicle, link: Transport, clock: Clock, o: ServerOptions) -> ToyServer:
    return ToyServer(vehicle, ToyCodec(link, clock, o.tlog))


# --- its onboard link ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ToyStatus:
    armed: bool
    offboard: bool
    holding: bool


class ToyLink(CommandLink):
    """The program's client of the FC over the toy protocol (`CommandLink` gives the lockstep's holding)."""

    protocol = "toy"

    def __init__(self, transport: Transport, clock: Clock) -> None:
        super().__init__(transport, clock, codec=ToyCodec(transport, clock))
        self._heard_s: float | None = None

    def _handle(self, item: tuple[int, bytes]) -> None:  # type: ignore[override]
        kind, payload = item
        now = self.clock.now_s()
        if kind == TICK and len(payload) == _TICK.size:
            ns, total = _TICK.unpack(payload)
            self._on_tick(None, total)
            self._on_tick(ns * 1e-9, None)
        elif kind == STATUS and len(payload) == 3:
            self.status = ToyStatus(*map(bool, payload))  # type: ignore[assignment]
            self._heard_s = now
        elif kind == ACK and len(payload) == 2 and payload[0] in ACK_KEYS:
            key = ACK_KEYS[payload[0]]
            result = mav.MAV_RESULT_ACCEPTED if payload[1] else mav.MAV_RESULT_DENIED
            self.acks[key] = CommandAck(key, result, now)

    def heartbeat_age_s(self, now_s: float) -> float:
        return math.inf if self._heard_s is None else now_s - self._heard_s

    def send_heartbeat(self) -> None:
        """The toy has no heartbeat of the onboard side."""

    def request_heartbeat(self) -> None:
        """The toy FC sends its status unasked."""

    def _command(self, command: int) -> None:
        self.acks.pop(ACK_KEYS[command], None)
        self._send_frame(self.codec.pack(COMMAND, bytes((command,))))

    def request_offboard(self) -> None:
        self._command(OFFBOARD)

    def request_hold(self) -> None:
        self._command(HOLD)

    def request_arm(self) -> None:
        self._command(ARM)

    def send_attitude_target(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                             thrust_fraction: float) -> None:
        if not math.isfinite(roll_rad + pitch_rad + yaw_rad + thrust_fraction):
            raise ValueError("setpoint not finite")
        q = quat_enu_flu_to_ned_frd_tuple(*quat_from_euler_tuple(roll_rad, pitch_rad, yaw_rad))
        roll, pitch, yaw = (math.degrees(a) for a in euler_from_quat(q))
        thrust = 100.0 * min(1.0, max(0.0, thrust_fraction))
        self._send_frame(self.codec.pack(SETPOINT, _SETPOINT.pack(roll, pitch, thrust, yaw)))
        self.setpoints_sent += 1

    def _answer_frame(self, tick_s: float) -> bytes:
        return self.codec.pack(ANSWER, _ANSWER.pack(round(tick_s * NS_PER_S)))


# --- the test ------------------------------------------------------------------------------------------
def register_toy() -> None:
    """The toy protocol into the three tables (as a plugin module's import would)."""
    register_protocol(LinkProtocol("toy", ToyCodec, toy_framing, MAX_FRAME_BYTES, frozenset({SOF}), frame_at,
                                   describe))
    register_server("toy", toy_server)
    register_command_link("toy", ToyLink)


@pytest.fixture
def toy() -> Iterator[str]:
    """The toy protocol in the three tables for one test, and out of them after."""
    register_toy()
    try:
        yield "toy"
    finally:
        unregister_protocol("toy")
        FC_SERVERS.pop("toy")
        COMMAND_LINKS.pop("toy")


def test_a_toy_protocol_registered_from_a_test_flies_a_scenario_in_lockstep(toy, tmp_path):
    s = load_scenarios(SCENARIOS / "gap_roll30_2ms.scenario.yaml")[0]
    result = run_scenario(s, tmp_path, RunOptions(in_process=True, protocol=toy))
    assert result.passed, [f"{c.name}: {c.observed}" for c in result.failed_checks]
    assert result.summary["lockstep"]["held"] is True
    frames = [f for _, f in read_tlog(result.tlog_path)]
    assert frames and all(f[0] == SOF for f in frames)
    kinds = {decode(f).type for f in frames}
    assert {"TOY_P", "TOY_C", "TOY_K", "TOY_S"} <= kinds  # setpoints, commands, their acks, the status
    assert "TOY_T" not in kinds and "TOY_A" not in kinds  # the lockstep's ticks are not the FC's traffic


def test_a_toy_protocol_flies_over_ptys_with_the_program_in_its_own_process(toy, tmp_path, monkeypatch):
    # the program's new interpreter registers the toy on start (sitecustomize), as a plugin module would
    (tmp_path / "plugin").mkdir()
    (tmp_path / "plugin" / "sitecustomize.py").write_text(
        "import test_protocol_registry\ntest_protocol_registry.register_toy()\n")
    paths = [str(tmp_path / "plugin"), str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in paths if p))
    s = load_scenarios(SCENARIOS / "gap_roll30_2ms.scenario.yaml")[0]
    result = run_scenario(s, tmp_path / "run", RunOptions(in_process=False, cold_start=True, protocol=toy))
    assert result.passed, [f"{c.name}: {c.observed}" for c in result.failed_checks]
    assert result.summary["onboard"]["toy"]["frames_sent"] > 0  # the program's own counters, over the pty
    assert {decode(f).type for _, f in read_tlog(result.tlog_path)} >= {"TOY_P", "TOY_C", "TOY_K", "TOY_S"}


def test_the_scenario_schema_and_the_program_take_a_registered_protocol(toy):
    text = (SCENARIOS / "gap_roll30_2ms.scenario.yaml").read_text()
    assert "links:" not in text
    text += "links:\n  command: {protocol: toy}\n"
    assert loads_scenarios(text)[0].links.command.protocol == toy
    assert ProgramConfig(fc_protocol=toy).fc_protocol == toy


def test_a_protocol_registered_after_a_run_was_set_up_is_an_option_of_the_next():
    """The program's options are parsed by a parser made once a process: one made before a protocol's
    registration must not refuse it afterwards (the harness's check of a run's options, and the
    program's own command line)."""
    assert program_config(["--fc-protocol", "mavlink"]).fc_protocol == "mavlink"  # (parsers made now)
    assert parser().parse_args(["--command-link", "memory", "--mocap-link", "memory"]).fc_protocol
    register_toy()
    try:
        assert program_config(["--fc-protocol", "toy"]).fc_protocol == "toy"
        args = parser().parse_args(["--command-link", "memory", "--mocap-link", "memory",
                                    "--fc-protocol", "toy"])
        assert args.fc_protocol == "toy"
    finally:
        unregister_protocol("toy")
        FC_SERVERS.pop("toy")
        COMMAND_LINKS.pop("toy")
    with pytest.raises(ValueError, match="invalid choice: 'toy'"):  # (and gone again with it)
        program_config(["--fc-protocol", "toy"])


def test_the_tables_refuse_a_taken_name_and_name_the_known_ones():
    with pytest.raises(ValueError, match="registered already"):
        register_server("mavlink", toy_server)
    with pytest.raises(ValueError, match="registered already"):
        register_command_link("dji_open", ToyLink)
    with pytest.raises(ValueError, match="shares a start byte"):
        register_protocol(replace(PROTOCOLS["mavlink"], name="other"))
    with pytest.raises(ValueError, match="mavlink, dji_open"):
        framing("toy")
    with pytest.raises(ValueError, match="mavlink, dji_open"):
        make_server("toy", None, None, None, ServerOptions())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="mavlink, dji_open"):
        ProgramConfig(fc_protocol="toy")


def test_each_server_takes_its_own_settings_and_refuses_another_protocols():
    vehicle, (fc_end, _) = EmulatedVehicle(load_profile("n3_tx2")), MemoryTransport.pair()
    asked = {"activation_code": 6, "rc_mode": "P", "param_file": "fc.params", "link_baud": 57600}
    mav_config, dji_config = server_config("mavlink", **asked), server_config("dji_open", **asked)
    assert (mav_config.param_file, mav_config.link_baud) == ("fc.params", 57600)  # type: ignore[attr-defined]
    assert (dji_config.activation_code, dji_config.rc_mode) == (6, "P")  # type: ignore[attr-defined]
    server = make_server("dji_open", vehicle, fc_end, SimClock(), ServerOptions(protocol_config=dji_config))
    assert server.config is dji_config  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="the mavlink server takes a ServerConfig, got a DjiServerConfig"):
        make_server("mavlink", vehicle, fc_end, SimClock(), ServerOptions(protocol_config=dji_config))
    with pytest.raises(ValueError, match="the OPEN protocol has no signing"):
        make_server("dji_open", vehicle, fc_end, SimClock(), ServerOptions(signing_key=bytes(32)))
    with pytest.raises(ValueError, match="RC mode switch must be P, A or F"):
        server_config("dji_open", rc_mode="X")
