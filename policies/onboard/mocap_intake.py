"""The program's mocap intake: a chunk of the mocap link's bytes to the state estimate in one compiled call.

For the usual bytes (whole, good one-node frames whose bodies all pass the reader's quick checks) one
call of `intake_frames` does what the reader's own path does frame by frame and body by body: the frame
and its payload checked (`hil.link.linktrack.good_mocap_frame`), each body's numbers read where they lie,
checked (`policies.mocap_reader.pose_passes`) and kept (`keep_pose`), then the vehicle's pose into the
estimator (`take_pose`) and the gap's into its pose check (`static_pose_update`), as the program's
``_on_pose`` hands them on. It stops at the first frame that is not so (a bad checksum, a body refused or
to be looked at closer, a frame cut by the read): the reader reads from there on its own path, which
counts what it refuses (`MocapReader`'s ``intake``). Each function it calls is the only definition of its
computation, run as plain Python on the reader's path and compiled here (`policies.compiling`). The
estimator's, the gap check's and the reader's states live in one array (`MocapIntake`), so that a call
unpacks one array argument, not three.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from hil.link.linktrack import (
    BODY_IDS,
    BODY_LEN,
    MAX_BODIES,
    MOCAP_BODIES_AT,
    MOCAP_PAYLOAD_AT,
    crc16_at,
    f32_at,
    good_mocap_frame,
    u32_at,
)
from policies.compiling import Kernel
from policies.mocap_reader import (
    READER_FLOATS,
    REFERENCE_STEP_S,
    keep_pose,
    pose_passes,
)
from policies.onboard.estimator import (
    GAP_FLOATS,
    STATE_FLOATS,
    STATIC_POSE_UPDATE,
    TAKE_POSE,
    PoseEstimator,
    StaticPoseCheck,
    static_pose_update,
    take_pose,
)

VEHICLE_BODY_ID = BODY_IDS["vehicle"]  # the body whose poses feed the estimator
GAP_BODY_ID = BODY_IDS["gap"]  # the body whose poses feed the gap's pose check
_MIN_DELAY, _LAST_STAMP = 0, 1  # (`policies.mocap_reader`'s state: the reference delay, the latest stamps)
#: a stamp of 2^53 us or more (its high u32 this or more) is not a float's exact integer: left to the
#: reader's own path
_STAMP_HIGH_LIMIT = 1 << 21
#: a body as the intake's first pass over a frame read it, for the second (`intake_frames`): id, stamp (s),
#: position (m), quaternion (w, x, y, z) as sent and its squared norm
BODY_FLOATS = 10


def body_at(buf: bytes, at: int) -> tuple[int, int, float, float, float, float, float, float, float, float]:
    """The body record at ``at`` of a mocap payload: id, flags, stamp (s; NaN when it is 2^53 us or
    more), position (m), quaternion (w, x, y, z) as sent."""
    high = u32_at(buf, at + 6)
    stamp_s = (u32_at(buf, at + 2) | high << 32) * 1e-6 if high < _STAMP_HIGH_LIMIT else math.nan
    return (buf[at] + 0, buf[at + 1] + 0, stamp_s, f32_at(buf, at + 10), f32_at(buf, at + 14),
            f32_at(buf, at + 18), f32_at(buf, at + 22), f32_at(buf, at + 26), f32_at(buf, at + 30),
            f32_at(buf, at + 34))


def intake_frames(est: np.ndarray, gap: np.ndarray, rd: np.ndarray, bodies: np.ndarray, buf: bytes,
                  now_s: float) -> tuple[int, int]:
    """Take the mocap frames at the start of ``buf``, read at ``now_s`` (s), as far as they are whole, good
    and their bodies pass the quick checks: each body kept in the reader's state ``rd``, the vehicle's
    pose into the estimator's state ``est`` (with its settings), the gap's into its check's
    ``gap``. Returns where it stopped in ``buf`` and the frames taken. ``bodies`` (`MAX_BODIES` x
    `BODY_FLOATS`) holds a frame's bodies from the checks to their taking: each body's bytes are decoded
    once. Run compiled (`MOCAP_INTAKE`)."""
    n = len(buf)
    start = 0
    frames = 0
    while start < n:
        length = good_mocap_frame(buf, start, n)
        if length == 0:
            break
        first = start + MOCAP_PAYLOAD_AT + MOCAP_BODIES_AT
        count = buf[first - 1] + 0
        newest_s = now_s - rd[_MIN_DELAY] + REFERENCE_STEP_S
        # every body passes, each id once: the frame is taken whole, else left as it is to the reader
        for k in range(count):
            body_id, flags, stamp_s, px, py, pz, qw, qx, qy, qz = body_at(buf, first + k * BODY_LEN)
            for j in range(k):
                if buf[first + j * BODY_LEN] == body_id:
                    return start, frames
            norm2 = qw * qw + qx * qx + qy * qy + qz * qz
            if not pose_passes(flags, px + py + pz, norm2, stamp_s, rd[_LAST_STAMP + body_id], newest_s):
                return start, frames
            b = k * BODY_FLOATS  # (kept for the second pass: no second decoding)
            bodies[b], bodies[b + 1], bodies[b + 2], bodies[b + 3], bodies[b + 4] = \
                body_id, stamp_s, px, py, pz
            bodies[b + 5], bodies[b + 6], bodies[b + 7], bodies[b + 8], bodies[b + 9] = qw, qx, qy, qz, norm2
        frame_no = u32_at(buf, start + MOCAP_PAYLOAD_AT + 2)
        for k in range(count):
            b = k * BODY_FLOATS
            body_id, stamp_s, px, py, pz = int(bodies[b]), bodies[b + 1], bodies[b + 2], bodies[b + 3], \
                bodies[b + 4]
            qw, qx, qy, qz, norm2 = bodies[b + 5], bodies[b + 6], bodies[b + 7], bodies[b + 8], bodies[b + 9]
            qw, qx, qy, qz = keep_pose(rd, body_id, px, py, pz, qw, qx, qy, qz, norm2, stamp_s, now_s,
                                       frame_no)
            if body_id == VEHICLE_BODY_ID:
                take_pose(est, stamp_s, now_s, px, py, pz, qw, qx, qy, qz)
            elif body_id == GAP_BODY_ID:
                static_pose_update(gap, px, py, pz, qw, qx, qy, qz, now_s)
        frames += 1
        start += length
    return start, frames


#: where the gap check's and the reader's states and the frame's bodies start in the intake's one array
#: (`intake_state`)
_GAP_AT = STATE_FLOATS
_READER_AT = _GAP_AT + GAP_FLOATS
_BODIES_AT = _READER_AT + READER_FLOATS
INTAKE_FLOATS = _BODIES_AT + MAX_BODIES * BODY_FLOATS


def intake_state(state: np.ndarray, buf: bytes, now_s: float) -> tuple[int, int]:
    """`intake_frames` on the estimator's, the gap check's and the reader's states and the frame's bodies
    kept in the one array ``state`` (`INTAKE_FLOATS`: `STATE_FLOATS`, `GAP_FLOATS`, `READER_FLOATS`, then
    `MAX_BODIES` x `BODY_FLOATS`), so that a call unpacks one array argument instead of four. Run compiled
    (`MOCAP_INTAKE`)."""
    return intake_frames(state[:_GAP_AT], state[_GAP_AT:_READER_AT], state[_READER_AT:_BODIES_AT],
                         state[_BODIES_AT:], buf, now_s)


_U32_AT = Kernel(u32_at)
#: the mocap chunk into the reader's, the estimator's and the gap check's state, compiled: `intake_state`
MOCAP_INTAKE = Kernel(intake_state, intake_frames=Kernel(
    intake_frames, good_mocap_frame=Kernel(good_mocap_frame, crc16_at=Kernel(crc16_at)), u32_at=_U32_AT,
    body_at=Kernel(body_at, u32_at=_U32_AT, f32_at=Kernel(f32_at, u32_at=_U32_AT)),
    pose_passes=Kernel(pose_passes), keep_pose=Kernel(keep_pose), take_pose=TAKE_POSE,
    static_pose_update=STATIC_POSE_UPDATE))


class MocapIntake:
    """The intake of a `MocapReader` for an estimator and a gap check (`mocap_intake`): the three states in
    one array (`intake_state`), the reader's part of it (``reader_state``, where the reader given this
    intake keeps its poses) and ``take``, called with the bytes and their time (s): `intake_state` compiled
    for that array (no dispatch a call)."""

    def __init__(self, estimator: PoseEstimator, gap_check: StaticPoseCheck) -> None:
        self.state = np.zeros(INTAKE_FLOATS)
        estimator.keep_state_in(self.state[:_GAP_AT])
        gap_check.keep_state_in(self.state[_GAP_AT:_READER_AT])
        #: the reader's pose state (`READER_FLOATS`), which the reader sets up
        self.reader_state = self.state[_READER_AT:_BODIES_AT]
        entry = MOCAP_INTAKE.entry(self.state, b"", 0.0)
        self.take: Callable[[bytes, float], tuple[int, int]] = functools.partial(entry, self.state)


def mocap_intake(estimator: PoseEstimator, gap_check: StaticPoseCheck) -> MocapIntake:
    """The intake of `MocapReader` for ``estimator`` and ``gap_check``, whose states move into its array
    (`MocapIntake`; ask for ``estimator.state`` after this)."""
    return MocapIntake(estimator, gap_check)
