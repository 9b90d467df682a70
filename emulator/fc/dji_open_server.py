"""The FC's DJI OPEN-protocol endpoint (Onboard SDK 3.x, as an N3 answers on its API UART), over the same
FC core as the MAVLink server: activation and version query, control authority, arm/disarm, flight
tasks, the flight-control setpoint (the N3 attitude-thrust interface, `emulator.fc.n3`), and the pushed
flight data at the rates the onboard side sets.

`DjiOpenServer.poll(now_s)` parses what arrived, acts on it and sends what is due at ``now_s`` (clock
seconds), as `MavlinkServer.poll` does. Bad input is counted in `stats` (and the codec's) and answered
where the protocol has a way (an ACK code); it never raises out of `poll`. Commands, codes and the
broadcast layout: docs/dji-open-link.md.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field, fields

from emulator.fc.modes import FcState
from emulator.fc.n3 import SetpointRejected
from emulator.fc.params import Parameters
from emulator.fc.telemetry import Home, TelemetryEncoder
from emulator.fc.vehicle import EmulatedVehicle
from hil.link import dji_open as dj
from hil.link.mavlink import quat_enu_flu_to_ned_frd_tuple

#: the SDK version (activation's third word) this FC accepts: OSDK 3.x's 0x03010A00 and later
MIN_SDK_VERSION = 0x03010A00
ACTIVATION_BYTES = 44  # u32 app id, u32 reserved, u32 SDK version, 32-byte bundle id
#: broadcast rates (Hz) by item before the onboard side sets them: Appendix.md's defaults
DEFAULT_RATES_HZ: tuple[float, ...] = (100.0, 100.0, 100.0, 100.0, 100.0, 100.0, 0.0, 50.0, 50.0, 10.0, 1.0,
                                       0.0)
CONTROL_LOST_CODE = 0x04  # the payload of the pushed "control lost" (0x02 0x01)
_SEC_TICKS = 400  # the time item counts 1/400 s
_STATE_FLAGS = 1 << dj.BROADCAST_BIT["status"] | 1 << dj.BROADCAST_BIT["control_device"]
_TASKS = frozenset({dj.TASK_TAKEOFF, dj.TASK_LAND, dj.TASK_GO_HOME, dj.TASK_START_MOTORS,
                    dj.TASK_STOP_MOTORS})


@dataclass(frozen=True)
class DjiServerConfig:
    """Identity and behaviour of the FC's OPEN-protocol endpoint."""

    #: the activation answer: 0 accepts; any other documented code (1-8) refuses every activation
    activation_code: int = dj.ACTIVATE_SUCCESS
    #: the RC's mode switch: "F" lets the onboard device obtain control; "P" or "A" refuse (code 0x0000)
    rc_mode: str = "F"
    home: Home = field(default_factory=Home)
    broadcast_rates_hz: tuple[float, ...] = DEFAULT_RATES_HZ
    #: the highest broadcast rate granted (Hz): the N3's 100 Hz UART push (200, 400 in OSDK 4 are not)
    max_rate_hz: float = 100.0

    def __post_init__(self) -> None:
        if not 0 <= self.activation_code <= 8:
            raise ValueError(f"activation code must be a documented one, 0..8, got {self.activation_code}")
        if self.rc_mode not in ("P", "A", "F"):
            raise ValueError(f"RC mode switch must be P, A or F, got {self.rc_mode!r}")
        if len(self.broadcast_rates_hz) != len(dj.BROADCAST_ITEMS):
            raise ValueError(f"broadcast rates: one per item ({len(dj.BROADCAST_ITEMS)})")


