"""Mocap over UWB end to end on real pseudo-terminals (and UDP): emulator-side MocapLinkServer ->
pty -> onboard MocapReader. Simulated time drives the models; the pty carries the real bytes."""

from __future__ import annotations

import time

import numpy as np
import pytest

from emulator.mocap import MocapConfig, MocapSystem, pose_of
from emulator.mocap_link import MocapLinkServer
from emulator.physics.state import VehicleState
from emulator.uwb import UartWire, UwbConfig, UwbRadio
from emulator.world.geometry import Gap
from hil.link.clock import SimClock, WallClock
from hil.link.linktrack import ONE_NODE_EXTRA_BYTES, ROLE_ANCHOR, ROLE_TAG, MocapFrameEncoder, mocap_frame_len
from hil.link.memory import MemoryTransport
from hil.link.pty import PtyTransport
from hil.link.transport import Transport
from hil.link.udp import UdpTransport
from policies.mocap_reader import MocapReader, PoseSample

GAP = Gap(centre_m=(0.0, 0.5, 2.1), roll_rad=-np.pi / 3)


def _vehicle(t: float) -> VehicleState:
    return VehicleState(time_s=t, pos_m=[-2.0 + 0.5 * t, -1.0, 0.5])


def _drain(reader: MocapReader, expected_bytes: int) -> None:
    """Read until the reader has every byte written so far (the pty delivers within milliseconds)."""
    deadline = time.monotonic() + 2.0
    while reader.counters.bytes_in < expected_bytes:
        assert time.monotonic() < deadline, "pty did not deliver the bytes within 2 s"
        reader.poll(timeout_s=0.05)


def _run(server: MocapLinkServer, reader: MocapReader, clock: SimClock, until_s: float) -> None:
    """Event-driven lockstep: jump to each event of the chain, write, let the reader read at that time."""
    written = server.stats.bytes_written
    while (t := server.next_event_s()) <= until_s:
        clock.advance_to(t)
        written += server.update(t, _vehicle(t), GAP)
        _drain(reader, written)


@pytest.fixture
def pty_pair():
    transport = PtyTransport.create(921600)
    clock = SimClock()
    samples: list[PoseSample] = []
    reader = MocapReader.open(transport.endpoint, clock=clock, stale_after_s=0.05, on_sample=samples.append)
    yield transport, clock, reader, samples
    reader.close()
    transport.close()


@pytest.mark.parametrize("loss", [
    UwbConfig(loss_prob=0.1, jitter_s=0.002, latency_s=0.01),
    UwbConfig(burst_enter_prob=0.02, burst_exit_prob=0.25, jitter_s=0.002, latency_s=0.01),
])
def test_reader_receives_the_rate_minus_the_loss(pty_pair, loss):
    transport, clock, reader, samples = pty_pair
    server = MocapLinkServer(transport, clock, np.random.default_rng(11), MocapConfig(rate_hz=120), loss)
    _run(server, reader, clock, until_s=10.0)
    expected = 120 * 10 * (1 - loss.mean_loss)
    got = reader.counters.frames_ok
    # binomial spread of 1200 frames at ~10 % loss is ~10 frames; bursts widen it: allow 6 %
    assert got == pytest.approx(expected, rel=0.06)
    assert got == server.stats.frames_written  # the last may still be on the UART at the end
    assert reader.counters.bad_checksum == reader.counters.bytes_skipped == 0
    assert len([s for s in samples if s.name == "gap"]) == got


def test_measured_latency_matches_the_configured_chain(pty_pair):
    transport, clock, reader, samples = pty_pair
    mocap = MocapConfig(rate_hz=120, processing_s=0.0)  # camera latency 5.56 ms at 120 Hz
    uwb = UwbConfig(latency_s=0.010, jitter_s=0.003)
    server = MocapLinkServer(transport, clock, np.random.default_rng(2), mocap, uwb)
    _run(server, reader, clock, until_s=10.0)
    lat = np.array([s.latency_s for s in samples if s.name == "vehicle"])
    fixed = 5.56e-3 + uwb.air_time_s(mocap_frame_len(2) - 16) + uwb.uart_time_s(mocap_frame_len(2))
    # mocap stamps travel in whole microseconds
    assert np.median(lat) == pytest.approx(fixed + 0.010, abs=0.3e-3)
    assert lat.std() == pytest.approx(0.003, rel=0.1)
    q10, q90 = np.quantile(lat, [0.1, 0.9])
    assert q10 == pytest.approx(fixed + 0.010 - 1.2816 * 0.003, abs=0.4e-3)
    assert q90 == pytest.approx(fixed + 0.010 + 1.2816 * 0.003, abs=0.4e-3)


