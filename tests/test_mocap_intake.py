"""The onboard program's mocap intake (the usual mocap bytes into the estimator and the gap's pose check in
one compiled call): the program sees the poses the reader's own path gives it, whatever the bytes (cut
frames, corrupt bytes, refused bodies, a new mocap clock), counted the same."""

from __future__ import annotations

import math

import numpy as np
from onboard_rig import rewrite_mocap

from hil.link.clock import SimClock
from hil.link.linktrack import MAX_BODIES, BodySample, MocapPacket, encode_mocap_frame
from hil.link.memory import MemoryTransport
from policies.mocap_reader import CLOCK_JUMP_FRAMES, MocapReader
from policies.onboard.estimator import PoseEstimator, StaticPoseCheck
from policies.onboard.mocap_intake import GAP_BODY_ID, VEHICLE_BODY_ID, mocap_intake

GAP_Q = (0.8660254, -0.5, 0.0, 0.0)


def _frame(k: int, t0_s: float = 0.0, extra: tuple[BodySample, ...] = ()) -> bytes:
    t = t0_s + k / 120
    vehicle = BodySample(1, t, (-2.0 + 0.3 * math.sin(k / 7), -1.0 + 0.01 * k, 0.5), (0.96, 0.0, 0.28, 0.0))
    return encode_mocap_frame(MocapPacket(k, (vehicle, BodySample(2, t, (0.0, 0.5, 2.1), GAP_Q), *extra)))


class _Side:
    """A reader feeding an estimator and a gap check, as the program wires them: through the intake, or
    through its pose callback alone."""

    def __init__(self, compiled: bool) -> None:
        self.clock = SimClock()
        self.out, end = MemoryTransport.pair()
        self.estimator = PoseEstimator(max_accel_m_s2=40.0)
        self.gap = StaticPoseCheck(0.05, math.radians(2.0))
        self.callbacks = 0
        intake = mocap_intake(self.estimator, self.gap) if compiled else None
        self.reader = MocapReader(end, self.clock, on_pose=self._on_pose, intake=intake)

    def _on_pose(self, body_id: int, stamp_s: float, pos: tuple, quat: tuple, received_s: float) -> None:
        self.callbacks += 1
        if body_id == GAP_BODY_ID:
            self.gap.update(pos, quat, received_s)
        elif body_id == VEHICLE_BODY_ID and not self.estimator.take(stamp_s, pos, quat, received_s):
            reader = self.reader
            if reader.clock_jumps != reader.intake_jumps:  # (the program's: the estimate follows the clock)
                reader.intake_jumps = reader.clock_jumps
                self.estimator.rebase(stamp_s, received_s)
                self.estimator.take(stamp_s, pos, quat, received_s)

    def send(self, data: bytes, t_s: float) -> None:
        self.clock.advance_to(t_s)
        self.out.send(data)
        self.reader.poll()


def test_the_intake_gives_the_program_what_the_readers_own_path_gives_it():
    sides = _Side(compiled=True), _Side(compiled=False)
    rng = np.random.default_rng(3)
    nan = float("nan")
    t = 0.0
    sends: list[tuple[bytes, float]] = []
    for k in range(400):
        t = k / 120 + 0.02 + float(rng.uniform(0.0, 0.004))
        data = _frame(k)
        if k % 3 == 0:  # two frames in one read
            data += _frame(k, extra=(BodySample(9, k / 120, (1.0, 1.0, 1.0), (1.0, 0.0, 0.0, 0.0)),))
        kind = k % 41
        if kind == 3:  # as many bodies as a frame holds (the intake keeps each for its second pass)
            data = _frame(k, extra=tuple(BodySample(9 + j, k / 120, (1.0, 1.0 + j, 1.0), (1.0, 0.0, 0.0, 0.0))
                                         for j in range(MAX_BODIES - 2)))
        elif kind == 5:
            data = rewrite_mocap(data, pos_m=(nan, 0.0, 0.0), body_ids=(1,))
        elif kind == 9:
            data = rewrite_mocap(data, quat_wxyz=(1.2, 0.0, 0.0, 0.0), body_ids=(2,))
        elif kind == 13:
            data = rewrite_mocap(data, stamp_us=2**62)
        elif kind == 17:
            data = rewrite_mocap(data, pos_shift_m=(0.0, 0.0, 0.3), body_ids=(2,))  # the gap moved: refused
        elif kind == 21:
            data = rewrite_mocap(data, pos_shift_m=(1.0, 0.0, 0.0), body_ids=(1,))  # a jump: implausible
        elif kind == 25:
            data = data[:30] + bytes([data[30] ^ 0x40]) + data[31:]  # corrupt: a bad checksum
        elif kind == 29:
            data = b"\x55\x02\x00" + data  # garbage before it
        elif kind == 33:
            data = encode_mocap_frame(MocapPacket(k, (BodySample(1, k / 120, (0.0, 0.0, 0.0), GAP_Q),) * 2))
        if kind == 37:  # cut in two reads
            sends += [(data[:45], t), (data[45:], t + 0.001)]
        else:
            sends.append((data, t))
    for k in range(2 * CLOCK_JUMP_FRAMES):  # the mocap restarted: its clock starts at 0 again
        t += 1 / 120
        sends.append((_frame(k), t))
    for data, at in sends:
        for side in sides:
            side.send(data, at)
    fast, plain = sides
    for a, b in ((fast.estimator, plain.estimator), (fast.gap, plain.gap)):
        assert np.array_equal(a._state, b._state, equal_nan=True)
    assert np.array_equal(fast.reader._rd, plain.reader._rd, equal_nan=True)
    assert fast.reader.counters == plain.reader.counters
    c = plain.reader.counters
    assert c.clock_jumps == 1 and c.bad_checksum >= 1 and c.bodies_non_finite and c.bodies_bad_quat
    assert c.bodies_stamp_future and c.bodies_stamp_backwards
    assert fast.gap.implausible and fast.estimator.implausible
    assert fast.estimator.updates > 300 and fast.gap.pose is not None
    assert fast.reader.latest("vehicle") is fast.reader.latest("vehicle")  # (made once a pose)
    assert repr(fast.reader.latest("vehicle")) == repr(plain.reader.latest("vehicle"))
    # most poses went through the intake: the callback saw only the others
    assert fast.callbacks < plain.callbacks / 4
