"""LinkTrack-style UWB frames (NodeFrame0-like) and the mocap payload they carry: encoder, streaming
decoder with resynchronisation. Link layer: imports neither `emulator` nor `policies`.

Frame (all integers little-endian), see docs/mocap-link-format.md:

    0x55 0x02 | frame_len u16 | role u8 | id u8 | reserved[4] | node_count u8 |
    node_count x [role u8 | id u8 | data_len u16 | data] | checksum u8 (sum of all preceding bytes)

Mocap payload (the data of one node):

    0x4D 'M' | version u8 | frame_no u32 | body_count u8 |
    body_count x [body_id u8 | flags u8 (bit 0 valid) | stamp_us u64 | pos f32[3] (m, ENU) |
                  quat f32[4] (w, x, y, z; body FLU -> world ENU)] | crc16 u16 (CCITT-FALSE over the payload)

The 8-bit sum of the frame lets about one corrupt frame in 256 through; the payload's CRC-16 is the
second line of defence, so a corrupt frame is never accepted as a pose.
"""

from __future__ import annotations

import binascii
import math
import struct
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

HEADER = 0x55
FUNCTION_NODE_FRAME0 = 0x02
_FRAME_START = bytes((HEADER, FUNCTION_NODE_FRAME0))
FIXED_LEN = 11  # header, function, length, role, id, reserved[4], node count
NODE_HEADER_LEN = 4  # role, id, data length
MAX_NODE_DATA = 224  # bytes of data one node may carry
MAX_NODES = 16  # nodes one frame may hold (this emulator's limit; a frame stays under 4 kB)
MAX_FRAME_LEN = FIXED_LEN + MAX_NODES * (NODE_HEADER_LEN + MAX_NODE_DATA) + 1

ROLE_NODE = 0
ROLE_ANCHOR = 1
ROLE_TAG = 2
ROLE_CONSOLE = 3

PAYLOAD_TYPE_MOCAP = 0x4D  # 'M'
PAYLOAD_VERSION = 1
_PAYLOAD_HEAD = struct.Struct("<BBIB")  # type, version, frame_no, body_count
_PAYLOAD_HEAD_LEN = _PAYLOAD_HEAD.size
_PAYLOAD_COUNT_AT = _PAYLOAD_HEAD_LEN - 1  # (body_count: the head's last byte)
_BODY = struct.Struct("<BBQ3f4f")  # body_id, flags, stamp_us, pos, quat
BODY_LEN = _BODY.size  # 38 bytes
MAX_BODIES = (MAX_NODE_DATA - _PAYLOAD_HEAD.size - 2) // BODY_LEN  # 5 bodies in one node
FLAG_VALID = 0x01

#: body ids both sides agree on; other ids are allowed and reported by number
BODY_IDS: dict[str, int] = {"vehicle": 1, "gap": 2}
BODY_NAMES: dict[int, str] = {v: k for k, v in BODY_IDS.items()}


_Parsed = TypeVar("_Parsed")


class FrameError(ValueError):
    """A frame or payload cannot be encoded or decoded (out of range, malformed, bad CRC)."""


# --- checksums -----------------------------------------------------------------------------------
def sum8(data: bytes) -> int:
    """The frame checksum: 8-bit sum of ``data``.

    Up to 256 bytes the sum is below Adler-32's modulus (65521), so the C Adler-32's low half is 1 +
    the plain sum."""
    if len(data) <= 256:
        return ((zlib.adler32(data) & 0xFFFF) - 1) & 0xFF
    return sum(data) & 0xFF


CRC16_INIT = 0xFFFF
_crc_hqx = binascii.crc_hqx  # (CRC-16/CCITT-FALSE's poly and no reflection: `crc16_ccitt`)
_isfinite = math.isfinite


def crc16_ccitt(data: bytes, crc: int = CRC16_INIT) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection) of ``data``."""
    return _crc_hqx(data, crc)


# --- frames --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Node:
    """One node block of a frame: the sending radio's role and id, and its data (<= 224 bytes)."""

    role: int
    node_id: int
    data: bytes


@dataclass(frozen=True)
class NodeFrame:
    """A NodeFrame0-like frame: the receiving module's role and id, and the nodes it heard."""

    role: int
    module_id: int
    nodes: tuple[Node, ...]


