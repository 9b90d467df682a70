"""The link channel model: loss (independent and in bursts) at its long-run rate, latency with jitter,
delivery in order, UART wire time, and the scenario file's names mapped to it with each link's
defaults."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from emulator.uwb import UwbConfig
from hil.link.channel import Channel, ChannelModel, UartWire
from hil.runner.wires import channel_model
from hil.scenario.schema import BurstLoss, LinkSpec


def _drops(model: ChannelModel, n: int, seed: int = 1) -> list[str | None]:
    channel = Channel(model, np.random.default_rng(seed))
    return [channel.drop() for _ in range(n)]


def test_independent_and_burst_loss_reach_their_long_run_rate():
    model = ChannelModel(loss_prob=0.05, burst_enter_prob=0.01, burst_exit_prob=0.2)
    drops = _drops(model, 200_000)
    assert sum(d is not None for d in drops) / len(drops) == pytest.approx(model.mean_loss, rel=0.05)
    assert "burst" in drops and "loss" in drops
    # bursts come in runs: a burst loss is followed by another far more often than loss alone gives
    pairs = sum(a == b == "burst" for a, b in pairwise(drops))
    assert pairs / drops.count("burst") > 0.5


def test_a_clean_channel_never_drops_and_keeps_order_under_jitter():
    channel = Channel(ChannelModel(latency_s=0.01, jitter_s=0.02), np.random.default_rng(3))
    assert not channel.can_lose
    arrivals = [channel.arrival_s(k * 1e-3) for k in range(2000)]
    assert arrivals == sorted(arrivals)
    assert all(a >= k * 1e-3 for k, a in enumerate(arrivals))  # latency never negative
    assert np.mean(np.diff(arrivals)) == pytest.approx(1e-3, rel=0.2)


def test_jitter_is_the_same_draws_whether_the_channel_can_lose_or_not():
    # a clean channel draws its jitter in blocks: the same numbers as one draw per message
    clean = Channel(ChannelModel(latency_s=0.05, jitter_s=0.004), np.random.default_rng(5))
    rng = np.random.default_rng(5)
    want = [max(0.0, 0.05 + rng.normal(0.0, 0.004)) for _ in range(200)]
    got = []
    for k in range(200):
        got.append(clean.arrival_s(k * 1.0) - k * 1.0)
    assert got == pytest.approx(want, abs=1e-12)


def test_uart_wire_time_queues_messages_behind_each_other():
    uart = UartWire(115200)
    first = uart.finish_s(0.0, 100)
    assert first == pytest.approx(100 * 10 / 115200)
    assert uart.finish_s(0.0, 100) == pytest.approx(2 * first)  # the line is busy until the first is out
    assert uart.finish_s(1.0, 1) == pytest.approx(1.0 + 10 / 115200)


@pytest.mark.parametrize("kwargs", [{"loss_prob": 1.5}, {"latency_s": -1.0}, {"jitter_s": float("nan")},
                                    {"burst_enter_prob": 0.1, "burst_exit_prob": 0.0}])
def test_bad_channel_settings_are_clear_errors(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs)).replace("enter", "exit")):
        ChannelModel(**kwargs)


def test_scenario_links_map_to_the_model_and_each_link_keeps_its_defaults():
    spec = LinkSpec(latency_ms=5.0, jitter_ms=1.0, loss=0.02, burst=BurstLoss(p_gb=0.01, p_bg=0.4))
    assert channel_model(spec) == ChannelModel(latency_s=0.005, jitter_s=0.001, loss_prob=0.02,
                                               burst_enter_prob=0.01, burst_exit_prob=0.4)
    assert channel_model(LinkSpec()) == ChannelModel()  # a clean command link
    radio = UwbConfig()  # the radio's own defaults, as data of the same model
    assert isinstance(radio, ChannelModel)
    assert (radio.latency_s, radio.jitter_s, radio.burst_exit_prob) == (0.020, 0.005, 0.3)
