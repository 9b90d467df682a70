"""The emulator side of a run: vehicle (physics + FC), the FC's MAVLink server on the command wire,
mocap over UWB on the mocap link, the gap world, faults on the airframe and the links, and the
recording, all advanced together on one SimClock by `advance_to(t)`.

Between two calls the loop stops only where something needs the vehicle's state or changes it (a
mocap exposure, a command frame reaching the FC, a fault switching, a world sample) and steps the
physics in batches in between; the radio and UART legs of the mocap chain are caught up at the next
stop with their own times. What the emulator side writes goes out once per call: the mocap frames in
one write (in lockstep held until the tick, see ``hold_mocap``), the FC's frames with the lockstep tick
in another.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from emulator.assembly import assemble
from emulator.esc.bus import EscBusConfig, EscBusStepper
from emulator.esc.bus import attach as attach_esc_bus
from emulator.fc import FcConfig
from emulator.loops.batched_steps import FastStepper
from emulator.mocap import MocapConfig, pose_of
from emulator.params import ParamError
from emulator.physics.native import NativeBackend
from emulator.physics.state import VehicleState
from emulator.profile import VehicleProfile
from emulator.servers.mavlink_server import RAW_MSG_IDS
from emulator.servers.registry import server_config
from emulator.uwb import UwbConfig
from emulator.world import Gap, LabVolume
from hil.link.clock import SimClock
from hil.link.mavlink import mav
from hil.link.protocols import framing
from hil.link.tlog import TlogWriter
from hil.link.transport import Transport
from hil.runner.faults import FaultSchedule
from hil.runner.mission import event_name
from hil.runner.recorder import Recorder
from hil.runner.wires import CommandWire, channel_model
from hil.scenario.schema import AirframeSpec, Scenario

FC_SYSTEM_ID = 1
#: the FC's telemetry in a run (s between messages): what the onboard program acts on (HEARTBEAT) and
#: a 10 Hz attitude and position trace for the .tlog; the full state is in timeseries.npz at 100 Hz.
#: `hil fc` keeps the PX4-like defaults; the onboard side may ask for more with SET_MESSAGE_INTERVAL.
RUN_STREAMS_S: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1 / 5,
    mav.MAVLINK_MSG_ID_ATTITUDE: 1 / 10,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1 / 10,
}


def make_gap(scenario: Scenario, seen: bool = False) -> Gap:
    """The scenario's gap; ``seen``: as the mocap system reports it (with ``mocap_bias``)."""
    g = scenario.gap
    if seen:
        b = scenario.mocap_bias
        g = replace(g, centre_m=tuple(c + e for c, e in zip(g.centre_m, b.gap_pos_m, strict=True)),
                    roll_deg=g.roll_deg + b.gap_roll_deg, yaw_deg=g.yaw_deg + b.gap_yaw_deg)
    return Gap.from_deg(
        g.centre_m,
        g.roll_deg,
        g.pitch_deg,
        g.yaw_deg,
        width_m=g.width_m,
        height_m=g.height_m,
        wall_thickness_m=g.wall_thickness_m,
    )


def flown_profile(profile: VehicleProfile, airframe: AirframeSpec) -> VehicleProfile:
    """The airframe the physics flies: ``profile`` with its mass and rotor thrust scaled (the thrust at
    the N3's 100 % with it); the profile itself when nothing is scaled."""
    if airframe == AirframeSpec():
        return profile
    k = airframe.thrust_scale
    return profile.with_changes(
        mass_kg=profile.mass_kg * airframe.mass_scale,
        thrust_coeff_n_s2=profile.thrust_coeff_n_s2 * k,
        max_thrust_per_rotor_n=profile.max_thrust_per_rotor_n * k,
        n3_full_thrust_n=profile.n3_full_thrust_n * k,
    )


