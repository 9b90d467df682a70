"""ESC bus figures: frames per second through the DroneCAN bus model, and the full stack's real-time
factor with the motors on the bus beside the one without it, measured in the same run."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from emulator.esc_bus import EscBus, EscBusConfig
from hil.benches import BenchRow, time_per_call
from hil.benches.runner import RTF_SCENARIO
from hil.runner import RunOptions, run_scenario
from hil.scenario import loads_scenarios
from hil.scenario.schema import EscBusSpec

RUNS = 3  # runs of each stack; the figure is their median


def collect(quick: bool) -> Iterator[BenchRow]:
    esc = EscBus(EscBusConfig(), np.random.default_rng(0), 0.0, lambda *a: None, lambda *a: None)
    throttles = np.array([0.1, 0.2, 0.3, 0.4])
    clock = [0.0]

    def one_frame() -> None:  # the FC's node to the four ESC nodes, as in flight
        clock[0] += 1e-3
        esc.fc_node.send_command(throttles, clock[0])
        esc.bus.advance_to(clock[0] + 1e-3)

    frames0 = esc.bus.stats.frames
    per_frame = time_per_call(one_frame, 0.2 if quick else 1.0)
    if esc.bus.stats.frames == frames0 or not np.allclose(esc.throttle, throttles, atol=1e-3):
        raise RuntimeError("bench: the RawCommands did not reach the ESC nodes")
    yield BenchRow("can_frames_per_s", 1.0 / per_frame, "frames/s",
                   "RawCommand (one frame) from the FC's node to its four ESC nodes through the bus model")
    base = loads_scenarios(RTF_SCENARIO)[0]
    on_bus = replace(base, links=replace(base.links, esc_bus=EscBusSpec()))
    runs = 1 if quick else RUNS
    rtf: dict[str, list[float]] = {"full_stack_rtf": [], "full_stack_rtf_esc_bus": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs):  # alternated, so that a busy spell of the machine meets both alike
            for name, s in (("full_stack_rtf", base), ("full_stack_rtf_esc_bus", on_bus)):
                r = run_scenario(s, Path(tmp) / f"{name}_{k}", RunOptions())
                if not r.passed:
                    failed = "; ".join(f"{c.name}: {c.observed}" for c in r.failed_checks)
                    raise RuntimeError(f"bench scenario failed its checks ({name}): {failed}")
                rtf[name].append(r.summary["real_time_factor"])
    med = {name: float(np.median(v)) for name, v in rtf.items()}
    for name, row in (("full_stack_rtf", "full_stack_rtf_beside_esc_bus"),
                      ("full_stack_rtf_esc_bus", "full_stack_rtf_esc_bus")):
        spread = ", ".join(f"{x:.1f}" for x in rtf[name])
        yield BenchRow(row, med[name], "x real time",
                       f"60 deg gap over ptys, lockstep, median of {runs} ({spread})")
    yield BenchRow("esc_bus_rtf_ratio", med["full_stack_rtf_esc_bus"] / med["full_stack_rtf"], "x",
                   "full stack with the motors on the DroneCAN bus / without it, same run")
