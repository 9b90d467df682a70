"""Batched steps of an emulated vehicle: while the FC flies an offboard attitude target, its inner loop
and the native physics run together in one numba call for a whole batch of 1 kHz steps (the lockstep
runner's fast path; it lives here because it keeps the FC's and the backend's own bookkeeping).

Same arithmetic as `EmulatedVehicle.step` (the FC's inner-loop kernel, then one physics step, each
millisecond); the batch stops before the FC's setpoint-loss timeout could fire, and anything else
(other FC states, other backends) takes the vehicle's own per-step path.
"""

from __future__ import annotations

from numba import njit

from emulator.fc import EmulatedVehicle, FcState
from emulator.fc.inner_loop import _control
from emulator.physics.kernels import step_vehicle
from emulator.physics.native import NativeBackend


@njit(cache=True, nogil=True)
def _fly_batch(x, aux, p, roll, pitch, yaw, thrust_n, gains, mix_inv, out, n_steps):  # pragma: no cover
    for _ in range(n_steps):
        _control(x[6:10], x[10:13], roll, pitch, yaw, thrust_n, gains, mix_inv, out)
        step_vehicle(x, aux, p, out, 1)


class FastStepper:
    """Steps one EmulatedVehicle; batches offboard flight on the native backend (see the module doc)."""

    def __init__(self, vehicle: EmulatedVehicle, native: bool) -> None:
        self.vehicle = vehicle
        self.native = native
        self.batched_steps = 0
        self.single_steps = 0

    @classmethod
    def for_vehicle(cls, vehicle: EmulatedVehicle) -> FastStepper:
        stepper = cls(vehicle, isinstance(vehicle.backend, NativeBackend))
        if stepper.native:  # compile (or load from the cache) now, not inside the timed loop
            be, inner = vehicle.backend, vehicle.fc.inner
            _fly_batch(be._x, be._aux, be._params, 0.0, 0.0, 0.0, 0.0, inner._params, inner._mix_inv,
                       inner._out, 0)
        return stepper

    def step(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps."""
        v = self.vehicle
        while n_steps > 0:
            n = self._batchable(n_steps)
            if n == 0:
                v.step(1)
                self.single_steps += 1
                n_steps -= 1
                continue
            self._fly(n)
            n_steps -= n

    def _batchable(self, n_steps: int) -> int:
        """How many of the next steps can run in one batch (0: take the per-step path)."""
        v = self.vehicle
        fc = v.fc
        tg = fc.target
        if not self.native or fc.state is not FcState.OFFBOARD or tg is None or tg.yaw_rate_rad_s is not None:
            return 0
        # the FC checks the timeout before each step at the step's start time
        room = fc.last_setpoint_s + fc.config.failsafe_timeout_s - v.time_s
        n_ok = int(room / v.dt_s) if room > 0 else 0
        return min(n_steps, n_ok)

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
        be._steps += n
        v.steps += n
        self.batched_steps += n
        v.invalidate_state()  # no VehicleState per batch: built only when someone reads it
        x = be._x
        # the FC's bookkeeping as its own per-step update would have left it
        t_last = be.time_s - v.dt_s
        fc._last_t = t_last
        fc._quat = x[6:10].copy()
        fc.detect_landed(x[2], x[5], t_last)
        fc.motor_cmd = inner._out
