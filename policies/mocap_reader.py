"""The onboard mocap reader: LinkTrack-style frames from a serial device, pty or UDP socket -> the latest
vehicle and gap poses, with their mocap timestamps, arrival times, ages and a stale flag.

A pose is taken only when it is plausible; each refusal is counted by kind in ``reader.counters``:
flagged not valid (occluded), a position or quaternion that is not finite, a quaternion whose norm is
off 1 by more than `QUAT_NORM_TOL`, a stamp more than `MAX_STAMP_LEAD_S` ahead of what the arrival
times allow (the reference is the smallest arrival-minus-stamp seen so far, followed in steps of
`REFERENCE_STEP_S`: the two clocks need not agree, but they advance together), and a stamp not after
the body's latest. A jump of the mocap clock
itself (or a bad first stamp that became the reference) is believed once `CLOCK_JUMP_FRAMES` frames
in a row agree with it: stamps increasing, arrival-minus-stamp within `MAX_STAMP_LEAD_S` of each other.

    reader = MocapReader.open("/dev/pts/6")
    while True:
        reader.poll(timeout_s=0.01)
        pose = reader.latest("vehicle")     # PoseSample or None; reader.is_stale("vehicle")

Run ``python -m policies.mocap_reader DEVICE`` to print the poses live.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hil.link.clock import Clock, WallClock
from hil.link.endpoint import open_link
from hil.link.linktrack import (
    BODY_IDS,
    BODY_NAMES,
    BODY_VALUES,
    FIXED_LEN,
    FLAG_VALID,
    NODE_HEADER_LEN,
    FrameDecoder,
    FrameError,
    unpack_mocap_payload,
)
from hil.link.transport import LinkError, Transport

DEFAULT_BAUD = 921600
DEFAULT_STALE_AFTER_S = 0.1
READ_BYTES = 65536  # one read takes up to this much
#: a read shorter than this emptied the link (a tty hands over at most its 4 KiB line buffer per read)
SHORT_READ_BYTES = 4000
LOCKSTEP_COUNT_MASK = 0x7FFFFFFF  # the lockstep harness counts the mocap bytes it wrote mod 2^31
#: a quaternion whose norm is further than this from 1 is refused (float32 on the wire: ~1e-7)
QUAT_NORM_TOL = 0.01
#: a stamp this much (s) ahead of the arrival times' reference is refused as from the future
MAX_STAMP_LEAD_S = 0.5
#: the reference arrival-minus-stamp is lowered when a pose comes this much (s) quicker than it (not
#: at every new minimum: frames read together share one arrival time and would each set one)
REFERENCE_STEP_S = 0.05
#: frames in a row that agree on a new mocap clock (refused until then) before it is believed
CLOCK_JUMP_FRAMES = 10
_NORM2_LO, _NORM2_HI = (1.0 - QUAT_NORM_TOL) ** 2, (1.0 + QUAT_NORM_TOL) ** 2
_Vec3 = tuple[float, float, float]
_Quat = tuple[float, float, float, float]
#: the reader's pose state in one array (`READER_FLOATS`): the smallest arrival minus stamp (s) of an
#: accepted pose (the reference for future stamps), the stamp (s) of each body id's latest accepted pose
#: (-inf: none yet), and each body id's latest valid pose, `POSE_FLOATS` each: position (m), unit
#: quaternion (w, x, y, z), stamp_s, received_s (-inf: none yet), frame_no
_MIN_DELAY, _LAST_STAMP, _POSES = 0, 1, 257
BODY_ID_COUNT = 256  # (a body id is one byte)
POSE_FLOATS = 10
_STAMP, _RECEIVED, _FRAME_NO = 7, 8, 9  # (in a pose's row)
READER_FLOATS = _POSES + BODY_ID_COUNT * POSE_FLOATS


@dataclass(frozen=True)
class PoseSample:
    """A body's pose as received: position (m, ENU), attitude body->world (w, x, y, z), the mocap
    exposure time ``stamp_s`` (mocap clock) and the arrival time ``received_s`` (reader clock)."""

    name: str
    body_id: int
    pos_m: np.ndarray
    quat_wxyz: np.ndarray
    stamp_s: float
    received_s: float
    frame_no: int

    @property
    def latency_s(self) -> float:
        """Arrival minus exposure (s); meaningful when both sides share a clock (lockstep, or one host
        with synchronised clocks)."""
        return self.received_s - self.stamp_s

    def age_s(self, now_s: float) -> float:
        """Time since arrival (s) at ``now_s`` on the reader's clock."""
        return now_s - self.received_s


