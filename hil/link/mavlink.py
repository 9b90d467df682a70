"""MAVLink 2 over a Transport: a codec with parse-error counters, optional signing, .tlog hooks, and the
ENU/FLU <-> NED/FRD conversions both sides need at the wire (common dialect, pymavlink underneath)."""

from __future__ import annotations

import functools
import hashlib
import math
import struct
from collections.abc import Callable, Collection
from dataclasses import dataclass, fields
from typing import Any, Protocol

import numpy as np
from fastcrc import crc16 as _fastcrc16
from pymavlink.dialects.v20 import common as mavlink2

from hil.link.clock import Clock
from hil.link.transport import Transport

#: the pymavlink dialect module (message classes, enums and constants)
mav = mavlink2
MAVLinkMessage = mavlink2.MAVLink_message

MAVLINK_V2_MAGIC, MAVLINK_V1_MAGIC = 0xFD, 0xFE
MAX_FRAME_BYTES = 280  # the longest MAVLink 2 frame: header, 255 payload bytes, CRC, signature
SIGNING_EPOCH_UNIX_S = 1420070400  # MAVLink signing timestamps count 10 us units from 2015-01-01
#: a stream (link id, system, component) first heard may start at most this far (10 us units: one
#: minute) behind the receiver's own signing timestamp (the MAVLink signing spec's window)
SIGNING_NEW_STREAM_WINDOW = 6_000_000
SIGNATURE_BYTES = 13  # link id (1), timestamp (6), signature (6)
FRAME_OVERHEAD_BYTES = 12  # MAVLink 2 header (10) and CRC (2), signature not counted
#: messages a signed link also takes unsigned: they ask or announce and change nothing (PX4 and ArduPilot
#: let RADIO_STATUS through unsigned for the same reason). Every other message (parameters, commands,
#: setpoints, modes, missions, FTP, SETUP_SIGNING, ...) must be signed with the key and a fresh timestamp.
UNSIGNED_OK_MSG_IDS: frozenset[int] = frozenset(
    {
        mavlink2.MAVLINK_MSG_ID_HEARTBEAT,
        mavlink2.MAVLINK_MSG_ID_RADIO_STATUS,
        mavlink2.MAVLINK_MSG_ID_PING,
        mavlink2.MAVLINK_MSG_ID_TIMESYNC,
        mavlink2.MAVLINK_MSG_ID_PARAM_REQUEST_LIST,
        mavlink2.MAVLINK_MSG_ID_PARAM_REQUEST_READ,
        mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST_LIST,
    }
)


class FrameRecorder(Protocol):
    """Receives every good frame in either direction (a .tlog writer)."""

    def record(self, frame: bytes, time_s: float) -> None: ...


@dataclass
class MavlinkStats:
    """What the codec saw on the wire (counts)."""

    frames_received: int = 0  # good frames handed to the caller
    frames_sent: int = 0
    frames_ignored: int = 0  # good frames of ids the caller does not use, dropped undecoded
    garbage_bytes: int = 0  # bytes skipped while looking for a frame start
    bad_crc: int = 0
    unknown_msg_id: int = 0
    malformed: int = 0  # bad length, bad flags, undecodable payload
    # signed links: frames refused, by kind (none of them is acted on or recorded)
    unsigned_refused: int = 0  # unsigned, of a type that must be signed
    bad_signature: int = 0  # signed, but not with the key (never taken as unsigned)
    replayed: int = 0  # timestamp not newer than the last one of its stream (link id, system, component)
    stale_timestamp: int = 0  # a new stream's first timestamp more than a minute behind ours

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def errors(self) -> int:
        return (self.garbage_bytes + self.bad_crc + self.unknown_msg_id + self.malformed
                + self.signing_refused)

    @property
    def signing_refused(self) -> int:
        """Frames a signed link refused, all kinds."""
        return self.unsigned_refused + self.bad_signature + self.replayed + self.stale_timestamp