def initial_state(scenario: Scenario, profile: VehicleProfile) -> tuple[VehicleState, float]:
    """The start state and the ground height (m): resting on the ground, or hovering at ``pos_m``."""
    ini = scenario.initial
    yaw = ini.yaw_rad
    quat = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    x, y, z = ini.pos_m
    if ini.on_ground:
        pos = np.array([x, y, z + 0.5 * profile.body_box_m[2]])
        return VehicleState(pos_m=pos, quat_wxyz=quat), z
    w = math.sqrt(profile.hover_throttle) * profile.max_rotor_speed_rad_s
    ground = min(0.0, scenario.lab.min_m[2])
    return VehicleState(
        pos_m=np.array([x, y, z]),
        vel_m_s=np.array(ini.vel_m_s, dtype=float),
        quat_wxyz=quat,
        rotor_speed_rad_s=np.full(4, w),
    ), ground


#: a run goes on past its duration while a check's window is open, by up to this (s)
CHECK_OVERRUN_S = 3.0
CHECK_WINDOW_MARGIN_S = 0.05  # past the window's end (s): the check reads the sample at its end
#: a state component larger than this (or NaN) is no flight any more (float32 holds up to 3.4e38)
DIVERGED_LIMIT = 1e30


class _FaultyLink(Transport):
    """The emulator's sending end of the mocap link with the link faults on it applied (mocap_dropped,
    corrupt_bytes: `FaultSchedule.on_frame`).

    Frames are held and written to the real link by `flush()` (once per `advance_to`: one write per
    tick instead of one per frame); bytes the real link refuses then are counted in ``bytes_refused``.
    """

    def __init__(self, raw: Transport, clock: SimClock, faults: FaultSchedule, rng: np.random.Generator):
        super().__init__()
        self.raw, self.clock, self.faults, self.rng = raw, clock, faults, rng
        self.endpoint = raw.endpoint
        self.bytes_dropped_fault = 0
        self.bytes_corrupted = 0
        self.bytes_refused = 0
        self._held: list[bytes] = []

    def _send_internal(self, data: bytes) -> int:
        faults = self.faults
        if faults.has_mocap_faults:
            out, n = faults.on_frame("mocap", data, self.clock.now_s(), self.rng)
            self.bytes_corrupted += n
            if out is None:
                self.bytes_dropped_fault += len(data)
                return len(data)
            data = out
        self._held.append(data)
        return len(data)

    def flush(self) -> int:
        """Write the held frames to the real link in one go; returns the bytes it took."""
        if not self._held:
            return 0
        data = b"".join(self._held) if len(self._held) > 1 else self._held[0]
        self._held.clear()
        sent = self.raw.send(data) if not self.raw.closed else 0
        self.bytes_refused += len(data) - sent
        return sent

    def _recv_internal(self, max_bytes: int) -> bytes:
        return b""

    def fileno(self) -> int:
        return self.raw.fileno()

    def _close_internal(self) -> None:
        self.raw.close()


