"""UWB radio and UART model: loss (independent and bursty), latency and jitter, limits, wire time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emulator.uwb import UartWire, UwbConfig, UwbRadio

PERIOD_S = 1 / 120


def _run(config: UwbConfig, n: int = 4000, seed: int = 0, size: int = 85):
    radio = UwbRadio(config, np.random.default_rng(seed))
    got, lost_pattern = [], []
    for k in range(n):
        t = k * PERIOD_S
        before = radio.stats.lost
        radio.send(t, k.to_bytes(4, "little") + bytes(size - 4))
        lost_pattern.append(radio.stats.lost > before)
        got += radio.update(t)
    got += radio.update(math.inf)
    return radio, got, lost_pattern


def test_independent_loss_matches_the_configured_probability():
    radio, got, _ = _run(UwbConfig(loss_prob=0.2, jitter_s=0.0))
    assert radio.stats.sent == 4000
    assert radio.stats.delivered + radio.stats.lost == 4000
    # binomial std for n = 4000, p = 0.2 is 0.0063: allow 4 sigma
    assert radio.stats.lost / 4000 == pytest.approx(0.2, abs=0.026)
    assert [int.from_bytes(d.data[:4], "little") for d in got] == sorted(
        int.from_bytes(d.data[:4], "little") for d in got)


def test_burst_loss_follows_gilbert_elliott_rates_and_comes_in_runs():
    cfg = UwbConfig(burst_enter_prob=0.02, burst_exit_prob=0.2, burst_loss_prob=1.0, jitter_s=0.0)
    radio, _, lost = _run(cfg, n=20000)
    assert cfg.mean_loss == pytest.approx(0.02 / 0.22)
    assert radio.stats.lost / 20000 == pytest.approx(cfg.mean_loss, rel=0.2)
    assert radio.stats.burst_lost == radio.stats.lost
    runs, cur = [], 0
    for x in lost:
        if x:
            cur += 1
        elif cur:
            runs.append(cur)
            cur = 0
    # mean burst length 1 / exit = 5 packets; independent loss at the same rate would give ~1.1
    assert np.mean(runs) == pytest.approx(5.0, rel=0.25)


def test_latency_has_the_configured_mean_and_jitter():
    cfg = UwbConfig(latency_s=0.02, jitter_s=0.004, air_rate_bps=6.8e6)
    _, got, _ = _run(cfg)
    lat = np.array([d.arrival_s - d.sent_s for d in got])
    air = cfg.air_time_s(85)
    assert lat.mean() == pytest.approx(0.02 + air, abs=0.0005)
    # order is kept, which lifts a few arrivals: the spread stays near the configured jitter
    assert lat.std() == pytest.approx(0.004, rel=0.15)
    assert np.all(np.diff([d.arrival_s for d in got]) >= 0)


def test_late_packets_are_counted():
    radio, got, _ = _run(UwbConfig(latency_s=0.02, jitter_s=0.01, late_after_s=0.03), n=2000)
    late = sum(d.arrival_s - d.sent_s > 0.03 for d in got)
    assert radio.stats.late == late
    assert 0.05 < late / len(got) < 0.3  # P(N(0.02, 0.01) > 0.03) = 16 %


def test_size_and_queue_limits_refuse_packets():
    radio = UwbRadio(UwbConfig(max_packet_bytes=100, queue_packets=2, air_rate_bps=8000.0,
                               air_overhead_bytes=0, jitter_s=0.0), np.random.default_rng(0))
    assert not radio.send(0.0, bytes(101))
    assert radio.stats.oversize == 1
    # 100 bytes at 8 kbit/s take 0.1 s of air: a third packet at once finds the queue full
    assert radio.send(0.0, bytes(100)) and radio.send(0.0, bytes(100))
    assert not radio.send(0.0, bytes(100))
    assert radio.stats.overflow == 1
    assert radio.send(0.15, bytes(100))  # the first has left the air by now
    arrivals = [d.arrival_s for d in radio.update(math.inf)]
    assert arrivals == pytest.approx([0.1 + 0.02, 0.2 + 0.02, 0.3 + 0.02])


def test_a_packet_sized_apart_from_its_data_takes_the_air_and_limits_of_that_size():
    """The mocap link hands the radio the frame the far side writes, sized by the node data it carries."""
    radio = UwbRadio(UwbConfig(max_packet_bytes=100, air_rate_bps=8000.0, air_overhead_bytes=0, jitter_s=0.0),
                     np.random.default_rng(0))
    assert not radio.send(0.0, b"frame", n_bytes=101)
    assert radio.stats.oversize == 1
    assert radio.send(0.0, b"frame", n_bytes=100)
    assert radio.arrived(math.inf) == [(pytest.approx(0.1 + 0.02), b"frame", 0.0)]


def test_uart_wire_time_at_the_baud():
    uart = UartWire(921600)
    done = uart.write(0.0, bytes(101))
    assert done == pytest.approx(101 * 10 / 921600)
    second = uart.write(0.0, bytes(101))  # queued behind the first
    assert second == pytest.approx(2 * 101 * 10 / 921600)
    assert uart.update(done - 1e-6) == []
    assert [len(b) for _, b in uart.update(second)] == [101, 101]
    assert uart.next_event_s() == math.inf


def test_same_seed_same_run_and_next_event():
    a = _run(UwbConfig(loss_prob=0.1, burst_enter_prob=0.01), n=500, seed=3)[1]
    b = _run(UwbConfig(loss_prob=0.1, burst_enter_prob=0.01), n=500, seed=3)[1]
    assert [d.arrival_s for d in a] == [d.arrival_s for d in b]
    radio = UwbRadio(UwbConfig(jitter_s=0.0), np.random.default_rng(0))
    assert radio.next_event_s() == math.inf
    radio.send(1.0, b"x")
    assert radio.next_event_s() == pytest.approx(1.02 + UwbConfig().air_time_s(1))


@pytest.mark.parametrize("field, value", [
    ("loss_prob", 1.5), ("latency_s", -0.1), ("jitter_s", math.nan), ("uart_baud", 0),
    ("queue_packets", 0), ("burst_exit_prob", 0.0),
])
def test_bad_config_is_a_clear_error(field, value):
    kwargs = {field: value}
    if field == "burst_exit_prob":
        kwargs["burst_enter_prob"] = 0.1
    with pytest.raises(ValueError, match=field):
        UwbConfig(**kwargs)


def test_radio_jitter_drawn_in_blocks_is_the_per_packet_sequence():
    cfg = UwbConfig(latency_s=0.01, jitter_s=0.004)
    radio = UwbRadio(cfg, np.random.default_rng(9))
    ref = np.random.default_rng(9)
    arrivals = []
    for k in range(300):  # past several blocks
        assert radio.send(k * 0.01, b"x" * 40)
        arrivals.extend(d.arrival_s for d in radio.update(k * 0.01 + 1.0))
    last = -math.inf
    for k, got in enumerate(arrivals):
        air_end = k * 0.01 + cfg.air_time_s(40)
        want = max(air_end + max(0.0, cfg.latency_s + ref.normal(0.0, cfg.jitter_s)), last)
        last = want
        assert got == want


class _RefUart:
    """`UartWire` as it was."""

    def __init__(self, baud: int, bits_per_byte: int = 10) -> None:
        self.baud, self.bits_per_byte = baud, bits_per_byte
        self._busy_until_s = -math.inf
        self._queue: list[tuple[float, bytes]] = []
        self.bytes_written = 0

    def write(self, now_s: float, data: bytes) -> float:
        done = max(now_s, self._busy_until_s) + len(data) * self.bits_per_byte / self.baud
        self._busy_until_s = done
        self._queue.append((done, bytes(data)))
        return done

    def update(self, now_s: float) -> list[tuple[float, bytes]]:
        n = 0
        while n < len(self._queue) and self._queue[n][0] <= now_s + 1e-12:
            n += 1
        out, self._queue = self._queue[:n], self._queue[n:]
        self.bytes_written += sum(len(d) for _, d in out)
        return out


@pytest.mark.parametrize(
    "cfg",
    [
        UwbConfig(latency_s=0.01, jitter_s=0.004),
        UwbConfig(loss_prob=0.1, burst_enter_prob=0.05, jitter_s=0.02, late_after_s=0.03, queue_packets=2),
        UwbConfig(jitter_s=0.0, max_packet_bytes=60, air_rate_bps=1e5),
    ],
)
def test_radio_data_and_deliveries_agree(cfg):
    a, b = UwbRadio(cfg, np.random.default_rng(2)), UwbRadio(cfg, np.random.default_rng(2))
    rng = np.random.default_rng(8)
    got_a, got_b, sent = [], [], {}
    for k in range(3000):
        t = k / 120 + float(rng.uniform(0, 1e-3))
        data = k.to_bytes(4, "little") + bytes(int(rng.integers(0, 80)))
        payload = bytearray(data) if k % 3 == 0 else data
        assert a.send(t, payload) == b.send(t, payload)
        sent[k] = t
        now = t + float(rng.uniform(0, 0.02))
        got_a += a.update(now)
        got_b += b.update_data(now)
    got_a += a.update(math.inf)
    got_b += b.update_data(math.inf)
    assert a.stats == b.stats and a.stats.delivered == len(got_a) > 1000
    assert [(d.arrival_s, d.data) for d in got_a] == got_b
    assert all(d.data.__class__ is bytes and d.sent_s == sent[int.from_bytes(d.data[:4], "little")]
               for d in got_a)


def test_uart_wire_is_the_reference_wire():
    rng = np.random.default_rng(4)
    wire, ref = UartWire(115200), _RefUart(115200)
    t = 0.0
    for k in range(5000):
        t += float(rng.choice([0.0, 1e-5, 1e-4, 1e-3, 5e-3]))
        if rng.random() < 0.6:
            data = bytes(int(rng.integers(1, 120)))
            data = bytearray(data) if k % 4 == 0 else data
            assert wire.write(t, data) == ref.write(t, data)
        now = t + float(rng.choice([0.0, 1e-4, 2e-3, 1e-2]))
        got = wire.update(now)
        assert got == ref.update(now)
        assert all(d.__class__ is bytes for _, d in got)
        assert wire.bytes_written == ref.bytes_written
        assert wire.next_event_s() == (ref._queue[0][0] if ref._queue else math.inf)
    assert wire.bytes_written > 10_000