def _u8(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise FrameError(f"{name} must be an integer 0..255, got {value!r}")
    return value


def encode_frame(frame: NodeFrame) -> bytes:
    """The bytes of ``frame``, checksum included. Raises FrameError when a field is out of range."""
    if len(frame.nodes) > MAX_NODES:
        raise FrameError(f"a frame holds at most {MAX_NODES} nodes, got {len(frame.nodes)}")
    if len(frame.nodes) == 1:
        node = frame.nodes[0]
        return encode_node_frame(node.data, frame.role, frame.module_id, node.role, node.node_id)
    body = bytearray()
    for node in frame.nodes:
        if len(node.data) > MAX_NODE_DATA:
            raise FrameError(f"node {node.node_id}: data is {len(node.data)} bytes, limit {MAX_NODE_DATA}")
        body += struct.pack("<BBH", _u8("node role", node.role), _u8("node id", node.node_id), len(node.data))
        body += node.data
    length = FIXED_LEN + len(body) + 1
    out = bytearray(struct.pack("<BBHBB", HEADER, FUNCTION_NODE_FRAME0, length,
                                _u8("role", frame.role), _u8("module id", frame.module_id)))
    out += bytes(4)
    out.append(len(frame.nodes))
    out += body
    out.append(sum8(out))
    return bytes(out)


#: the bytes of a one-node frame before its data: header, function, frame length, role, module id,
#: reserved[4], node count (1), then the node's role, id and data length
_ONE_NODE_HEAD = struct.Struct("<BBHBB4xBBBH")
_ONE_NODE_DATA_AT = _ONE_NODE_HEAD.size  # 15: where a one-node frame's data starts
ONE_NODE_EXTRA_BYTES = _ONE_NODE_HEAD.size + 1  # a one-node frame's bytes besides its data (checksum too)


def _one_node_head(data_len: int, role: int, module_id: int, node_role: int, node_id: int
                   ) -> tuple[bytes, int]:
    """The bytes of a one-node frame before its ``data_len`` bytes of data, and their sum. Raises
    FrameError when a field is out of range."""
    if data_len > MAX_NODE_DATA:
        raise FrameError(f"node {node_id}: data is {data_len} bytes, limit {MAX_NODE_DATA}")
    raw = _ONE_NODE_HEAD.pack(HEADER, FUNCTION_NODE_FRAME0, FIXED_LEN + NODE_HEADER_LEN + data_len + 1,
                              _u8("role", role), _u8("module id", module_id), 1, _u8("node role", node_role),
                              _u8("node id", node_id), data_len)
    return raw, sum(raw)


#: (data length, role, module id, node role, node id) -> `_one_node_head` of them
_ONE_NODE_HEADS: dict[tuple[int, int, int, int, int], tuple[bytes, int]] = {}
_BYTE = tuple(bytes((b,)) for b in range(256))


def encode_node_frame(
    data: bytes, role: int = ROLE_TAG, module_id: int = 0, node_role: int = ROLE_ANCHOR, node_id: int = 0
) -> bytes:
    """The bytes of a frame holding one node with ``data`` (<= 224 bytes): what `encode_frame` makes of
    ``NodeFrame(role, module_id, (Node(node_role, node_id, data),))``, without building the objects.
    Raises FrameError when a field is out of range."""
    key = (len(data), role, module_id, node_role, node_id)
    head = _ONE_NODE_HEADS.get(key)
    if head is None or not (role.__class__ is module_id.__class__ is node_role.__class__
                            is node_id.__class__ is int):  # 1.0 == 1 as a key, but is no byte
        if len(_ONE_NODE_HEADS) > 256:
            _ONE_NODE_HEADS.clear()
        head = _ONE_NODE_HEADS[key] = _one_node_head(*key)
    return b"".join((head[0], data, _BYTE[(head[1] + sum8(data)) & 0xFF]))


def _node_spans(buf: bytes | bytearray | memoryview, start: int = 0) -> list[tuple[int, int]]:
    """(offset of the node header, data length) of each node of the complete, checked frame at ``start``."""
    pos, out = start + FIXED_LEN, []
    for _ in range(buf[start + 10]):
        dlen = buf[pos + 2] | buf[pos + 3] << 8
        out.append((pos, dlen))
        pos += NODE_HEADER_LEN + dlen
    return out


def _node_data(buf: bytes | bytearray | memoryview, start: int = 0) -> tuple[bytes, ...]:
    """The data of each node of the complete, checked frame at ``start``: `_parse_frame` without the
    objects."""
    if buf[start + 10] == 1:  # header at 11 (role, id, data length at 13), data from 15
        at = start + 15
        data = buf[at : at + (buf[start + 13] | buf[start + 14] << 8)]
        return (data if data.__class__ is bytes else bytes(data),)
    return tuple(bytes(buf[p + NODE_HEADER_LEN : p + NODE_HEADER_LEN + n])
                 for p, n in _node_spans(buf, start))


def _parse_frame(buf: bytes | bytearray | memoryview, start: int = 0) -> NodeFrame:
    """Split the complete, checksum-verified frame at ``start`` into nodes (structure already checked)."""
    data = _node_data(buf, start)
    spans = _node_spans(buf, start)
    nodes = tuple(Node(buf[p], buf[p + 1], d) for (p, _), d in zip(spans, data, strict=True))
    return NodeFrame(role=buf[start + 4], module_id=buf[start + 5], nodes=nodes)


def decode_frame(data: bytes) -> NodeFrame:
    """Decode exactly one frame; raises FrameError naming what is wrong."""
    dec = FrameDecoder()
    frames = dec.feed(data)
    if len(frames) != 1 or dec.buffered or dec.stats.bytes_skipped:
        raise FrameError(
            f"not exactly one valid frame ({len(frames)} decoded, {dec.stats.bad_checksum} bad checksum, "
            f"{dec.stats.bytes_skipped} bytes skipped, {dec.buffered} left over)"
        )
    return frames[0]


#: `FrameDecoder._check`'s verdicts on a frame that is not (yet) good: more bytes needed, lengths that do
#: not add up, a bad checksum (a good frame's verdict is its length, > 0)
_WAIT, _BAD_STRUCTURE, _BAD_CHECKSUM = 0, -1, -2


@dataclass
class DecoderStats:
    """Decoder counters: frames accepted, bad checksums, bad structure, resyncs, bytes thrown away."""

    frames_ok: int = 0
    bad_checksum: int = 0
    bad_structure: int = 0  # a header was found but lengths or node count did not add up
    resyncs: int = 0  # times the decoder had to hunt for the next header
    bytes_skipped: int = 0
    bytes_in: int = 0
    bytes_ok: int = 0  # bytes in accepted frames; bytes_in = bytes_ok + bytes_skipped + buffered


@dataclass
class FrameDecoder:
    """Streaming decoder: feed it any chunks of bytes, get complete valid frames back.

    On a bad header, impossible lengths or a bad checksum it drops one byte and searches for the next
    0x55 0x02, so a corrupt frame never hides the good frame behind it. Every byte it receives ends up
    either in an accepted frame or in ``stats.bytes_skipped`` (or still buffered).
    """

    stats: DecoderStats = field(default_factory=DecoderStats)
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _hunting: bool = field(default=False, repr=False)

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def count_good(self, nbytes: int, frames: int) -> None:
        """Count ``frames`` good frames of ``nbytes`` in all read by someone else (a compiled reader of
        the usual frames, `good_mocap_frame`) where this decoder held nothing, as `feed` counts them."""
        stats = self.stats
        stats.bytes_in += nbytes
        stats.frames_ok += frames
        stats.bytes_ok += nbytes
        self._hunting = False

    def feed(self, data: bytes) -> list[NodeFrame]:
        """Add ``data``; return the frames completed by it, in order."""
        return self._decode(data, _parse_frame)

    def feed_node_data(self, data: bytes) -> list[tuple[bytes, ...]]:
        """`feed`, giving only the data of each node (in order) of each frame completed, without
        building the frame objects; the same counters."""
        return self._decode(data, _node_data)

    def _decode(self, data: bytes, parse: Callable[[bytes | bytearray, int], _Parsed]) -> list[_Parsed]:
        """Add ``data``; return ``parse`` of each frame completed by it (the bytes and the frame's offset
        in them), in order."""
        stats = self.stats
        stats.bytes_in += len(data)
        held = self._buf
        if held:
            held += data
            buf = held
        else:  # (the usual case: read from ``data`` itself, keep only what is left of it)
            buf = data if data.__class__ is bytes else bytes(data)  # (a view has no `find`)
        out: list[_Parsed] = []
        n = len(buf)
        start = 0
        check = self._check
        while start < n:  # (at n: nothing left to look at, no header to hunt for)
            if not buf.startswith(_FRAME_START, start):  # (both header bytes there, in one C call)
                start = self._find_header(buf, start)  # (a frame starting right here skips nothing)
            avail = n - start
            if avail < FIXED_LEN:
                break
            length = check(buf, start, avail)  # (a good frame's length, else a verdict <= 0)
            if length > 0:
                out.append(parse(buf, start))  # (no copy of the frame)
                stats.frames_ok += 1
                stats.bytes_ok += length
                self._hunting = False
                start += length
                continue
            if length == _WAIT:
                break
            if length == _BAD_CHECKSUM:
                stats.bad_checksum += 1
            else:
                stats.bad_structure += 1
            self._skip(1)
            start += 1
        if buf is held:
            del held[:start]
        elif start < n:
            held += buf[start:]
        return out

    def _skip(self, n: int) -> None:
        if not self._hunting:
            self.stats.resyncs += 1
            self._hunting = True
        self.stats.bytes_skipped += n

    def _find_header(self, buf: bytes | bytearray, start: int) -> int:
        """Index of the next possible frame start at or after ``start`` (skipped bytes counted)."""
        n = len(buf)
        i = start
        while i < n:
            j = buf.find(HEADER, i)
            if j < 0:
                self._skip_range(n - i)
                return n
            if j + 1 < n and buf[j + 1] != FUNCTION_NODE_FRAME0:
                self._skip_range(j + 1 - i)
                i = j + 1
                continue
            self._skip_range(j - i)
            return j
        return n

    def _skip_range(self, n: int) -> None:
        if n > 0:
            self._skip(n)

    @staticmethod
    def _check(buf: bytes | bytearray, start: int, avail: int) -> int:
        """The length of the good frame at ``start``, else `_WAIT` (need more bytes), `_BAD_STRUCTURE`
        or `_BAD_CHECKSUM`."""
        length = buf[start + 2] | (buf[start + 3] << 8)
        n_nodes = buf[start + 10]
        if length <= FIXED_LEN or length > MAX_FRAME_LEN or n_nodes > MAX_NODES:
            return _BAD_STRUCTURE
        # walk the node headers as far as they are buffered: their lengths must add up to the frame's
        pos, end, have = start + FIXED_LEN, start + length - 1, start + avail
        while n_nodes:
            data_at = pos + NODE_HEADER_LEN
            if data_at > end:
                return _BAD_STRUCTURE
            if data_at > have:
                return _WAIT
            dlen = buf[pos + 2] | (buf[pos + 3] << 8)
            if dlen > MAX_NODE_DATA:
                return _BAD_STRUCTURE
            pos = data_at + dlen
            n_nodes -= 1
        if pos != end:
            return _BAD_STRUCTURE
        if avail < length:
            return _WAIT
        if sum8(buf[start:end]) != buf[end]:  # (a slice's copy is cheaper than a view of it)
            return _BAD_CHECKSUM
        return length


# --- mocap payload -------------------------------------------------------------------------------
@dataclass(frozen=True)
class BodySample:
    """One tracked rigid body in a mocap frame: position (m, ENU), attitude (w, x, y, z), mocap time (s)."""

    body_id: int
    stamp_s: float
    pos_m: tuple[float, float, float]
    quat_wxyz: tuple[float, float, float, float]
    valid: bool = True

    @property
    def name(self) -> str:
        """'vehicle', 'gap', or 'body<N>' for other ids."""
        return BODY_NAMES.get(self.body_id, f"body{self.body_id}")


@dataclass(frozen=True)
class MocapPacket:
    """A mocap frame as carried in one node's data: frame number and the bodies seen."""

    frame_no: int
    bodies: tuple[BodySample, ...]


def encode_mocap_payload(packet: MocapPacket) -> bytes:
    """The node data for ``packet`` (<= 224 bytes, <= 5 bodies). Timestamps are sent in whole us."""
    return encode_mocap_rows(
        packet.frame_no, [(b.body_id, b.valid, b.stamp_s, (*b.pos_m, *b.quat_wxyz)) for b in packet.bodies]
    )


#: the payload's fields before the CRC, by body count (the decoder's unpack)
_PAYLOAD_BODIES = tuple(struct.Struct("<BBIB" + "BBQ3f4f" * n) for n in range(MAX_BODIES + 1))


def _crc16_table() -> np.ndarray:
    """CRC-16/CCITT-FALSE (the same CRC as `crc16_ccitt`) of each byte value alone from a zero register."""
    out = []
    for b in range(256):
        crc = b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
        out.append(crc & 0xFFFF)
    table = np.array(out, dtype=np.int64)
    table.flags.writeable = False
    return table


#: CRC-16/CCITT-FALSE of each byte value: the table `pack_mocap_frame` and `crc16_at` run the CRC by (an
#: array: compiled, a constant that compiles in a quarter of the time a tuple's 256 items take)
CRC16_TABLE = _crc16_table()


#: values `pack_mocap_frame` takes per body: pos (3), quat (4), valid (1.0 or 0.0)
PACKED_VALUES = 8


def pack_mocap_frame(out: np.ndarray, frame_no: int, n: int, ints: np.ndarray, values: np.ndarray) -> int:
    """Write the mocap payload of ``n`` bodies and what follows it into the one-node frame ``out``
    (uint8, its head already there: `MocapFrameEncoder.head`): the payload's fields (``frame_no``, then
    per body ``b`` its id and stamp (us) ``ints[2 b : 2 b + 2]`` and its values ``values[8 b : 8 b + 8]``:
    7 sent as float32, then the valid flag, nonzero if valid), its CRC and the frame's checksum (the sum
    of every byte before it); returns the frame's length. The only packer of the format: plain
    arithmetic on arrays, run as it is by `MocapFrameEncoder.encode` and compiled into the emulator's
    exposure kernel. Fields are not checked here (the callers do)."""
    p = _ONE_NODE_DATA_AT
    out[p] = PAYLOAD_TYPE_MOCAP
    out[p + 1] = PAYLOAD_VERSION
    for j in range(4):
        out[p + 2 + j] = (frame_no >> (8 * j)) & 0xFF
    out[p + 6] = n
    p += _PAYLOAD_HEAD_LEN
    floats = np.empty(7, np.float32)  # (a body's values as float32, C's rounding; their bytes below)
    float_bytes = floats.view(np.uint8)
    for b in range(n):
        r = PACKED_VALUES * b
        out[p] = ints[2 * b]
        out[p + 1] = FLAG_VALID if values[r + 7] != 0.0 else 0
        s = int(ints[2 * b + 1])
        for j in range(8):
            out[p + 2 + j] = (s >> (8 * j)) & 0xFF
        for j in range(7):
            floats[j] = values[r + j]
        out[p + 10 : p + BODY_LEN] = float_bytes
        p += BODY_LEN
    crc = CRC16_INIT
    for i in range(_ONE_NODE_DATA_AT, p):
        crc = ((crc << 8) & 0xFFFF) ^ int(CRC16_TABLE[((crc >> 8) ^ int(out[i])) & 0xFF])
    out[p] = crc & 0xFF
    out[p + 1] = crc >> 8
    p += 2
    total = 0
    for i in range(p):
        total += int(out[i])
    out[p] = total & 0xFF
    return p + 1


class MocapFrameEncoder:
    """Mocap rows straight to the bytes of a one-node frame carrying their payload, for one receiving
    module (``role``, ``module_id``) and one sending node (``node_role``, ``node_id``): what
    `encode_node_frame` makes of `encode_mocap_rows`, in one call. Raises FrameError as they do."""

    __slots__ = ("_heads",)

    def __init__(self, role: int = ROLE_TAG, module_id: int = 0, node_role: int = ROLE_ANCHOR,
                 node_id: int = 0) -> None:
        # by body count: the bytes before the payload in the frame
        self._heads = tuple(_one_node_head(s.size + 2, role, module_id, node_role, node_id)[0]
                            for s in _PAYLOAD_BODIES)

    def head(self, n_bodies: int) -> bytes:
        """The bytes of the frame of ``n_bodies`` bodies before its payload (`pack_mocap_frame` writes
        the rest)."""
        return self._heads[n_bodies]

    def encode(self, frame_no: int, rows: Sequence[tuple[int, bool, float, Sequence[float]]]) -> bytes:
        """The frame of the payload of ``rows`` (body id, valid, stamp_s, 7 values: pos (m) then quat
        (w, x, y, z)); timestamps are sent in whole us."""
        n = len(rows)
        if n > MAX_BODIES:
            raise FrameError(f"a mocap payload holds at most {MAX_BODIES} bodies, got {n}")
        if not 0 <= frame_no <= 0xFFFFFFFF:
            raise FrameError(f"frame_no must fit in 32 bits, got {frame_no}")
        ids, ints, values = [], [], []
        for body_id, valid, stamp_s, body_values in rows:
            # a finite sum means every value is finite (inf and NaN propagate); else look closer
            if len(body_values) != 7 or not (_isfinite(sum(body_values))
                                             or all(_isfinite(v) for v in body_values)):
                raise FrameError(f"body {body_id}: position and quaternion must be 3 + 4 finite numbers")
            if not 0 <= stamp_s < 1.8e13:
                raise FrameError(f"body {body_id}: stamp_s must be >= 0, got {stamp_s}")
            if body_id.__class__ is not int or not 0 <= body_id <= 0xFF:
                _u8("body id", body_id)
            ids.append(body_id)
            ints += (body_id, round(stamp_s * 1e6))
            values += body_values
            values.append(1.0 if valid else 0.0)
        head = self._heads[n]
        out = np.zeros(mocap_frame_len(n), np.uint8)
        out[: len(head)] = np.frombuffer(head, np.uint8)
        packed = np.array(values, np.float64)
        with np.errstate(over="ignore"):
            fits = np.isfinite(packed.astype(np.float32)).reshape(n, PACKED_VALUES).all(axis=1)
        if not fits.all():  # (as a C cast rounds: past float32's range is inf)
            raise FrameError(f"body {ids[int(np.argmin(fits))]}: a value is out of float32's range")
        pack_mocap_frame(out, frame_no, n, np.array(ints, np.int64), packed)
        return out.tobytes()


_MOCAP_FRAMES = MocapFrameEncoder()


def encode_mocap_rows(frame_no: int, rows: Sequence[tuple[int, bool, float, Sequence[float]]]) -> bytes:
    """`encode_mocap_payload` of rows (body id, valid, stamp_s, 7 values: pos (m) then quat (w, x, y,
    z)), without building the packet: the same bytes and the same FrameErrors (the data of
    `MocapFrameEncoder`'s frame)."""
    return _MOCAP_FRAMES.encode(frame_no, rows)[_ONE_NODE_DATA_AT:-1]


#: values `unpack_mocap_payload` gives per body: id, flags, stamp (us), position (3), quaternion (4)
BODY_VALUES = 10


def unpack_mocap_payload(data: bytes) -> tuple[Any, ...]:
    """The fields of node data written by ``encode_mocap_payload``, flat: type, version, frame_no,
    body count, then `BODY_VALUES` per body (body_id, flags, stamp_us, x, y, z, qw, qx, qy, qz), for
    readers that need numbers only. Raises FrameError as `decode_mocap_payload` does."""
    size = len(data)
    if size < _PAYLOAD_HEAD_LEN + 2:
        raise FrameError(f"mocap payload too short ({size} bytes)")
    kind, version, count = data[0], data[1], data[_PAYLOAD_COUNT_AT]  # (`_PAYLOAD_HEAD`'s fields)
    if kind != PAYLOAD_TYPE_MOCAP:
        raise FrameError(f"not a mocap payload (type 0x{kind:02X})")
    if version != PAYLOAD_VERSION:
        raise FrameError(f"mocap payload version {version} not supported (want {PAYLOAD_VERSION})")
    if size != _PAYLOAD_HEAD_LEN + count * BODY_LEN + 2:
        raise FrameError(f"mocap payload of {size} bytes does not hold {count} bodies")
    if _crc_hqx(data[:-2], CRC16_INIT) != data[-2] | data[-1] << 8:
        raise FrameError("mocap payload CRC mismatch")
    if count <= MAX_BODIES:
        return _PAYLOAD_BODIES[count].unpack_from(data)
    values = list(_PAYLOAD_HEAD.unpack_from(data))
    for k in range(count):
        values += _BODY.unpack_from(data, _PAYLOAD_HEAD.size + k * BODY_LEN)
    return tuple(values)


def decode_mocap_payload(data: bytes) -> MocapPacket:
    """Parse node data written by ``encode_mocap_payload``; raises FrameError if it is not one."""
    values = unpack_mocap_payload(data)
    bodies = []
    for k in range(4, len(values), BODY_VALUES):
        body_id, flags, stamp_us, *vals = values[k:k + BODY_VALUES]
        bodies.append(BodySample(body_id=body_id, stamp_s=stamp_us * 1e-6, pos_m=tuple(vals[:3]),
                                 quat_wxyz=tuple(vals[3:]), valid=bool(flags & FLAG_VALID)))
    return MocapPacket(frame_no=values[2], bodies=tuple(bodies))


# --- a mocap frame read where it lies, in numba-compilable style: plain Python here (the link layer compiles
# nothing), compiled by the onboard side that calls them (its mocap intake); the checks are those of
# `FrameDecoder` and `unpack_mocap_payload` for the one frame shape they take, and a frame they refuse is
# left to those


#: where a one-node frame's data (the mocap payload) starts, and where its bodies start in the payload
MOCAP_PAYLOAD_AT = FIXED_LEN + NODE_HEADER_LEN
MOCAP_BODIES_AT = _PAYLOAD_HEAD_LEN


def crc16_at(buf: bytes, start: int, end: int) -> int:
    """`crc16_ccitt` of ``buf[start:end]``, read in place."""
    crc = CRC16_INIT
    for i in range(start, end):
        crc = ((crc << 8) & 0xFFFF) ^ CRC16_TABLE[((crc >> 8) ^ buf[i]) & 0xFF]
    return crc


def u32_at(buf: bytes, at: int) -> int:
    """The little-endian u32 at ``at``. (Compiled, a byte is a uint8 and would shift as a uint64, which
    mixed with an int64 makes a float: each is made an int64 with ``+ 0`` first, here and below.)"""
    return (buf[at] + 0) | (buf[at + 1] + 0) << 8 | (buf[at + 2] + 0) << 16 | (buf[at + 3] + 0) << 24


def f32_at(buf: bytes, at: int) -> float:
    """The little-endian IEEE binary32 at ``at``, as the float it is (struct's "<f")."""
    bits = u32_at(buf, at)
    exponent, mantissa = (bits >> 23) & 0xFF, bits & 0x7FFFFF
    if exponent == 0xFF:
        value = math.inf if mantissa == 0 else math.nan
    elif exponent == 0:
        value = math.ldexp(float(mantissa), -149)
    else:
        value = math.ldexp(float(mantissa | 0x800000), exponent - 150)
    return -value if bits >> 31 else value


def good_mocap_frame(buf: bytes, start: int, end: int) -> int:
    """The length of the frame at ``start`` when ``buf[start:end]`` holds all of it and it is a good
    one-node frame (header, lengths, checksum) whose data is a good mocap payload (type, version, size,
    CRC), else 0 (not such a frame, or not yet all there: `FrameDecoder` and `unpack_mocap_payload` say
    which)."""
    if end - start < MOCAP_PAYLOAD_AT or buf[start] != HEADER or buf[start + 1] != FUNCTION_NODE_FRAME0 \
            or buf[start + 10] != 1:
        return 0
    length = (buf[start + 2] + 0) | (buf[start + 3] + 0) << 8
    size = (buf[start + 13] + 0) | (buf[start + 14] + 0) << 8  # the node's data, the payload
    if size > MAX_NODE_DATA or length != MOCAP_PAYLOAD_AT + size + 1 or length > end - start:
        return 0
    last = start + length - 1
    total = 0
    for i in range(start, last):
        total += buf[i]
    if total & 0xFF != buf[last]:
        return 0
    p = start + MOCAP_PAYLOAD_AT
    if size < _PAYLOAD_HEAD_LEN + 2 or buf[p] != PAYLOAD_TYPE_MOCAP or buf[p + 1] != PAYLOAD_VERSION \
            or size != _PAYLOAD_HEAD_LEN + (buf[p + _PAYLOAD_COUNT_AT] + 0) * BODY_LEN + 2:
        return 0
    if crc16_at(buf, p, last - 2) != ((buf[last - 2] + 0) | (buf[last - 1] + 0) << 8):
        return 0
    return length


def encode_mocap_frame(packet: MocapPacket, module_id: int = 0, node_id: int = 0) -> bytes:
    """A whole frame carrying ``packet`` as the data of one anchor node (the mocap station's radio)."""
    return encode_node_frame(encode_mocap_payload(packet), ROLE_TAG, module_id, ROLE_ANCHOR, node_id)


def mocap_frame_len(n_bodies: int) -> int:
    """Bytes on the wire of a mocap frame with ``n_bodies`` bodies."""
    return FIXED_LEN + NODE_HEADER_LEN + _PAYLOAD_HEAD.size + n_bodies * BODY_LEN + 2 + 1