@dataclass
class ReaderCounters:
    """What the reader has seen (frames, bytes)."""

    frames_ok: int = 0  # frames with a good checksum and a good mocap payload
    bad_checksum: int = 0
    bad_structure: int = 0  # header found but lengths did not add up
    bad_payload: int = 0  # good checksum, but not a valid mocap payload (CRC, type, size)
    bytes_bad_payload: int = 0  # bytes of the frames counted in bad_payload
    resyncs: int = 0
    bytes_skipped: int = 0
    bytes_in: int = 0
    bodies_invalid: int = 0  # body records flagged not valid (occluded)
    bodies_non_finite: int = 0  # position or quaternion NaN or infinite
    bodies_bad_quat: int = 0  # quaternion norm off 1 by more than QUAT_NORM_TOL
    bodies_stamp_future: int = 0  # stamp more than MAX_STAMP_LEAD_S ahead of the arrival times
    bodies_stamp_backwards: int = 0  # stamp not after the body's latest accepted one
    clock_jumps: int = 0  # new mocap clocks believed (CLOCK_JUMP_FRAMES frames agreeing on it)


class Intake(Protocol):
    """A compiled consumer of a reader's usual bytes (`MocapReader`'s ``intake``; the onboard program's is
    `policies.onboard.mocap_intake.MocapIntake`)."""

    #: the array (`READER_FLOATS`) the reader keeps its pose state in, which ``take`` reads and writes
    reader_state: np.ndarray
    #: called with the bytes and the time they are stamped with (s): where it stopped, the frames taken
    take: Callable[[bytes, float], tuple[int, int]]