@dataclass
class DjiServerStats:
    """What the server did with what it received (counts)."""

    setpoints_applied: int = 0
    setpoints_rejected: int = 0
    setpoints_without_control: int = 0  # setpoints taken while the onboard device has no authority: not flown
    commands_accepted: int = 0
    commands_denied: int = 0
    commands_unknown: int = 0  # command sets or ids this FC does not answer (ACK 0xFF02)
    commands_unactivated: int = 0  # commands before activation (ACK 0xFF01)
    encrypted_refused: int = 0  # AES frames (ACK 0xFF00: the emulator has no key)
    retries_answered: int = 0  # a reliable command sent again: its ACK again, not acted on twice
    malformed: int = 0  # payloads of the wrong size or value
    broadcasts_sent: int = 0
    handler_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class DjiOpenServer:
    """Serves one vehicle's FC over one OPEN-protocol codec."""

    def __init__(self, vehicle: EmulatedVehicle, codec: dj.OpenCodec, config: DjiServerConfig | None = None
                 ) -> None:
        self.vehicle = vehicle
        self.fc = vehicle.fc
        self.codec = codec
        #: the FC's parameters (`emulator.fc.params`), set from files and scenarios: the OPEN protocol
        #: has no parameter messages, and no MAVLink telemetry whose rates they would set
        self.params = Parameters(self.fc, streams=None)
        self.config = config or DjiServerConfig()
        self.stats = DjiServerStats()
        # the MAVLink side's battery model and flat-Earth position, without its MAVLink packer
        self.telemetry = TelemetryEncoder(vehicle, None, self.config.home)  # type: ignore[arg-type]
        self.activated = False
        self.sdk_control = False  # the onboard device holds control authority
        self._rates_hz = list(self.config.broadcast_rates_hz)
        self._next_due = [0.0] * len(self._rates_hz)
        self._next_push_s = 0.0
        self._urgent = 0  # flag bits pushed at the next push whether due or not
        self._last_ack: dict[int, tuple[int, bytes]] = {}  # session -> (seq, ACK frame) of reliable ones
        self._events_seen = 0
        self._statustexts: list[str] = []
        #: called with (flag, roll, pitch, thrust, yaw, now_s) after a setpoint is applied
        self.on_setpoint: Callable[..., None] | None = None
        self._handlers: dict[tuple[int, int], Callable[[dj.Frame, float], bytes | None]] = {
            (dj.SET_ACTIVATION, dj.CMD_VERSION): self._on_version,
            (dj.SET_ACTIVATION, dj.CMD_ACTIVATE): self._on_activate,
            (dj.SET_ACTIVATION, dj.CMD_BROADCAST_FREQ): self._on_broadcast_freq,
            (dj.SET_CONTROL, dj.CMD_CONTROL_AUTHORITY): self._on_control_authority,
            (dj.SET_CONTROL, dj.CMD_TASK): self._on_task,
            (dj.SET_CONTROL, dj.CMD_ARM): self._on_arm,
        }

    @property
    def state(self) -> FcState:
        return self.fc.state

    # --- the loop ------------------------------------------------------------------------------
    def poll(self, now_s: float) -> None:
        """Parse and act on what arrived, then push what is due at ``now_s``."""
        transport = self.codec.transport
        if _input_due(transport):
            for f in self.codec.receive():
                self.handle(f, now_s)
        if self._events_seen != len(self.fc.events):
            self._on_events(now_s)
        self.telemetry.track_battery(now_s)
        if self.activated and now_s >= self._next_push_s:
            self._push(now_s)

    def handle(self, f: dj.Frame, now_s: float) -> None:
        """Act on one good command frame; never raises."""
        try:
            self._handle(f, now_s)
        except Exception:  # a frame the handlers did not foresee: counted, never fatal
            self.stats.handler_errors += 1

    def _handle(self, f: dj.Frame, now_s: float) -> None:
        if f.is_ack:  # (the codec keeps ACKs apart; the FC waits for none)
            return
        if f.enc != dj.ENC_NONE:
            self.stats.encrypted_refused += 1
            self._ack(f, dj.ack_code(dj.ACK_KEY_ERROR))
            return
        if f.cmd_set == dj.SET_CONTROL and f.cmd_id == dj.CMD_SETPOINT:  # (the per-tick case first)
            self._on_setpoint(f, now_s)
            return
        if f.session in dj.RELIABLE_SESSIONS:
            last = self._last_ack.get(f.session)
            if last is not None and last[0] == f.seq:  # sent again: its ACK was lost
                self.stats.retries_answered += 1
                self.codec.transport.send(last[1])
                return
        handler = self._handlers.get((f.cmd_set, f.cmd_id))
        if handler is None:
            self.stats.commands_unknown += 1
            self._ack(f, dj.ack_code(dj.ACK_NO_RIGHTS))
            return
        if not self.activated and handler not in (self._on_version, self._on_activate):
            self.stats.commands_unactivated += 1
            self._ack(f, dj.ack_code(dj.ACK_NO_AUTHORISATION))
            return
        value = handler(f, now_s)
        if value is not None:
            self._ack(f, value)

    def _ack(self, f: dj.Frame, value: bytes) -> None:
        if not f.wants_ack:
            return
        frame = self.codec.send_ack(f.session, f.seq, value)
        if f.session in dj.RELIABLE_SESSIONS:
            self._last_ack[f.session] = (f.seq, frame)

    def statustext(self, severity: int, text: str, now_s: float, key: str | None = None) -> bool:
        """The OPEN protocol has no text channel: kept in ``texts`` (for `hil fc`'s summary)."""
        self._statustexts.append(text)
        return True

    @property
    def texts(self) -> list[str]:
        return list(self._statustexts)

    # --- commands -------------------------------------------------------------------------------
    def _count(self, ok: bool) -> None:
        if ok:
            self.stats.commands_accepted += 1
        else:
            self.stats.commands_denied += 1

    def _on_version(self, f: dj.Frame, now_s: float) -> bytes:
        code = dj.ACK_SUCCESS if self.activated else dj.ACK_NO_AUTHORISATION
        name = dj.FC_VERSION_NAME.ljust(32, b"\x00")
        return dj.ack_code(code) + struct.pack("<I", dj.crc32(name)) + name

    def _on_activate(self, f: dj.Frame, now_s: float) -> bytes:
        p = f.payload
        if len(p) != ACTIVATION_BYTES:
            self.stats.malformed += 1
            self._count(False)
            return dj.ack_code(dj.ACTIVATE_BAD_PARAMETERS)
        _app_id, _reserved, sdk_version = struct.unpack_from("<III", p)
        code = self.config.activation_code
        if code == dj.ACTIVATE_SUCCESS and sdk_version < MIN_SDK_VERSION:
            code = dj.ACTIVATE_SDK_VERSION
        if code == dj.ACTIVATE_SUCCESS and not self.activated:
            self.activated = True
            self._next_push_s = now_s
        self._count(code == dj.ACTIVATE_SUCCESS)
        return dj.ack_code(code)

    def _on_broadcast_freq(self, f: dj.Frame, now_s: float) -> bytes:
        p = f.payload
        n = len(dj.BROADCAST_ITEMS)
        if len(p) != 16 or any(c not in dj.BROADCAST_RATES_HZ and c != dj.BROADCAST_KEEP for c in p[:n]):
            self.stats.malformed += 1
            self._count(False)
            return dj.ack_code(0x0001)
        for i, c in enumerate(p[:n]):
            if c != dj.BROADCAST_KEEP:
                self._rates_hz[i] = min(dj.BROADCAST_RATES_HZ[c], self.config.max_rate_hz)
                self._next_due[i] = now_s
        self._next_push_s = now_s
        self._count(True)
        return dj.ack_code(dj.ACK_SUCCESS)

    def _byte_arg(self, f: dj.Frame, allowed: frozenset[int] | tuple[int, ...]) -> int | None:
        """The command's one-byte argument when it is one of ``allowed``, else None (counted)."""
        p = f.payload
        if len(p) == 1 and p[0] in allowed:
            return p[0]
        self.stats.malformed += 1
        self._count(False)
        return None

    def _on_control_authority(self, f: dj.Frame, now_s: float) -> bytes:
        arg = self._byte_arg(f, (0, 1))
        if arg is None:
            return dj.ack_code(dj.CONTROL_OBTAIN_FAILED)
        if arg == 1:
            if self.config.rc_mode != "F":
                self._count(False)
                return dj.ack_code(dj.CONTROL_NEEDS_F_MODE)
            self.sdk_control = True
            self._push_state_now(now_s)  # the onboard side sees its authority at once
            if self.fc.state.armed and self.fc.state is not FcState.OFFBOARD:
                self.fc.request_offboard(now_s)  # flies the setpoints once they stream (`_on_setpoint`)
            self._count(True)
            return dj.ack_code(dj.CONTROL_OBTAINED)
        self.sdk_control = False
        self._push_state_now(now_s)
        self.fc.request_hold(now_s, "control authority released")
        self._count(True)
        return dj.ack_code(dj.CONTROL_RELEASED)

    def _on_arm(self, f: dj.Frame, now_s: float) -> bytes:
        arg = self._byte_arg(f, (0, 1))
        if arg is None:
            return dj.ack_code(dj.ARM_CANNOT)
        if not self.sdk_control:
            self._count(False)
            return dj.ack_code(dj.ARM_NEEDS_CONTROL)
        armed = self.fc.state.armed
        if (arg == 1) == armed:
            self._count(True)
            return dj.ack_code(dj.ARM_ALREADY)
        res = self.fc.arm(now_s) if arg == 1 else self.fc.disarm(now_s)
        self._count(res.accepted)
        return dj.ack_code(dj.ARM_SUCCESS if res.accepted else dj.ARM_CANNOT)

    def _on_task(self, f: dj.Frame, now_s: float) -> bytes:
        task = self._byte_arg(f, _TASKS)
        if task is None:
            return dj.ack_code(dj.TASK_FAILED)
        if not self.sdk_control:
            self._count(False)
            return dj.ack_code(dj.ACK_NO_RIGHTS)
        fc = self.fc
        if task == dj.TASK_START_MOTORS:
            res = fc.arm(now_s)
        elif task == dj.TASK_STOP_MOTORS:
            res = fc.disarm(now_s)
        elif task == dj.TASK_TAKEOFF:
            # the N3 spins up and climbs on its own; here: armed, and the onboard setpoints fly the climb
            res = fc.arm(now_s)
        elif task == dj.TASK_LAND:
            res = fc.request_land(now_s)
        else:  # go home: no home to fly to indoors, the FC holds instead
            res = fc.request_hold(now_s, "go home: holding (no home indoors)")
        self._count(res.accepted)
        return dj.ack_code(dj.TASK_STARTED if res.accepted else dj.TASK_FAILED)

    # --- setpoints -------------------------------------------------------------------------------
    def _on_setpoint(self, f: dj.Frame, now_s: float) -> None:
        values = dj.read_setpoint(f.payload)
        if values is None:
            self.stats.malformed += 1
            return
        if not self.activated:
            self.stats.commands_unactivated += 1
            return
        # validated and taken as MAVLink's are (the FC core flies a target in OFFBOARD only): without
        # authority a setpoint is not flown, as the N3 ignores it, and the stream is counted as PX4's is
        try:
            self.fc.set_setpoint_values(*values, now_s)
        except SetpointRejected:
            self.stats.setpoints_rejected += 1
            return
        self.stats.setpoints_applied += 1
        fc = self.fc
        if not self.sdk_control:
            self.stats.setpoints_without_control += 1
        elif fc.state is FcState.HOLD or (fc.state is FcState.DISARMED and not fc.offboard_selected):
            fc.request_offboard(now_s)  # with authority the stream flies as soon as it is a stream
        if self.on_setpoint is not None:
            self.on_setpoint(*values, now_s)

    def _on_events(self, now_s: float) -> None:
        events = self.fc.events
        for ev in events[self._events_seen :]:
            self._statustexts.append(ev.reason)
            if ev.to_state.failsafe and self.sdk_control:
                # setpoints lost: the FC takes over, the onboard device must obtain control again
                self.sdk_control = False
                self.codec.transport.send(self.codec.pack_command(
                    dj.SET_BROADCAST, dj.CMD_CONTROL_LOST, bytes((CONTROL_LOST_CODE,))))
        self._events_seen = len(events)
        self._push_state_now(now_s)  # let the onboard side see the new state now

    # --- broadcast ------------------------------------------------------------------------------
    def _push_state_now(self, now_s: float) -> None:
        """Push the flight status and control device items (those with a rate) at the next poll."""
        if self.activated:
            self._urgent = _STATE_FLAGS
            self._next_push_s = now_s

    def _push(self, now_s: float) -> None:
        """One flight-data frame of the items due at ``now_s`` (and the state items after a change); the
        next push at the earliest due."""
        flags, self._urgent = self._urgent, 0
        nxt = math.inf
        due, rates = self._next_due, self._rates_hz
        for i, hz in enumerate(rates):
            if hz <= 0.0:
                flags &= ~(1 << i)
                continue
            if now_s >= due[i] - 1e-9:
                flags |= 1 << i
                d = due[i] + 1.0 / hz
                due[i] = d if d > now_s else now_s + 1.0 / hz
            if due[i] < nxt:
                nxt = due[i]
        self._next_push_s = nxt
        if flags:
            payload = flight_data(self, now_s, flags)
            self.codec.transport.send(self.codec.pack_command(dj.SET_BROADCAST, dj.CMD_FLIGHT_DATA, payload))
            self.stats.broadcasts_sent += 1

    def flight_status(self) -> int:
        """The broadcast's flight status: standby (motors off), take-off (motors on, on the ground), in
        air, landing, finished landing."""
        fc = self.fc
        st = fc.state
        if st is FcState.DISARMED:
            return dj.FLIGHT_STANDBY
        landing = st in (FcState.LAND, FcState.FAILSAFE_LAND)
        if fc.landed:
            return dj.FLIGHT_LANDED if landing else dj.FLIGHT_TAKEOFF
        return dj.FLIGHT_LANDING if landing else dj.FLIGHT_IN_AIR

    def control_device(self) -> tuple[int, int]:
        """(API control mode, device byte): the device is the onboard computer while it holds authority
        and the FC flies its setpoints, else the RC; bit 3 says the onboard device has asked for it."""
        fc = self.fc
        flying_sdk = self.sdk_control and fc.state in (FcState.OFFBOARD, FcState.HOLD, FcState.DISARMED)
        device = dj.DEVICE_ONBOARD if flying_sdk else dj.DEVICE_RC
        mode = 0
        if flying_sdk and fc.target is not None and fc.state is FcState.OFFBOARD:
            mode = 14 if fc.target.yaw_rate_rad_s is not None else 13  # HORIZ_ANG_VERT_THR_YAW_RATE/ANG
        return mode, device | (0x08 if self.sdk_control else 0)