def frame_size(buf: bytes | bytearray, i: int) -> int:
    """The length (bytes, signature included) of the MAVLink 2 or 1 frame that starts at ``buf[i]``,
    by its header: 0 when the header is not complete in ``buf``, -1 when ``buf[i]`` starts no frame."""
    magic = buf[i]
    if magic == MAVLINK_V2_MAGIC:
        return 12 + buf[i + 1] + (13 if buf[i + 2] & 0x01 else 0) if i + 3 <= len(buf) else 0
    if magic == MAVLINK_V1_MAGIC:
        return 8 + buf[i + 1] if i + 2 <= len(buf) else 0
    return -1


@functools.cache
def max_frame_bytes(msg_id: int, signed: bool) -> int:
    """The longest frame of message ``msg_id`` on the wire (bytes; trailing zeros may make it shorter)."""
    size = mavlink2.mavlink_map[msg_id].unpacker.size + FRAME_OVERHEAD_BYTES
    return size + SIGNATURE_BYTES if signed else size


class FrameSplitter:
    """Cuts a MAVLink byte stream into frames by their length fields (no CRC check: a codec does
    that); bytes before a frame start are passed on as they are. Another protocol's stream is cut the
    same way with its own ``size_of`` (`frame_size`'s contract) and start bytes ``starts``."""

    def __init__(self, size_of: Callable[[bytes | bytearray, int], int] | None = None,
                 starts: bytes = bytes((MAVLINK_V2_MAGIC, MAVLINK_V1_MAGIC))) -> None:
        self._buf = bytearray()
        self._size_of = size_of or frame_size
        self._starts = starts

    def feed(self, data: bytes) -> list[bytes]:
        """The complete frames (and runs of other bytes) of what has come so far, in order."""
        held = self._buf
        if held:
            held += data
            buf = held
        else:  # (the usual case: cut ``data`` itself, keep only what is left of it)
            buf = data
        out: list[bytes] = []
        i, n = 0, len(buf)
        size_of, starts = self._size_of, self._starts
        while i < n:
            size = size_of(buf, i)
            if size < 0:
                j = i + 1
                while j < n and buf[j] not in starts:
                    j += 1
                out.append(bytes(buf[i:j]))
                i = j
                continue
            if size == 0 or i + size > n:
                break
            frame = buf[i : i + size]
            out.append(frame if frame.__class__ is bytes else bytes(frame))
            i += size
        if buf is held:
            del held[:i]
        elif i < n:
            held += buf[i:]
        return out


def parse_signing_key(text: str) -> bytes:
    """A signing key from hex (64 hex digits = 32 bytes); ValueError with the reason otherwise."""
    try:
        key = bytes.fromhex(text.strip())
    except ValueError as exc:
        raise ValueError(f"signing key must be hex digits: {exc}") from None
    if len(key) != 32:
        raise ValueError(f"signing key must be 32 bytes (64 hex digits), got {len(key)} bytes")
    return key