class MocapReader:
    """Reads mocap frames from ``transport``; keeps the latest valid pose of each body (the checks a pose
    passes are in the module docstring).

    ``stale_after_s``: a body whose latest valid pose arrived longer ago than this is stale.
    ``on_sample``: called with every valid PoseSample as it is parsed (for logs, estimators).
    ``on_pose``: called with the numbers of every valid pose as it is parsed (then, with ``on_sample``
    unset, a PoseSample is made only when `latest` asks for it): body id, mocap time ``stamp_s``,
    position (m), unit quaternion (w, x, y, z) and arrival time (s), as the PoseSample would hold them.
    ``intake``: the same consumer compiled, for the usual bytes (whole good frames whose bodies pass the
    checks): its ``reader_state`` is the array (`READER_FLOATS`) this reader keeps its pose state in, and
    its ``take``, called with the bytes and the time they are stamped with, takes the frames from the
    start that it can, keeps their poses there as this reader's own path would (`keep_pose`) and hands
    them on, and returns where it stopped and the frames taken;
    the reader reads the rest itself (``on_pose`` then gets those poses). It is used only while it has
    followed every clock jump the reader believed (``intake_jumps``, set by its owner) and never with
    ``on_sample``.
    """

    def __init__(
        self,
        transport: Transport,
        clock: Clock | None = None,
        stale_after_s: float = DEFAULT_STALE_AFTER_S,
        on_sample: Callable[[PoseSample], None] | None = None,
        on_pose: Callable[[int, float, _Vec3, _Quat, float], None] | None = None,
        intake: Intake | None = None,
    ) -> None:
        if not (math.isfinite(stale_after_s) and stale_after_s > 0):
            raise ValueError(f"stale_after_s must be > 0, got {stale_after_s}")
        self.transport = transport
        self.clock: Clock = clock if clock is not None else WallClock()
        self.stale_after_s = stale_after_s
        self.on_sample = on_sample
        self.on_pose = on_pose
        self._decoder = FrameDecoder()
        self._feed_node_data = self._decoder.feed_node_data  # (bound once: per read)
        self._decoder_holds = False  # whether the decoder holds the start of a frame (after `_feed`'s read)
        self._bad_payload = 0
        self._bytes_bad_payload = 0
        self._frames_ok = 0
        #: refused body records by kind, as named in ReaderCounters
        self._refused = dict.fromkeys(("bodies_invalid", "bodies_non_finite", "bodies_bad_quat",
                                       "bodies_stamp_future", "bodies_stamp_backwards", "clock_jumps"), 0)
        #: the poses' state (`READER_FLOATS`): the reference delay, each body's latest stamp and pose
        self._rd = np.empty(READER_FLOATS) if intake is None else intake.reader_state
        self._rd[:] = -math.inf
        self._rd[_MIN_DELAY] = math.inf
        self._rows = self._rd[_POSES:].reshape(BODY_ID_COUNT, POSE_FLOATS)  # (a view: a body's pose)
        #: body id -> the run of refused stamps agreeing on a new clock: frames, delay (s), last stamp
        #: (s), arrival of the first (s)
        self._jump: dict[int, tuple[int, float, float, float]] = {}
        #: body id -> the PoseSample of its latest pose, once made (`latest`)
        self._samples: dict[int, PoseSample] = {}
        #: the poses' consumer compiled (`intake`), and the clock jumps it has followed
        self._intake = None if intake is None else intake.take
        self.intake_jumps = 0
        self.lockstep_short_reads = 0  # `poll_to` calls that got fewer bytes than announced
        self._lockstep_read = 0  # bytes read by `poll_to` (mod 2^31)

    @classmethod
    def open(cls, spec: str, baud: int = DEFAULT_BAUD, **kwargs: object) -> MocapReader:
        """Open ``spec``: a device or pty path ("/dev/pts/6", "/dev/ttyUSB0") at ``baud``, or a link
        spec such as "udp:HOST:PORT" (listen), "udpout:HOST:PORT", "tcpout:HOST:PORT"."""
        return cls(open_transport(spec, baud), **kwargs)  # type: ignore[arg-type]

    # --- reading -----------------------------------------------------------------------------
    def poll(self, timeout_s: float = 0.0) -> int:
        """Read what has arrived (waiting up to ``timeout_s`` for the first bytes); returns the number
        of mocap frames accepted. Never raises on bad data; raises LinkError if the link is gone."""
        accepted = 0
        data = self.transport.recv(timeout_s, READ_BYTES)
        while data:
            accepted += self._feed(data)
            # a read that did not fill the buffer took all there was: no second (empty) read
            drained = len(data) < SHORT_READ_BYTES and getattr(self.transport, "short_read_is_all", False)
            data = b"" if drained else self.transport.recv(0.0, READ_BYTES)
        return accepted

    def poll_to(self, total_bytes: int, timeout_s: float = 1.0) -> int:
        """Lockstep: read until ``total_bytes`` (mod 2^31) have been read through this method, waiting up
        to ``timeout_s`` of wall time, and no further (the next tick's bytes may follow at once): the
        harness says how many it has written in all. Returns the mocap frames accepted; a shortfall is
        counted in ``lockstep_short_reads`` and read with the next call."""
        accepted = 0
        left = (total_bytes - self._lockstep_read) & LOCKSTEP_COUNT_MASK
        deadline = None
        recv = self.transport.recv
        while left > 0:
            data = recv(0.0, left)  # (what has arrived, usually all: no clock read for a deadline)
            if not data:
                if deadline is None:
                    deadline = time.monotonic() + timeout_s
                data = recv(max(0.0, deadline - time.monotonic()), left)
                if not data:
                    self.lockstep_short_reads += 1
                    break
            left -= len(data)
            self._lockstep_read = (self._lockstep_read + len(data)) & LOCKSTEP_COUNT_MASK
            accepted += self._feed(data)
        return accepted

    def _feed(self, data: bytes) -> int:
        """Decode bytes read from the link and take the valid poses of each good mocap payload; returns
        the mocap frames accepted."""
        accepted = 0
        now_s = self.clock.now_s()  # (every pose of the read: arrived now)
        rd = self._rd
        intake = self._intake
        if (intake is not None and data.__class__ is bytes and self.on_sample is None
                and self.intake_jumps == self._refused["clock_jumps"] and not self._decoder_holds):
            end, accepted = intake(data, now_s)  # (the usual case: all of it; the state is ``rd``)
            if accepted:
                self._frames_ok += accepted
                self._decoder.count_good(end, accepted)
                if end == len(data):
                    return accepted
                data = data[end:]
        on_sample, on_pose = self.on_sample, self.on_pose
        decoded = self._feed_node_data(data)
        self._decoder_holds = self._decoder.buffered != 0  # (only this path leaves bytes held)
        for nodes in decoded:
            taken = 0
            for payload in nodes:
                try:
                    values = unpack_mocap_payload(payload)
                except FrameError:
                    self._bad_payload += 1
                    continue
                taken += 1
                self._frames_ok += 1
                frame_no = values[2]
                # a later stamp is from the future or lowers the reference
                newest_s = now_s - rd.item(_MIN_DELAY) + REFERENCE_STEP_S
                for k in range(4, len(values), BODY_VALUES):
                    body_id, flags, stamp_us, px, py, pz, qw, qx, qy, qz = values[k:k + BODY_VALUES]
                    pos_sum = px + py + pz  # NaN when a coordinate is NaN or infinite
                    norm2 = qw * qw + qx * qx + qy * qy + qz * qz  # (a NaN or infinite one fails the range)
                    stamp_s = stamp_us * 1e-6
                    last = rd.item(_LAST_STAMP + body_id)
                    if not pose_passes(flags, pos_sum, norm2, stamp_s, last, newest_s):
                        if self._refuse(body_id, flags, pos_sum, norm2, stamp_s, now_s, last):
                            continue
                        newest_s = now_s - rd.item(_MIN_DELAY) + REFERENCE_STEP_S
                    quat = keep_pose(rd, body_id, px, py, pz, qw, qx, qy, qz, norm2, stamp_s, now_s, frame_no)
                    pos = (px, py, pz)
                    if on_sample is not None:
                        sample = self._samples[body_id] = _new_sample(_body_name(body_id), body_id,
                                                                      np.array(pos), np.array(quat), stamp_s,
                                                                      now_s, frame_no)
                        on_sample(sample)
                    if on_pose is not None:
                        on_pose(body_id, stamp_s, pos, quat, now_s)
            if not taken:
                self._bytes_bad_payload += FIXED_LEN + 1 + sum(NODE_HEADER_LEN + len(d) for d in nodes)
            accepted += taken
        return accepted

    def _refuse(self, body_id: int, flags: int, pos_sum: float, norm2: float, stamp_s: float, now_s: float,
                last: float) -> bool:
        """Whether a body record that failed the quick checks of `_feed` is refused (counted by kind), or
        taken after all: a new lowest arrival-minus-stamp, or the frame that confirms a clock jump."""
        refused = self._refused
        rd = self._rd
        if not flags & FLAG_VALID:
            kind = "bodies_invalid"
        elif pos_sum - pos_sum != 0.0 or norm2 - norm2 != 0.0:
            kind = "bodies_non_finite"
        elif not _NORM2_LO <= norm2 <= _NORM2_HI:
            kind = "bodies_bad_quat"
        else:
            delay = now_s - stamp_s
            min_delay = rd.item(_MIN_DELAY)
            future = delay < min_delay - MAX_STAMP_LEAD_S < math.inf  # (none before a first pose)
            if not future and stamp_s > last:
                rd[_MIN_DELAY] = min(min_delay, delay)  # came quicker: the new reference
                return False
            if self._clock_jumped(body_id, stamp_s, delay, now_s):
                refused["clock_jumps"] += 1
                rd[_MIN_DELAY] = delay
                rd[_LAST_STAMP:_LAST_STAMP + BODY_ID_COUNT] = -math.inf
                self._jump.clear()
                return False
            kind = "bodies_stamp_future" if future else "bodies_stamp_backwards"
        refused[kind] += 1
        return True

    def _clock_jumped(self, body_id: int, stamp_s: float, delay_s: float, now_s: float) -> bool:
        """Note a refused stamp of ``body_id``; True when it completes `CLOCK_JUMP_FRAMES` in a row that
        agree on a new clock (increasing stamps, delays within `MAX_STAMP_LEAD_S`, no pose of the body
        accepted in between)."""
        run = self._jump.get(body_id)
        if run is not None:
            frames, delay0, stamp0, since_s = run
            received = self._rows[body_id].item(_RECEIVED)  # (-inf: none yet)
            if stamp_s > stamp0 and abs(delay_s - delay0) <= MAX_STAMP_LEAD_S and received < since_s:
                if frames + 1 >= CLOCK_JUMP_FRAMES:
                    return True
                self._jump[body_id] = (frames + 1, delay0, stamp_s, since_s)
                return False
        self._jump[body_id] = (1, delay_s, stamp_s, now_s)
        return False

    # --- what pilots ask -----------------------------------------------------------------------
    def latest(self, body: str | int = "vehicle") -> PoseSample | None:
        """The latest valid pose of ``body`` ("vehicle", "gap" or a body id), None if none yet."""
        body_id = _body_id(body)
        if not 0 <= body_id < BODY_ID_COUNT:
            return None
        row = self._rows[body_id]
        px, py, pz, qw, qx, qy, qz, stamp_s, received_s, frame_no = row.tolist()
        if received_s == -math.inf:
            return None
        sample = self._samples.get(body_id)
        if sample is None or (sample.stamp_s, sample.received_s, sample.frame_no) != (stamp_s, received_s,
                                                                                         frame_no):
            # (a pose kept as numbers: made a PoseSample now, once)
            sample = self._samples[body_id] = _new_sample(
                _body_name(body_id), body_id, np.array((px, py, pz)), np.array((qw, qx, qy, qz)), stamp_s,
                received_s, int(frame_no))
        return sample

    def age_s(self, body: str | int = "vehicle") -> float:
        """Seconds since ``body``'s latest valid pose arrived (inf if none yet)."""
        body_id = _body_id(body)
        if not 0 <= body_id < BODY_ID_COUNT:
            return math.inf
        return self.clock.now_s() - self._rows[body_id].item(_RECEIVED)

    def is_stale(self, body: str | int = "vehicle") -> bool:
        """True when ``body`` has no valid pose younger than ``stale_after_s``."""
        return self.age_s(body) > self.stale_after_s

    @property
    def clock_jumps(self) -> int:
        """New mocap clocks followed so far (as in `counters`, without building them)."""
        return self._refused["clock_jumps"]

    @property
    def counters(self) -> ReaderCounters:
        s = self._decoder.stats
        return ReaderCounters(
            frames_ok=self._frames_ok, bad_checksum=s.bad_checksum, bad_structure=s.bad_structure,
            bad_payload=self._bad_payload, bytes_bad_payload=self._bytes_bad_payload,
            resyncs=s.resyncs, bytes_skipped=s.bytes_skipped,
            bytes_in=s.bytes_in, **self._refused,
        )

    def close(self) -> None:
        self.transport.close()

    def __enter__(self) -> MocapReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _body_id(body: str | int) -> int:
    if isinstance(body, int):
        return body
    known = BODY_IDS.get(body)
    if known is not None:
        return known
    if body.startswith("body") and body[4:].isdigit():
        return int(body[4:])
    raise KeyError(f"unknown body {body!r}; known: {', '.join(BODY_IDS)} or body<N>")


