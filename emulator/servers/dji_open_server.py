"""The FC's DJI OPEN-protocol endpoint (Onboard SDK 3.x, as an N3 with FC firmware 3.3 answers on its API
UART), over the same FC core as the MAVLink server: version query and activation, control authority,
arm/disarm, flight tasks (take-off, landing, motors), the flight-control setpoint (`emulator.fc.n3`), the
telemetry subscription (`emulator.servers.dji_subscription`) and the broadcast flight data at the rates the
onboard side sets (values: `emulator.servers.dji_telemetry`). On a serial line the pushes keep to the line's
data-rate budget (`emulator.servers.link_budget`): their rates scaled down to fit, the ACKs first.

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
from typing import Any

from emulator.fc.modes import DISARMED, CommandResult, FcState
from emulator.fc.n3 import (
    ACCEPTED_FIELDS,
    ATTITUDE_THRUST_FLAGS,
    SetpointRejected,
    attitude_thrust_target,
    attitude_thrust_values,
)
from emulator.kernel_cache import entry
from emulator.params import Parameters
from emulator.servers import dji_telemetry
from emulator.servers.arrivals import arrivals
from emulator.servers.dji_subscription import Subscriptions
from emulator.servers.link_budget import LinkBudget
from emulator.servers.telemetry import Home, TelemetryEncoder
from emulator.vehicle import EmulatedVehicle
from hil.link import dji_open as dj

#: the version (activation's third word: OSDK puts the FC firmware there) this FC accepts: 3.1.10 on
MIN_SDK_VERSION = 0x03010A00
ACTIVATION_BYTES = 44  # u32 app id, u32 reserved, u32 version, 32-byte bundle id
#: broadcast rates (Hz) by item before the onboard side sets them: OSDK's defaults for an A3/N3
DEFAULT_RATES_HZ: tuple[float, ...] = (50.0, 50.0, 50.0, 50.0, 50.0, 50.0, 0.0, 0.0, 0.0, 50.0, 50.0, 10.0,
                                       1.0, 1.0)
_TASKS = frozenset({dj.TASK_TAKEOFF, dj.TASK_LAND, dj.TASK_GO_HOME, dj.TASK_START_MOTORS,
                    dj.TASK_STOP_MOTORS})
#: the link budget's stream keys: one per broadcast item, one per subscription package (0-4)
ITEM_STREAMS = tuple(f"broadcast {name}" for name, _ in dj.BROADCAST_ITEMS)
PACKAGE_STREAMS = tuple(f"package {pkg}" for pkg in range(dj.SUB_MAX_PACKAGES))
#: the bytes of a flight-data frame, its items aside, and of a subscription push, its topics aside
BROADCAST_FRAME_BYTES = dj.COMMAND_FRAME_BYTES + dj.BROADCAST_FLAG_BYTES
PACKAGE_FRAME_BYTES = dj.COMMAND_FRAME_BYTES + 1  # (the package id)
#: the FC states whose flight the onboard device's setpoints take over (with authority): the FC's hover
#: and the setpoint-loss hover (a failsafe landing, of any cause, is not interrupted). (A tuple: its
#: members are found by identity, where a set would call the enum's Python ``__hash__``.)
_TAKEOVER_STATES = (FcState.HOLD, FcState.FAILSAFE_HOVER)


@dataclass(frozen=True)
class DjiServerConfig:
    """Identity and behaviour of the FC's OPEN-protocol endpoint."""

    #: the activation answer: 0 accepts; any other documented code (1-8) refuses every activation
    activation_code: int = dj.ACTIVATE_SUCCESS
    #: the RC's mode switch: "F" lets the onboard device obtain control; "P" or "A" refuse (code 0x0000)
    rc_mode: str = "F"
    home: Home = field(default_factory=Home)
    broadcast_rates_hz: tuple[float, ...] = DEFAULT_RATES_HZ
    #: the highest broadcast rate granted (Hz): the N3's 100 Hz UART push (codes 6, 7, OSDK's 200 and
    #: 400 Hz, are granted this)
    max_rate_hz: float = 100.0
    #: the command link's baud when it is a serial line (bit/s): the pushes then keep to its data rate
    #: (`emulator.servers.link_budget`); None: no budget unless ``budget_bytes_s`` sets one
    link_baud: int | None = None
    #: the pushes' data-rate budget (bytes/s; 0: half a serial line, none off one), as MAVLink's
    #: MAV_0_RATE (`hil fc --link-budget-bytes-s`: the OPEN protocol has no parameters)
    budget_bytes_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.activation_code <= 8:
            raise ValueError(f"activation code must be a documented one, 0..8, got {self.activation_code}")
        if self.rc_mode not in ("P", "A", "F"):
            raise ValueError(f"RC mode switch must be P, A or F, got {self.rc_mode!r}")
        if len(self.broadcast_rates_hz) != len(dj.BROADCAST_ITEMS):
            raise ValueError(f"broadcast rates: one per item ({len(dj.BROADCAST_ITEMS)})")
        if not (math.isfinite(self.budget_bytes_s) and self.budget_bytes_s >= 0):
            raise ValueError(f"link budget must be a finite number >= 0 bytes/s, got {self.budget_bytes_s!r}")


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
    broadcasts_sent: int = 0  # flight-data frames written (not those the link budget dropped)
    subscription_pushes: int = 0
    subscription_refused: int = 0  # 0x0B commands answered with a code other than success
    handler_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

