"""The motion-capture system: tracks rigid bodies (vehicle, gap) at a fixed rate with camera and
processing latency, position and attitude noise and occlusion dropouts. Seeded; world ENU, SI units."""

from __future__ import annotations

import heapq
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from emulator.kernel_cache import entry
from hil.link.linktrack import (
    MAX_BODIES,
    PACKED_VALUES,
    FrameError,
    MocapFrameEncoder,
    mocap_frame_len,
    pack_mocap_frame,
)

MIN_RATE_HZ = 100.0
MAX_RATE_HZ = 360.0
MAX_CATCH_UP_S = 0.5  # exposures further behind than this are skipped, not replayed
TRACKED_LIMIT_M = 1000.0  # a body further than this from the origin on any axis is not seen (m)
_BLOCK = 256  # random draws taken ahead at once
_F64 = np.dtype(np.float64)
#: a measured body as the exposure kernel writes it: x, y, z (m), qw, qx, qy, qz, valid (1.0 or 0.0), as
#: the LinkTrack packer takes it
_VALUES_PER_BODY = PACKED_VALUES


def _noise_room(n: int) -> int:
    """How many standard normal draws the exposure kernel's buffer holds for ``n`` bodies: a block drawn
    ahead, or one frame's draws (at most 6 a body)."""
    return max(_BLOCK, 6 * n)


def optitrack_latency_s(rate_hz: float) -> float:
    """Camera latency of an OptiTrack-class system at ``rate_hz`` (s): 5.56 ms up to 180 Hz,
    4.17 ms up to 240 Hz, 2.78 ms up to 360 Hz (published figures, stepped between them)."""
    if rate_hz <= 180.0:
        return 5.56e-3
    if rate_hz <= 240.0:
        return 4.17e-3
    return 2.78e-3


@dataclass(frozen=True)
class BodyPose:
    """A rigid body's true pose: position (m, ENU) and attitude body->world (w, x, y, z)."""

    pos_m: np.ndarray
    quat_wxyz: np.ndarray


def pose_of(obj: object) -> BodyPose:
    """The pose of ``obj``: a position from ``pos_m`` (or ``centre_m``, as a gap has) and an attitude
    from ``quat_wxyz`` (attribute or method). Raises TypeError naming what is missing."""
    pos = getattr(obj, "pos_m", None)
    if pos is None:
        pos = getattr(obj, "centre_m", None)
    quat = getattr(obj, "quat_wxyz", None)
    if callable(quat):
        quat = quat()
    if pos is None or quat is None:
        raise TypeError(f"{type(obj).__name__} has no pose: need pos_m (or centre_m) and quat_wxyz")
    return BodyPose(pos_m=np.asarray(pos, dtype=float).reshape(3),
                    quat_wxyz=np.asarray(quat, dtype=float).reshape(4))