#: body id -> name, filled as ids are seen (the same names as `BodySample.name`)
_NAMES: dict[int, str] = {}


def _body_name(body_id: int) -> str:
    name = _NAMES.get(body_id)
    if name is None:
        name = _NAMES[body_id] = BODY_NAMES.get(body_id, f"body{body_id}")
    return name


def _new_sample(name: str, body_id: int, pos_m: np.ndarray, quat_wxyz: np.ndarray, stamp_s: float,
                received_s: float, frame_no: int) -> PoseSample:
    """A PoseSample without the frozen dataclass's per-field __setattr__ calls (two per mocap frame):
    the same fields, set straight into the instance dict."""
    sample = object.__new__(PoseSample)
    sample.__dict__.update(name=name, body_id=body_id, pos_m=pos_m, quat_wxyz=quat_wxyz, stamp_s=stamp_s,
                           received_s=received_s, frame_no=frame_no)
    return sample


def pose_passes(flags: int, pos_sum: float, norm2: float, stamp_s: float, last_s: float,
                newest_s: float) -> bool:
    """The quick checks of a body record: flagged valid, its coordinates' sum ``pos_sum`` finite (m), its
    quaternion's squared norm ``norm2`` within `QUAT_NORM_TOL`, its stamp after the body's latest
    ``last_s`` and not after ``newest_s`` (s). A record failing them is looked at closer (`_refuse`).
    Plain Python, compiled too by the program's mocap intake."""
    return (flags & FLAG_VALID) != 0 and pos_sum - pos_sum == 0.0 and _NORM2_LO <= norm2 <= _NORM2_HI \
        and last_s < stamp_s <= newest_s


