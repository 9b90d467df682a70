"""Batched steps of an emulated vehicle: while the FC flies an offboard attitude target, or holds,
hovers or lands in the air on its own velocity controller, its controller and the native physics run
together in one numba call for a whole batch of 1 kHz steps (the lockstep runner's fast path; it lives
here because it keeps the FC's and the backend's own bookkeeping).

Same arithmetic as `EmulatedVehicle.step` (the FC's controller, then one physics step, each
millisecond); a batch stops before anything the FC's own step would act on: the setpoint-loss timeout,
the failsafe hover's end, the body reaching the ground. Anything else (other FC states, other
backends, yaw-rate targets) takes the vehicle's own per-step path.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from emulator.fc import EmulatedVehicle, FcState
from emulator.fc.flight_controller import HOLD_STATES
from emulator.fc.hold import hold_command
from emulator.fc.inner_loop import _control
from emulator.physics.kernels import step_vehicle
from emulator.physics.native import NativeBackend

#: FC states flown by the velocity controller while in the air, with their climb rate's sign
_CLIMB_SIGN = {st: -1.0 if st in (FcState.LAND, FcState.FAILSAFE_LAND) else 0.0 for st in HOLD_STATES}


@njit(cache=True, nogil=True)
def _fly_batch(x, aux, p, roll, pitch, yaw, thrust_n, gains, mix_inv, out, n_steps):  # pragma: no cover
    for _ in range(n_steps):
        _control(x[6:10], x[10:13], roll, pitch, yaw, thrust_n, gains, mix_inv, out)
        step_vehicle(x, aux, p, out, 1)


@njit(cache=True, nogil=True)
def _hold_batch(x, aux, p, hold, hold_params, gains, mix_inv, out, n_steps):  # pragma: no cover
    """Velocity-hold steps (`FlightController._velocity_hold` per step) until ``n_steps`` or the body
    would count as landed; returns the steps taken. ``hold``: climb rate (m/s, up), yaw (NED, rad),
    rest height (m), landed margin (m); ``hold_params``: the FC's `hold_params`."""
    climb, yaw, rest_z, margin = hold[0], hold[1], hold[2], hold[3]
    for k in range(n_steps):
        if x[2] - rest_z <= margin and abs(x[5]) < 0.3:
            return k  # the FC would see the landing at this step: its own step takes over
        roll, pitch, thrust = hold_command(x[3], x[4], x[5], climb, yaw, hold_params)
        _control(x[6:10], x[10:13], roll, pitch, yaw, thrust, gains, mix_inv, out)
        step_vehicle(x, aux, p, out, 1)
    return n_steps


class FastStepper:
    """Steps one EmulatedVehicle; batches offboard flight on the native backend (see the module doc)."""

    def __init__(self, vehicle: EmulatedVehicle, native: bool) -> None:
        self.vehicle = vehicle
        self.native = native
        self.batched_steps = 0
        self.single_steps = 0
        self._hold = np.zeros(4)

    @classmethod
    def for_vehicle(cls, vehicle: EmulatedVehicle) -> FastStepper:
        stepper = cls(vehicle, isinstance(vehicle.backend, NativeBackend))
        if stepper.native:  # compile (or load from the cache) now, not inside the timed loop
            be, inner = vehicle.backend, vehicle.fc.inner
            _fly_batch(be._x, be._aux, be._params, 0.0, 0.0, 0.0, 0.0, inner._params, inner._mix_inv,
                       inner._out, 0)
            _hold_batch(be._x, be._aux, be._params, stepper._hold, vehicle.fc.hold_params, inner._params,
                        inner._mix_inv, inner._out, 0)
        return stepper

    def step(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps."""
        v = self.vehicle
        while n_steps > 0:
            n = self._batchable(n_steps)
            if n > 0:
                self._fly(n)
                n_steps -= n
                continue
            n = self._hold_steps(n_steps)
            if n > 0:
                n_steps -= n
                continue
            v.step(1)
            self.single_steps += 1
            n_steps -= 1

    def _batchable(self, n_steps: int) -> int:
        """How many of the next steps can run in one batch (0: take the per-step path)."""
        v = self.vehicle
        fc = v.fc
        tg = fc.target
        if (
            not self.native
            or fc.machine.state is not FcState.OFFBOARD
            or tg is None
            or tg.yaw_rate_rad_s is not None
        ):
            return 0
        # the FC checks the timeout before each step at the step's start time
        room = fc.last_setpoint_s + fc.config.failsafe_timeout_s - v.time_s
        n_ok = int(room / v.backend.dt_s) if room > 0 else 0
        return n_steps if n_steps < n_ok else n_ok

    def _hold_steps(self, n_steps: int) -> int:
        """Up to ``n_steps`` batched steps of the FC's velocity hold (hold, hover, land in the air);
        returns the steps taken (0: take the per-step path)."""
        v = self.vehicle
        fc = v.fc
        sign = _CLIMB_SIGN.get(fc.state)
        if not self.native or sign is None or fc.landed:
            return 0
        cfg = fc.config
        if fc.state is FcState.FAILSAFE_HOVER:  # ends failsafe_hover_s after it began
            room = fc.machine.since_s + cfg.failsafe_hover_s - v.time_s
            n_steps = min(n_steps, int(room / v.dt_s) if room > 0 else 0)
        elif fc.state is FcState.HOLD and fc.offboard_selected and not fc.stream_ok(v.time_s):
            return 0
        if n_steps <= 0:
            return 0
        be, inner = v.backend, fc.inner
        assert isinstance(be, NativeBackend)
        h = self._hold
        h[0] = sign * cfg.land_speed_m_s
        h[1] = fc.hold_heading_rad(be._x[6:10])  # latched at the first hold step, as the FC's own
        h[2] = fc._rest_height_m
        h[3] = cfg.landed_margin_m
        n = _hold_batch(be._x, be._aux, be._params, h, fc.hold_params, inner._params, inner._mix_inv,
                        inner._out, n_steps)
        if n > 0:  # every step began in the air: the FC's landed flag stays as it was
            self._after_batch(n, detect_landed=False)
        return n

    def _fly(self, n: int) -> None:
        v = self.vehicle
        fc, be, inner = v.fc, v.backend, v.fc.inner
        tg = fc.target
        assert tg is not None and isinstance(be, NativeBackend)
        _fly_batch(
            be._x,
            be._aux,
            be._params,
            tg.roll_rad,
            tg.pitch_rad,
            tg.yaw_rad,
            tg.thrust_n,
            inner._params,
            inner._mix_inv,
            inner._out,
            n,
        )
        self._after_batch(n)

    def _after_batch(self, n: int, detect_landed: bool = True) -> None:
        v = self.vehicle
        fc, be = v.fc, v.backend
        assert isinstance(be, NativeBackend)
        be._steps += n
        v.steps += n
        self.batched_steps += n
        v.invalidate_state()  # no VehicleState per batch: built only when someone reads it
        x = be._x
        # the FC's bookkeeping as its own per-step update would have left it
        t_last = be.time_s - be.dt_s
        fc._last_t = t_last
        if detect_landed:
            fc.detect_landed(x.item(2), x.item(5), t_last)  # (plain floats: the same comparisons)
        fc.motor_cmd = fc.inner._out
