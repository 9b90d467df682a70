"""The onboard state estimate: position, velocity and acceleration from timestamped mocap poses (a
constant-acceleration Kalman filter per axis), attitude straight from the mocap quaternion.

Mocap gives pose only; velocity and acceleration are estimated here, as on the real vehicle (where
position and velocity come from motion capture too). The filter runs on the mocap exposure stamps, so
link jitter does not enter the derivatives; the estimate handed to a pilot is predicted from the
latest stamp over the time since that pose arrived plus a configured exposure-to-arrival latency (the
two clocks need not agree, so the mean latency is a setting, not a measurement). The pose-to-pose
variation of that latency (radio jitter, 5 ms std by default) is measured, though: the arrival-minus-
stamp difference is averaged over ``delay_window_s``, and a pose that came later than the average is
predicted over the extra delay (clock offset and slow drift cancel in the difference).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hil.link.mavlink import euler_from_quat
from policies.compiling import Kernel


@dataclass(frozen=True)
class EstimatorConfig:
    """Noise model: mocap position noise (m, 1 sigma), jerk spectral density ((m/s^3)^2 s), reset gap (s),
    the mean latency (s) from exposure to arrival that the estimate is predicted over, and the window (s)
    over which the arrival-minus-stamp difference is averaged to take out the jitter around that mean."""

    pos_noise_m: float = 0.003
    jerk_psd: float = 2000.0
    #: a silence longer than this restarts the filter at rest: between two stamps, or between two
    #: accepted arrivals (then whatever the new stamp: a mocap clock that jumped back is followed)
    reset_after_s: float = 0.5
    # exposure -> arrival with the default links: camera 5.6 ms + processing 0.5 ms + UWB radio 20 ms
    # + air and UART time ~1 ms + reading ~1 ms (measured mean 28.3 ms, std 4.4 ms)
    latency_s: float = 0.028
    delay_window_s: float = 1.0  # time constant of the running mean of (arrival - stamp)
    #: a pose further than this many times ``pos_noise_m`` (per axis) from where the filter predicts it, on
    #: top of what the vehicle's acceleration limit and ``max_speed_change_m_s`` move it in the interval, is
    #: no pose of the vehicle
    jump_sigmas: float = 10.0
    #: the speed (m/s) a crash can take or give the vehicle at once, faster than its rotors can: a fall
    #: stopped by the floor (the filter has predicted the fall) or the start of a filter restarted at rest
    max_speed_change_m_s: float = 6.0

    def __post_init__(self) -> None:
        for name in ("pos_noise_m", "jerk_psd", "reset_after_s", "delay_window_s", "jump_sigmas",
                     "max_speed_change_m_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"EstimatorConfig.{name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.latency_s) and 0 <= self.latency_s < self.reset_after_s):
            raise ValueError(f"EstimatorConfig.latency_s must be in [0, reset_after_s), got {self.latency_s}")


@dataclass(frozen=True)
class StateEstimate:
    """Position (m), velocity (m/s), acceleration (m/s^2) in world ENU; ZYX Euler angles (rad) and the
    attitude quaternion (w, x, y, z) of body FLU -> world ENU."""

    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    euler_rad: np.ndarray
    quat_wxyz: np.ndarray


class PoseEstimator:
    """Feed poses with `update(stamp_s, pos_m, quat_wxyz, received_s)`; read `estimate(now_s)`.

    The per-axis filters share one covariance (the same model and measurements on every axis), kept as
    the six scalars of the symmetric 3x3 matrix; the products with F and Q are written out. A pose goes in
    through `take_pose` and the state comes out through `predicted_state`, each one compiled call
    (`policies.compiling`) on the state kept in one array.

    Given the vehicle's acceleration limit ``max_accel_m_s2`` (thrust / mass + g), a pose the vehicle
    cannot have reached from the filter's state is refused (`plausible_jump_m`; counted in ``rejected``
    and ``implausible``): a glitch of the tracker (a swapped rigid body, a reflection) is not flown on.
    Without it (inf) every finite pose in order is taken."""

    def __init__(self, config: EstimatorConfig | None = None, max_accel_m_s2: float = math.inf) -> None:
        self.config = config or EstimatorConfig()
        if not max_accel_m_s2 > 0:
            raise ValueError(f"max_accel_m_s2 must be a positive number, got {max_accel_m_s2!r}")
        self.max_accel_m_s2 = max_accel_m_s2
        #: the filter's state, the latest pose's attitude and the counters, then the settings, as
        #: `take_pose` and `predicted_state` keep and read them (`STATE_FLOATS`; the properties below read
        #: it): one array, so that a compiled call unpacks one array argument, not two
        self._state = np.zeros(STATE_FLOATS)
        self._state[_STAMP] = self._state[_RECEIVED] = -math.inf
        self._state[_QUAT] = 1.0  # (level until the first pose)
        cfg = self.config
        self._state[_SETTINGS:] = (cfg.pos_noise_m, cfg.jerk_psd, cfg.delay_window_s, cfg.reset_after_s,
                                   cfg.latency_s, max_accel_m_s2, cfg.max_speed_change_m_s, cfg.jump_sigmas)
        self._euler: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._euler_at = 0.0  # the `updates` count `_euler` was made at
        # (the compiled forms for this state's array and floats: no dispatch a call)
        self._take = TAKE_POSE.entry(self._state, *(0.0,) * 9)
        self._predict = PREDICTED_STATE.entry(self._state, 0.0)

    @property
    def state(self) -> np.ndarray:
        """The array `take_pose` keeps and `predicted_state` reads (`STATE_FLOATS`): a compiled step's
        argument, not to be written by its callers."""
        return self._state

    def keep_state_in(self, view: np.ndarray) -> None:
        """Keep the state in ``view`` from now on (float64, `STATE_FLOATS`, C-contiguous: a part of a larger
        array that a compiled call takes whole, one array argument instead of several); the state so far is
        copied there, and `state` is ``view`` (ask for it after this)."""
        view[:] = self._state
        self._state = view

    @property
    def ready(self) -> bool:
        return self._state.item(_READY) != 0.0

    @property
    def quat_wxyz(self) -> tuple[float, float, float, float]:
        """The latest pose's attitude (w, x, y, z; body FLU -> world ENU), unit; level before the first."""
        return tuple(self._state[_QUAT:_QUAT + 4].tolist())  # type: ignore[return-value]

    @property
    def updates(self) -> int:
        """Poses taken."""
        return int(self._state.item(_UPDATES))

    @property
    def rejected(self) -> int:
        """Poses out of order, repeated, not finite or implausible."""
        return int(self._state.item(_REJECTED))

    @property
    def implausible(self) -> int:
        """Poses further from the prediction than the vehicle can move."""
        return int(self._state.item(_IMPLAUSIBLE))

    @property
    def implausible_run(self) -> int:
        """Of the implausible poses, how many in a row since the latest pose taken."""
        return int(self._state.item(_IMPLAUSIBLE_RUN))

    @property
    def latest_jump_m(self) -> float:
        """The latest implausible pose's distance from the prediction (m)."""
        return self._state.item(_LATEST_JUMP)

    def age_s(self, now_s: float) -> float:
        """Time (s) from the arrival of the latest accepted pose to ``now_s`` (inf before the first)."""
        return now_s - self._state.item(_RECEIVED)

    def update(self, stamp_s: float, pos_m: np.ndarray, quat_wxyz: np.ndarray, received_s: float) -> bool:
        """Take one pose (exposure time ``stamp_s``, arrival ``received_s``, s); False if rejected."""
        try:
            px, py, pz = map(float, _items(pos_m))
            qw, qx, qy, qz = map(float, _items(quat_wxyz))
            stamp_s, received_s = float(stamp_s), float(received_s)
        except (TypeError, ValueError):
            self._state[_REJECTED] += 1
            return False
        return self.take(stamp_s, (px, py, pz), (qw, qx, qy, qz), received_s)

    def take(self, stamp_s: float, pos_m: tuple[float, float, float],
             quat_wxyz: tuple[float, float, float, float], received_s: float) -> bool:
        """`update` of a pose given as plain floats: ``pos_m`` (m) and ``quat_wxyz`` tuples of floats, as
        the mocap reader hands them over (the per-frame path, without the conversions)."""
        px, py, pz = pos_m
        qw, qx, qy, qz = quat_wxyz
        return self._take(self._state, stamp_s, received_s, px, py, pz, qw, qx, qy, qz) == TAKEN

    def rebase(self, stamp_s: float, received_s: float) -> None:
        """The mocap clock jumped (the reader followed it): read the pose of exposure ``stamp_s``,
        arriving at ``received_s``, as one that came as late as the latest pose; the state is kept."""
        if self.ready:
            st = self._state
            shift = (stamp_s - received_s) - (st[_STAMP] - st[_RECEIVED])  # new clock - old clock (s)
            st[_STAMP] += shift
            st[_DELAY] -= shift
            st[_MEAN_DELAY] -= shift

    def state_tuples(self, now_s: float) -> tuple[tuple[float, float, float], tuple[float, float, float],
                                                  tuple[float, float, float]]:
        """`estimate`'s position (m), velocity (m/s) and acceleration (m/s^2) at ``now_s`` as (x, y, z)
        tuples of plain floats (the per-step path); ValueError if no pose has come yet."""
        if self._state.item(_READY) == 0.0:
            raise ValueError("no pose received yet")
        px, py, pz, vx, vy, vz, ax, ay, az = self._predict(self._state, now_s)
        return (px, py, pz), (vx, vy, vz), (ax, ay, az)

    def euler_rad(self) -> tuple[float, float, float]:
        """ZYX Euler angles (rad) of `quat_wxyz` (made once per pose)."""
        updates = self._state.item(_UPDATES)
        if self._euler_at != updates:
            self._euler, self._euler_at = euler_from_quat(self.quat_wxyz), updates
        return self._euler

    def estimate(self, now_s: float) -> StateEstimate:
        """The state predicted to ``now_s`` (reader clock) from the latest pose: over its age, plus the
        configured mean latency, plus how much later than the average it arrived. ValueError if no
        pose has come yet."""
        pos, vel, acc = self.state_tuples(now_s)
        return _new_estimate(np.array(pos), np.array(vel), np.array(acc), np.array(self.euler_rad()),
                             np.array(self.quat_wxyz))