class CorruptingTransport(Transport):
    """Fault injector in front of a real transport: in about half the frames it overwrites a fifth of
    the bytes with random values (10 % of all bytes), and remembers which frames it spoiled."""

    def __init__(self, inner: Transport, rng: np.random.Generator) -> None:
        super().__init__()
        self.inner, self.rng = inner, rng
        self.clean: list[bytes] = []
        self.corrupt: list[bytes] = []
        self.bytes_changed = 0

    def _send_internal(self, data: bytes) -> int:
        raw = bytearray(data)
        if self.rng.random() < 0.5:
            idx = self.rng.choice(len(raw), size=len(raw) // 5, replace=False)
            for i in idx:
                raw[i] = (raw[i] + int(self.rng.integers(1, 256))) & 0xFF
            self.bytes_changed += len(idx)
            self.corrupt.append(bytes(raw))
        else:
            self.clean.append(bytes(raw))
        return self.inner.send(bytes(raw))

    def _recv_internal(self, max_bytes: int) -> bytes:
        return self.inner.recv(0.0, max_bytes)

    def _close_internal(self) -> None:
        pass


def test_ten_percent_corrupt_bytes_every_corrupt_frame_counted_none_accepted(pty_pair):
    transport, clock, reader, samples = pty_pair
    faulty = CorruptingTransport(transport, np.random.default_rng(9))
    server = MocapLinkServer(faulty, clock, np.random.default_rng(3), MocapConfig(rate_hz=240),
                             UwbConfig(latency_s=0.005, jitter_s=0.001))
    _run(server, reader, clock, until_s=5.0)
    c = reader.counters
    total = sum(map(len, faulty.clean + faulty.corrupt))
    assert faulty.bytes_changed / total == pytest.approx(0.10, abs=0.015)
    assert len(faulty.corrupt) > 400 and len(faulty.clean) > 400
    # the stream goes on: every clean frame is accepted, in order, and nothing else is
    assert c.frames_ok == len(faulty.clean)
    clean_numbers = [int.from_bytes(f[17:21], "little") for f in faulty.clean]
    assert [s.frame_no for s in samples if s.name == "vehicle"] == clean_numbers
    # every byte of every corrupt frame was thrown away and counted, none made it into a pose
    assert c.bytes_skipped + c.bytes_bad_payload == sum(map(len, faulty.corrupt))
    assert c.bytes_in == total
    assert c.bad_checksum + c.bad_structure + c.bad_payload >= len(faulty.corrupt) // 2
    assert c.resyncs > 0


def test_stale_flag_and_age_follow_the_reader_clock(pty_pair):
    transport, clock, reader, _ = pty_pair
    server = MocapLinkServer(transport, clock, np.random.default_rng(0), MocapConfig(rate_hz=100),
                             UwbConfig(latency_s=0.005, jitter_s=0.0))
    assert reader.latest("vehicle") is None and reader.is_stale("vehicle")
    _run(server, reader, clock, until_s=1.0)
    assert not reader.is_stale("vehicle") and not reader.is_stale("gap")
    assert reader.age_s("vehicle") < 0.011
    pose = reader.latest("vehicle")
    assert pose.pos_m == pytest.approx(_vehicle(pose.stamp_s).pos_m, abs=2e-3)
    assert reader.latest("gap").quat_wxyz == pytest.approx(GAP.quat_wxyz(), abs=5e-3)
    clock.advance_to(1.04)
    assert not reader.is_stale("vehicle")
    clock.advance_to(1.06)  # the link went quiet: 50 ms threshold passed
    assert reader.is_stale("vehicle") and reader.is_stale("gap")
    with pytest.raises(KeyError, match="unknown body"):
        reader.latest("drone")


def test_poses_as_plain_values_give_the_frames_of_the_pose_objects():
    """The runner hands the vehicle's and the gap's poses over as 7 plain numbers each."""
    gap = pose_of(GAP)
    gap_values = (*gap.pos_m.tolist(), *gap.quat_wxyz.tolist())
    runs = []
    for plain in (False, True):
        ours, theirs = MemoryTransport.pair()
        clock = SimClock()
        server = MocapLinkServer(ours, clock, np.random.default_rng(4), MocapConfig(),
                                 UwbConfig(jitter_s=0.002, loss_prob=0.1))
        got = bytearray()
        for k in range(2000):
            clock.advance_to(t := k * 1e-3)
            v = _vehicle(t)
            vehicle = (*v.pos_m.tolist(), *v.quat_wxyz.tolist()) if plain else v
            server.update(t, vehicle, gap_values if plain else GAP)
            got += theirs.recv(0.0)
        runs.append((bytes(got), server.stats))
    assert runs[0] == runs[1]
    assert runs[0][1].frames_written > 150


@pytest.mark.realtime
def test_wall_clock_run_over_a_pty_delivers_the_rate():
    """Real time: server and reader in one process on a WallClock for 1 s (tolerance: 10 %)."""
    clock = WallClock()
    with PtyTransport.create(921600) as transport:
        reader = MocapReader.open(transport.endpoint, clock=clock)
        server = MocapLinkServer(transport, clock, np.random.default_rng(0), MocapConfig(rate_hz=120),
                                 UwbConfig(latency_s=0.002, jitter_s=0.0))
        while (now := clock.now_s()) < 1.0:
            server.update(now, _vehicle(now), GAP)
            reader.poll(timeout_s=max(0.0, min(server.next_event_s() - clock.now_s(), 0.01)))
        reader.poll(timeout_s=0.05)
        lat = [reader.latest("vehicle").latency_s]
        reader.close()
    assert reader.counters.frames_ok == pytest.approx(120 * (1.0 - 0.0099), rel=0.1)
    assert 0.0 < lat[0] < 0.05


def test_udp_socket_carries_the_same_frames():
    clock = SimClock()
    reader = MocapReader.open("udp:127.0.0.1:0", clock=clock)
    host, port = reader.transport.endpoint.split(":")[1:]
    with UdpTransport.client(host, int(port)) as link:
        server = MocapLinkServer(link, clock, np.random.default_rng(0), MocapConfig(),
                                 UwbConfig(jitter_s=0.0))
        _run(server, reader, clock, until_s=0.5)
    assert reader.counters.frames_ok == server.stats.frames_written > 50
    assert reader.latest("gap") is not None
    reader.close()


@pytest.mark.parametrize("mocap, uwb", [
    (MocapConfig(), UwbConfig(jitter_s=0.004, latency_s=0.01)),  # the compiled step, several jitter blocks
    # the radio's own steps
    (MocapConfig(), UwbConfig(jitter_s=0.004, latency_s=0.01, loss_prob=0.1, late_after_s=0.012)),
    # refusals, a busy wire
    (MocapConfig(), UwbConfig(jitter_s=0.0, air_rate_bps=5e4, queue_packets=1, uart_baud=115200)),
    # occlusions (drawn per frame and body) through the compiled step
    (MocapConfig(occlusion_prob=0.1, occlusion_mean_s=0.02), UwbConfig(jitter_s=0.004, latency_s=0.01)),
    # frames ready out of their order, more on their way than the first room holds
    (MocapConfig(rate_hz=360, processing_s=0.006), UwbConfig(jitter_s=0.004, latency_s=0.15)),
    # the radio's own steps onto the same frames on their way, more than the first room holds
    (MocapConfig(rate_hz=360), UwbConfig(jitter_s=0.004, latency_s=0.15, loss_prob=0.1, late_after_s=0.152)),
])
@pytest.mark.parametrize("read_counts", [True, False])
def test_the_links_radio_and_wire_are_the_radio_and_the_uart_sent_to_by_hand(mocap, uwb, read_counts):
    """The link carries each frame from the tracker through the radio, its channel and the UART in one
    step (compiled where the channel cannot lose): the same bytes at the same times, and the same counts,
    as a tracker, `UwbRadio` and `UartWire` driven one frame at a time. The compiled step takes a frame
    through the radio only once it could be off the UART: counts read along the way, or only at the end,
    count the frames ready by then as sent all the same."""
    ours, theirs = MemoryTransport.pair(1 << 20)
    clock = SimClock()
    server = MocapLinkServer(ours, clock, np.random.default_rng(6), mocap, uwb)
    # the hand-driven chain: the tracker, the radio and the UART on the generators the link spawns
    tracker_rng, radio_rng = np.random.default_rng(6).spawn(2)
    tracker = MocapSystem(mocap, tracker_rng, MocapFrameEncoder(ROLE_TAG, 0, ROLE_ANCHOR, 0))
    radio, uart = UwbRadio(uwb, radio_rng), UartWire(uwb.uart_baud, uwb.uart_bits_per_byte)
    gap = pose_of(GAP)
    gap_values = (*gap.pos_m.tolist(), *gap.quat_wxyz.tolist())
    for k in range(3000):
        t = k * 7e-4
        v = _vehicle(t)
        vehicle = (*v.pos_m.tolist(), *v.quat_wxyz.tolist())
        server.update(t, vehicle, gap_values)
        tracker.expose_values(t, (1, 2), vehicle + gap_values)
        for ready_s, _, frame in tracker.released(t):
            radio.send(ready_s, frame, len(frame) - ONE_NODE_EXTRA_BYTES)
        for arrival_s, frame, _ in radio.arrived(t):
            uart.write(arrival_s, frame)
        assert theirs.recv(0.0) == b"".join(chunk for _, chunk in uart.update(t))
        if read_counts and k % 3 == 0:  # (the counts read while frames are on their way, and not read)
            assert server.stats.radio == radio.stats
    assert server.stats.radio == radio.stats and server.stats.frames_written > 50
    assert server.stats.mocap == tracker.stats
