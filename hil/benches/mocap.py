"""Bench group `mocap`: LinkTrack frame parsing speed (the decoder alone, and the onboard reader with its
checks, as the program runs it), and pty latency from write to parsed pose beside the frame's wire time
at 921600 baud."""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterator

from hil.benches import BenchRow, time_per_call
from hil.link.clock import SimClock
from hil.link.linktrack import (
    BodySample,
    FrameDecoder,
    MocapPacket,
    decode_mocap_payload,
    encode_mocap_frame,
)
from hil.link.memory import MemoryTransport
from hil.link.pty import PtyTransport
from policies.mocap_reader import MocapReader
from policies.onboard.estimator import PoseEstimator, StaticPoseCheck
from policies.onboard.mocap_intake import mocap_intake

BAUD = 921600
BATCH = 100


def _frame(k: int) -> bytes:
    t = k / 120
    return encode_mocap_frame(MocapPacket(k, (
        BodySample(1, t, (-2.0 + 0.01 * k, -1.0, 0.5), (1.0, 0.0, 0.0, 0.0)),
        BodySample(2, t, (0.0, 0.5, 2.1), (0.8660254, -0.5, 0.0, 0.0)),
    )))


def _ignore_pose(*_: object) -> None:
    return None


def collect(quick: bool) -> Iterator[BenchRow]:
    stream = b"".join(_frame(k) for k in range(BATCH))

    def parse_batch() -> None:
        for frame in FrameDecoder().feed(stream):
            decode_mocap_payload(frame.nodes[0].data)

    per_batch_s = time_per_call(parse_batch, min_time_s=0.2 if quick else 1.0)
    yield BenchRow("mocap_parse_frames_per_s", BATCH / per_batch_s, "frames/s",
                   "decode + checksum + payload CRC, 2 bodies a frame")

    feed, end = MemoryTransport.pair(len(stream) + 1)
    clock = SimClock()
    clock.advance_to(BATCH / 120 + 0.03)  # every frame has arrived, the last one 30 ms after exposure

    def read_batch() -> None:
        reader = MocapReader(end, clock, on_pose=_ignore_pose)  # a new reader: stamps start afresh
        feed.send(stream)
        reader.poll()

    per_batch_s = time_per_call(read_batch, min_time_s=0.2 if quick else 1.0)
    yield BenchRow("mocap_reader_frames_per_s", BATCH / per_batch_s, "frames/s",
                   "MocapReader.poll over an in-memory link, every pose through a Python callback (the "
                   "reader's own path, as for a frame the compiled intake leaves to it), 2 bodies a frame")

    frames = [_frame(k) for k in range(BATCH)]

    def intake_batch() -> None:
        estimator = PoseEstimator(max_accel_m_s2=30.0)  # new ones: stamps and the estimate start afresh
        intake = mocap_intake(estimator, StaticPoseCheck(0.1, 0.1))
        frame_clock = SimClock()
        reader = MocapReader(end, frame_clock, on_pose=_ignore_pose, intake=intake)
        for k, frame in enumerate(frames):  # each frame read as it arrives, 30 ms after its exposure
            frame_clock.advance_to(k / 120 + 0.03)
            feed.send(frame)
            reader.poll()

    per_batch_s = time_per_call(intake_batch, min_time_s=0.2 if quick else 1.0)
    feed.close()
    end.close()
    yield BenchRow("mocap_intake_frames_per_s", BATCH / per_batch_s, "frames/s",
                   "MocapReader.poll with the onboard program's compiled intake (frames into the estimator "
                   "and the gap check), 2 bodies a frame, each read as it arrives (120 Hz), a new reader and "
                   "estimator every 100 frames")

    n = 50 if quick else 500
    delays_s = []
    with PtyTransport.create(BAUD) as link:
        reader = MocapReader.open(link.endpoint, BAUD)
        try:
            for k in range(n):
                frame = _frame(k)
                ok = reader.counters.frames_ok
                start = time.perf_counter()
                link.send(frame)
                while reader.counters.frames_ok == ok:
                    reader.poll(timeout_s=0.1)
                    if time.perf_counter() - start > 1.0:
                        break
                delays_s.append(time.perf_counter() - start)
        finally:
            reader.close()
    yield BenchRow("mocap_latency_us", statistics.median(delays_s) * 1e6, "us",
                   f"pty write -> reader parsed, median of {n}, no modelled radio or wire time")
    yield BenchRow("mocap_frame_wire_us", len(_frame(0)) * 10 / BAUD * 1e6, "us",
                   f"{len(_frame(0))} B at {BAUD} baud, 8N1 (what a real UART adds)")
