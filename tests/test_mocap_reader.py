"""The onboard reader as a pilot uses it: `python -m policies.mocap_reader DEVICE` printing live poses
from a pty fed in real time, clear errors for devices that are not there, and implausible poses refused
and counted by kind (never taken as the latest pose)."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import numpy as np
import pytest
from onboard_rig import rewrite_mocap

from emulator.mocap import MocapConfig
from emulator.mocap_link import MocapLinkServer
from emulator.physics.state import VehicleState
from emulator.uwb import UwbConfig
from emulator.world.geometry import Gap
from hil.link.clock import SimClock, WallClock
from hil.link.linktrack import BodySample, MocapPacket, encode_mocap_frame
from hil.link.memory import MemoryTransport
from hil.link.pty import PtyTransport
from policies.mocap_reader import CLOCK_JUMP_FRAMES, MocapReader, PoseSample, main


def test_module_prints_vehicle_and_gap_poses_live():
    clock = WallClock()
    gap = Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=-np.pi / 3)
    with PtyTransport.create(921600) as transport:
        server = MocapLinkServer(transport, clock, np.random.default_rng(0), MocapConfig(rate_hz=120),
                                 UwbConfig(latency_s=0.002, jitter_s=0.0))
        proc = subprocess.Popen(
            [sys.executable, "-m", "policies.mocap_reader", transport.endpoint,
             "--count", "3", "--rate", "10"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        deadline = time.monotonic() + 20.0
        while proc.poll() is None and time.monotonic() < deadline:
            now = clock.now_s()
            server.update(now, VehicleState(time_s=now, pos_m=[-2.0, -1.0, 0.5]), gap)
            time.sleep(0.002)
        if proc.poll() is None:
            proc.kill()
        out, err = proc.communicate(timeout=5)
    assert proc.returncode == 0, err
    lines = out.splitlines()
    vehicle = [ln for ln in lines if ln.strip().startswith("vehicle")]
    gap_lines = [ln for ln in lines if ln.strip().startswith("gap")]
    assert len(vehicle) == 3 and len(gap_lines) == 3
    # the last lines show the poses once frames have arrived, to the noise (0.2 mm, 1 mrad = 0.06 deg)
    # and the printed digits (1 mm, 0.1 deg)
    for line, want in ((vehicle[-1], [-2.0, -1.0, 0.5, 0.0, 0.0, 0.0]),
                       (gap_lines[-1], [0.0, 0.5, 2.1, -60.0, 0.0, 0.0])):
        got = _numbers(line)
        assert got[:3] == pytest.approx(want[:3], abs=0.002), line
        assert got[3:] == pytest.approx(want[3:], abs=0.35), line


def _numbers(line: str) -> list[float]:
    m = re.search(r"pos=\(\s*(\S+)\s+(\S+)\s+(\S+)\) m\s+rpy=\(\s*(\S+)\s+(\S+)\s+(\S+)\) deg", line)
    assert m, f"no pose in {line!r}"
    return [float(x) for x in m.groups()]


def test_missing_device_is_a_clear_error(capsys):
    assert main(["/dev/does-not-exist-mocap"]) == 1
    assert "cannot open" in capsys.readouterr().err
    assert main(["udp:127.0.0.1:notaport"]) == 1
    assert "bad link spec" in capsys.readouterr().err


GAP_Q = (0.8660254, -0.5, 0.0, 0.0)  # rolled -60 deg


def _frame(k: int, t0_s: float = 0.0) -> bytes:
    """Mocap frame ``k`` at 120 Hz (stamps from ``t0_s``), vehicle moving along x and the gap."""
    t = t0_s + k / 120
    vehicle = BodySample(1, t, (-2.0 + 0.01 * k, -1.0, 0.5), (1.0, 0.0, 0.0, 0.0))
    return encode_mocap_frame(MocapPacket(k, (vehicle, BodySample(2, t, (0.0, 0.5, 2.1), GAP_Q))))


class _Feed:
    """A reader on an in-memory link, on a simulated clock: `send(data, t)` delivers at ``t`` (s)."""

    def __init__(self) -> None:
        self.clock = SimClock()
        self.out, end = MemoryTransport.pair()
        self.reader = MocapReader(end, self.clock, stale_after_s=0.1)

    def send(self, data: bytes, t_s: float) -> None:
        self.clock.advance_to(t_s)
        self.out.send(data)
        self.reader.poll()


def test_implausible_poses_are_refused_counted_by_kind_and_the_next_good_one_is_taken():
    f = _Feed()
    reader = f.reader
    k = 0

    def good() -> None:  # the next good frame, 20 ms after its exposure: taken at once
        nonlocal k
        k += 1
        f.send(_frame(k), k / 120 + 0.02)
        pose = reader.latest("vehicle")
        assert pose.frame_no == k and pose.stamp_s == pytest.approx(k / 120, abs=1e-6)
        assert not reader.is_stale("vehicle") and reader.latest("gap").frame_no == k

    def bad(data: bytes, bodies: tuple[str, ...] = ("vehicle", "gap")) -> None:
        """``data`` arrives 4 ms after the last good frame; the poses of ``bodies`` stay as they were."""
        before = [reader.latest(b) for b in bodies]
        f.send(data, k / 120 + 0.024)
        assert all(reader.latest(b) is p for b, p in zip(bodies, before, strict=True))

    for _ in range(10):
        good()
    nan = float("nan")
    bad(rewrite_mocap(_frame(k + 1), pos_m=(nan, -1.0, 0.5), body_ids=(1,)), ("vehicle",))
    good()
    bad(rewrite_mocap(_frame(k + 1), quat_wxyz=(float("inf"), 0.0, 0.0, 0.0), body_ids=(2,)), ("gap",))
    good()
    bad(rewrite_mocap(_frame(k + 1), quat_wxyz=(1.1, 0.0, 0.0, 0.0)))  # a norm 10 % off
    good()
    bad(rewrite_mocap(_frame(k + 1), stamp_us=2**62))  # 146,000 years ahead
    good()
    bad(rewrite_mocap(_frame(k + 1), stamp_us=round((k + 1) / 120 * 1e6) + 600_000))  # 0.6 s ahead
    good()
    bad(_frame(k - 5))  # an old frame again: its stamps go backwards
    bad(_frame(k))  # the latest again: its stamps do not advance
    good()
    c = reader.counters
    refused = c.bodies_non_finite, c.bodies_bad_quat, c.bodies_stamp_future, c.bodies_stamp_backwards
    # backwards: the two replayed frames, and the good body of each frame with one bad body, sent again
    # in the good frame after it
    assert refused == (2, 2, 4, 6)
    assert c.bodies_invalid == 0 and c.clock_jumps == 0 and c.frames_ok == k + 7
    # a quaternion a little off unit length (float32 rounding, 0.5 %) is taken, normalised
    f.send(rewrite_mocap(_frame(k + 1), quat_wxyz=(1.005, 0.0, 0.0, 0.0)), (k + 1) / 120 + 0.02)
    assert reader.latest("vehicle").frame_no == k + 1
    assert reader.latest("vehicle").quat_wxyz == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-12)


def test_a_bad_first_stamp_or_a_new_mocap_clock_is_followed_once_frames_agree_on_it():
    f = _Feed()
    reader = f.reader
    f.send(rewrite_mocap(_frame(0), stamp_us=2**62), 0.02)  # the first pose: nothing to compare it with
    assert reader.latest("vehicle").frame_no == 0
    for k in range(1, CLOCK_JUMP_FRAMES):  # the good frames after it go "backwards" from it ...
        f.send(_frame(k), k / 120 + 0.02)
        assert reader.latest("vehicle").frame_no == 0
    f.send(_frame(CLOCK_JUMP_FRAMES), CLOCK_JUMP_FRAMES / 120 + 0.02)  # ... until enough agree
    assert reader.latest("vehicle").frame_no == CLOCK_JUMP_FRAMES and reader.counters.clock_jumps == 1
    assert reader.counters.bodies_stamp_backwards == 2 * (CLOCK_JUMP_FRAMES - 1)
    # frames with stamps all over the place never agree on a clock
    rng = np.random.default_rng(5)
    t = 1.0
    for k in range(100, 140):
        t += 1 / 120
        f.send(rewrite_mocap(_frame(k), stamp_us=int(rng.integers(0, 2**62))), t)
        f.send(_frame(k, t0_s=t - k / 120 - 0.02), t)  # and good ones in between
    assert reader.counters.clock_jumps == 1 and reader.latest("vehicle").frame_no == 139
    # the mocap system restarted: its clock starts at 0 again, and is followed after as many frames
    for k in range(CLOCK_JUMP_FRAMES):
        t += 1 / 120
        f.send(_frame(k), t)
    assert reader.counters.clock_jumps == 2 and reader.latest("vehicle").frame_no == CLOCK_JUMP_FRAMES - 1


def test_reader_samples_are_ordinary_pose_samples():
    a, _b = MemoryTransport.pair()
    got: list[PoseSample] = []
    reader = MocapReader(a, clock=SimClock(2.0), on_sample=got.append)
    packet = MocapPacket(42, (BodySample(1, 1.5, (1.0, 2.0, 3.0), (1.004, 0.0, 0.0, 0.0)),
                              BodySample(7, 1.5, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
                              BodySample(2, 1.5, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), valid=False),
                              BodySample(3, 1.5, (0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0))))
    assert reader._feed(encode_mocap_frame(packet)) == 1
    assert [s.name for s in got] == ["vehicle", "body7"]
    want = PoseSample("vehicle", 1, np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.0, 0.0, 0.0]), 1.5, 2.0, 42)
    s = got[0]
    assert repr(s) == repr(want) and s.frame_no == 42 and s.age_s(2.25) == 0.25
    with pytest.raises(AttributeError):
        s.stamp_s = 0.0  # type: ignore[misc]
    assert reader.latest("vehicle") is s and reader.latest(7) is got[1] and reader.latest("body7") is got[1]
    assert reader.latest("gap") is None and reader.counters.bodies_invalid == 1
    assert reader.counters.bodies_bad_quat == 1  # body 3's quaternion of norm 2
    with pytest.raises(KeyError, match="unknown body"):
        reader.latest("wing")