@dataclass(frozen=True)
class MocapConfig:
    """Tracker settings. ``latency_s`` None takes the OptiTrack camera figure for ``rate_hz``."""

    rate_hz: float = 120.0
    latency_s: float | None = None  # camera latency (s); None: optitrack_latency_s(rate_hz)
    processing_s: float = 0.5e-3  # mean extra processing latency (s), exponentially distributed
    pos_noise_m: float = 0.2e-3  # position noise, std per axis (m)
    att_noise_rad: float = 1.0e-3  # attitude noise, std per axis of a small rotation (rad)
    occlusion_prob: float = 0.0  # chance per frame and body that an occlusion starts
    occlusion_mean_s: float = 0.05  # mean occlusion length (s), exponentially distributed

    def __post_init__(self) -> None:
        if not MIN_RATE_HZ <= self.rate_hz <= MAX_RATE_HZ:
            raise ValueError(
                f"mocap rate_hz must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}], got {self.rate_hz}")
        for name in ("processing_s", "pos_noise_m", "att_noise_rad", "occlusion_mean_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"mocap {name} must be finite and >= 0, got {v}")
        if self.latency_s is not None and not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ValueError(f"mocap latency_s must be finite and >= 0, got {self.latency_s}")
        if not 0.0 <= self.occlusion_prob <= 1.0:
            raise ValueError(f"mocap occlusion_prob must be in [0, 1], got {self.occlusion_prob}")

    @property
    def camera_latency_s(self) -> float:
        """The fixed part of the latency (s)."""
        return optitrack_latency_s(self.rate_hz) if self.latency_s is None else self.latency_s

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class TrackedBody:
    """One body in a mocap frame: measured pose, or ``valid`` False while it is occluded."""

    body_id: int
    pos_m: np.ndarray
    quat_wxyz: np.ndarray
    valid: bool


@dataclass(frozen=True)
class MocapFrame:
    """A frame: exposure time ``stamp_s`` (mocap time), when it leaves the mocap PC ``ready_s``, bodies."""

    frame_no: int
    stamp_s: float
    ready_s: float
    bodies: tuple[TrackedBody, ...]


#: a body of a frame as plain values: body id, valid, stamp_s, the 7 values pos_m (3) then quat_wxyz (4)
_Row = tuple[int, bool, float, list[float]]


class FrameRows(NamedTuple):
    """A frame as plain values, what the mocap link encodes: per body (body id, valid, stamp_s, the 7
    values pos_m (3) then quat_wxyz (4)); an occluded body has zeros and the identity."""

    frame_no: int
    stamp_s: float
    ready_s: float
    rows: list[tuple[int, bool, float, list[float]]]


def frame_of(rows: FrameRows) -> MocapFrame:
    """The `MocapFrame` of ``rows``."""
    return MocapFrame(
        frame_no=rows.frame_no,
        stamp_s=rows.stamp_s,
        ready_s=rows.ready_s,
        bodies=tuple(TrackedBody(body_id, np.array(v[:3]), np.array(v[3:]), valid)
                     for body_id, valid, _, v in rows.rows),
    )


@dataclass
class MocapStats:
    frames: int = 0
    bodies_occluded: int = 0  # body-frames reported invalid
    frames_skipped: int = 0  # exposures not taken because update() came too late


def _pose_arrays(obj: object) -> tuple[np.ndarray, np.ndarray]:
    """(pos_m (3,), quat_wxyz (4,)) float arrays of ``obj``, as `pose_of` reads them; a VehicleState's
    own read-only arrays are used as they are."""
    pos = getattr(obj, "pos_m", None)
    quat = getattr(obj, "quat_wxyz", None)
    if (
        pos.__class__ is np.ndarray
        and quat.__class__ is np.ndarray
        and pos.shape == (3,)
        and quat.shape == (4,)
        and (pos.dtype is _F64 or pos.dtype == _F64)
        and (quat.dtype is _F64 or quat.dtype == _F64)
    ):
        return pos, quat
    pose = pose_of(obj)
    return pose.pos_m, pose.quat_wxyz


class MocapSystem:
    """Samples true poses on its frame grid (k / rate_hz) and releases frames after their latency.

    Scheduler-friendly: call ``update(now_s, truth)`` at any times; each exposure due by ``now_s`` is
    taken from the truth given in that call (sample and hold), and frames whose latency has passed are
    returned. ``next_event_s()`` says when to call next.
    """

    def __init__(self, config: MocapConfig, rng: np.random.Generator,
                 frames: MocapFrameEncoder | None = None) -> None:
        """With ``frames`` each exposure is kept as the bytes of its LinkTrack frame, as that encoder
        writes it (frame number modulo 2**32, up to `MAX_BODIES` bodies), encoded by the exposure
        kernel itself: `released` gives them in place of rows, and the rows' readers (`update`,
        `update_rows`, `release_rows`) are refused."""
        self.config = config
        self._frames = frames
        self._rng = rng
        self._next_exposure_k = 0
        #: the frames exposed and not yet released: (ready_s, frame number, rows or the frame's bytes), a
        #: heap (its head the next release; read, never changed, by the mocap link)
        self.pending: list[tuple[float, int, list[_Row] | bytes]] = []
        self._occluded_until: dict[int, float] = {}
        self.stats = MocapStats()
        self._period_s = config.period_s
        self._latency_s = config.camera_latency_s
        #: how many standard normal draws the kernel's buffer holds (without occlusion: a block taken ahead,
        #: the noise being the generator's only use besides the processing latency's, one call per block,
        #: not per frame), and the next one to use
        self._noise_len = 0
        self._normal_next = 0
        self._noise = np.zeros(0)
        self._exp_block: list[float] = []
        self._exp_next = 0
        self._pos_sd, self._att_sd = float(config.pos_noise_m), float(config.att_noise_rad)
        self._occlusion_prob, self._processing_s = config.occlusion_prob, config.processing_s
        self._buffers_for(2)
        # the exposure kernel's form for its buffer (uint8 bytes, whatever their size), compiled or loaded
        # from numba's cache now, not at the first exposure, and called without numba's type dispatch
        self._expose = entry(_expose_kernel, self._mem, 0, 0.0, 0.0, 0, 0, 0, 0, 0)

    def _buffers_for(self, n: int) -> None:
        """The kernel's buffer for exposures of ``n`` bodies (`_expose_kernel`'s ``mem``), and its structs:
        the true poses in (7 doubles each) then the measured values out (`_VALUES_PER_BODY` doubles
        each), each written and read by Python in one call; then the frame's fields, the standard normal
        draws (how many it has room for, then `_noise_room` or more), the occlusion flags and the frame's
        bytes. The draws not yet used are kept."""
        if self._frames is not None and n > MAX_BODIES:
            raise ValueError(f"a LinkTrack mocap frame holds at most {MAX_BODIES} bodies, got {n}")
        self._n_bodies = n
        fields_at = (7 + _VALUES_PER_BODY) * 8 * n  # (the frame's fields, then its bytes: `_expose_kernel`)
        noise_at = fields_at + 16 * n + 8
        kept = self._noise[: self._noise_len].copy()  # (the draws of a block not used yet stay)
        room = max(_noise_room(n), len(kept))
        occluded_at = noise_at + 8 * room
        frame_at = occluded_at + n
        frame_len = mocap_frame_len(n) if self._frames is not None else 0
        self._io_buf = bytearray(frame_at + frame_len)
        self._mem = np.frombuffer(self._io_buf, np.uint8)
        np.frombuffer(self._io_buf, np.int64, 1, noise_at - 8)[0] = room
        self._noise = np.frombuffer(self._io_buf, np.float64, room, noise_at)
        self._noise[: len(kept)] = kept
        self._occluded = np.frombuffer(self._io_buf, np.uint8, n, occluded_at)
        self._put_poses = struct.Struct(f"<{7 * n}d").pack_into
        self._get_values = struct.Struct(f"<{7 * 8 * n}x{_VALUES_PER_BODY * n}d").unpack_from
        #: each body's index and its first value's
        self._rows_at = tuple((i, _VALUES_PER_BODY * i) for i in range(n))
        # the frame's fields (each body's id, then its stamp (us), set by the kernel) and its bytes (its
        # head written once), as the kernel packs them
        self._ints = np.frombuffer(self._io_buf, np.int64, 2 * n, fields_at)
        self._frame_buf = memoryview(self._io_buf)[frame_at:]
        self._frame_ids: tuple[int, ...] = ()
        if self._frames is not None:
            head = self._frames.head(n)
            self._frame_buf[: len(head)] = head

    def next_event_s(self) -> float:
        """The next time something happens: an exposure or a frame leaving (s)."""
        t = self._next_exposure_k * self._period_s
        return min(t, self.pending[0][0]) if self.pending else t

    def next_exposure_s(self) -> float:
        """When the next exposure is taken (s): the only event that needs the true poses."""
        return self._next_exposure_k * self._period_s

    def next_release_s(self) -> float:
        """When the next frame already exposed is ready (s; inf when none is waiting)."""
        return self.pending[0][0] if self.pending else math.inf

    def release_rows(self, now_s: float) -> list[FrameRows]:
        """The frames already exposed that are ready by ``now_s``, oldest first (no new exposure)."""
        if self._frames is not None:
            raise ValueError("this tracker keeps its frames as LinkTrack bytes, not rows (see `released`)")
        period = self._period_s
        return [FrameRows(k, k * period, ready_s, rows) for ready_s, k, rows in self.released(now_s)]

    def released(self, now_s: float) -> list[tuple[float, int, list[_Row] | bytes]]:
        """`release_rows` as (ready_s, frame number, rows) (the frame's stamp is its number x the
        period), without a `FrameRows` per frame; with an encoder (see ``__init__``) the frame's
        LinkTrack bytes in place of its rows (what the mocap link sends)."""
        pending = self.pending
        limit = now_s + 1e-12
        if not pending or pending[0][0] > limit:
            return []  # nothing ready yet (most calls)
        pop = heapq.heappop
        out = [pop(pending)]
        while pending and pending[0][0] <= limit:
            out.append(pop(pending))
        return out

    def update(self, now_s: float, truth: Mapping[int, object]) -> list[MocapFrame]:
        """Take the exposures due by ``now_s`` from ``truth`` (body id -> anything ``pose_of`` reads, or
        a tuple of plain floats (x, y, z (m), qw, qx, qy, qz));
        return the frames ready by then, oldest first."""
        return [frame_of(r) for r in self.update_rows(now_s, truth)]

    def update_rows(self, now_s: float, truth: Mapping[int, object]) -> list[FrameRows]:
        """`update` as plain values (no objects per body)."""
        self.expose(now_s, truth)
        return self.release_rows(now_s)

    def expose(self, now_s: float, truth: Mapping[int, object]) -> None:
        """Take the exposures due by ``now_s`` from ``truth`` (as `update`), releasing none."""
        if self._next_exposure_k * self._period_s > now_s + 1e-12:
            return  # none due (nor any to catch up: that needs ``now_s`` past the next)
        body_ids = sorted(truth)
        poses: list[float] = []
        for body_id in body_ids:
            obj = truth[body_id]
            if obj.__class__ is tuple:  # plain values: (x, y, z (m), qw, qx, qy, qz)
                if len(obj) != 7:
                    raise ValueError(f"body {body_id}: a pose of plain values is 7 numbers, got {len(obj)}")
                poses += obj
            else:
                pos, quat = _pose_arrays(obj)
                poses += pos.tolist()
                poses += quat.tolist()
        self.expose_values(now_s, body_ids, poses)

    def expose_values(self, now_s: float, body_ids: Sequence[int], poses: Sequence[float]) -> None:
        """`expose` of true poses as plain values: ``body_ids`` in increasing order and ``poses`` their
        7 values each, one body after the other (x, y, z (m), qw, qx, qy, qz)."""
        period = self._period_s
        k = self._next_exposure_k
        if now_s - k * period > MAX_CATCH_UP_S:
            # called after a long gap (or first at a late time): do not replay frames nobody could see
            skip_to = math.floor(now_s / period)
            self.stats.frames_skipped += skip_to - k
            k = self._next_exposure_k = skip_to
        if k * period > now_s + 1e-12:
            return  # none due
        n = len(body_ids)
        if n != self._n_bodies:
            self._buffers_for(n)
        frames = self._frames is not None
        if frames and body_ids is not self._frame_ids:
            self._frame_ids_for(body_ids)
        self._put_poses(self._io_buf, 0, *poses)  # (held for every exposure due: the kernel only reads it)
        mem, at = self._mem, self._rows_at
        pos_sd, att_sd, processing_s = self._pos_sd, self._att_sd, self._processing_s
        stats, latency_s, expose = self.stats, self._latency_s, self._expose
        while k * period <= now_s + 1e-12:
            # frame ``k``, exposed at ``t_s``, queued for its ready time
            t_s = k * period
            self._next_exposure_k = k + 1
            if self._occlusion_prob > 0:
                # the draws keep the order of one body after the other (occlusion, position noise,
                # attitude noise): taken here, the noise handed to the kernel in that order
                occluded, noise = self._occlusions(t_s, body_ids, poses)
                self._occluded[:] = occluded
                self._noise[: len(noise)] = noise
                n_invalid = expose(mem, n, pos_sd, att_sd, 1, len(noise), 0, k & 0xFFFFFFFF,
                                   round(t_s * 1e6))[0]
                extra = self._rng.exponential(processing_s) if processing_s > 0 else 0.0
            else:
                # without occlusion the noise of the whole frame comes from the block drawn ahead; a
                # block that cannot give it all is drawn anew (the kernel says how many draws it takes)
                frame_no, stamp_us = k & 0xFFFFFFFF, round(t_s * 1e6)
                n_invalid, nxt = expose(mem, n, pos_sd, att_sd, 0, self._noise_len, self._normal_next,
                                        frame_no, stamp_us)
                if n_invalid < 0:
                    size = self._noise_len = max(_BLOCK, nxt)
                    self._noise[:size] = self._rng.standard_normal(size)
                    n_invalid, nxt = expose(mem, n, pos_sd, att_sd, 0, size, 0, frame_no, stamp_us)
                self._normal_next = nxt
                extra = 0.0
                if processing_s > 0:  # an exponential draw from the block of standard ones drawn ahead
                    j, block = self._exp_next, self._exp_block
                    if j >= len(block):
                        block = self._exp_block = self._rng.standard_exponential(_BLOCK).tolist()
                        j = 0
                    self._exp_next = j + 1
                    extra = processing_s * block[j]
            stats.bodies_occluded += n_invalid
            stats.frames += 1
            if frames:
                heapq.heappush(self.pending, (t_s + latency_s + extra, k, bytes(self._frame_buf)))
            else:
                v = self._get_values(self._io_buf)
                rows = []
                for i, r in at:
                    rows.append((body_ids[i], v[r + 7] != 0.0, t_s, v[r : r + 7]))
                heapq.heappush(self.pending, (t_s + latency_s + extra, k, rows))
            k += 1

    def _frame_ids_for(self, body_ids: Sequence[int]) -> None:
        """Put ``body_ids`` into the frame's fields (checked: one byte each)."""
        ids = tuple(body_ids)  # (a tuple is itself: the next call with it is known by identity)
        if ids != self._frame_ids:
            for body_id in ids:
                if body_id.__class__ is not int or not 0 <= body_id <= 0xFF:
                    raise FrameError(f"body id must be an integer 0..255, got {body_id!r}")
            self._ints[::2] = ids
        self._frame_ids = ids

    def _occlusions(self, t_s: float, body_ids: list[int], poses: list[float]
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Which bodies an occlusion hides at ``t_s`` (1) and the noise of the others, drawn one body
        after the other: occlusion, then position noise, then attitude noise."""
        cfg, rng = self.config, self._rng
        n_noise = (3 if cfg.pos_noise_m > 0 else 0) + (3 if cfg.att_noise_rad > 0 else 0)
        occluded = np.zeros(len(body_ids), np.uint8)
        noise: list[float] = []
        for i, body_id in enumerate(body_ids):
            px, py, pz, qw, qx, qy, qz = poses[7 * i : 7 * i + 7]
            valid = trackable(px, py, pz, qw * qw + qx * qx + qy * qy + qz * qz)
            until = self._occluded_until.get(body_id, -1.0)
            if t_s >= until and rng.random() < cfg.occlusion_prob:
                until = self._occluded_until[body_id] = t_s + rng.exponential(cfg.occlusion_mean_s)
            if t_s < until:
                valid = False
                occluded[i] = 1
            if valid and n_noise:
                noise += rng.standard_normal(n_noise).tolist()
        return occluded, np.array(noise, dtype=np.float64)


def trackable(px: float, py: float, pz: float, sq: float) -> bool:
    """Whether the tracker sees a body at ``px, py, pz`` (m) whose attitude quaternion has the squared norm
    ``sq``: inside the tracked volume and a real attitude (NaN fails every comparison: a diverged
    simulation is reported invalid, as an occluded body is)."""
    return math.isfinite(sq) and sq > 0.25 and (
        -TRACKED_LIMIT_M <= px <= TRACKED_LIMIT_M and -TRACKED_LIMIT_M <= py <= TRACKED_LIMIT_M
        and -TRACKED_LIMIT_M <= pz <= TRACKED_LIMIT_M)


def measured_pose(px: float, py: float, pz: float, qw: float, qx: float, qy: float, qz: float, sq: float,
                  pos_sd: float, att_sd: float, z0: float, z1: float, z2: float, z3: float, z4: float,
                  z5: float) -> tuple[float, float, float, float, float, float, float]:
    """A body's pose as the tracker measures it: the position (m) plus ``pos_sd`` (m) x the standard
    normal draws ``z0..z2``, the attitude (w, x, y, z; ``sq`` its squared norm) normalised and turned by
    the small rotation whose vector is ``att_sd`` (rad) x ``z3..z5``, with w >= 0. Plain arithmetic on
    floats, compiled: the tracker's exposure kernel runs it per body and frame, the RL environment over
    its rows."""
    if pos_sd > 0:  # as normal(0, sd) makes them from the same draws: 0 + sd * z
        px += 0.0 + pos_sd * z0
        py += 0.0 + pos_sd * z1
        pz += 0.0 + pos_sd * z2
    n = math.sqrt(sq)
    aw, ax, ay, az = qw / n, qx / n, qy / n, qz / n
    if att_sd > 0:  # times the small rotation of a noise rotation vector
        rx = 0.0 + att_sd * z3
        ry = 0.0 + att_sd * z4
        rz = 0.0 + att_sd * z5
        angle = math.sqrt(rx * rx + ry * ry + rz * rz)
        if angle < 1e-12:
            bw, bx, by, bz = 1.0, 0.5 * rx, 0.5 * ry, 0.5 * rz
        else:
            sk = math.sin(0.5 * angle) / angle
            bw, bx, by, bz = math.cos(0.5 * angle), rx * sk, ry * sk, rz * sk
        aw, ax, ay, az = (aw * bw - ax * bx - ay * by - az * bz,
                          aw * bx + ax * bw + ay * bz - az * by,
                          aw * by - ax * bz + ay * bw + az * bx,
                          aw * bz + ax * by - ay * bx + az * bw)
    if aw < 0:
        aw, ax, ay, az = -aw, -ax, -ay, -az
    return px, py, pz, aw, ax, ay, az


_trackable = njit(cache=True)(trackable)
_measured_pose = njit(cache=True)(measured_pose)
_pack_mocap_frame = njit(cache=True)(pack_mocap_frame)


@njit(cache=True)
def _expose_kernel(mem: np.ndarray, n: int, pos_sd: float, att_sd: float, occlusion: int, noise_len: int,
                   k: int, frame_no: int, stamp_us: int) -> tuple[int, int]:
    """One exposure of ``n`` bodies on the bytes ``mem`` (one array: numba unboxes each array argument on
    every call), which hold ``io`` (float64, (7 + `_VALUES_PER_BODY`) ``n``), ``ints`` (int64, 2 ``n``),
    ``room`` (int64), ``noise`` (float64, ``room``, of which the first ``noise_len`` are drawn), ``occluded``
    (uint8, ``n``: read when ``occlusion`` is 1) and the rest ``frame``: the bodies' true poses (``io``'s
    first 7 ``n``, 7 each: x, y, z, qw, qx, qy, qz) as the tracker measures them, into the values after them
    (`_VALUES_PER_BODY` each: the 7, then 1.0 if valid else 0.0): `trackable` and not ``occluded``, then
    `measured_pose` with the standard normal draws ``noise[k:]``, 3 for the position when ``pos_sd`` > 0
    (m), then 3 for the attitude when ``att_sd`` > 0 (rad), body after body; an invalid body gets zeros
    and the identity.
    Returns (bodies invalid, the next draw's index), or (-1, draws the frame takes) with nothing
    measured when ``noise`` does not hold them after ``k``. With a ``frame`` (not empty: the LinkTrack
    frame's bytes, its head there) the measured bodies are packed into it too (`pack_mocap_frame`: frame
    ``frame_no``, each body stamped ``stamp_us``; ``ints`` holds the bodies' ids, the kernel their
    stamps)."""
    fields_at = (7 + _VALUES_PER_BODY) * 8 * n
    io = mem[:fields_at].view(np.float64)
    ints = mem[fields_at : fields_at + 16 * n].view(np.int64)
    noise_at = fields_at + 16 * n + 8
    occluded_at = noise_at + 8 * mem[noise_at - 8 : noise_at].view(np.int64)[0]
    noise = mem[noise_at : occluded_at].view(np.float64)[:noise_len]
    occluded = mem[occluded_at : occluded_at + n]
    frame = mem[occluded_at + n :]
    poses, values = io[: 7 * n], io[7 * n :]
    n_noise = (3 if pos_sd > 0 else 0) + (3 if att_sd > 0 else 0)
    seen = 0
    for b in range(n):
        o = 7 * b
        qw, qx, qy, qz = poses[o + 3], poses[o + 4], poses[o + 5], poses[o + 6]
        ok = _trackable(poses[o], poses[o + 1], poses[o + 2], qw * qw + qx * qx + qy * qy + qz * qz)
        if occlusion and occluded[b]:
            ok = False
        values[_VALUES_PER_BODY * b + 7] = 1.0 if ok else 0.0
        seen += ok
    if k + seen * n_noise > noise.size:
        return -1, seen * n_noise
    invalid = 0
    for b in range(n):
        o, r = 7 * b, _VALUES_PER_BODY * b
        if values[r + 7] == 0.0:
            invalid += 1
            values[r : r + 7] = 0.0
            values[r + 3] = 1.0
            continue
        z0 = z1 = z2 = z3 = z4 = z5 = 0.0
        if pos_sd > 0:
            z0, z1, z2 = noise[k], noise[k + 1], noise[k + 2]
            k += 3
        if att_sd > 0:
            z3, z4, z5 = noise[k], noise[k + 1], noise[k + 2]
            k += 3
        qw, qx, qy, qz = poses[o + 3], poses[o + 4], poses[o + 5], poses[o + 6]
        m = _measured_pose(poses[o], poses[o + 1], poses[o + 2], qw, qx, qy, qz,
                           qw * qw + qx * qx + qy * qy + qz * qz, pos_sd, att_sd, z0, z1, z2, z3, z4, z5)
        for j in range(7):
            values[r + j] = m[j]
    if frame.size:
        for b in range(n):
            ints[2 * b + 1] = stamp_us
        _pack_mocap_frame(frame, frame_no, n, ints, values)
    return invalid, k