class StaticPoseCheck:
    """The poses of a body that does not move (the gap): the first is the reference, and a later one
    further than ``jump_m`` (m) from it or turned more than ``turn_rad`` (rad) from it is refused
    (a swapped rigid body, a reflection). `pose` is the latest one taken. The check and its state run
    compiled (`static_pose_update` on one array), as the program's mocap intake runs it."""

    def __init__(self, jump_m: float, turn_rad: float) -> None:
        self.jump_m, self.turn_rad = jump_m, turn_rad
        #: `static_pose_update`'s state (`GAP_FLOATS`)
        self._state = np.zeros(GAP_FLOATS)
        self._state[_G_JUMP_M], self._state[_G_TURN_RAD] = jump_m, turn_rad
        self._state[_G_RECEIVED] = -math.inf
        self._pose: tuple[np.ndarray, np.ndarray] | None = None  # `pose`'s arrays, made when first asked for
        self._pose_at = 0.0  # the poses taken when `_pose` was made
        self._update = STATIC_POSE_UPDATE.entry(self._state, *(0.0,) * 8)  # (no dispatch a call)

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The latest pose taken: position (m), quaternion (w, x, y, z); None before the first."""
        st = self._state
        taken = st.item(_G_TAKEN)
        if taken == 0.0:
            return None
        if self._pose is None or self._pose_at != taken:
            self._pose = (st[_G_POSE:_G_POSE + 3].copy(), st[_G_POSE + 3:_G_POSE + 7].copy())
            self._pose_at = taken
        return self._pose

    def keep_state_in(self, view: np.ndarray) -> None:
        """Keep the state in ``view`` from now on (float64, `GAP_FLOATS`, C-contiguous; as
        `PoseEstimator.keep_state_in`); the state so far is copied there."""
        view[:] = self._state
        self._state = view

    @property
    def received_s(self) -> float:
        """Arrival of the latest pose taken (s; -inf before the first)."""
        return self._state.item(_G_RECEIVED)

    @property
    def implausible(self) -> int:
        """Poses refused."""
        return int(self._state.item(_G_IMPLAUSIBLE))

    @property
    def implausible_run(self) -> int:
        """Poses refused in a row since the latest pose taken."""
        return int(self._state.item(_G_IMPLAUSIBLE_RUN))

    @property
    def latest_jump_m(self) -> float:
        """The latest refused pose's distance from the reference (m)."""
        return self._state.item(_G_LATEST_JUMP)

    def update(self, pos_m: Sequence[float], quat_wxyz: Sequence[float], received_s: float) -> bool:
        """Take one pose (arriving at ``received_s``, s); False if refused."""
        (px, py, pz), (qw, qx, qy, qz) = pos_m, quat_wxyz
        return self._update(self._state, px, py, pz, qw, qx, qy, qz, received_s)


#: `static_pose_update`'s state: the refusal limits (m, rad), 1.0 once the reference is set, the reference
#: (position (m), quaternion (w, x, y, z)), the latest pose taken (the same seven), its arrival (s), the
#: poses taken, refused, refused in a row since the latest taken, and the latest refused one's jump (m)
_G_JUMP_M, _G_TURN_RAD, _G_HAS_REF, _G_REF, _G_POSE, _G_RECEIVED = 0, 1, 2, 3, 10, 17
_G_TAKEN, _G_IMPLAUSIBLE, _G_IMPLAUSIBLE_RUN, _G_LATEST_JUMP = 18, 19, 20, 21
GAP_FLOATS = 22


def static_pose_update(st: np.ndarray, px: float, py: float, pz: float, qw: float, qx: float, qy: float,
                       qz: float, received_s: float) -> bool:
    """`StaticPoseCheck.update` on its state ``st`` (`GAP_FLOATS`): whether the pose (position m,
    quaternion w, x, y, z, arriving at ``received_s``, s) lies within the limits of the reference (the
    first pose); counted there. Run compiled by numba (`policies.compiling`)."""
    if st[_G_HAS_REF] == 0.0:
        st[_G_HAS_REF] = 1.0
        st[_G_REF], st[_G_REF + 1], st[_G_REF + 2] = px, py, pz
        st[_G_REF + 3], st[_G_REF + 4], st[_G_REF + 5], st[_G_REF + 6] = qw, qx, qy, qz
    dx, dy, dz = px - st[_G_REF], py - st[_G_REF + 1], pz - st[_G_REF + 2]
    jump = math.sqrt(dx * dx + dy * dy + dz * dz)
    # the angle between the attitudes (the cosine at most 1, a NaN taken as 1)
    c = abs(qw * st[_G_REF + 3] + qx * st[_G_REF + 4] + qy * st[_G_REF + 5] + qz * st[_G_REF + 6])
    turn = 2.0 * math.acos(c if c < 1.0 else 1.0)
    if jump > st[_G_JUMP_M] or turn > st[_G_TURN_RAD]:
        st[_G_IMPLAUSIBLE] += 1.0
        st[_G_IMPLAUSIBLE_RUN] += 1.0
        st[_G_LATEST_JUMP] = jump
        return False
    st[_G_POSE], st[_G_POSE + 1], st[_G_POSE + 2] = px, py, pz
    st[_G_POSE + 3], st[_G_POSE + 4], st[_G_POSE + 5], st[_G_POSE + 6] = qw, qx, qy, qz
    st[_G_RECEIVED] = received_s
    st[_G_TAKEN] += 1.0
    st[_G_IMPLAUSIBLE_RUN] = 0.0
    return True


def _items(v: object) -> object:
    """The numbers of a 1-D array as floats (one call, not one per element); anything else as is."""
    return v.tolist() if v.__class__ is np.ndarray and v.ndim == 1 else v  # type: ignore[attr-defined]


def _new_estimate(pos_m: np.ndarray, vel_m_s: np.ndarray, acc_m_s2: np.ndarray, euler_rad: np.ndarray,
                  quat_wxyz: np.ndarray) -> StateEstimate:
    """A StateEstimate without the frozen dataclass's per-field __setattr__ calls (once per control
    step): the same fields, set straight into the instance dict."""
    est = object.__new__(StateEstimate)
    est.__dict__.update(pos_m=pos_m, vel_m_s=vel_m_s, acc_m_s2=acc_m_s2, euler_rad=euler_rad,
                        quat_wxyz=quat_wxyz)
    return est


# --- the filter's arithmetic, on plain floats and tuples: `PoseEstimator` runs it compiled once per pose
# and control step (`take_pose`, `predicted_state`, `policies.compiling`), and the RL environment compiles
# the same functions over its rows (`hil.rl.link_observe`)


def filter_update(x: tuple, P: tuple, mean_delay_s: float, restart: bool, dt: float, delay: float,
                  px: float, py: float, pz: float, pos_noise_m: float, jerk_psd: float,
                  delay_window_s: float) -> tuple:
    """One pose into the filter: (state (p, v, a of x, y, z: m, m/s, m/s^2), shared covariance (p00,
    p01, p02, p11, p12, p22), running mean of arrival - stamp (s)) after the pose at position
    ``px, py, pz`` (m), ``dt`` (s) after the last one, that arrived ``delay`` (s) after its stamp;
    ``restart``: start at rest at the pose instead."""
    r2 = pos_noise_m * pos_noise_m
    if restart:
        return (px, 0.0, 0.0, py, 0.0, 0.0, pz, 0.0, 0.0), (r2, 0.0, 0.0, 1.0, 0.0, 10.0), delay
    mean_delay_s += min(1.0, dt / delay_window_s) * (delay - mean_delay_s)
    p00, p01, p02, p11, p12, p22 = P
    h = dt * dt / 2
    # F P F^T + Q, F = [[1, dt, h], [0, 1, dt], [0, 0, 1]], Q = q [dt^5/20 ...] (white jerk)
    a0, a1, a2 = p00 + dt * p01 + h * p02, p01 + dt * p11 + h * p12, p02 + dt * p12 + h * p22
    b1, b2 = p11 + dt * p12, p12 + dt * p22
    q, dt2 = jerk_psd, dt * dt
    dt3 = dt2 * dt
    n00 = a0 + dt * a1 + h * a2 + q * dt3 * dt2 / 20
    n01 = a1 + dt * a2 + q * dt2 * dt2 / 8
    n02 = a2 + q * dt3 / 6
    n11 = b1 + dt * b2 + q * dt3 / 3
    n12 = b2 + q * dt2 / 2
    n22 = p22 + q * dt
    s = n00 + r2
    k0, k1, k2 = n00 / s, n01 / s, n02 / s
    P = (n00 - k0 * n00, n01 - k0 * n01, n02 - k0 * n02, n11 - k1 * n01, n12 - k1 * n02, n22 - k2 * n02)
    # predict and correct each axis (written out: this runs at the mocap rate)
    xp, xv, xa, yp, yv, ya, zp, zv, za = x
    xp, yp, zp = xp + dt * xv + h * xa, yp + dt * yv + h * ya, zp + dt * zv + h * za
    ex, ey, ez = px - xp, py - yp, pz - zp
    return ((xp + k0 * ex, xv + dt * xa + k1 * ex, xa + k2 * ex,
             yp + k0 * ey, yv + dt * ya + k1 * ey, ya + k2 * ey,
             zp + k0 * ez, zv + dt * za + k1 * ez, za + k2 * ez), P, mean_delay_s)


#: `take_pose`'s verdicts
TAKEN, REJECTED, IMPLAUSIBLE = 0, 1, 2
#: the state array of `take_pose`: the filter's state x (p, v, a of x, y, z), its shared covariance (p00,
#: p01, p02, p11, p12, p22), the latest pose's stamp and arrival (s), its arrival - stamp and the running
#: mean of that (s), 1.0 once a pose is taken, the latest pose's unit quaternion (w, x, y, z), the poses
#: taken, rejected and implausible, the implausible ones in a row since the latest taken and the latest
#: one's jump (m)
_X, _P, _STAMP, _RECEIVED, _DELAY, _MEAN_DELAY, _READY = 0, 9, 15, 16, 17, 18, 19
_QUAT, _UPDATES, _REJECTED, _IMPLAUSIBLE, _IMPLAUSIBLE_RUN, _LATEST_JUMP = 20, 24, 25, 26, 27, 28
#: then the settings: pos_noise_m, jerk_psd, delay_window_s, reset_after_s, latency_s, max_accel_m_s2,
#: max_speed_change_m_s, jump_sigmas
_SETTINGS = 29
_NOISE_M, _JERK_PSD, _DELAY_WINDOW_S, _RESET_AFTER_S, _LATENCY_S, _MAX_ACCEL, _SPEED_CHANGE, _SIGMAS = range(
    _SETTINGS, _SETTINGS + 8)
STATE_FLOATS = _SETTINGS + 8


def take_pose(st: np.ndarray, stamp_s: float, received_s: float, px: float, py: float, pz: float, qw: float,
              qx: float, qy: float, qz: float) -> int:
    """One pose (exposure ``stamp_s``, arrival ``received_s``, s; position m; quaternion w, x, y, z) into
    the state ``st`` (`STATE_FLOATS`, under the settings it holds), counted there: the
    verdict (`TAKEN`; `REJECTED`: out of order, repeated or not finite; `IMPLAUSIBLE`: a jump the vehicle
    cannot make). `PoseEstimator.take` runs it compiled by numba (`policies.compiling`), and so does the
    program's mocap intake."""
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    reset_after_s = st[_RESET_AFTER_S]
    if not math.isfinite(px + py + pz + qn + stamp_s + received_s) or qn == 0.0 or (
            stamp_s <= st[_STAMP] and received_s - st[_RECEIVED] <= reset_after_s):
        st[_REJECTED] += 1.0
        return REJECTED
    dt = stamp_s - st[_STAMP]
    delay = received_s - stamp_s
    restart = st[_READY] == 0.0 or not 0.0 < dt <= reset_after_s
    x = (st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7], st[8])
    max_accel = st[_MAX_ACCEL]
    if not restart and max_accel < math.inf:
        ex, ey, ez, _, _, _ = predicted(x, dt)
        jump = math.sqrt((px - ex) ** 2 + (py - ey) ** 2 + (pz - ez) ** 2)
        if jump > plausible_jump_m(dt, max_accel, st[_SPEED_CHANGE], st[_SIGMAS], st[_NOISE_M]):
            st[_REJECTED] += 1.0
            st[_IMPLAUSIBLE] += 1.0
            st[_IMPLAUSIBLE_RUN] += 1.0
            st[_LATEST_JUMP] = jump
            return IMPLAUSIBLE
    P = (st[_P], st[_P + 1], st[_P + 2], st[_P + 3], st[_P + 4], st[_P + 5])
    x, P, mean_delay_s = filter_update(x, P, st[_MEAN_DELAY], restart, dt, delay, px, py, pz, st[_NOISE_M],
                                       st[_JERK_PSD], st[_DELAY_WINDOW_S])
    for k in range(9):
        st[_X + k] = x[k]
    for k in range(6):
        st[_P + k] = P[k]
    st[_STAMP], st[_RECEIVED], st[_DELAY], st[_READY] = stamp_s, received_s, delay, 1.0
    st[_MEAN_DELAY] = mean_delay_s
    st[_QUAT], st[_QUAT + 1], st[_QUAT + 2], st[_QUAT + 3] = qw / qn, qx / qn, qy / qn, qz / qn
    st[_UPDATES] += 1.0
    st[_IMPLAUSIBLE_RUN] = 0.0
    return TAKEN


