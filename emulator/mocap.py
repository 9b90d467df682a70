"""The motion-capture system: tracks rigid bodies (vehicle, gap) at a fixed rate with camera and
processing latency, position and attitude noise and occlusion dropouts. Seeded; world ENU, SI units."""

from __future__ import annotations

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
DRAW_BLOCK = 256  # random draws taken ahead at once
_F64 = np.dtype(np.float64)
#: a measured body as the exposure kernel writes it: x, y, z (m), qw, qx, qy, qz, valid (1.0 or 0.0), as
#: the LinkTrack packer takes it
_VALUES_PER_BODY = PACKED_VALUES
#: the tracker's numbers in its state (`tracker_step`): the next exposure's number, its stage (``FRESH``,
#: ``SUPPLIED`` with an occluded frame's draws given, ``MEASURED`` and not queued yet), the standard normal
#: draws in the exposure buffer (how many, the next), the exponential ones in the state (how many, the
#: next), the period, camera latency, mean processing latency (s), position and attitude noise (m, rad), an
#: occluded frame's processing latency (s), whether the generator draws each frame (occlusion: 1.0),
#: whether each frame queued is handed back (rows: 1.0), where the frame's bytes start in the exposure
#: buffer, the frames the queue has room for, the float64 words of a frame's bytes in it, then the counts
#: (frames, bodies invalid, exposures skipped)
TK_K, TK_STAGE, TK_NOISE_LEN, TK_NOISE_NEXT, TK_EXP_LEN, TK_EXP_NEXT = range(6)
TK_PERIOD, TK_LATENCY, TK_PROCESSING, TK_POS_SD, TK_ATT_SD, TK_EXTRA = range(6, 12)
TK_OCCLUSION, TK_HAND_BACK, TK_FRAME_AT, TK_ROOM, TK_SLOT_WORDS = range(12, 17)
TK_FRAMES, TK_INVALID, TK_SKIPPED = range(17, 20)
TK_LEN = 20
FRESH, SUPPLIED, MEASURED = 0.0, 1.0, 2.0
#: a queued frame's place: its status (`FREE`, `PENDING`), ready time (s), number, length (bytes)
Q_STATUS, Q_READY, Q_K, Q_BYTES = range(4)
SLOT_LEN = 4
FREE, PENDING = 0.0, 1.0
#: what `tracker_step` says: done, a frame queued (its rows to take), or what it needs to go on: a block of
#: standard normal draws, a block of exponential ones, an occluded frame's draws, room in the queue
DONE, QUEUED, NEED_NORMALS, NEED_EXPONENTIALS, NEED_OCCLUSION, NEED_ROOM = 0, 1, -1, -2, -3, -4
_FIRST_ROOM = 8  # frames the queue has room for at first (doubled when full)


def tracker_state_len(room: int, slot_words: int) -> int:
    """The length of a tracker's state (float64): its numbers (``TK_*``), the exponential draws taken ahead,
    ``room`` queued frames' places and as many frames' bytes of ``slot_words`` words each."""
    return TK_LEN + DRAW_BLOCK + room * (SLOT_LEN + slot_words)