#: a setpoint's command set and id, as its frame's data starts
_SETPOINT_COMMAND = bytes((dj.SET_CONTROL, dj.CMD_SETPOINT))


class DjiOpenServer:
    """Serves one vehicle's FC over one OPEN-protocol codec."""

    def __init__(self, vehicle: EmulatedVehicle, codec: dj.OpenCodec, config: DjiServerConfig | None = None
                 ) -> None:
        self.vehicle = vehicle
        self.fc = vehicle.fc
        self._fc_events = vehicle.fc.events  # (the FC's list of events, appended to)
        self.codec = codec
        self._timed_transport: object | None = None  # the transport `_arrivals` is of
        self._arrivals: Any = arrivals(None)  # what ``next_input_s`` is read from (the transport)
        #: the FC's parameters (`emulator.params`), set from files and scenarios: the OPEN protocol
        #: has no parameter messages, and no MAVLink telemetry whose rates they would set
        self.params = Parameters(self.fc, streams=None)
        self.config = config or DjiServerConfig()
        self.stats = DjiServerStats()
        # the MAVLink side's battery model and flat-Earth position, without its MAVLink packer
        self.telemetry = TelemetryEncoder(vehicle, None, self.config.home)  # type: ignore[arg-type]
        self.activated = False
        self.sdk_control = False  # the onboard device holds control authority
        #: the home point (world ENU east, north, m): where the motors last started (None: not yet)
        self.home_en_m: tuple[float, float] | None = None
        self._rates_hz = list(self.config.broadcast_rates_hz)  # asked (Hz)
        #: pushed at (Hz): the rates asked, the same list, unless a budget scales them (`_regrant`)
        self._granted_hz = self._rates_hz
        self._next_due = [0.0] * len(self._rates_hz)
        self._next_push_s = 0.0
        self.subscriptions = Subscriptions(frozenset(dji_telemetry.TOPIC_VALUES))
        #: the link's data-rate budget (None: none, every push at the rate asked)
        self.budget: LinkBudget | None = None
        self._push_bytes: dict[str, float] = {}  # a budget stream key -> the bytes one push costs
        if self.config.link_baud is not None or self.config.budget_bytes_s > 0:
            self.budget = LinkBudget(self.config.link_baud, getattr(codec.transport, "uart", None),
                                     self._push_bytes.__getitem__, rate_bytes_s=self.config.budget_bytes_s)
            self._granted_hz = list(self._rates_hz)
            self._regrant(0.0)
        #: told the sentence that says a rate was granted less than asked: the OPEN ACK has no room for a
        #: reason (`emulator.servers.registry.FcServer.on_untold`; `hil fc` prints it)
        self.on_untold: Callable[[str], None] | None = None
        self._last_ack: dict[int, tuple[int, bytes]] = {}  # session -> (seq, ACK frame) of reliable ones
        self._events_seen = 0
        #: the last poll's time (s; None before the first): what the pushes' battery is read at
        self.now_s: float | None = None
        self._statustexts: list[str] = []
        #: called with (flag, roll, pitch, thrust, yaw, now_s) after a setpoint is applied
        self.on_setpoint: Callable[..., None] | None = None
        self._attitude_thrust = setpoint_kernel()
        self._handlers: dict[tuple[int, int], Callable[[dj.Frame, float], bytes | None]] = {
            (dj.SET_ACTIVATION, dj.CMD_VERSION): self._on_version,
            (dj.SET_ACTIVATION, dj.CMD_ACTIVATE): self._on_activate,
            (dj.SET_ACTIVATION, dj.CMD_BROADCAST_FREQ): self._on_broadcast_freq,
            (dj.SET_CONTROL, dj.CMD_CONTROL_AUTHORITY): self._on_control_authority,
            (dj.SET_CONTROL, dj.CMD_TASK): self._on_task,
            (dj.SET_CONTROL, dj.CMD_ARM): self._on_arm,
            (dj.SET_SUBSCRIBE, dj.CMD_SUB_VERSION): self._on_sub_version,
            (dj.SET_SUBSCRIBE, dj.CMD_SUB_ADD): self._on_sub_add,
            (dj.SET_SUBSCRIBE, dj.CMD_SUB_RESET): self._on_sub_reset,
            (dj.SET_SUBSCRIBE, dj.CMD_SUB_REMOVE): self._on_sub_remove,
        }

    @property
    def state(self) -> FcState:
        return self.fc.state

    # --- the loop ------------------------------------------------------------------------------
    def poll(self, now_s: float) -> None:
        """Parse and act on what arrived, then push what is due at ``now_s``."""
        prev_s, self.now_s = self.now_s, now_s
        codec = self.codec
        if codec.transport is not self._timed_transport:  # (looked up once per transport)
            self._timed_transport = codec.transport
            self._arrivals = arrivals(codec.transport)
        if self._arrivals.next_input_s <= now_s + 1e-12:
            for f in codec.receive(0.0, now_s):  # (logged at the time they are acted on)
                self.handle(f, now_s)
        if self._events_seen != len(self._fc_events):
            self.telemetry.state_changed(prev_s, now_s)  # (the battery's armed time)
            self._on_events(now_s)
        if self.activated and now_s >= self._next_push_s:
            self._push(now_s)
        if now_s >= self.subscriptions.next_s - 1e-9:  # (never without packages: inf)
            self._push_packages(now_s)

    def handle(self, f: dj.Frame, now_s: float) -> None:
        """Act on one good command frame; never raises."""
        try:
            if f.is_ack:  # (the codec keeps ACKs apart; the FC waits for none)
                return
            if f.enc != dj.ENC_NONE:
                self.stats.encrypted_refused += 1
                self._ack(f, dj.ack_code(dj.ACK_KEY_ERROR))
                return
            data = f.data
            if data[:2] == _SETPOINT_COMMAND:  # (the per-tick case first)
                self._on_setpoint(data[2:], now_s)
                return
            if f.session in dj.RELIABLE_SESSIONS:
                last = self._last_ack.get(f.session)
                if last is not None and last[0] == f.seq:  # sent again: its ACK was lost
                    self.stats.retries_answered += 1
                    if self.budget is None or self.budget.admit(len(last[1]), False):
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
        except Exception:  # a frame the handlers did not foresee: counted, never fatal
            self.stats.handler_errors += 1

    def _ack(self, f: dj.Frame, value: bytes) -> None:
        if not f.wants_ack:
            return
        if self.budget is not None and not self.budget.admit(dj.MIN_FRAME_BYTES + len(value), False):
            frame = dj.encode_ack(f.session, f.seq, value)  # the line's buffer is full: kept for a resend
        else:
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
        return dj.version_value(dj.ACK_SUCCESS if self.activated else dj.ACK_NO_AUTHORISATION)

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
        # (the codes past the N3's 14 items are not read: OSDK's own sample leaves them unset)
        if len(p) != 16 or any(c not in dj.BROADCAST_RATES_HZ and c != dj.BROADCAST_KEEP for c in p[:n]):
            self.stats.malformed += 1
            self._count(False)
            return dj.ack_code(0x0001)
        for i, c in enumerate(p[:n]):
            if c != dj.BROADCAST_KEEP:
                self._rates_hz[i] = min(dj.BROADCAST_RATES_HZ[c], self.config.max_rate_hz)
                self._next_due[i] = now_s
        self._next_push_s = now_s
        if self.budget is not None:
            self._regrant(now_s)
            self._say_broadcast_caps([i for i, c in enumerate(p[:n]) if c != dj.BROADCAST_KEEP])
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
        fc = self.fc
        if arg == 1:
            if self.config.rc_mode != "F":
                self._count(False)
                return dj.ack_code(dj.CONTROL_NEEDS_F_MODE)
            self.sdk_control = True
            if fc.state in _TAKEOVER_STATES:
                fc.request_offboard(now_s)  # a stream already flowing flies now; else once it flows
            self._count(True)
            return dj.ack_code(dj.CONTROL_OBTAINED)
        self.sdk_control = False
        if fc.state is FcState.OFFBOARD:  # the FC hovers; its own tasks (take-off, landing) go on
            fc.request_hold(now_s, "control authority released")
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
            return dj.ack_code(dj.TASK_INVALID_COMMAND)
        if not self.sdk_control:
            self._count(False)
            return dj.ack_code(dj.ACK_NO_RIGHTS)
        code, res = self._task(task, now_s)
        self._count(res.accepted)
        return dj.ack_code(code if not res.accepted else dj.TASK_SUCCESS)

    def _task(self, task: int, now_s: float) -> tuple[int, CommandResult]:
        """(the code a refusal gets, the FC's answer) of a flight task."""
        fc = self.fc
        refused = CommandResult(False)
        if task == dj.TASK_START_MOTORS:
            return (dj.TASK_MOTOR_ON, refused) if fc.state.armed else (dj.TASK_MOTOR_ON, fc.arm(now_s))
        if task == dj.TASK_STOP_MOTORS:
            if not fc.state.armed:
                return dj.TASK_MOTOR_OFF, refused
            return dj.TASK_IN_AIR, fc.disarm(now_s)
        if task == dj.TASK_TAKEOFF:
            if fc.state is FcState.TAKEOFF:
                return dj.TASK_ALREADY_RUNNING, refused
            return dj.TASK_IN_AIR, fc.request_takeoff(now_s)
        if fc.landed:
            return dj.TASK_NOT_IN_AIR, refused
        if task == dj.TASK_LAND:
            return dj.TASK_ALREADY_RUNNING, fc.request_land(now_s)
        if self.home_en_m is None:
            return dj.TASK_NO_HOME_POINT, refused
        return dj.TASK_NOT_IN_AIR, fc.request_go_home(now_s, self.home_en_m)

    # --- subscription (0x0B): one-byte codes ------------------------------------------------------
    def _sub_code(self, code: int) -> bytes:
        if code != dj.SUB_SUCCESS:
            self.stats.subscription_refused += 1
        self._count(code == dj.SUB_SUCCESS)
        return bytes((code,))

    def _on_sub_version(self, f: dj.Frame, now_s: float) -> bytes:
        p = f.payload
        if len(p) != 4:
            return self._sub_code(dj.SUB_ILLEGAL_DATA_LENGTH)
        ok = struct.unpack("<I", p)[0] == dj.SUB_DB_VERSION
        return self._sub_code(dj.SUB_SUCCESS if ok else dj.SUB_VERSION_MISMATCH)

    def _on_sub_add(self, f: dj.Frame, now_s: float) -> bytes:
        code = self.subscriptions.add(f.payload, now_s)
        if code == dj.SUB_SUCCESS and self.budget is not None:
            self._regrant(now_s)
            pkg = f.payload[0]
            p = self.subscriptions.packages[pkg]
            self._say_if_capped(PACKAGE_STREAMS[pkg], p.hz, p.granted_hz)
        return self._sub_code(code)

    def _on_sub_remove(self, f: dj.Frame, now_s: float) -> bytes:
        return self._sub_code(self._regranted(self.subscriptions.remove(f.payload), now_s))

    def _on_sub_reset(self, f: dj.Frame, now_s: float) -> bytes:
        return self._sub_code(self._regranted(self.subscriptions.reset(), now_s))

    # --- the link's data-rate budget -------------------------------------------------------------
    def _regrant(self, now_s: float) -> None:
        """Scale the broadcast items' and the packages' rates alike to fit the budget (`LinkBudget.grant`).
        Each push's cost is its bytes on the line; the broadcast items asked at one rate share one frame
        (its header, command, flag word and CRC), so items kept at one rate stay in one frame."""
        budget = self.budget
        assert budget is not None
        costs, asked = self._push_bytes, {}
        costs.clear()
        for i, hz in enumerate(self._rates_hz):
            if hz > 0.0:
                key = ITEM_STREAMS[i]
                asked[key] = 1.0 / hz
                sharing = sum(1 for r in self._rates_hz if r == hz)
                costs[key] = dj.BROADCAST_STRUCTS[i].size + BROADCAST_FRAME_BYTES / sharing
        packages = self.subscriptions.packages
        for pkg, p in packages.items():
            asked[PACKAGE_STREAMS[pkg]] = 1.0 / p.hz
            costs[PACKAGE_STREAMS[pkg]] = PACKAGE_FRAME_BYTES + p.data_bytes
        granted = budget.grant(asked)
        rates = [1.0 / granted[key] if key in granted else 0.0 for key in ITEM_STREAMS]
        if rates != self._granted_hz:  # the items due together from now, one frame a rate
            self._granted_hz = rates
            self._next_due = [now_s] * len(rates)
            self._next_push_s = now_s
        for pkg, p in packages.items():
            p.granted_hz = 1.0 / granted[PACKAGE_STREAMS[pkg]]

    def _regranted(self, code: int, now_s: float) -> int:
        """``code``; the rates granted again first when it is a success and there is a budget."""
        if code == dj.SUB_SUCCESS and self.budget is not None:
            self._regrant(now_s)
        return code

    def _say_broadcast_caps(self, items: list[int]) -> None:
        """Say the broadcast ``items`` just asked for that are granted less: one line per rate asked and
        granted, naming its items."""
        capped: dict[tuple[float, float], list[str]] = {}
        for i in items:
            capped.setdefault((self._rates_hz[i], self._granted_hz[i]), []).append(dj.BROADCAST_ITEMS[i][0])
        for (asked_hz, granted_hz), names in capped.items():
            self._say_if_capped("broadcast " + ",".join(names), asked_hz, granted_hz)

    def _say_if_capped(self, stream: str, asked_hz: float, granted_hz: float) -> None:
        """Record and say a request granted less than asked (the OPEN ACK has no room for a reason)."""
        if self.budget is None or granted_hz >= asked_hz * (1 - 1e-9):
            return
        text = self.budget.capped(stream, asked_hz, granted_hz)
        self._statustexts.append(text)
        if self.on_untold is not None:
            self.on_untold(f"link budget: {text} (the OPEN ACK says success: it has no room for a reason)")

    # --- setpoints -------------------------------------------------------------------------------
    def _on_setpoint(self, payload: bytes, now_s: float) -> None:
        values = dj.read_setpoint(payload)
        if values is None:
            self.stats.malformed += 1
            return
        if not self.activated:
            self.stats.commands_unactivated += 1
            return
        # validated and taken as MAVLink's are (the FC core flies a target in OFFBOARD only): without
        # authority a setpoint is not flown, as the N3 ignores it, and the stream is counted as PX4's is
        flag, x, y, z, yaw = values  # (a call with its arguments listed: no tuple built for it)
        fc = self.fc
        if flag in ATTITUDE_THRUST_FLAGS:  # (the per-tick case: the N3's checks and target, fewer calls)
            profile = fc.profile
            verdict, roll, pitch, heading, rate = self._attitude_thrust(
                flag, x, y, z, yaw, profile.max_tilt_deg, profile.max_yaw_rate_deg_s)
            if verdict != ACCEPTED_FIELDS:
                self.stats.setpoints_rejected += 1
                return
            fc.take_target(attitude_thrust_target(flag, roll, pitch, heading, rate, z, profile), now_s)
        else:
            try:
                fc.set_setpoint_values(flag, x, y, z, yaw, now_s)
            except SetpointRejected:
                self.stats.setpoints_rejected += 1
                return
        self.stats.setpoints_applied += 1
        if not self.sdk_control:
            self.stats.setpoints_without_control += 1
        elif (st := fc.machine.state) in _TAKEOVER_STATES or (
                st is DISARMED and not fc.offboard_selected):
            fc.request_offboard(now_s)  # with authority the stream flies as soon as it is a stream
        if self.on_setpoint is not None:
            self.on_setpoint(*values, now_s)

    def _on_events(self, now_s: float) -> None:
        events = self.fc.events
        # (setpoints lost: the FC hovers, then lands, and the onboard device keeps its authority, as an
        # N3 does: OSDK's own samples pause their stream between moves and go on flying after)
        for ev in events[self._events_seen :]:
            self._statustexts.append(ev.reason)
            if ev.from_state is FcState.DISARMED:  # the motors start: the home point is where it is
                x = self.vehicle.state_vector()
                self.home_en_m = (float(x[0]), float(x[1]))
        self._events_seen = len(events)

    # --- broadcast and subscription pushes -------------------------------------------------------
    def _push_packages(self, now_s: float) -> None:
        for pkg, p in self.subscriptions.due(now_s):
            data = dji_telemetry.package_data(self, pkg, p.uids, p.timestamp, now_s)
            if self._send_push(dj.CMD_SUBSCRIPTION_DATA, data):
                self.stats.subscription_pushes += 1

    def _push(self, now_s: float) -> None:
        """One flight-data frame of the items due at ``now_s``; the next push at the earliest due."""
        flags = 0
        nxt = math.inf
        due, rates = self._next_due, self._granted_hz
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
        if flags and self._send_push(dj.CMD_FLIGHT_DATA, dji_telemetry.flight_data(self, now_s, flags)):
            self.stats.broadcasts_sent += 1

    def _send_push(self, cmd_id: int, payload: bytes) -> bool:
        """Push a frame of the broadcast set unless the line's queue is too deep for it (counted in the
        budget's ``frames_dropped``); whether it went."""
        if self.budget is not None and not self.budget.admit(dj.COMMAND_FRAME_BYTES + len(payload), True):
            return False
        codec = self.codec
        codec.transport.send(codec.pack_command(dj.SET_BROADCAST, cmd_id, payload))
        return True


def setpoint_kernel() -> Callable[..., tuple]:
    """The N3's `attitude_thrust_values` compiled (or loaded from the cache) for a setpoint's flag and fields
    as the int and floats its struct unpacks, called without numba's type dispatch: each server binds it at
    construction, and `emulator.assembly.warm_up` calls this before a wall clock starts (the protocol's
    registered warm-up)."""
    return entry(attitude_thrust_values, 0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0)