_S = dj.BROADCAST_STRUCTS
_RC_MODE = {"P": dj.RC_MODE_P, "A": dj.RC_MODE_A, "F": dj.RC_MODE_F}


def flight_data(server: DjiOpenServer, now_s: float, flags: int) -> bytes:
    """The flight-data payload (0x02 0x00) of the items in ``flags`` at ``now_s`` (s)."""
    parts = [struct.pack("<H", flags)]
    x = server.vehicle.state_vector().tolist() if flags & 0b111110 else None
    for i in range(len(_S)):
        if not flags >> i & 1:
            continue
        if i == 0:
            parts.append(_S[0].pack(int(now_s * _SEC_TICKS) & 0xFFFFFFFF, int(now_s % 1.0 * 1e9), 0))
        elif i == 1:
            assert x is not None
            parts.append(_S[1].pack(*quat_enu_flu_to_ned_frd_tuple(*x[6:10])))
        elif i == 2:
            acc = server.vehicle.state.accel_m_s2.tolist()  # world ENU (m/s^2), gravity excluded
            parts.append(_S[2].pack(acc[1], acc[0], acc[2]))
        elif i == 3:
            assert x is not None
            parts.append(_S[3].pack(x[4], x[3], x[5], 1))
        elif i == 4:
            assert x is not None
            parts.append(_S[4].pack(x[10], -x[11], -x[12]))
        elif i == 5:
            assert x is not None
            lat, lon = server.telemetry.lat_lon_deg(x[0:3])
            h = x[2] - server.fc.config.ground_z_m
            alt = server.config.home.alt_m + x[2]
            parts.append(_S[5].pack(math.radians(lat), math.radians(lon), alt, h, 0))
        elif i == 6:
            parts.append(_S[6].pack(0, 0, 0))
        elif i == 7:
            parts.append(_S[7].pack(0, 0, 0, 0, _RC_MODE[server.config.rc_mode], -4545))
        elif i == 8:
            parts.append(_S[8].pack(0.0, 0.0, 0.0, 0))
        elif i == 9:
            parts.append(_S[9].pack(server.flight_status()))
        elif i == 10:
            _, pct = server.telemetry.battery()
            parts.append(_S[10].pack(pct))
        else:
            parts.append(_S[11].pack(*server.control_device()))
    return b"".join(parts)


def _input_due(transport: object) -> bool:
    """False only when a transport that models arrival times says nothing can be read now."""
    nxt = getattr(transport, "next_arrival_s", None)
    clock = getattr(transport, "clock", None)
    if nxt is None or clock is None or transport.closed:  # type: ignore[attr-defined]
        return True
    return nxt() <= clock.now_s() + 1e-12