def keep_pose(rd: np.ndarray, body_id: int, px: float, py: float, pz: float, qw: float, qx: float,
              qy: float, qz: float, norm2: float, stamp_s: float, now_s: float,
              frame_no: int) -> tuple[float, float, float, float]:
    """A body's pose taken into the reader's state ``rd`` (`READER_FLOATS`): its stamp the body's
    latest, the pose (the quaternion of squared norm ``norm2`` made unit) its latest, arrived at
    ``now_s`` (s); returns the unit quaternion (w, x, y, z). Plain Python, compiled too by the program's
    mocap intake."""
    rd[_LAST_STAMP + body_id] = stamp_s
    norm = math.sqrt(norm2)
    qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
    r = _POSES + body_id * POSE_FLOATS
    rd[r], rd[r + 1], rd[r + 2], rd[r + 3], rd[r + 4], rd[r + 5], rd[r + 6] = px, py, pz, qw, qx, qy, qz
    rd[r + _STAMP], rd[r + _RECEIVED], rd[r + _FRAME_NO] = stamp_s, now_s, frame_no
    return qw, qx, qy, qz


def open_transport(spec: str, baud: int = DEFAULT_BAUD) -> Transport:
    """A transport for ``spec``: a device path ("/dev/pts/6"), or any link spec of
    `hil.link.endpoint` opened on the onboard side ("udp:HOST:PORT", "serial:DEVICE:BAUD", ...).
    Raises ValueError for a bad spec, LinkError when it cannot be opened."""
    if spec.startswith("/"):
        spec = f"serial:{spec}:{int(baud)}"
    return open_link(spec, "onboard")


