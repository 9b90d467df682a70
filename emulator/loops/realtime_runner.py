"""Running an emulated vehicle and its links in real time: physics to the wall clock, links polled ~1 kHz,
and the watch of the setpoint and mocap streams as the wire sees them (`WireWatch`)."""

from __future__ import annotations

import select
import threading
from collections.abc import Sequence
from typing import Protocol

from emulator.mocap_link import MocapLinkServer
from emulator.servers.registry import FcServer
from emulator.vehicle import EmulatedVehicle
from hil.link.clock import Clock, GapStats, PacingStats, WallClock

POLL_PERIOD_S = 0.001  # the loop wakes at least this often, and at once when a link has data


class Pollable(Protocol):
    """A link endpoint driven by the loop (the MAVLink server, a mocap link)."""

    def poll(self, now_s: float) -> None: ...


class RealtimeRunner:
    """Steps ``vehicle`` to ``clock`` and polls ``links``; wakes early when one of ``wait_fds`` is readable.

    `run()` blocks until ``duration_s`` of clock time has passed or `stop()` is called (any thread);
    `start()` runs it in a background thread.
    """

    def __init__(
        self,
        vehicle: EmulatedVehicle,
        links: Sequence[Pollable],
        *,
        clock: Clock | None = None,
        duration_s: float | None = None,
        wait_fds: Sequence[int] = (),
    ) -> None:
        self.vehicle = vehicle
        vehicle.compile_kernels()  # before the clock matters: not a stall of seconds in the first flight
        self.links = list(links)
        self.clock = clock or WallClock()
        self.duration_s = duration_s
        self.wait_fds = list(wait_fds)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.lock = threading.Lock()  # held while stepping and polling: take it to read a consistent state
        #: how well the loop kept the wall clock (lateness, physics caught up), for the exit summary
        self.pacing = PacingStats(POLL_PERIOD_S, vehicle.dt_s)

    def run(self) -> None:
        clock, vehicle, pacing = self.clock, self.vehicle, self.pacing
        while not self._stop.is_set():
            now = clock.now_s()
            pacing.wake(now)
            if self.duration_s is not None and now >= self.duration_s:
                break
            with self.lock:
                # links first: what arrived by `now` is applied before physics catches up to `now`, so a
                # stalled loop (a slow disk, a compile) cannot fake a setpoint loss
                for link in self.links:
                    link.poll(now)
                vehicle.step_to(now)
            if self.wait_fds:
                select.select(self.wait_fds, [], [], POLL_PERIOD_S)
            else:
                self._stop.wait(POLL_PERIOD_S)

    def start(self) -> RealtimeRunner:
        """Run in a daemon thread; errors are kept in ``error``."""

        def target() -> None:
            try:
                self.run()
            except BaseException as exc:
                self.error = exc

        self._thread = threading.Thread(target=target, name="fc-realtime", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Ask the loop to end and wait for its thread (if started)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)


class WireWatch:
    """The setpoint and mocap streams as the wire sees them: rates and the longest silences."""

    def __init__(self, server: FcServer, mocap: MocapLinkServer | None) -> None:
        self.server, self.mocap = server, mocap
        self.setpoints, self.mocap_frames = GapStats(), GapStats()

    def poll(self, now_s: float) -> None:
        self.setpoints.update(now_s, self.server.stats.setpoints_applied)
        if self.mocap is not None:
            self.mocap_frames.update(now_s, self.mocap.frames_written)

    def as_dict(self) -> dict[str, object]:
        return {"setpoints_at_fc": self.setpoints.as_dict(),
                "mocap_frames_written": self.mocap_frames.as_dict()}