class MavlinkCodec:
    """MAVLink 2 frames over a byte-stream Transport, stamped by a Clock.

    ``receive()`` returns the good messages now available and counts everything else in ``stats``.
    With ``signing_key`` set, outgoing frames are signed, and an incoming frame is taken only when it
    is signed with the key and a timestamp newer than the last of its stream (link id, system,
    component; a new stream within a minute of ours), or unsigned with an id in ``unsigned_ok``. A
    frame with a bad signature is refused whatever its id; refusals are counted by kind in ``stats``.
    """

    def __init__(
        self,
        transport: Transport,
        clock: Clock,
        system_id: int,
        component_id: int,
        *,
        signing_key: bytes | None = None,
        unsigned_ok: Collection[int] = UNSIGNED_OK_MSG_IDS,
        link_id: int = 0,
        signing_epoch_unix_s: float = SIGNING_EPOCH_UNIX_S,
        recorder: FrameRecorder | None = None,
        accept_ids: Collection[int] | None = None,
        raw_ids: Collection[int] = (),
    ) -> None:
        """``accept_ids``: the message ids the caller uses; other well-formed frames are CRC-checked
        and dropped without being decoded (counted in ``stats.frames_ignored``). None decodes all.
        ``raw_ids``: ids the caller decodes itself: a good frame of one of them that the unsigned fast
        path takes is handed back as the frame's bytes (counted and recorded as a decoded one), not as
        a message; `decode_frame` of those bytes is the message it stands for. Frames pymavlink's
        parser takes (after bad bytes, split frames) still come as messages."""
        if not (0 <= system_id <= 255 and 0 <= component_id <= 255):
            raise ValueError(f"MAVLink ids must be 0..255, got system {system_id}, component {component_id}")
        self.transport = transport
        self.clock = clock
        self.recorder = recorder
        self.stats = MavlinkStats()
        #: packs (and signs) what the codec does not frame itself; its signing state is the parser's
        self._mav = mavlink2.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._parser = self._new_parser()
        self._parser_empty = True  # whether ``_parser`` holds no bytes (kept by `_parse_slow`)
        self._unsigned_ok = frozenset(unsigned_ok)
        #: the last timestamp taken of each signed stream (link id, system, component)
        self._stream_stamps: dict[tuple[int, int, int], int] = {}
        self._signing_epoch_unix_s = signing_epoch_unix_s
        self._accept = None if accept_ids is None else frozenset(accept_ids)
        self._raw = frozenset(raw_ids)
        self._signing = signing_key is not None  # (fixed for the codec's life)
        #: what `_take_leading` does with a good unsigned frame, by the id's three bytes on the wire
        #: (`_leading_table`: one table for the codecs of the same rules)
        self._leading = _leading_table(self._signing, self._unsigned_ok, self._accept, self._raw)
        if signing_key is not None:
            if len(signing_key) != 32:
                raise ValueError(f"signing key must be 32 bytes, got {len(signing_key)}")
            self._mav.signing.secret_key = signing_key
            self._mav.signing.sign_outgoing = True
            self._mav.signing.link_id = link_id
            self._refresh_signing_time()

    def _new_parser(self) -> mavlink2.MAVLink:
        """pymavlink's parser for incoming bytes. It holds no key: it frames and decodes signed frames,
        and `_refusal` judges their signatures (pymavlink's own check takes a frame with a bad signature
        for an unsigned one and moves a stream's timestamp before it knows the signature is good)."""
        parser = mavlink2.MAVLink(None, srcSystem=self._mav.srcSystem, srcComponent=self._mav.srcComponent)
        parser.robust_parsing = True
        return parser

    @property
    def system_id(self) -> int:
        return self._mav.srcSystem

    @property
    def component_id(self) -> int:
        return self._mav.srcComponent

    @property
    def signing(self) -> bool:
        """Whether the codec signs and judges signatures (set by its ``signing_key``)."""
        return self._signing

    @property
    def mav(self) -> mavlink2.MAVLink:
        """The pymavlink object, for its ``*_encode`` helpers."""
        return self._mav

    def send(self, msg: MAVLinkMessage) -> bytes:
        """Pack, sign (if configured), write and record ``msg``; returns the frame."""
        frame = self.pack(msg)
        self.transport.send(frame)
        return frame

    def pack(self, msg: MAVLinkMessage) -> bytes:
        """Pack, sign (if configured) and record ``msg`` as if sent; the caller writes the frame."""
        if self._signing:
            self._refresh_signing_time()
        return self._sent(bytes(msg.pack(self._mav)))

    def pack_payload(self, msg_id: int, payload: bytes) -> bytes:
        """`pack` for a message given as its full payload (fields in wire order, as the message's
        ``unpacker`` packs them): the same frame pymavlink would make, without building the message
        (signed links go through pymavlink)."""
        if self._signing:
            return self.pack(message_from_payload(msg_id, payload))
        m = self._mav
        seq = m.seq
        frame = encode_frame(msg_id, payload, seq, m.srcSystem, m.srcComponent)
        # (`_sent`, without its call: a frame or more a tick)
        m.seq = (seq + 1) & 0xFF
        self.stats.frames_sent += 1
        recorder = self.recorder
        if recorder is not None:
            recorder.record(frame, self.clock.now_s())
        return frame

    def _sent(self, frame: bytes) -> bytes:
        """Count and record ``frame``, framed on the packer's sequence number, and step that number."""
        self._mav.seq = (self._mav.seq + 1) & 0xFF  # one sequence, pymavlink's public ``seq``
        self.stats.frames_sent += 1
        if self.recorder is not None:
            self.recorder.record(frame, self.clock.now_s())
        return frame

    def receive(self, timeout_s: float = 0.0, time_s: float | None = None) -> list[Any]:
        """Parse what has arrived (waiting up to ``timeout_s`` for the first bytes); good messages only
        (frames as bytes for ``raw_ids``, see `__init__`). ``time_s``: see `feed`."""
        data = self.transport.recv(timeout_s)
        return self.feed(data, time_s) if data else []

    def feed(self, data: bytes, time_s: float | None = None) -> list[Any]:
        """Parse ``data`` as if it had arrived on the transport: the good messages (MAVLinkMessage; frames
        as bytes for ``raw_ids``, see `__init__`). The recorder stamps its frames ``time_s`` (s, clock
        time): when the receiver acts on them (an FC's poll), so that its log and its timers agree
        however late the read came; the clock's time of the read by default.

        The leading complete, unsigned MAVLink 2 frames whose CRC is good are handled here, in stream
        order: ids not accepted are dropped undecoded, ``raw_ids`` are handed over as bytes, others are
        decoded (a signed link refuses those that must be signed). From the first byte that is not such a
        frame on (signed frames too), or while pymavlink's parser holds bytes, the rest goes to that
        parser (`_parse_slow`)."""
        good: list[Any] = []
        n = len(data)
        # (no such frame first, or the parser holds bytes: all to the parser at once)
        if n < 12 or data[0] != MAVLINK_V2_MAGIC or data[2] or not self._parser_empty:
            if n or not self._parser_empty:
                self._parse_slow(data, good, time_s)
            return good
        if data.__class__ is not bytes:
            data = bytes(data)  # (its slices are the frames handed on)
        leading, stats, recorder, crc = self._leading, self.stats, self.recorder, _mcrf4xx
        if recorder is not None and time_s is None:
            time_s = self.clock.now_s()
        i = 0
        while True:
            end = i + 12 + data[i + 1]  # (the incompatibility flags are 0: no signature)
            if end > n:
                break
            known = leading.get(data[i + 7 : i + 10])  # (the message id, 24 bits little-endian)
            if known is None:
                break  # an unknown id: pymavlink counts it
            extra, kind = known
            # the CRC (from 0xFFFF) of header and payload, then CRC_EXTRA, compared with the frame's (low
            # byte first)
            if crc(data[i + 1 : end - 2] + extra) != data[end - 2] | data[end - 1] << 8:
                break  # a bad frame: pymavlink counts it
            if kind == _REFUSE:
                stats.unsigned_refused += 1
            else:
                frame = data if end == n and not i else data[i:end]  # (one frame read: no copy of it)
                if kind == _IGNORE:
                    stats.frames_ignored += 1
                else:
                    good.append(frame if kind == _RAW else decode_frame(frame))
                    stats.frames_received += 1
                if recorder is not None:
                    recorder.record(frame, time_s)  # type: ignore[arg-type]
            i = end
            if i + 12 > n or data[i] != MAVLINK_V2_MAGIC or data[i + 2]:
                break
        if i < n:
            self._parse_slow(data[i:] if i else data, good, time_s)
        return good

    def _parse_slow(self, data: bytes, good: list[MAVLinkMessage], time_s: float | None = None) -> None:
        """pymavlink's parser on ``data``; good messages appended to ``good`` (recorded at ``time_s``, see
        `feed`)."""
        try:
            msgs = self._parser.parse_buffer(data) or []
        except Exception:  # pymavlink raising on input it should have flagged: drop what it holds
            self.stats.malformed += 1
            self._parser = self._new_parser()
            self._parser_empty = True
            return
        self._parser_empty = self._parser.buf_len() == 0
        now_s = self.clock.now_s() if time_s is None else time_s
        signing = self._signing
        for m in msgs:
            if isinstance(m, mavlink2.MAVLink_bad_data):
                self._count_bad(m)
            elif isinstance(m, mavlink2.MAVLink_unknown):
                self.stats.unknown_msg_id += 1
            elif signing and self._refused(bytes(m.get_msgbuf()), m.get_msgId()):
                continue
            else:
                self.stats.frames_received += 1
                if self.recorder is not None:
                    self.recorder.record(bytes(m.get_msgbuf()), now_s)
                good.append(m)

    def _count_bad(self, m: Any) -> None:
        reason = str(m.reason)
        if reason == "Bad prefix":
            self.stats.garbage_bytes += len(m.data)
        elif reason.startswith("invalid MAVLink CRC"):
            self.stats.bad_crc += 1
        else:
            self.stats.malformed += 1

    def _refused(self, frame: bytes, msg_id: int) -> bool:
        """On a signed link: whether ``frame`` (CRC checked) is refused, counted by kind. A good
        signature moves its stream's timestamp, as the MAVLink signing spec says; nothing else does."""
        stats = self.stats
        if frame[0] != MAVLINK_V2_MAGIC or not frame[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
            if msg_id in self._unsigned_ok:
                return False
            stats.unsigned_refused += 1
            return True
        signing = self._mav.signing
        if hashlib.sha256(signing.secret_key + frame[:-6]).digest()[:6] != frame[-6:]:
            stats.bad_signature += 1
            return True
        stamp = int.from_bytes(frame[-12:-6], "little")
        stream = (frame[-SIGNATURE_BYTES], frame[5], frame[6])  # link id, system, component
        last = self._stream_stamps.get(stream)
        if last is not None and stamp <= last:
            stats.replayed += 1
            return True
        if last is None:
            self._refresh_signing_time()
            if stamp + SIGNING_NEW_STREAM_WINDOW < signing.timestamp:
                stats.stale_timestamp += 1
                return True
        self._stream_stamps[stream] = stamp
        signing.timestamp = max(signing.timestamp, stamp)  # what we sign with next is never older
        return False

    def _refresh_signing_time(self) -> None:
        stamp = int((self._signing_epoch_unix_s - SIGNING_EPOCH_UNIX_S + self.clock.now_s()) * 1e5)
        self._mav.signing.timestamp = max(self._mav.signing.timestamp, stamp, 0)


#: what `MavlinkCodec._take_leading` does with a good unsigned frame (`_leading_table`)
_REFUSE, _IGNORE, _RAW, _DECODE = range(4)
#: MAVLink's CRC-16/MCRF4XX of ``data`` continued from ``crc`` (0xFFFF to start): fastcrc's, the one
#: pymavlink itself computes with
_mcrf4xx = _fastcrc16.mcrf4xx
#: message id -> its CRC_EXTRA byte (the ids pymavlink knows), the last byte the frame's CRC covers
_CRC_EXTRA: dict[int, bytes] = {
    msg_id: bytes((cls.crc_extra,)) for msg_id, cls in mavlink2.mavlink_map.items()
}


@functools.lru_cache(maxsize=16)
def _leading_table(signing: bool, unsigned_ok: frozenset[int], accept: frozenset[int] | None,
                   raw: frozenset[int]) -> dict[bytes, tuple[bytes, int]]:
    """A codec's `MavlinkCodec._take_leading` table: each id pymavlink knows, as its three bytes on the
    wire -> (its CRC_EXTRA byte, what is done with a good unsigned frame of it: refused on a signing link
    when the id must be signed, dropped undecoded when not accepted, handed over as bytes, or decoded).
    Built once for each set of rules (a run builds codecs of the same rules): the codecs only read it."""

    def kind(msg_id: int) -> int:
        if signing and msg_id not in unsigned_ok:
            return _REFUSE
        if accept is not None and msg_id not in accept:
            return _IGNORE
        return _RAW if msg_id in raw else _DECODE

    return {msg_id.to_bytes(3, "little"): (extra, kind(msg_id)) for msg_id, extra in _CRC_EXTRA.items()}


def frame_ok(frame: bytes) -> bool:
    """Whether ``frame`` is one whole MAVLink 2 or 1 frame (signature included) of an id pymavlink knows,
    its length as its header says and its CRC good (the signature is not judged)."""
    if not frame or frame_size(frame, 0) != len(frame):
        return False
    if frame[0] == MAVLINK_V2_MAGIC:
        msg_id, crc_at = frame[7] | frame[8] << 8 | frame[9] << 16, 10 + frame[1]
    else:
        msg_id, crc_at = frame[5], 6 + frame[1]
    extra = _CRC_EXTRA.get(msg_id)
    if extra is None:
        return False
    return _mcrf4xx(extra, _mcrf4xx(frame[1:crc_at], 0xFFFF)) == frame[crc_at] | frame[crc_at + 1] << 8


#: a MAVLink 2 header after its start byte: length, incompatibility and compatibility flags (both 0: pad
#: bytes), sequence, system, component, message id (24 bits: low 16, high 8)
_V2_HEADER_TAIL = struct.Struct("<B2xBBBHB")
_V2_START = bytes((MAVLINK_V2_MAGIC,))
_CRC_BYTES = struct.Struct("<H")  # the frame's CRC, low byte first


def encode_frame(msg_id: int, payload: bytes, seq: int, system_id: int, component_id: int) -> bytes:
    """An unsigned MAVLink 2 frame of ``payload`` (full length; trailing zeros are trimmed to one byte
    at least, as MAVLink 2 does), byte for byte what pymavlink makes of the same message."""
    body = payload.rstrip(b"\x00") or payload[:1]
    covered = _V2_HEADER_TAIL.pack(len(body), seq, system_id, component_id, msg_id & 0xFFFF,
                                   msg_id >> 16) + body
    # MAVLink's CRC-16/MCRF4XX (from 0xFFFF, fastcrc's default) of header and payload, then CRC_EXTRA:
    # one call on the joined bytes
    return _V2_START + covered + _CRC_BYTES.pack(_mcrf4xx(covered + _CRC_EXTRA[msg_id]))


#: pymavlink's parser, for its public `decode` of single frames
_DECODER = mavlink2.MAVLink(None)


def message_from_payload(msg_id: int, payload: bytes) -> MAVLinkMessage:
    """The pymavlink message of ``payload`` (zero-padded or cut to the message's size, as pymavlink
    does); KeyError for an unknown id."""
    size = mavlink2.mavlink_map[msg_id].unpacker.size
    return decode_frame(encode_frame(msg_id, bytes(payload[:size]), 0, 0, 0))


def decode_frame(frame: bytes) -> MAVLinkMessage:
    """The message of one complete, unsigned MAVLink 2 frame whose CRC has been checked, with the header,
    payload and buffer pymavlink's parser gives it."""
    return _DECODER.decode(bytearray(frame))


#: the first byte of every MAVLink 2 and 1 frame
START_BYTES = frozenset({MAVLINK_V2_MAGIC, MAVLINK_V1_MAGIC})


def good_frame_at(data: bytes, j: int) -> bytes | None:
    """The whole, CRC-checked MAVLink frame that starts at ``data[j]``, or None."""
    size = frame_size(data, j)
    frame = data[j : j + size]
    return frame if size > 0 and frame_ok(frame) else None


def describe_frame(frame: bytes) -> tuple[str, str, str, dict[str, Any]]:
    """A captured (CRC-checked) frame read for a person: message type, sender ('fc': the autopilot
    component; else 'peer'), one line and the fields; a frame pymavlink cannot read is UNDECODED."""
    try:
        msg = decode_frame(frame)
    except Exception as exc:  # a frame pymavlink cannot read: say so, go on
        return "UNDECODED", "?", f"MAVLink frame not decoded ({type(exc).__name__}): {frame.hex(' ')}", {}
    sender = "fc" if msg.get_srcComponent() == mav.MAV_COMP_ID_AUTOPILOT1 else "peer"
    fields = {k: v for k, v in msg.to_dict().items() if k != "mavpackettype"}
    fields.update(src_system=msg.get_srcSystem(), src_component=msg.get_srcComponent(), seq=msg.get_seq(),
                  signed=bool(frame[0] == 0xFD and frame[2] & mav.MAVLINK_IFLAG_SIGNED))
    return msg.get_type(), sender, "MAVLink " + str(msg), fields


# --- frames: world ENU / body FLU inside, NED / FRD on the wire ------------------------------
_SQRT_HALF = math.sqrt(0.5)
_Q_ENU_NED = np.array([0.0, _SQRT_HALF, _SQRT_HALF, 0.0])  # pi about (x+y): swaps NED <-> ENU
_Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])  # pi about x: swaps FLU <-> FRD


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a*b of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _canonical(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_enu_flu_to_ned_frd(q_wxyz: np.ndarray) -> np.ndarray:
    """Body(FLU)->world(ENU) attitude -> body(FRD)->world(NED) attitude, (w, x, y, z)."""
    return _canonical(quat_multiply(quat_multiply(_Q_ENU_NED, np.asarray(q_wxyz, float)), _Q_FLU_FRD))


def quat_enu_flu_to_ned_frd_tuple(
    w: float, x: float, y: float, z: float
) -> tuple[float, float, float, float]:
    """`quat_enu_flu_to_ned_frd` in plain floats, for the per-tick paths (unit, w >= 0)."""
    s = _SQRT_HALF
    sw, sx, sy, sz = s * w, s * x, s * y, s * z
    qw, qx, qy, qz = -(sw + sz), -sx - sy, sy - sx, -(sw - sz)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qw < 0:
        n = -n
    return qw / n, qx / n, qy / n, qz / n


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """A world vector ENU -> NED (the same map both ways)."""
    return np.array([v[1], v[0], -v[2]])


ned_to_enu = enu_to_ned


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """A body vector FLU -> FRD (the same map both ways)."""
    return np.array([v[0], -v[1], -v[2]])


frd_to_flu = flu_to_frd


def euler_from_quat(q_wxyz: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad; aerospace Z-Y-X) of a (w, x, y, z) attitude in its own frames."""
    w, x, y, z = q_wxyz
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    sin_pitch = 2.0 * (w * y - z * x)
    # (clamped to -1..1 as max(-1.0, min(1.0, sin_pitch)) does, a NaN to 1.0, without the two calls)
    sin_pitch = sin_pitch if sin_pitch < 1.0 else 1.0
    pitch = math.asin(sin_pitch if sin_pitch > -1.0 else -1.0)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """(w, x, y, z) of aerospace Z-Y-X Euler angles (rad)."""
    return np.array(quat_from_euler_tuple(roll_rad, pitch_rad, yaw_rad))


def quat_from_euler_tuple(
    roll_rad: float, pitch_rad: float, yaw_rad: float
) -> tuple[float, float, float, float]:
    """`quat_from_euler` as plain floats."""
    half = roll_rad / 2
    cr, sr = math.cos(half), math.sin(half)
    half = pitch_rad / 2
    cp, sp = math.cos(half), math.sin(half)
    half = yaw_rad / 2
    cy, sy = math.cos(half), math.sin(half)
    # (cr * cp * cy is (cr * cp) * cy: each pair's product made once)
    crcp, srsp, srcp, crsp = cr * cp, sr * sp, sr * cp, cr * sp
    return crcp * cy + srsp * sy, srcp * cy - crsp * sy, crsp * cy + srcp * sy, crcp * sy - srsp * cy


def quat_ned_frd_from_euler(
    roll_rad: float, pitch_rad: float, yaw_rad: float
) -> tuple[float, float, float, float]:
    """The attitude of aerospace Z-Y-X Euler angles of body FLU -> world ENU (rad) as body FRD -> world NED
    (w, x, y, z; unit, w >= 0): `quat_enu_flu_to_ned_frd_tuple` of `quat_from_euler_tuple`."""
    w, x, y, z = quat_from_euler_tuple(roll_rad, pitch_rad, yaw_rad)
    return quat_enu_flu_to_ned_frd_tuple(w, x, y, z)


# --- PX4 custom modes (HEARTBEAT.custom_mode) ------------------------------------------------
PX4_MAIN_MANUAL = 1
PX4_MAIN_ALTCTL = 2
PX4_MAIN_POSCTL = 3
PX4_MAIN_AUTO = 4
PX4_MAIN_ACRO = 5
PX4_MAIN_OFFBOARD = 6
PX4_MAIN_STABILIZED = 7
PX4_AUTO_TAKEOFF = 2
PX4_AUTO_LOITER = 3  # "Hold"
PX4_AUTO_RTL = 5
PX4_AUTO_LAND = 6


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4's custom_mode word: main mode in bits 16..23, sub mode in bits 24..31."""
    return (main_mode & 0xFF) << 16 | (sub_mode & 0xFF) << 24


def px4_mode_parts(custom_mode: int) -> tuple[int, int]:
    """(main mode, sub mode) of a PX4 custom_mode word."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF

