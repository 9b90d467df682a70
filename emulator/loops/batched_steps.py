"""Batched steps of an emulated vehicle: while the FC flies an offboard attitude target, or holds,
hovers or lands in the air on its own velocity controller, its controller and the native physics run
together in one numba call for a whole batch of 1 kHz steps (the lockstep runner's fast path).

It steps through the public contract of its parts: the backend's `NativeBackend.kernel_buffer` (its
clock counted there, `KERNEL_CLOCK`), the inner loop's `control` kernel with its ``params``, ``mix_inv``
and ``motor_cmd`` (its ``buffer``, split by `loop_views`), the FC's `hold_command` parameters,
`landed_test` (the hold's), `batch_plan`, `quiet_steps` and `flew_outside`.
Same arithmetic as `EmulatedVehicle.step` (the FC's controller, then one physics step, each
millisecond); a batch stops before anything the FC's own step would act on: the setpoint-loss timeout,
the failsafe hover's end, the body reaching the ground. Anything else (other FC states, other backends,
yaw-rate targets) takes the vehicle's own per-step path.

numba caches these kernels in a folder per digest of the emulator's sources (`emulator.kernel_cache`):
a change to a kernel they call from another module (the inner loop with its mixer, the physics step)
compiles them afresh.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from emulator.fc import FcState
from emulator.fc.flight_controller import HOLD_STATES, steps_before
from emulator.fc.hold import hold_command
from emulator.fc.inner_loop import control, control_quat, loop_views, target_quat_floats
from emulator.fc.landed import body_landed
from emulator.kernel_cache import entry
from emulator.physics.kernels import step_vehicle
from emulator.physics.native import KERNEL_CLOCK, KERNEL_PARAMS, KERNEL_POSE, NativeBackend
from emulator.physics.state import QUAT, STATE_SIZE
from emulator.vehicle import EmulatedVehicle
from emulator.world.box_kernel import check_packed, quat_to_rot_into

_steps_before = njit(cache=True, nogil=True)(steps_before)  # (the FC's count, compiled for `_fly_batch`)


@njit(cache=True)  # (GIL kept: releasing and taking it around a few-us call costs more than it saves)
def _fly_batch(buf, roll, pitch, yaw, thrust_n, until_s, rest_z, margin, loop, n_max, time_s, dt_s,
               capture_at, landed_now):  # pragma: no cover
    """The steps of a held attitude target (the FC's `batch_plan`: ``until_s`` its setpoint-loss
    failsafe's time (s), ``rest_z`` and ``margin`` its landed test's resting height and margin (m)) that
    begin before ``until_s``, of the next ``n_max`` steps of ``dt_s`` from ``time_s`` (s)
    (`steps_before`), on the backend's `NativeBackend.kernel_buffer` ``buf`` with the inner loop's
    ``buffer`` ``loop``, the steps counted on its clock; returns (the steps flown, the FC's landed test of
    the body after them: `FlightController.detect_landed`, the backend's time after them (s)).

    ``capture_at`` (1 to ``n_max``; 0: none): the pose after that many steps is copied into ``buf``'s
    captured pose (`NativeBackend.captured_pose`) and the batch flies on, as two batches split there would
    have flown (the steps taken said by the count returned: at least ``capture_at`` when captured). Where
    the split could differ the batch ends at the capture, as the first of the two would: when the
    setpoint-loss time lies within a step of the batch's end (the second's count is then its own), and
    when the landed test after the capture differs from the FC's ``landed_now`` (the FC acts on it)."""
    if capture_at > 0 and _steps_before(until_s - time_s, dt_s, n_max + 1) <= n_max:
        n_max = capture_at
    n_steps = _steps_before(until_s - time_s, dt_s, n_max)
    if n_steps <= 0:
        return 0, False, time_s
    x, aux, p = buf[:STATE_SIZE], buf[STATE_SIZE:KERNEL_PARAMS], buf[KERNEL_PARAMS:KERNEL_POSE]
    gains, mix_inv, out = loop_views(loop)
    d0, d1, d2, d3 = target_quat_floats(roll, pitch, yaw)  # the target is held: its quaternion once
    at = capture_at if capture_at > 0 else -1
    for i in range(n_steps):
        if i == at:
            _capture(x, buf)
            landed = body_landed(x[2], x[5], rest_z, margin)
            if landed != landed_now:
                return i, landed, _count(buf, i, dt_s)
        control_quat(x[6:10], x[10:13], d0, d1, d2, d3, thrust_n, gains, mix_inv, out)
        step_vehicle(x, aux, p, out, 1)
    if n_steps == capture_at:
        _capture(x, buf)
    return n_steps, body_landed(x[2], x[5], rest_z, margin), _count(buf, n_steps, dt_s)


@njit(cache=True, nogil=True, inline="always")
def _count(buf, n_steps, dt_s):  # pragma: no cover
    """Count ``n_steps`` steps of ``dt_s`` (s) taken on ``buf``'s clock (`KERNEL_CLOCK`); returns the
    backend's time after them (s), as `NativeBackend.advance_clock` gives it."""
    steps = buf[KERNEL_CLOCK] + n_steps
    buf[KERNEL_CLOCK] = steps
    return buf[KERNEL_CLOCK + 1] + steps * dt_s


@njit(cache=True, nogil=True, inline="always")
def _capture(x, buf):  # pragma: no cover
    """The pose of state row ``x`` into ``buf``'s captured pose (`NativeBackend.captured_pose`)."""
    at = KERNEL_POSE
    buf[at], buf[at + 1], buf[at + 2] = x[0], x[1], x[2]
    buf[at + 3], buf[at + 4], buf[at + 5], buf[at + 6] = x[6], x[7], x[8], x[9]


@njit(cache=True, nogil=True, inline="always")
def _checked(x, world, rot, least):  # pragma: no cover
    """A row's world check after a physics step: (its obstacle code, its least clearance so far (m))."""
    quat_to_rot_into(x[6:10], rot)
    code, clr, _, _ = check_packed(x[0:3], rot, world)
    return code, min(least, clr)


@njit(cache=True, parallel=True)
def fly_targets(xs, auxs, p, targets, gains, mix_inv, outs, n_steps, worlds, which, every_step, codes,
                clearance):  # pragma: no cover
    """Many vehicles of one profile, each flying its own offboard attitude target for ``n_steps`` physics
    steps (the FC's inner loop, then one physics step, each step: `_fly_batch`'s arithmetic), rows in
    parallel, the world checked (`emulator.world.box_kernel`, row i against ``worlds[which[i]]``) after
    every physics step (``every_step``) or after the last one. Rows of ``xs`` (N, STATE_SIZE) and ``auxs``
    (N, AUX_SIZE) (`BatchPhysics.kernel_arrays`) advance in place; ``targets`` (N, 4): NED roll, pitch,
    yaw (rad) and thrust (N), already within the FC's limits; ``gains``, ``mix_inv``: an `InnerLoop`'s
    ``params`` and ``mix_inv``; ``outs`` (N, 4): the last throttles. A row stops at its first collision,
    its code (0: none) in ``codes`` (N,), its least clearance over the checks (m) in ``clearance`` (N,).
    No FC state: the caller keeps the vehicles in OFFBOARD.

    Rows go in pairs, a physics step of one and then of the other: each row's step depends on its last
    one, and two independent chains side by side keep the core busier (the flight 13 % faster here);
    each row's arithmetic is its own, the same as flown alone."""
    n = xs.shape[0]
    for j in prange((n + 1) // 2):
        a = 2 * j
        b = a + 1 if a + 1 < n else a  # (an odd batch's last pair is one row)
        xa, auxa, outa, tga = xs[a], auxs[a], outs[a], targets[a]
        xb, auxb, outb, tgb = xs[b], auxs[b], outs[b], targets[b]
        a0, a1, a2, a3 = target_quat_floats(tga[0], tga[1], tga[2])
        b0, b1, b2, b3 = target_quat_floats(tgb[0], tgb[1], tgb[2])
        codes[a] = codes[b] = 0
        live_a, live_b = True, b != a
        least_a = least_b = np.inf
        rot = np.empty((3, 3))
        for k in range(n_steps):
            if live_a:
                control_quat(xa[6:10], xa[10:13], a0, a1, a2, a3, tga[3], gains, mix_inv, outa)
                step_vehicle(xa, auxa, p, outa, 1)
            if live_b:
                control_quat(xb[6:10], xb[10:13], b0, b1, b2, b3, tgb[3], gains, mix_inv, outb)
                step_vehicle(xb, auxb, p, outb, 1)
            if every_step or k == n_steps - 1:
                if live_a:
                    codes[a], least_a = _checked(xa, worlds[which[a]], rot, least_a)
                    live_a = codes[a] == 0
                if live_b:
                    codes[b], least_b = _checked(xb, worlds[which[b]], rot, least_b)
                    live_b = codes[b] == 0
                if not (live_a or live_b):
                    break
        clearance[a] = least_a
        if b != a:
            clearance[b] = least_b


@njit(cache=True)  # (the GIL kept, as for `_fly_batch`)
def _hold_batch(buf, climb, yaw, landed_test, hold_params, loop, n_steps, dt_s):  # pragma: no cover
    """Velocity-hold steps (`FlightController._velocity_hold` per step) of ``dt_s`` (s) at climb rate
    ``climb`` (m/s, up) and heading ``yaw`` (NED, rad) until ``n_steps`` or the body would count as
    landed (`FlightController.detect_landed`, ``landed_test``: its `FlightController.landed_test`), on
    the backend's `NativeBackend.kernel_buffer` ``buf`` with the inner loop's ``buffer`` ``loop``, the
    steps counted on its clock; returns (the steps taken, the backend's time after them (s))."""
    x, aux, p = buf[:STATE_SIZE], buf[STATE_SIZE:KERNEL_PARAMS], buf[KERNEL_PARAMS:KERNEL_POSE]
    gains, mix_inv, out = loop_views(loop)
    rest_z, margin = landed_test[0], landed_test[1]
    for k in range(n_steps):
        if body_landed(x[2], x[5], rest_z, margin):
            # the FC would see the landing at this step: its own step takes over
            return k, _count(buf, k, dt_s)
        roll, pitch, thrust = hold_command(x[3], x[4], x[5], climb, yaw, hold_params, 0.0, 0.0)
        control(x[6:10], x[10:13], roll, pitch, yaw, thrust, gains, mix_inv, out)
        step_vehicle(x, aux, p, out, 1)
    return n_steps, _count(buf, n_steps, dt_s)


class FastStepper:
    """Steps one EmulatedVehicle; batches offboard flight on the native backend (see the module doc)."""

    def __init__(self, vehicle: EmulatedVehicle, native: bool) -> None:
        self.vehicle = vehicle
        self.native = native
        self.batched_steps = 0
        self.single_steps = 0
        self._dt_s = vehicle.dt_s  # (the backend's step, fixed for its life)
        #: the pose (x, y, z (m), qw, qx, qy, qz) a `step` with ``capture_at`` captured
        self.pose_captured: tuple[float, ...] = ()
        # what a batch reads, bound once (a tick batches about three times): the vehicle's FC and
        # backend, and the arrays the kernels advance in place (`NativeBackend.kernel_arrays`, the inner
        # loop's, the FC's landed test), the same objects for the backend's life
        self._fc = vehicle.fc
        self._backend = vehicle.backend
        if native:
            fc = vehicle.fc
            inner = fc.inner
            self._buffer = buf = vehicle.backend.kernel_buffer  # type: ignore[attr-defined]
            self._x = vehicle.backend.kernel_arrays[0]  # type: ignore[attr-defined]
            self._loop = loop = inner.buffer
            self._landed_test = landed_test = fc.landed_test
            # the kernels' forms for these arrays, floats and ints (compiled or loaded from the cache
            # now, not inside the timed loop), called without numba's type dispatch
            self._fly_batch = entry(_fly_batch, buf, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, loop, 0, 0.0, 0.0, 0,
                                    False)
            self._captured_pose = vehicle.backend.captured_pose  # type: ignore[attr-defined]
            self._pose_values = vehicle.backend.pose_values  # type: ignore[attr-defined]
            self._hold_batch = entry(_hold_batch, buf, 0.0, 0.0, landed_test, fc.hold_params, loop, 0, 0.0)

    @classmethod
    def for_vehicle(cls, vehicle: EmulatedVehicle) -> FastStepper:
        return cls(vehicle, isinstance(vehicle.backend, NativeBackend))

    def step(self, n_steps: int, time_s: float | None = None, capture_at: int = 0) -> float | None:
        """Advance ``n_steps`` physics steps from the backend's time ``time_s`` (s; None: read it);
        returns the vehicle's time (s) after them on the native backend (None on another: ask the
        vehicle). ``capture_at`` (1 to ``n_steps``; 0: none): the pose after that many of the steps
        (`NativeBackend.pose_values` then) is kept in ``pose_captured``, the steps the same, in the same
        order, as two calls split there would take (a batch flies through it: `_fly_batch`)."""
        if not self.native:
            v = self.vehicle
            if capture_at > 0:
                v.step(capture_at)
                self.pose_captured = v.pose_values()
                n_steps -= capture_at
            v.step(n_steps)
            self.single_steps += n_steps + capture_at
            return None
        fc, v, dt = self._fc, self.vehicle, self._dt_s
        if time_s is None:
            time_s = self._backend.time_s
        capture = capture_at  # (the steps still before the capture; 0: none, or taken)
        while n_steps > 0:
            n = 0
            plan = fc.batch_plan  # (an offboard attitude target: flown in batches, `batch_target`)
            if plan is not None:
                # (the kernel counts the steps on the backend's clock and hands back its time)
                n, landed, t_after = self._fly_batch(self._buffer, *plan, self._loop, n_steps, time_s, dt,
                                                     capture, fc.landed)
            if n == 0:
                landed = None  # (the hold batch stops before a landing: the flag stays as it is)
                n, t_after = self._hold_steps(capture or n_steps, time_s)
            if n > 0:
                # the counts and the FC's bookkeeping as its own per-step update would have left them (the
                # vehicle builds its state anew once its step count has moved)
                time_s = t_after
                v.steps += n
                self.batched_steps += n
                fc.flew_outside(time_s - dt, landed)
            else:
                v.step(1)
                self.single_steps += 1
                n = 1
                time_s = self._backend.time_s
            n_steps -= n
            if capture:
                if n < capture:
                    capture -= n
                else:  # (past it: captured inside the batch; at it: the pose now)
                    self.pose_captured = self._captured_pose() if n > capture else self._pose_values()
                    capture = 0
        return time_s

    def _hold_steps(self, n_steps: int, time_s: float) -> tuple[int, float]:
        """Up to ``n_steps`` batched steps of the FC's velocity hold (hold, hover, land in the air) from
        the backend's time ``time_s`` (s); returns (the steps taken (0: take the per-step path), the
        backend's time after them (s)). Every step taken began in the air: the FC's landed flag stays as
        it was."""
        fc = self._fc
        st = fc.machine.state
        if st not in HOLD_STATES or fc.landed:
            return 0, time_s
        if st is FcState.HOLD and fc.offboard_selected and not fc.stream_ok(time_s):
            return 0, time_s
        dt = self._dt_s
        n_steps = fc.quiet_steps(time_s, dt, n_steps)
        if n_steps <= 0:
            return 0, time_s
        yaw = fc.hold_heading_rad(self._x[QUAT])  # latched at the first hold step, as the FC's own
        return self._hold_batch(self._buffer, fc.hold_climb_m_s(), yaw, self._landed_test, fc.hold_params,
                                self._loop, n_steps, dt)
