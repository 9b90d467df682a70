"""The harness's lockstep convention, spoken by the runner (`hil.runner.lockstep`) and the onboard
program (`policies.onboard.command_link`): how simulated time advances only once the onboard program
is done with a tick. It is the harness's own, not a MAVLink or DJI standard.

A tick at simulated time t: the harness writes the mocap bytes due by t on the mocap link, then on the
command link, from the FC's ids, a count and a request:
    NAMED_VALUE_INT name "mocap_n", value = the mocap bytes written in all, mod 2^31 (a total, not a
        per-tick count, so a tick lost to corrupt bytes costs nothing: the next says it again); the
        program reads the mocap link up to there before acting on the tick;
    TIMESYNC tc1 = 0, ts1 = t in ns (a request).
The program acts on everything before the request, then answers TIMESYNC tc1 = ts1 = t in ns. The
harness sends no tick at t = 0 (its answer TIMESYNC(0, 0) would read as a request). A tick not answered
within `RESEND_S` of wall time (`STARTUP_RESEND_S` until the first answer: a process opening its port
drops what was written before) is sent again after `RESEND_FILLER`; the program answers a repeat but
acts on a tick once.

The convention's logic is in plain values (`tick_request_s`, `tick_answer_ns`, `mocap_count`); its
frames on each command-link protocol are at the end of this module (`mavlink_framing`, `dji_framing`, read
through `hil.link.protocols`): MAVLink 2 as above, and DJI's OPEN protocol, where the tick is one frame of
command set `SET_HIL` (0xFE, which DJI does not use, so an Onboard SDK program never sees it) on session
0: id 0x00 carries the tick time (i64 ns) and the mocap total (u32), id 0x01 the answer (i64 ns), read
through the same plain-value functions.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from hil.link import dji_open
from hil.link.mavlink import MAX_FRAME_BYTES, FrameSplitter, encode_frame, mav

MOCAP_COUNT_NAME = "mocap_n"
MOCAP_COUNT_MASK = 0x7FFFFFFF  # the count is mod 2^31 (a non-negative int32)
NS_PER_S = 1_000_000_000
#: wall time after which an unanswered tick is sent again (a repeat is only answered: spurious ones
#: cost nothing)
RESEND_S = 0.1
#: the same until the first answer (a new process opening its port drops what came before)
STARTUP_RESEND_S = 0.002
_MOCAP_COUNT_RAW = MOCAP_COUNT_NAME.encode("ascii")
_MOCAP_COUNT_NUL = _MOCAP_COUNT_RAW + b"\x00"
_MOCAP_COUNT_NUL_LEN = len(_MOCAP_COUNT_NUL)


def tick_request_s(tc1: int, ts1: int) -> float | None:
    """The tick time (s) of a request TIMESYNC(tc1, ts1), None when it is no request."""
    return ts1 * 1e-9 if tc1 == 0 else None


def tick_answer_ns(tc1: int, ts1: int) -> int | None:
    """The tick time (ns) a TIMESYNC(tc1, ts1) answers, None when it is no answer."""
    return tc1 if tc1 == ts1 and tc1 != 0 else None


def mocap_count(name: str | bytes, value: int) -> int | None:
    """The mocap byte total a NAMED_VALUE_INT(name, value) announces, None when it is no count (the
    name as text, or as the wire's bytes up to the first NUL)."""
    if value < 0:
        return None
    if name.__class__ is bytes:  # (the name up to its first NUL: all of it, or a prefix and a NUL; the
        # payload's whole field first, as the tick frames carry it)
        return int(value) if name in (_MOCAP_COUNT_FIELD, _MOCAP_COUNT_RAW) \
            or name[:_MOCAP_COUNT_NUL_LEN] == _MOCAP_COUNT_NUL else None
    return int(value) if name == MOCAP_COUNT_NAME else None


# --- on MAVLink 2 --------------------------------------------------------------------------------
TIMESYNC_ID = mav.MAVLINK_MSG_ID_TIMESYNC
MOCAP_COUNT_ID = mav.MAVLINK_MSG_ID_NAMED_VALUE_INT
TICK_MSG_IDS = frozenset({TIMESYNC_ID, MOCAP_COUNT_ID})
#: written before a repeated tick: longer than any MAVLink frame, so a parser collecting a frame of a
#: corrupt length completes it; zeros are never a frame start
RESEND_FILLER = bytes(MAX_FRAME_BYTES)
_TIMESYNC = mav.MAVLink_timesync_message.unpacker
_NAMED_INT = mav.MAVLink_named_value_int_message.unpacker
#: the count's name as NAMED_VALUE_INT's name field holds it (NUL-padded): what `mocap_count` reads first
_MOCAP_COUNT_FIELD = _NAMED_INT.unpack(_NAMED_INT.pack(0, 0, _MOCAP_COUNT_RAW))[2]


def tick_frames(t_s: float, mocap_total: int, system_id: int, component_id: int) -> bytes:
    """The tick at ``t_s`` (s) from the FC (``system_id``, ``component_id``): the mocap count, then the
    request; sequence numbers 0."""
    ms = round(t_s * 1e3) & 0xFFFFFFFF
    count = _NAMED_INT.pack(ms, mocap_total & MOCAP_COUNT_MASK, _MOCAP_COUNT_RAW)
    request = _TIMESYNC.pack(0, round(t_s * NS_PER_S))
    return encode_frame(MOCAP_COUNT_ID, count, 0, system_id, component_id) + encode_frame(
        TIMESYNC_ID, request, 0, system_id, component_id
    )


def answer_payload(tick_s: float) -> bytes:
    """The TIMESYNC payload that answers the tick at ``tick_s`` (s), for the program's codec to frame."""
    ns = round(tick_s * NS_PER_S)
    return _TIMESYNC.pack(ns, ns)


#: zeros after a frame's payload to its message's full size (MAVLink 2 trims trailing zeros), so the
#: message's ``unpacker`` reads it from offset 0: ``unpack_from(payload + pad)``
_TIMESYNC_PAD = bytes(_TIMESYNC.size)
_NAMED_INT_PAD = bytes(_NAMED_INT.size)
_TIMESYNC_ID_BYTES = TIMESYNC_ID.to_bytes(3, "little")  # (a MAVLink 2 header's message id, at 7..9)


def answered_ns(frame: bytes) -> int | None:
    """The tick time (ns) a frame answers (a MAVLink 2 TIMESYNC answer), else None. No CRC check: the
    harness reads the program's frames before they enter the modelled link."""
    if frame[7:10] != _TIMESYNC_ID_BYTES or frame[0] != 0xFD or len(frame) < 12:  # (the id first: a slice
        return None  # of a short frame is shorter, no error)
    tc1, ts1 = _TIMESYNC.unpack_from(frame[10 : 10 + frame[1]] + _TIMESYNC_PAD)
    return tick_answer_ns(tc1, ts1)


def read_tick_frame(frame: bytes) -> tuple[float | None, int | None]:
    """(tick request time (s), mocap count) of a good MAVLink 2 frame of `TICK_MSG_IDS`, None where it
    says none."""
    payload = frame[10 : 10 + frame[1]]
    if frame[7] == TIMESYNC_ID:  # both ids < 256: the id's upper bytes are 0
        tc1, ts1 = _TIMESYNC.unpack_from(payload + _TIMESYNC_PAD)
        return tick_request_s(tc1, ts1), None
    _, value, name = _NAMED_INT.unpack_from(payload + _NAMED_INT_PAD)
    return None, mocap_count(name, value)


def is_mavlink_setpoint(frame: bytes) -> bool:
    """Whether a frame is a MAVLink 2 SET_ATTITUDE_TARGET (id 82)."""
    return len(frame) > 9 and frame[0] == 0xFD and frame[7] == 82 and frame[8] == frame[9] == 0


# --- on DJI's OPEN protocol ----------------------------------------------------------------------
_DJI_TICK = struct.Struct("<qI")
_DJI_ANSWER = struct.Struct("<q")
#: written before a repeated tick: as long as the longest frame; zeros are never a SOF
DJI_RESEND_FILLER = bytes(dji_open.MAX_FRAME_BYTES)
_DJI_ANSWER_LEN = dji_open.MIN_FRAME_BYTES + 2 + _DJI_ANSWER.size


_DJI_TICK_COMMAND = bytes((dji_open.SET_HIL, dji_open.CMD_HIL_TICK))  # (how the tick frame's data starts)


def dji_tick_frames(t_s: float, mocap_total: int) -> bytes:
    """The tick at ``t_s`` (s) as one OPEN-protocol frame (session 0, SEQ 0): the command
    (`dji_open.encode_command`'s data, framed by `dji_open.encode` without the call between)."""
    payload = _DJI_TICK.pack(round(t_s * NS_PER_S), mocap_total & MOCAP_COUNT_MASK)
    return dji_open.encode(0, 0, _DJI_TICK_COMMAND + payload)


def dji_read_tick(payload: bytes) -> tuple[float | None, int | None]:
    """(tick request time (s), mocap count) of a tick frame's payload; (None, None) when malformed."""
    if len(payload) != _DJI_TICK.size:
        return None, None
    ns, total = _DJI_TICK.unpack(payload)
    return tick_request_s(0, ns), mocap_count(MOCAP_COUNT_NAME, total)


def dji_answer_payload(tick_s: float) -> bytes:
    """The payload of the answer (`dji_open.CMD_HIL_ANSWER`) to the tick at ``tick_s`` (s)."""
    return _DJI_ANSWER.pack(round(tick_s * NS_PER_S))


def dji_answered_ns(frame: bytes) -> int | None:
    """The tick time (ns) an OPEN-protocol frame answers, else None (no CRC check, as `answered_ns`)."""
    if len(frame) != _DJI_ANSWER_LEN or frame[0] != dji_open.SOF or frame[12] != dji_open.SET_HIL \
            or frame[13] != dji_open.CMD_HIL_ANSWER:
        return None
    (ns,) = _DJI_ANSWER.unpack_from(frame, 14)
    return tick_answer_ns(ns, ns)


def is_dji_setpoint(frame: bytes) -> bool:
    """Whether a frame is an OPEN-protocol flight-control setpoint (0x01 0x03)."""
    return len(frame) > 14 and frame[0] == dji_open.SOF and frame[12] == dji_open.SET_CONTROL \
        and frame[13] == dji_open.CMD_SETPOINT


# --- the framings, by protocol -----------------------------------------------------------------------
class Splitter(Protocol):
    def feed(self, data: bytes) -> list[bytes]: ...


@dataclass(frozen=True)
class Framing:
    """How the harness's ticks and the onboard program's frames look on one command-link protocol."""

    tick_frames: Callable[[float, int], bytes]  # (t (s), mocap byte total) -> the tick's bytes
    answered_ns: Callable[[bytes], int | None]
    resend_filler: bytes
    splitter: Callable[[], Splitter]  # a new frame cutter of the onboard program's bytes
    is_setpoint: Callable[[bytes], bool]


def mavlink_framing(system_id: int = 1, component_id: int = mav.MAV_COMP_ID_AUTOPILOT1) -> Framing:
    """The lockstep's framing on MAVLink, the FC's ticks sent with its ids."""

    def fc_tick_frames(t_s: float, mocap_total: int) -> bytes:
        """`tick_frames` from the FC's ids (a closure: a partial with keywords merges them at each call)."""
        return tick_frames(t_s, mocap_total, system_id, component_id)

    return Framing(fc_tick_frames, answered_ns, RESEND_FILLER, FrameSplitter, is_mavlink_setpoint)


def dji_framing(system_id: int = 1, component_id: int = 0) -> Framing:
    """The lockstep's framing on DJI's OPEN protocol (which has no sender ids: they are not used)."""
    return Framing(dji_tick_frames, dji_answered_ns, DJI_RESEND_FILLER, dji_open.FrameSplitter,
                   is_dji_setpoint)