def predicted_state(st: np.ndarray, now_s: float) -> tuple[float, ...]:
    """`PoseEstimator.state_tuples`'s numbers from the state ``st`` (`take_pose`'s): position (m), velocity
    (m/s) and acceleration (m/s^2) predicted to ``now_s`` (s, reader clock), x, y, z each. Run compiled by
    numba (`policies.compiling`)."""
    h = prediction_horizon_s(now_s - st[_RECEIVED], st[_LATENCY_S], st[_DELAY], st[_MEAN_DELAY],
                             st[_RESET_AFTER_S])
    x = (st[0], st[1], st[2], st[3], st[4], st[5], st[6], st[7], st[8])
    px, py, pz, vx, vy, vz = predicted(x, h)
    return px, py, pz, vx, vy, vz, x[2], x[5], x[8]


def plausible_jump_m(dt_s: float, accel_m_s2: float, speed_change_m_s: float, sigmas: float,
                     noise_m: float) -> float:
    """The furthest a pose ``dt_s`` (s) after the last may lie from the filter's prediction (m): what an
    acceleration of ``accel_m_s2`` (m/s^2) and a sudden speed change of ``speed_change_m_s`` (m/s) move a
    body in that time, plus ``sigmas`` times the tracker's noise ``noise_m`` (m, per axis) in three axes."""
    return 0.5 * accel_m_s2 * dt_s * dt_s + speed_change_m_s * dt_s + sigmas * noise_m * math.sqrt(3.0)


def prediction_horizon_s(age_s: float, latency_s: float, delay_s: float, mean_delay_s: float,
                         reset_after_s: float) -> float:
    """How far (s) to predict the latest pose: over its age since arrival (``age_s``, 0 if negative),
    the mean latency, and how much later than the average it arrived; within [0, reset_after_s]."""
    h = (age_s if age_s > 0.0 else 0.0) + latency_s + (delay_s - mean_delay_s)  # (no max, min calls:
    h = 0.0 if h < 0.0 else h  # per control step; the same choices, NaN passing as through them)
    return reset_after_s if reset_after_s < h else h


def predicted(x: tuple, h: float) -> tuple:
    """Position (m) and velocity (m/s) of the filter's state ``x`` predicted ``h`` (s) ahead at its
    constant acceleration: (px, py, pz, vx, vy, vz)."""
    px, vx, ax, py, vy, ay, pz, vz, az = x
    hh = h * h / 2
    return (px + vx * h + ax * hh, py + vy * h + ay * hh, pz + vz * h + az * hh,
            vx + ax * h, vy + ay * h, vz + az * h)


_PREDICTED = Kernel(predicted)
#: one pose into the estimator's state, compiled: `take_pose`
TAKE_POSE = Kernel(take_pose, filter_update=Kernel(filter_update), predicted=_PREDICTED,
                   plausible_jump_m=Kernel(plausible_jump_m))
#: the gap's pose check, compiled: `static_pose_update`
STATIC_POSE_UPDATE = Kernel(static_pose_update)
#: the estimator's state predicted, compiled: `predicted_state`
PREDICTED_STATE = Kernel(predicted_state, prediction_horizon_s=Kernel(prediction_horizon_s),
                         predicted=_PREDICTED)