def _euler_deg(q: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (deg, Z-Y-X) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def format_pose(name: str, sample: PoseSample | None, now_s: float) -> str:
    """One line for ``name``: position (m), roll/pitch/yaw (deg), age (ms)."""
    if sample is None:
        return f"{name:<7} (none yet)"
    r, p, y = _euler_deg(sample.quat_wxyz)
    x, yy, z = sample.pos_m
    return (f"{name:<7} pos=({x:+7.3f} {yy:+7.3f} {z:+7.3f}) m  rpy=({r:+6.1f} {p:+6.1f} {y:+6.1f}) deg  "
            f"age={sample.age_s(now_s) * 1e3:6.1f} ms")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m policies.mocap_reader",
                                     description="print mocap poses received over a LinkTrack-style link")
    parser.add_argument("device", help="/dev/pts/N, /dev/ttyUSB0, udp:HOST:PORT or udpout:HOST:PORT")
    parser.add_argument("--baud", type=int, default=DEFAULT_BAUD)
    parser.add_argument("--rate", type=float, default=10.0, help="lines printed per second")
    parser.add_argument("--count", type=int, default=0, help="stop after this many lines (0: run until ^C)")
    args = parser.parse_args(argv)
    try:
        reader = MocapReader.open(args.device, args.baud)
    except (LinkError, ValueError) as e:
        print(f"mocap_reader: {e}", file=sys.stderr)
        return 1
    lines = 0
    try:
        with reader:
            next_print = reader.clock.now_s()
            while args.count <= 0 or lines < args.count:
                reader.poll(timeout_s=0.005)
                now = reader.clock.now_s()
                if now < next_print:
                    continue
                next_print = now + 1.0 / args.rate
                c = reader.counters
                stale = [n for n in ("vehicle", "gap") if reader.is_stale(n)]
                print(f"t={now:8.3f} s  frames ok={c.frames_ok} bad={c.bad_checksum + c.bad_payload} "
                      f"skipped={c.bytes_skipped} B{'  STALE: ' + ','.join(stale) if stale else ''}")
                for name in ("vehicle", "gap"):
                    print("  " + format_pose(name, reader.latest(name), now))
                sys.stdout.flush()
                lines += 1
    except KeyboardInterrupt:
        pass
    except LinkError as e:
        print(f"mocap_reader: link lost: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