class EmulatorSide:
    """Everything on the flight-controller side of one run (see the module docstring)."""

    def __init__(
        self,
        scenario: Scenario,
        profile: VehicleProfile,
        rng: np.random.Generator,
        command_raw: Transport,
        mocap_raw: Transport,
        *,
        clock: SimClock,
        backend: str,
        tlog: TlogWriter | None,
        duration_s: float,
    ) -> None:
        self.scenario, self.profile, self.clock = scenario, profile, clock
        self.faults = FaultSchedule(scenario.faults)
        cmd_rng, mocap_rng, corrupt_rng = rng.spawn(3)
        state, ground_z = initial_state(scenario, profile)
        self.gap = make_gap(scenario)
        # the gap does not move: its pose (as the mocap system reports it) is read once
        gap_pose = pose_of(make_gap(scenario, seen=True))
        self._gap_pose = (*gap_pose.pos_m.tolist(), *gap_pose.quat_wxyz.tolist())
        protocol = scenario.links.command.protocol
        self.wire = CommandWire(
            command_raw, clock, scenario.links.command, cmd_rng, self.faults,
            framing(protocol, FC_SYSTEM_ID, mav.MAV_COMP_ID_AUTOPILOT1),
        )
        m = scenario.links.mocap
        uwb = UwbConfig(**asdict(channel_model(m)), uart_baud=m.baud)
        self.mocap_link = _FaultyLink(mocap_raw, clock, self.faults, corrupt_rng)
        emu = assemble(
            profile, self.wire, clock, initial_state=state, backend=backend,
            fc_config=FcConfig(ground_z_m=ground_z),
            gap=self.gap, lab=LabVolume(scenario.lab.min_m, scenario.lab.max_m), mocap_link=self.mocap_link,
            mocap_rng=mocap_rng, mocap_config=MocapConfig(rate_hz=m.rate_hz), uwb_config=uwb,
            protocol_config=server_config(protocol, stream_intervals_s=dict(RUN_STREAMS_S)),
            system_id=FC_SYSTEM_ID, tlog=tlog, protocol=protocol,
            raw_ids=RAW_MSG_IDS,  # setpoints reach the server as frames (see RAW_MSG_IDS)
        )
        self.vehicle, self.codec, self.server = emu.vehicle, emu.codec, emu.server
        self.world, self.mocap = emu.world, emu.mocap
        assert self.world is not None and self.mocap is not None
        # the scenario's FC parameters, set as a ground station would (each change in the .tlog)
        self.server.params.set_many(dict(scenario.params))
        if not scenario.initial.on_ground:
            self.vehicle.fc.arm(0.0)  # in the air: armed, holding, waiting for the onboard program
        self.recorder = Recorder(self.world, profile, duration_s, self.vehicle.fc, self.server, self.mocap)
        self.esc: EscBusStepper | None = None
        if scenario.links.esc_bus is not None:  # the motors behind ESCs on a DroneCAN bus
            b = scenario.links.esc_bus
            config = EscBusConfig(bitrate_bps=b.bitrate_bps, command_rate_hz=b.command_rate_hz,
                                  status_rate_hz=b.status_rate_hz, loss=b.loss, corruption=b.corruption,
                                  **self.server.params.esc_settings())
            self.esc = attach_esc_bus(self.vehicle, self.server, config, rng.spawn(1)[0])
        self.fast: FastStepper | EscBusStepper = self.esc or FastStepper.for_vehicle(self.vehicle)
        #: the loop's step: ``(n_steps, the vehicle's time (s))`` -> the time after them (None: ask the
        #: vehicle); the batched stepper starts from the time handed to it, the ESC bus's reads its own
        esc = self.esc
        self._step = self.fast.step if esc is None else (lambda n_steps, _time_s: esc.step(n_steps))
        #: the batched stepper that captures a pose inside its steps, with its backend's time after a
        #: number of steps (None, None: another stepper or backend, which stops at each exposure)
        fast = self.fast
        native = isinstance(fast, FastStepper) and isinstance(fast.vehicle.backend, NativeBackend)
        self._capturing: tuple[FastStepper | None, Any] = (
            (fast, fast.vehicle.backend.time_after_s) if native else (None, None))  # type: ignore[union-attr]
        #: the native backend's own state row, which its steps advance in place (None on another
        #: backend): what a sample copies, without a copy of its own first
        backend = self.vehicle.backend
        self._state_row = backend.kernel_arrays[0] if isinstance(backend, NativeBackend) else None
        self._dt_s = self.vehicle.dt_s  # (the backend's step, fixed for its life)
        self.vehicle.compile_kernels()  # (its own per-step path too: no compile inside a run's loop)
        self._frozen_truth: tuple[float, ...] | None = None
        self._exposure_period_s = self.mocap.mocap.config.period_s  # (the tracker's frame grid, s)
        self._force_on = False
        #: keep the mocap frames until ``mocap_link.flush()`` (lockstep: written with the next tick)
        self.hold_mocap = False
        self._next_boundary_s = self.faults.next_boundary_s(-1.0)
        self._overflow_s: float | None = None  # when the state grew past what the wire formats hold
        self.recorder.sample(0.0, self.vehicle.state_vector())
        # what `advance_to` reads at every call, the same objects for the run's life, bound once. The loop
        # stops at mocap exposures only (the radio and the UART are caught up at the next stop, each frame
        # keeping its own times); with faults on the mocap link it stops at every mocap event, as the
        # faults act at the time a frame reaches the link, and captures no exposure inside a batch
        exact = self.faults.has_mocap_faults
        mocap, vehicle, rec = self.mocap, self.vehicle, self.recorder
        next_mocap = mocap.next_event_s if exact else mocap.mocap.next_exposure_s
        fast, time_after = self._capturing
        self._loop_parts = (
            exact, next_mocap, self.wire.next_arrival_s, self._step, clock.advance_to, mocap.update,
            mocap.deliver, rec.sample, self.server.poll, vehicle.pose_values, vehicle.state_vector,
            self._state_row, self._dt_s, None if exact else fast, time_after, self._exposure_period_s,
            self._gap_pose, rec, vehicle)
        #: as the last `advance_to` left them: the next exposure's time (s; asked again with faults on the
        #: mocap link, where it is the next mocap event), the vehicle's time (s) and its step count then (the
        #: time is asked again when something else stepped it since)
        self._m_next, self._t_vehicle, self._steps_at = next_mocap(), vehicle.time_s, vehicle.steps

    @property
    def time_s(self) -> float:
        return self.clock.now_s()

    @property
    def diverged_s(self) -> float | None:
        """Sim time (s) the simulated state stopped being a state (NaN, Inf, or too large for any wire
        format), as far as seen; None while it is one. A run ends there: nothing after it means anything."""
        return self._overflow_s if self._overflow_s is not None else self.recorder.nonfinite_seen_s

    def advance_to(self, t_end_s: float) -> float | None:
        """Run the emulator side from now to ``t_end_s`` (s), then let the FC answer and send what is
        due at ``t_end_s`` and put the command-link bytes that have arrived on the wire. Once the state
        has diverged (`diverged_s`) it does nothing. Returns `diverged_s` as it leaves it (a loop
        checks it after every call: no property read a tick)."""
        if self._overflow_s is not None:
            return self._overflow_s
        t = self.clock.now_s()
        (exact, next_mocap, next_arrival, step, advance_clock, update, deliver, sample, poll, pose_values,
         state_vector, state_row, dt, fast, time_after, period, gap_pose, rec, vehicle) = self._loop_parts
        floor = math.floor
        boundary = self._next_boundary_s  # (changed only where a fault switches, below)
        t_stop = t_end_s - 1e-12
        # an exposure between two other stops needs only the pose at its step: the stepper (``fast``)
        # captures it while it flies on to the next stop (`FastStepper.step`'s ``capture_at``), and the
        # exposure is taken there, before anything else of that stop, as a stop of its own would have
        # taken it first; not with faults on the mocap link, a frozen mocap, or another stepper.
        # The next mocap event, command frame's arrival and sample change only where the loop acts on
        # them (an exposure or a delivery, the FC's poll, a sample, a fault switching): asked there (the
        # next exposure and the vehicle's time kept from the last call, see ``__init__``)
        m_next = next_mocap() if exact else self._m_next
        arrival, next_sample = next_arrival(), rec.next_sample_s
        t_vehicle = self._t_vehicle if vehicle.steps == self._steps_at else vehicle.time_s
        #: an exposure taken at a stop after its own, while it is taken: its time (s) and pose
        exposing: tuple[float, tuple[float, ...]] | None = None
        try:
            while t < t_stop:
                t_next = t_end_s  # (the earliest of the five, as min() but without a call a stop)
                if arrival < t_next:
                    t_next = arrival
                if next_sample < t_next:
                    t_next = next_sample
                if boundary < t_next:
                    t_next = boundary
                if m_next < t_next:
                    if (fast is not None and t + 1e-9 <= m_next < t_next - 1e-9
                            and t_next < m_next + period - 1e-9 and self._frozen_truth is None):
                        # (the one exposure before t_next, well apart from it and from now)
                        k = floor((m_next - t_vehicle) / dt + 1e-6)  # physics steps up to the exposure
                        if k < 0:
                            k = 0
                        n = floor((t_next - time_after(k)) / dt + 1e-6)  # and on from there to t_next
                        if n < 0:
                            n = 0
                        if k > 0:
                            t_vehicle = fast.step(k + n, t_vehicle, k)
                            pose = fast.pose_captured
                        else:
                            pose = pose_values()
                            if n > 0:
                                t_vehicle = fast.step(n, t_vehicle)
                        exposing = (m_next, pose)
                        update(m_next, pose, gap_pose)
                        exposing = None
                        m_next = next_mocap()
                        n = 0
                    else:
                        t_next = m_next
                        n = -1
                else:
                    n = -1
                if n < 0:
                    if t_next < t + 1e-9:
                        t_next = t + 1e-9
                    n = floor((t_next - t_vehicle) / dt + 1e-6)  # physics steps up to t_next
                    if n > 0:
                        t_vehicle = step(n, t_vehicle)  # (the stepper's time, or None: the vehicle's)
                        if t_vehicle is None:
                            t_vehicle = vehicle.time_s
                # the clock reads a stop's time where something there reads the clock: the FC's poll,
                # a fault switching; at every stop with faults on the mocap link (the frames reaching
                # the link) or another stepper (the ESC bus's messages to the FC); the mocap chain, the
                # batched stepper and the recorder take the time as an argument
                if fast is None:
                    advance_clock(t_next)
                t = t_next
                if t >= boundary - 1e-12:
                    # switch at the boundary itself: ``t`` may sit a rounding error before it, where the
                    # fault ending there would still read as active and never be switched off
                    advance_clock(t)
                    self._switch_faults(max(t, boundary))
                    boundary = self._next_boundary_s
                    m_next, arrival, t_vehicle = next_mocap(), next_arrival(), vehicle.time_s
                mocap_due = t >= m_next - 1e-12
                if mocap_due:
                    frozen = self._frozen_truth
                    update(t, pose_values() if frozen is None else frozen, gap_pose)
                    m_next = next_mocap()
                if t >= arrival - 1e-12:
                    advance_clock(t)
                    poll(t)
                    arrival = next_arrival()
                if t >= next_sample - 1e-12:
                    if not mocap_due:
                        deliver(t)
                        if exact:
                            m_next = next_mocap()
                    next_sample = sample(t, state_row if state_row is not None else state_vector())
            self._m_next, self._t_vehicle, self._steps_at = m_next, t_vehicle, vehicle.steps
            advance_clock(t)  # (the last stop's time, as the loop leaves the clock)
            deliver(t_end_s)
            poll(t_end_s)
            if not self.hold_mocap:
                self.mocap_link.flush()
            self.wire.pump()
            return rec.nonfinite_seen_s  # (`diverged_s`: no overflow on this path)
        except OverflowError:
            # a pose or a velocity past float32's range cannot be put on the wire (mocap, telemetry):
            # the physics diverged, which a run reports as such instead of crashing
            # (an exposure taken after its step: its own time and pose, as at a stop of its own)
            advance_clock(t)  # (the stop's time, where the clock is read from now on)
            t_bad, pose = (t, pose_values()) if exposing is None else exposing
            if all(abs(v) < DIVERGED_LIMIT for v in pose):
                raise
            self._overflow_s = t_bad
            return t_bad

    def checks_open_until_s(self) -> float | None:
        """Until when (sim s) a check's window is still open, as far as recorded: the recovery check
        looks ``recovery.time_s`` after the first crossing. None when no window is open or known; a
        loop ends a run no earlier than this (by up to `CHECK_OVERRUN_S` past its duration)."""
        e = self.scenario.expect
        crossed = self.recorder.first_crossing_seen_s
        if e.recovery is None or not e.crosses_gap or crossed is None:
            return None
        return crossed + e.recovery.time_s + CHECK_WINDOW_MARGIN_S

    def mission_events(self, events: list[dict[str, Any]]) -> None:
        """The onboard program reported ``events``: time the faults that wait for one of them, from now
        on (a fault never starts in the simulated past)."""
        faults = self.faults
        now = self.clock.now_s()
        for ev in events:
            name = event_name(ev)
            if name is not None and faults.at_event(name, float(ev["t_s"]), now):
                self._next_boundary_s = min(self._next_boundary_s, faults.next_boundary_s(now - 1e-9))

    def _switch_faults(self, t: float) -> None:
        self.faults.switch(t, self)
        self._next_boundary_s = self.faults.next_boundary_s(t)

    # what the faults of `hil.scenario.fault_kinds` act on (its `FaultTarget`)

    def set_wind(self, force_n: np.ndarray, moment_nm: np.ndarray) -> None:
        """An external force (N, world ENU) and moment (N m, body FLU) on the airframe from now on."""
        self.vehicle.backend.set_external_force(force_n)
        self.vehicle.backend.set_external_torque(moment_nm)

    def freeze_mocap(self, frozen: bool) -> None:
        """Keep the mocap reporting the pose of now (True) or the vehicle's again (False)."""
        if frozen and self._frozen_truth is None:
            self._frozen_truth = self.vehicle.pose_values()
        elif not frozen:
            self._frozen_truth = None

    def fc_param(self, name: str) -> float | int:
        """The FC parameter ``name``'s value."""
        return self.server.params.get(name)

    def set_fc_param(self, name: str, value: float | int, time_s: float, why: str) -> None:
        """Set an FC parameter as a ground station would (the change in the .tlog); one the FC refuses
        is said on the link as a warning (``why: reason``) and the run goes on."""
        try:
            self.server.params.set(name, value)
        except ParamError as exc:
            self.server.statustext(mav.MAV_SEVERITY_WARNING, f"{why}: {exc.reason}", time_s)

    # what the emulator side reports at the end of a run

    @property
    def attitude_lag_s(self) -> float:
        """The FC's nominal attitude response (s): the first-order lag its derived loop makes, 1 / its
        roll gain."""
        return 1.0 / self.vehicle.fc.gains.inner.attitude_p_per_s[0]

    def failsafes(self) -> tuple[tuple[str, float], ...]:
        """The failsafe states the FC entered, with when (state, sim s)."""
        return tuple((e.to_state.value, e.time_s) for e in self.vehicle.fc.events if e.to_state.failsafe)

    def fc_report_events(self) -> list[dict[str, Any]]:
        """The FC's state changes as report events."""
        events = self.vehicle.fc.events
        return [{"time_s": e.time_s, "source": "fc",
                 "text": f"{e.from_state.value} -> {e.to_state.value}: {e.reason}"} for e in events]

    def world_report_events(self) -> list[dict[str, Any]]:
        """The collision (if any) as a report event."""
        c = self.recorder.collision
        return [] if c is None else [{"time_s": c.time_s, "source": "world",
                                      "text": f"collision: {c.obstacle}"}]

    def summary_figures(self) -> dict[str, Any]:
        """The emulator side's own entries of summary.json: its links' statistics, the ESC bus's, the
        FC's final state."""
        return {
            "links": self.link_stats(),
            "esc_bus": None if self.esc is None else self.esc.summary(self.time_s),
            "fc_final_state": self.vehicle.fc.state.value,
        }

    def link_stats(self) -> dict[str, Any]:
        """The command and mocap links' statistics over the run: a ``summary`` of delivered fractions
        and rates (what the link checks read) and each link's counters."""
        wire, server, mocap = self.wire, self.server, self.mocap
        st = mocap.stats
        sim = max(self.time_s, 1e-9)
        sent = wire.setpoints_sent
        applied = server.stats.setpoints_applied
        radio = st.radio
        summary = {
            "command_delivered_fraction": applied / sent if sent else None,
            "command_rate_hz": applied / sim,
            "mocap_delivered_fraction": radio.delivered / radio.sent if radio.sent else None,
            "mocap_rate_hz": st.frames_written / sim,
        }
        return {
            "summary": summary,
            "command": {
                "setpoints_sent": sent,
                "setpoints_applied": applied,
                **{f"to_fc_{k}": v for k, v in wire.to_fc.as_dict().items()},
                **{f"to_onboard_{k}": v for k, v in wire.to_onboard.as_dict().items()},
                **{f"fc_codec_{k}": v for k, v in self.codec.stats.as_dict().items()},
            },
            "mocap": {
                "frames_exposed": st.mocap.frames,
                "radio_sent": radio.sent,
                "radio_delivered": radio.delivered,
                "radio_lost": radio.lost,
                "radio_late": radio.late,
                "frames_written": st.frames_written,
                "bytes_written": st.bytes_written,
                "bytes_dropped_fault": self.mocap_link.bytes_dropped_fault,
                "bytes_corrupted": self.mocap_link.bytes_corrupted,
            },
        }

    def close(self) -> None:
        self.vehicle.close()