def _noise_room(n: int) -> int:
    """How many standard normal draws the exposure kernel's buffer holds for ``n`` bodies: a block drawn
    ahead, or one frame's draws (at most 6 a body)."""
    return max(DRAW_BLOCK, 6 * n)


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

    The tracker's rules for a frame (the catch-up after a long gap, the exposures due, their noise and
    processing latency from the draws taken ahead, the queue of frames by ready time and their release)
    are one compiled step on the tracker's state (`tracker_step`, `queue_take`): the methods here run it
    and answer what it asks for (draws, an occlusion's draws, room), as a caller that composes the same
    step into a kernel of its own does (the mocap link: `answer`).
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
        #: the number of the next exposure (taken at this x the period), as the tracker's step left it in
        #: its state (set by whoever runs the step: here, or the mocap link's kernel)
        self.exposure_k = 0
        self._period_s = config.period_s
        #: the frames' rows by their place in the queue (a tracker without an encoder)
        self._rows: dict[int, list[_Row]] = {}
        self._occluded_until: dict[int, float] = {}
        self._noise = np.zeros(0)
        self._slot_words = -(-mocap_frame_len(MAX_BODIES) // 8) if frames is not None else 0
        self._grow(_FIRST_ROOM)
        tk = self.state
        tk[TK_PERIOD], tk[TK_LATENCY], tk[TK_PROCESSING] = (
            self._period_s, config.camera_latency_s, config.processing_s)
        tk[TK_POS_SD], tk[TK_ATT_SD] = config.pos_noise_m, config.att_noise_rad
        tk[TK_OCCLUSION] = 1.0 if config.occlusion_prob > 0 else 0.0
        tk[TK_HAND_BACK] = 0.0 if frames is not None else 1.0
        self._buffers_for(2)
        # the tracker's compiled step and release for its buffer and state, compiled or loaded from numba's
        # cache now, not at the first exposure, and called without numba's type dispatch
        self._step = entry(tracker_step, self._mem, tk, 0.0, 0)
        self._take = entry(queue_take, tk, 0.0)
        self._next_ready = entry(queue_next_ready, tk)

    @property
    def stats(self) -> MocapStats:
        """The tracker's counts so far (a snapshot)."""
        tk = self.state
        return MocapStats(frames=int(tk[TK_FRAMES]), bodies_occluded=int(tk[TK_INVALID]),
                          frames_skipped=int(tk[TK_SKIPPED]))

    def _grow(self, room: int) -> None:
        """The tracker's state (`tracker_state_len`) with room for ``room`` frames exposed and not yet
        released, what it held kept."""
        new = np.zeros(tracker_state_len(room, self._slot_words))
        old = getattr(self, "state", None)
        if old is not None:
            old_room = int(old[TK_ROOM])
            at = TK_LEN + DRAW_BLOCK
            new[: at + old_room * SLOT_LEN] = old[: at + old_room * SLOT_LEN]
            bytes_at, old_bytes_at = at + room * SLOT_LEN, at + old_room * SLOT_LEN
            n_words = old_room * self._slot_words
            new[bytes_at : bytes_at + n_words] = old[old_bytes_at : old_bytes_at + n_words]
        new[TK_ROOM], new[TK_SLOT_WORDS] = room, self._slot_words
        #: the tracker's state (float64, `tracker_state_len`): its numbers (``TK_*``), the exponential draws
        #: taken ahead, the frames queued (their places, then their bytes)
        self.state = new
        self._frame_bytes = memoryview(new[TK_LEN + DRAW_BLOCK + room * SLOT_LEN :].view(np.uint8))

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
        kept = self._noise[: int(self.state[TK_NOISE_LEN])].copy()  # (the draws of a block not used yet stay)
        room = max(_noise_room(n), len(kept))
        occluded_at = noise_at + 8 * room
        frame_at = occluded_at + n
        frame_len = mocap_frame_len(n) if self._frames is not None else 0
        self._io_buf = bytearray(frame_at + frame_len)
        self._mem = np.frombuffer(self._io_buf, np.uint8)
        self.state[TK_FRAME_AT] = frame_at
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
        t = self.exposure_k * self._period_s
        r = self._next_ready(self.state)
        return r if r < t else t

    def next_exposure_s(self) -> float:
        """When the next exposure is taken (s): the only event that needs the true poses."""
        return self.exposure_k * self._period_s

    def next_release_s(self) -> float:
        """When the next frame already exposed is ready (s; inf when none is waiting)."""
        return self._next_ready(self.state)

    def release_rows(self, now_s: float) -> list[FrameRows]:
        """The frames already exposed that are ready by ``now_s``, oldest first (no new exposure)."""
        if self._frames is not None:
            raise ValueError("this tracker keeps its frames as LinkTrack bytes, not rows (see `released`)")
        period = self._period_s
        return [FrameRows(k, k * period, ready_s, rows) for ready_s, k, rows in self.released(now_s)]

    def released(self, now_s: float) -> list[tuple[float, int, list[_Row] | bytes]]:
        """`release_rows` as (ready_s, frame number, rows) (the frame's stamp is its number x the
        period), without a `FrameRows` per frame; with an encoder (see ``__init__``) the frame's
        LinkTrack bytes in place of its rows (what the mocap link sends). The earliest ready first (of
        two ready at the same time, the lower number)."""
        out: list[tuple[float, int, list[_Row] | bytes]] = []
        take, tk = self._take, self.state
        while True:
            slot, ready_s, k, n_bytes = take(tk, now_s)
            if slot < 0:
                return out
            if self._frames is not None:
                at = slot * 8 * self._slot_words
                out.append((ready_s, k, self._frame_bytes[at : at + n_bytes].tobytes()))
            else:
                out.append((ready_s, k, self._rows.pop(slot)))

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
        if self.exposure_k * self._period_s > now_s + 1e-12:
            return  # none due (nor any to catch up: that needs ``now_s`` past the next)
        self.expose_values(now_s, *self.values_of(truth))

    @staticmethod
    def values_of(truth: Mapping[int, object]) -> tuple[list[int], list[float]]:
        """``truth`` (as `update` takes it) as `expose_values` takes it: the body ids in increasing order
        and their 7 values each."""
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
        return body_ids, poses

    def expose_values(self, now_s: float, body_ids: Sequence[int], poses: Sequence[float]) -> None:
        """`expose` of true poses as plain values: ``body_ids`` in increasing order and ``poses`` their
        7 values each, one body after the other (x, y, z (m), qw, qx, qy, qz)."""
        if self.exposure_k * self._period_s > now_s + 1e-12:
            return  # none due (nor any to catch up: that needs ``now_s`` past the next)
        mem = self.lay_out(body_ids, poses)
        step, tk, n = self._step, self.state, len(body_ids)
        code, self.exposure_k, aux = step(mem, tk, now_s, n)
        while code != DONE:
            self.answer(code, self.exposure_k, aux, body_ids, poses)
            mem, tk = self._mem, self.state
            code, self.exposure_k, aux = step(mem, tk, now_s, n)

    def lay_out(self, body_ids: Sequence[int], poses: Sequence[float]) -> np.ndarray:
        """The exposure kernel's buffer (what `tracker_step` takes as ``mem``) for ``body_ids`` (in
        increasing order), holding the true poses ``poses`` (7 values a body)."""
        if len(body_ids) != self._n_bodies:
            self._buffers_for(len(body_ids))
        if self._frames is not None and body_ids is not self._frame_ids:
            self._frame_ids_for(body_ids)
        self._put_poses(self._io_buf, 0, *poses)  # (held for every exposure due: the kernel only reads it)
        return self._mem

    def answer(self, code: int, k: int, aux: int, body_ids: Sequence[int], poses: Sequence[float]) -> None:
        """Give the tracker's step what it asked for (``code``, of ``NEED_*``, or `QUEUED`), before frame
        ``k``, as `tracker_step` says: standard normal draws (a block, at least ``aux``), exponential
        draws (a block), an occluded frame's draws (its occlusions, noise and processing latency, from
        the generator body after body), more room, or the rows of the frame just queued in place
        ``aux``. The buffer (`lay_out`) and the state may be new ones after it."""
        tk = self.state
        if code == NEED_NORMALS:
            size = max(DRAW_BLOCK, aux)
            self._noise[:size] = self._rng.standard_normal(size)
            tk[TK_NOISE_LEN], tk[TK_NOISE_NEXT] = size, 0
        elif code == NEED_EXPONENTIALS:
            tk[TK_LEN : TK_LEN + DRAW_BLOCK] = self._rng.standard_exponential(DRAW_BLOCK)
            tk[TK_EXP_LEN], tk[TK_EXP_NEXT] = DRAW_BLOCK, 0
        elif code == NEED_OCCLUSION:
            # the draws keep the order of one body after the other (occlusion, position noise, attitude
            # noise), then the processing latency's
            occluded, noise = self._occlusions(k * self._period_s, body_ids, poses)
            self._occluded[:] = occluded
            self._noise[: len(noise)] = noise
            processing_s = self.config.processing_s
            tk[TK_EXTRA] = self._rng.exponential(processing_s) if processing_s > 0 else 0.0
            tk[TK_NOISE_LEN], tk[TK_NOISE_NEXT], tk[TK_STAGE] = len(noise), 0, SUPPLIED
        elif code == NEED_ROOM:
            self._grow(2 * int(tk[TK_ROOM]))
        elif code == QUEUED:  # (frame ``k - 1``, exposed at its time, its values still in the buffer)
            t_s, v = (k - 1) * self._period_s, self._get_values(self._io_buf)
            self._rows[aux] = [(body_ids[i], v[r + 7] != 0.0, t_s, v[r : r + 7]) for i, r in self._rows_at]
        else:
            raise ValueError(f"the tracker's step asked for {code}")

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


@njit(cache=True)
def tracker_step(mem: np.ndarray, tk: np.ndarray, now_s: float, n: int) -> tuple[int, int, int]:
    """The tracker's rules for its frames up to ``now_s`` (s), on its state ``tk`` (`tracker_state_len`:
    ``TK_*``, the exponential draws, the queue) and the exposure kernel's buffer ``mem`` (the true poses of
    ``n`` bodies there, `MocapSystem.lay_out`): an exposure more than `MAX_CATCH_UP_S` behind is skipped to
    the last one due (not replayed); each exposure due is measured (`_expose_kernel`, its standard normal
    draws from those taken ahead, or an occluded frame's given) and queued in a free place, ready after
    the camera latency and a processing latency (the mean x an exponential draw taken ahead, or an occluded
    frame's given). Returns (`DONE`, the next exposure's number, 0), or (one of ``NEED_*`` with what was
    done kept: call again once answered (`MocapSystem.answer`), the next exposure's number, the normal
    draws needed), or (`QUEUED`, the next exposure's number, the place of the frame just queued) where the
    caller takes each frame's rows (``TK_HAND_BACK``)."""
    period = tk[TK_PERIOD]
    k = int(tk[TK_K])
    if now_s - k * period > MAX_CATCH_UP_S:
        # called after a long gap (or first at a late time): do not replay frames nobody could see
        skip_to = math.floor(now_s / period)
        tk[TK_SKIPPED] += skip_to - k
        k = skip_to
        tk[TK_K] = k
    room, words = int(tk[TK_ROOM]), int(tk[TK_SLOT_WORDS])
    at = TK_LEN + DRAW_BLOCK
    slots = tk[at : at + room * SLOT_LEN]
    frames = tk[at + room * SLOT_LEN : at + room * (SLOT_LEN + words)].view(np.uint8)
    frame_at = int(tk[TK_FRAME_AT])
    n_bytes = mem.size - frame_at
    occlusion = tk[TK_OCCLUSION] != 0.0
    limit = now_s + 1e-12
    while k * period <= limit:
        # frame ``k``, exposed at ``t_s``, queued for its ready time
        t_s = k * period
        free = -1
        for s in range(room):
            if slots[s * SLOT_LEN + Q_STATUS] == FREE:
                free = s
                break
        if free < 0:
            return NEED_ROOM, k, 0
        stage = tk[TK_STAGE]
        if stage != MEASURED:
            if occlusion and stage == FRESH:
                return NEED_OCCLUSION, k, 0
            invalid, nxt = _expose_kernel(mem, n, tk[TK_POS_SD], tk[TK_ATT_SD], 1 if occlusion else 0,
                                          int(tk[TK_NOISE_LEN]), int(tk[TK_NOISE_NEXT]), k & 0xFFFFFFFF,
                                          round(t_s * 1e6))
            if invalid < 0:  # (a block that cannot give the frame's draws is drawn anew)
                return NEED_NORMALS, k, nxt
            tk[TK_NOISE_NEXT] = nxt
            tk[TK_INVALID] += invalid
            tk[TK_FRAMES] += 1
            tk[TK_STAGE] = MEASURED
        extra = 0.0
        if occlusion:
            extra = tk[TK_EXTRA]
        elif tk[TK_PROCESSING] > 0:  # an exponential draw from the block of standard ones drawn ahead
            j = int(tk[TK_EXP_NEXT])
            if j >= tk[TK_EXP_LEN]:
                return NEED_EXPONENTIALS, k, 0
            tk[TK_EXP_NEXT] = j + 1
            extra = tk[TK_PROCESSING] * tk[TK_LEN + j]
        o = free * SLOT_LEN
        slots[o + Q_STATUS], slots[o + Q_READY] = PENDING, t_s + tk[TK_LATENCY] + extra
        slots[o + Q_K], slots[o + Q_BYTES] = k, n_bytes
        if words:
            frames[free * 8 * words : free * 8 * words + n_bytes] = mem[frame_at:]
        tk[TK_STAGE] = FRESH
        k += 1
        tk[TK_K] = k
        if tk[TK_HAND_BACK] != 0.0:
            return QUEUED, k, free
    return DONE, k, 0


@njit(cache=True)
def queue_head(tk: np.ndarray, limit_s: float) -> int:
    """The place of the frame the tracker releases next by ``limit_s`` (s) (the earliest ready; of two
    ready at the same time, the lower number), or -1 when none is ready by then."""
    room = int(tk[TK_ROOM])
    at = TK_LEN + DRAW_BLOCK
    best, best_ready, best_k = -1, 0.0, 0.0
    for s in range(room):
        o = at + s * SLOT_LEN
        if tk[o + Q_STATUS] == PENDING:
            ready = tk[o + Q_READY]
            if ready <= limit_s and (best < 0 or ready < best_ready
                                     or (ready == best_ready and tk[o + Q_K] < best_k)):
                best, best_ready, best_k = s, ready, tk[o + Q_K]
    return best


@njit(cache=True)
def queue_take(tk: np.ndarray, now_s: float) -> tuple[int, float, int, int]:
    """The frame the tracker releases next by ``now_s`` (s), taken off its queue: (its place, ready time
    (s), number, length (bytes)), or (-1, 0.0, 0, 0) when none is ready (its bytes stay in its place
    until the next exposure)."""
    s = queue_head(tk, now_s + 1e-12)
    if s < 0:
        return -1, 0.0, 0, 0
    o = TK_LEN + DRAW_BLOCK + s * SLOT_LEN
    tk[o + Q_STATUS] = FREE
    return s, tk[o + Q_READY], int(tk[o + Q_K]), int(tk[o + Q_BYTES])


@njit(cache=True)
def queue_next_ready(tk: np.ndarray) -> float:
    """When the next frame already exposed is ready (s; inf when none is waiting)."""
    at = TK_LEN + DRAW_BLOCK
    nxt = math.inf
    for s in range(int(tk[TK_ROOM])):
        o = at + s * SLOT_LEN
        if tk[o + Q_STATUS] == PENDING and tk[o + Q_READY] < nxt:
            nxt = tk[o + Q_READY]
    return nxt
