"""Recording a run on the emulator side: world samples (crossing, clearance, collisions, lab bounds)
and the time-series columns of timeseries.npz, into preallocated arrays.

Sampled every 10 ms of sim time, every 1 ms while the body is within reach of the wall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from emulator.fc import FcState, FlightController
from emulator.fc.n3 import AttitudeThrustTarget, MotionTarget
from emulator.kernel_cache import entry
from emulator.mocap_link import MocapLinkServer
from emulator.physics.state import POS, QUAT, STATE_SIZE, VEL
from emulator.profile import VehicleProfile
from emulator.servers.registry import FcServer
from emulator.world import CrossingTracker, Obstacle, World

SAMPLE_S = 0.01  # away from the wall (s)
NEAR_WALL_SAMPLE_S = 0.001  # within NEAR_WALL_M of the gap plane (s)
NEAR_WALL_M = 0.6
GROUND_HIT_SPEED_M_S = 1.0  # touching the ground slower than this is a landing, not a crash
RATE_WINDOW_S = 1.0
PENDING_ROWS = 128  # samples the pending buffer holds at first (it grows when full)

COLUMNS = (
    "t_s",
    "pos_m_x",
    "pos_m_y",
    "pos_m_z",
    "vel_m_s_x",
    "vel_m_s_y",
    "vel_m_s_z",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "roll_cmd_deg",
    "pitch_cmd_deg",
    "yaw_cmd_deg",
    "thrust_cmd_pct",
    "clearance_m",
    "command_rate_hz",
    "mocap_rate_hz",
    "command_lost",
    "mocap_lost",
    "fc_state",
    "thrust_n",
    "body_rate_rad_s",
    "yaw_sp_deg",
    "motor_max_pct",
    "setpoint_age_s",
)
#: what `Recorder.sample` keeps for `Recorder.flush` beside the state, a row of plain numbers: t (s),
#: offset along the gap normal (m), setpoints applied, mocap frames written, command frames lost, mocap
#: packets lost, the heading the FC steers to (rad, NED; NaN: none), when the FC last took a setpoint
#: (s), the FC state's code (`FC_STATE_CODES`), the FC target's four columns (`_command`), the four
#: motor commands (0..1)
_S_T, _S_WALL, _S_APPLIED, _S_FRAMES, _S_CMD_LOST, _S_MOCAP_LOST, _S_YAW_SP, _S_SETPOINT_S = range(8)
_S_STATE, _S_CMD, _S_MOTORS = 8, 9, 13  # (the target's columns and the motors: four each)
_S_SIZE = _S_MOTORS + 4
_NO_COMMAND = (math.nan,) * 4  # no FC target yet
_OBSTACLES = tuple(World.obstacle(code) for code in range(4))  # by `ObstacleCode`
#: the `fc_state` column's code of each FC state: its place in `FcState`
FC_STATE_CODES = {st.value: i for i, st in enumerate(FcState)}
_COL = {name: i for i, name in enumerate(COLUMNS)}  # column positions by name
_T, _POS_X, _ROLL, _PITCH, _YAW, _CLEARANCE, _THRUST, _BODY_RATE = (_COL[n] for n in (
    "t_s", "pos_m_x", "roll_deg", "pitch_deg", "yaw_deg", "clearance_m", "thrust_n", "body_rate_rad_s"))
_CMD = slice(_COL["roll_cmd_deg"], _COL["thrust_cmd_pct"] + 1)  # the FC target's four columns (`_command`)
_CMD0 = _CMD.start
_CMD_RATE, _MOCAP_RATE, _CMD_LOST, _MOCAP_LOST, _FC_STATE, _YAW_SP, _MOTOR_MAX, _SETPOINT_AGE = (
    _COL[n] for n in ("command_rate_hz", "mocap_rate_hz", "command_lost", "mocap_lost", "fc_state",
                      "yaw_sp_deg", "motor_max_pct", "setpoint_age_s"))
assert COLUMNS[_POS_X : _POS_X + 6] == tuple(f"{q}_{a}" for q in ("pos_m", "vel_m_s") for a in "xyz")
assert COLUMNS[_CMD] == ("roll_cmd_deg", "pitch_cmd_deg", "yaw_cmd_deg", "thrust_cmd_pct")


def _command(tg: AttitudeThrustTarget | MotionTarget | None, full_thrust_n: float,
             ) -> tuple[float, float, float, float]:
    """The FC target's columns: roll, pitch, yaw (deg; NaN when it flies a yaw rate), thrust (%); a
    velocity or position target (DJI's motion control) commands neither attitude nor thrust: NaN."""
    if tg is None:
        return _NO_COMMAND
    degrees = math.degrees
    yaw = degrees(tg.yaw_rad) if tg.yaw_rate_rad_s is None else math.nan
    if isinstance(tg, MotionTarget):
        return math.nan, math.nan, yaw, math.nan
    return degrees(tg.roll_rad), degrees(tg.pitch_rad), yaw, 100.0 * tg.thrust_n / full_thrust_n


@njit(cache=True)
def _state_columns(t: np.ndarray, x: np.ndarray, clr: np.ndarray, in_slab: np.ndarray, kf: float,
                   out: np.ndarray) -> None:
    """Fill the columns of ``out`` (N, len(COLUMNS)) that come from the states ``x`` (N, STATE_SIZE) at
    times ``t``: time, position, velocity, roll/pitch/yaw (deg, the body FRD -> world NED attitude, as
    `euler_from_quat` of `quat_enu_flu_to_ned_frd_tuple`), clearance (m, NaN outside the slab), thrust
    (N, kf * sum of squared rotor speeds) and body rate (rad/s)."""
    s = math.sqrt(0.5)
    r2d = 180.0 / math.pi
    for i in range(x.shape[0]):
        out[i, _T] = t[i]
        for k in range(6):  # position and velocity, in the state's order
            out[i, _POS_X + k] = x[i, k]
        w, qx0, qy0, qz0 = x[i, 6], x[i, 7], x[i, 8], x[i, 9]
        qw, qx, qy, qz = -(s * w + s * qz0), -(s * qx0) - s * qy0, s * qy0 - s * qx0, -(s * w - s * qz0)
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if qw < 0:
            n = -n
        qw, qx, qy, qz = qw / n, qx / n, qy / n, qz / n
        out[i, _ROLL] = math.atan2(2 * (qw * qx + qy * qz), 1 - 2 * (qx * qx + qy * qy)) * r2d
        out[i, _PITCH] = math.asin(max(-1.0, min(1.0, 2 * (qw * qy - qz * qx)))) * r2d
        out[i, _YAW] = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)) * r2d
        out[i, _CLEARANCE] = clr[i] if in_slab[i] else np.nan
        w0, w1, w2, w3 = x[i, 13], x[i, 14], x[i, 15], x[i, 16]
        out[i, _THRUST] = kf * (w0 * w0) + kf * (w1 * w1) + kf * (w2 * w2) + kf * (w3 * w3)
        wx, wy, wz = x[i, 10], x[i, 11], x[i, 12]
        out[i, _BODY_RATE] = math.sqrt(wx * wx + wy * wy + wz * wz)


@njit(cache=True)
def _sample_columns(s: np.ndarray, ht: np.ndarray, ha: np.ndarray, hf: np.ndarray, n0: int,
                    out: np.ndarray) -> None:
    """Fill the columns of ``out`` (N, len(COLUMNS)) that come from the samples' rows ``s`` (N, `_S_*`),
    recorded as rows ``n0`` on: the command and mocap rates over the last `RATE_WINDOW_S` (from the
    oldest recorded sample inside it, with the history ``ht``, ``ha``, ``hf`` (times (s), setpoints
    applied, mocap frames written by row), these rows' entries written here), the FC target's four
    columns, the lost counts, the FC state's code, the heading setpoint (deg) and the setpoint's age (s;
    inf before the first). The motors' column is not among them."""
    m = s.shape[0]
    n1 = n0 + m
    for i in range(m):
        ht[n0 + i], ha[n0 + i], hf[n0 + i] = s[i, _S_T], s[i, _S_APPLIED], s[i, _S_FRAMES]
    recorded = ht[:n1]
    for i in range(m):
        k = n0 + i
        t = s[i, _S_T]
        h0 = min(np.searchsorted(recorded, t - RATE_WINDOW_S), k)
        span = max(t - ht[h0], 1e-9)
        moving = t > 0
        out[i, _CMD_RATE] = (ha[k] - ha[h0]) / span if moving else 0.0
        out[i, _MOCAP_RATE] = (hf[k] - hf[h0]) / span if moving else 0.0
        for j in range(4):
            out[i, _CMD0 + j] = s[i, _S_CMD + j]
        out[i, _CMD_LOST], out[i, _MOCAP_LOST] = s[i, _S_CMD_LOST], s[i, _S_MOCAP_LOST]
        out[i, _FC_STATE] = s[i, _S_STATE]
        out[i, _YAW_SP] = np.degrees(s[i, _S_YAW_SP])
        out[i, _SETPOINT_AGE] = t - s[i, _S_SETPOINT_S]


@njit(cache=True)
def _take_sample(pending: np.ndarray, k: int, x: np.ndarray, t: float, applied: int, frames: int,
                 cmd_lost: int, mocap_lost: int, yaw_sp: float, setpoint_s: float, state_code: int,
                 cmd0: float, cmd1: float, cmd2: float, cmd3: float, motors: np.ndarray) -> float:
    """Keep the sample at ``t`` (s) of the state ``x`` (STATE_SIZE,) as pending sample ``k``, row
    ``1 + k`` of ``pending`` (its `_S_T` ... columns, then the state's: the offset along the gap normal
    from the gap's centre (m) and normal, ``pending[0, :6]``, then the other arguments in their order:
    the FC target's four columns ``cmd0`` .. ``cmd3`` and the four motor commands ``motors``); returns
    the next sample's time (s), sooner within `NEAR_WALL_M` of the gap plane. (Arrays are few: numba
    unboxes each array of each call; a float costs a fraction of one.)"""
    fixed = pending[0]
    row = pending[1 + k]
    for j in range(x.shape[0]):
        row[_S_SIZE + j] = x[j]
    n_wall = (x[0] - fixed[0]) * fixed[3] + (x[1] - fixed[1]) * fixed[4] + (x[2] - fixed[2]) * fixed[5]
    row[_S_T], row[_S_WALL], row[_S_APPLIED], row[_S_FRAMES] = t, n_wall, applied, frames
    row[_S_CMD_LOST], row[_S_MOCAP_LOST], row[_S_YAW_SP] = cmd_lost, mocap_lost, yaw_sp
    row[_S_SETPOINT_S], row[_S_STATE] = setpoint_s, state_code
    row[_S_CMD], row[_S_CMD + 1], row[_S_CMD + 2], row[_S_CMD + 3] = cmd0, cmd1, cmd2, cmd3
    for j in range(4):
        row[_S_MOTORS + j] = motors[j]
    return t + (NEAR_WALL_SAMPLE_S if abs(n_wall) < NEAR_WALL_M else SAMPLE_S)


@njit(cache=True)
def _nonfinite_and_outside(x: np.ndarray, lab_min: np.ndarray, lab_max: np.ndarray) -> tuple[int, float]:
    """Of the states ``x`` (N, STATE_SIZE): the first with a component not finite (-1: none), and how far
    the positions go outside the box ``lab_min`` .. ``lab_max`` (m; 0 inside, NaN with a NaN position)."""
    first = -1
    for i in range(x.shape[0]):
        for k in range(x.shape[1]):
            if not np.isfinite(x[i, k]):
                first = i
                break
        if first >= 0:
            break
    below = above = -np.inf  # the largest of lab_min - pos and of pos - lab_max, NaN kept (as np.max)
    for i in range(x.shape[0]):
        for k in range(3):
            d, u = lab_min[k] - x[i, k], x[i, k] - lab_max[k]
            if d > below or d != d:
                below = d
            if u > above or u != u:
                above = u
            if below != below:
                break
        if below != below:
            break
    out = below  # (then the larger of those and 0, as Python's max of the three)
    if above > out:
        out = above
    if out < 0.0:
        out = 0.0
    return first, out


#: the columns `state_values` gives
_STATE_VALUES = (*COLUMNS[_T : _POS_X + 6], "roll_deg", "pitch_deg", "yaw_deg", *COLUMNS[_CMD], "thrust_n",
                 "body_rate_rad_s")


def state_values(t_s: float, x: np.ndarray, target: AttitudeThrustTarget | MotionTarget | None,
                 profile: VehicleProfile) -> dict[str, float]:
    """One state's columns that need neither the world nor the history (a live view's): time,
    position, velocity, roll/pitch/yaw (deg), the FC target's four columns and the thrust (N)."""
    out = np.full((1, len(COLUMNS)), np.nan)
    _state_columns(np.array([t_s]), x.reshape(1, -1), np.zeros(1), np.zeros(1, np.bool_),
                   float(profile.thrust_coeff_n_s2), out)
    out[0, _CMD] = _command(target, profile.n3_full_thrust_n)
    row = out[0].tolist()
    return {name: row[_COL[name]] for name in _STATE_VALUES}


@dataclass(frozen=True)
class Collision:
    """The first collision that counts: what, when (sim s), where (m) and how fast (m/s)."""

    obstacle: str
    time_s: float
    pos_m: tuple[float, float, float]
    speed_m_s: float


class Recorder:
    """World checks and time-series rows for one run of at most ``duration_s`` (s), of the vehicle
    that FC ``fc`` flies with ``server`` on its command link and ``mocap`` tracking it."""

    def __init__(self, world: World, profile: VehicleProfile, duration_s: float, fc: FlightController,
                 server: FcServer, mocap: MocapLinkServer) -> None:
        self.world = world
        self.profile = profile
        self._tracker = CrossingTracker(world)  # (which compiles the world's checks now)
        level = np.zeros((1, STATE_SIZE))
        level[0, QUAT] = (1.0, 0.0, 0.0, 0.0)
        no = np.zeros(1)
        _state_columns(no, level, no, np.zeros(1, np.bool_), 1.0, np.empty((1, len(COLUMNS))))
        _sample_columns(np.zeros((1, _S_SIZE)), np.zeros(1), np.zeros(1), np.zeros(1), 0,
                        np.empty((1, len(COLUMNS))))
        self.next_sample_s = 0.0
        cap = int(duration_s / SAMPLE_S) + 2000
        self._cap = cap
        self._data = np.full((cap, len(COLUMNS)), np.nan)
        self._n = 0  # rows recorded
        #: per recorded row: time (s), setpoints applied, mocap frames written (for the rates)
        self._hist_t, self._hist_applied, self._hist_frames = np.empty(cap), np.empty(cap), np.empty(cap)
        self._collision: Collision | None = None
        self._max_outside_lab_m = 0.0
        self._attitude_error_deg_at_crossing: float | None = None
        self._crossings_seen = 0
        self._nonfinite_s: float | None = None  # sim time of the first non-finite state (s)
        #: the same, as far as recorded (no flush): what a loop may read every tick
        self.nonfinite_seen_s: float | None = None
        #: sim time of the first crossing of the gap plane as far as recorded (no flush), None before
        self.first_crossing_seen_s: float | None = None
        #: samples taken and not yet checked and recorded (see `sample`): rows 1 .. ``n_pending``, each
        #: its `_S_T` ... columns and then its state (grown when full); row 0 holds what a sample's row
        #: takes that never changes: the gap's centre (m) and normal (c_x, c_y, c_z, e1_x, e1_y, e1_z)
        self._pending = np.empty((1 + PENDING_ROWS, _S_SIZE + STATE_SIZE))
        self._pending_room = PENDING_ROWS
        self.n_pending = 0
        self._gap_axes = world.gap.axes()
        self._lab_min = np.asarray(world.lab.min_m, dtype=np.float64)
        self._lab_max = np.asarray(world.lab.max_m, dtype=np.float64)
        _nonfinite_and_outside(level, self._lab_min, self._lab_max)  # (compiled now, not in a run's loop)
        self._pending[0, :6] = (*world.gap.centre_m, *self._gap_axes[1])
        self._thrust_coeff = float(profile.thrust_coeff_n_s2)
        self._full_thrust_n = profile.n3_full_thrust_n
        # what a sample reads besides the state, the same objects for the run's life
        self._fc, self._machine, self._mocap = fc, fc.machine, mocap
        self._server_stats, self._to_fc = server.stats, server.codec.transport.to_fc
        self._radio_stats = mocap.radio.stats
        # the FC target's columns and the FC state's code, made again when the target or state changes
        self._target: object = self  # (no target seen yet)
        self._cmd = _NO_COMMAND
        self._state: FcState | None = None
        self._state_code = -1
        # the sample's kernel for these arrays, ints and floats, called without numba's type dispatch
        self._take_sample = entry(_take_sample, self._pending, 0, level[0], 0.0, 0, 0, 0, 0, 0.0, 0.0, 0,
                                  0.0, 0.0, 0.0, 0.0, fc.motor_cmd)

    # --- results (what is pending is processed first) --------------------------------------------
    @property
    def tracker(self) -> CrossingTracker:
        self.flush()
        return self._tracker

    @property
    def collision(self) -> Collision | None:
        """The first collision that counts, None if none."""
        self.flush()
        return self._collision

    @property
    def max_outside_lab_m(self) -> float:
        """How far the body went outside the lab volume at most (m)."""
        self.flush()
        return self._max_outside_lab_m

    @property
    def nonfinite_state_s(self) -> float | None:
        """Sim time (s) of the first sample whose simulated state was not finite (NaN or Inf: the
        physics diverged), None if every one was."""
        self.flush()
        return self._nonfinite_s

    @property
    def attitude_error_at_crossing_deg(self) -> float | None:
        """The attitude error at the first crossing of the gap plane (deg), None if none."""
        self.flush()
        return self._attitude_error_deg_at_crossing

    # --- sampling -------------------------------------------------------------------------------
    def sample(self, t: float, x: np.ndarray) -> float:
        """Take the sample at sim time ``t`` (s) of the state ``x`` (a flat `VehicleState.to_vector`
        row, float64, copied now): what the row needs is copied now and ``next_sample_s`` set (and
        returned); the world checks and the row itself wait for `flush` (the lockstep loop calls it while
        the onboard program works on a tick; results and `columns` call it first)."""
        k = self.n_pending
        if k == self._pending_room:
            self._grow_pending()
        fc, to_fc = self._fc, self._to_fc
        tg = fc.target  # (the same target object for every sample until the next setpoint)
        if tg is not self._target:
            self._target = tg
            self._cmd = _command(tg, self._full_thrust_n)
        c0, c1, c2, c3 = self._cmd
        st = self._machine.state  # (the same state for long stretches: its code looked up on a change)
        if st is not self._state:
            self._state, self._state_code = st, FC_STATE_CODES.get(st.value, -1)
        plan = fc.batch_plan  # (an offboard attitude target: its yaw is the heading the FC steers to)
        nxt = self.next_sample_s = self._take_sample(
            self._pending, k, x, t, self._server_stats.setpoints_applied,
            self._mocap.frames_written, to_fc.frames_lost + to_fc.frames_dropped_fault,
            self._radio_stats.lost, fc.heading_setpoint_rad() if plan is None else plan[2],
            fc.last_setpoint_s, self._state_code, c0, c1, c2, c3, fc.motor_cmd)
        self.n_pending = k + 1
        return nxt

    def _grow_pending(self) -> None:
        """Room for twice as many pending samples (a loop that flushes seldom)."""
        self._pending = np.concatenate((self._pending, np.empty_like(self._pending[1:])))
        self._pending_room *= 2

    def flush(self, at_least: int = 1) -> None:
        """Check and record the samples taken since the last call, if there are ``at_least`` of them
        (the lockstep loop gathers a batch: the checks and rows are computed for all at once)."""
        n = self.n_pending
        if n >= at_least and n:
            pending = self._pending[1 : 1 + n]
            self._record(pending[:, :_S_SIZE].copy(), pending[:, _S_SIZE:].copy())
            self.n_pending = 0

    def _record(self, rows: np.ndarray, x: np.ndarray) -> None:
        """World checks, the crossing tracker and the time-series rows of a batch of samples (their
        rows of numbers (N, `_S_SIZE`) and their states (N, STATE_SIZE)), as the samples would have been
        taken one by one."""
        n_rows = len(rows)
        t = np.ascontiguousarray(rows[:, _S_T])
        pos, quat = x[:, POS], x[:, QUAT]
        first, outside = _nonfinite_and_outside(x, self._lab_min, self._lab_max)
        if self._nonfinite_s is None and first >= 0:
            # NaN compares false, so no check below would notice: note it for the `finite_state` check
            self._nonfinite_s = self.nonfinite_seen_s = float(t[first])
        codes, clr, in_slab = self.world.check_states_values(pos, quat)
        k0 = 1 if t[0] <= 0 else 0  # the sample at t = 0 is no step of a trajectory
        if k0 < n_rows:
            tracker = self._tracker
            done = tracker.add_checked_batch(t[k0:], pos[k0:], codes[k0:], clr[k0:], in_slab[k0:],
                                             np.ascontiguousarray(rows[k0:, _S_WALL]))
            if done and self._crossings_seen == 0:
                self._attitude_error_deg_at_crossing = self._attitude_error_deg(quat[k0 + done[0][0]])
                self.first_crossing_seen_s = tracker.crossings[0].time_s
            self._crossings_seen = tracker.crossing_count
        vel = x[:, VEL]
        if self._collision is None and codes.any():
            with np.errstate(over="ignore", invalid="ignore"):  # a diverged state is reported elsewhere
                speed = np.sqrt(vel[:, 0] * vel[:, 0] + vel[:, 1] * vel[:, 1] + vel[:, 2] * vel[:, 2])
            for i, hit in enumerate(_OBSTACLES[c] for c in codes.tolist()):
                if hit is not None and (hit is not Obstacle.GROUND or speed[i] >= GROUND_HIT_SPEED_M_S):
                    px, py, pz = pos[i].tolist()
                    self._collision = Collision(str(hit), float(t[i]), (px, py, pz), float(speed[i]))
                    break
        if outside > self._max_outside_lab_m:
            self._max_outside_lab_m = outside
        m = min(n_rows, self._cap - self._n)  # rows that still fit
        if m <= 0:
            return
        n0, n1 = self._n, self._n + m
        block = self._data[n0:n1]
        _state_columns(t[:m], x[:m], clr[:m], in_slab[:m], self._thrust_coeff, block)
        _sample_columns(rows[:m], self._hist_t, self._hist_applied, self._hist_frames, n0, block)
        block[:, _MOTOR_MAX] = 100.0 * np.max(rows[:m, _S_MOTORS : _S_MOTORS + 4], axis=1)
        self._n = n1

    def _attitude_error_deg(self, quat: np.ndarray) -> float:
        """Angle between the body's z axis and the gap's short-side axis e2, either sign (deg)."""
        w, x, y, z = quat
        body_z = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        c = abs(float(body_z @ self._gap_axes[2]))
        return math.degrees(math.acos(min(1.0, c)))

    def columns(self) -> dict[str, np.ndarray]:
        """The recorded columns, trimmed to the samples taken."""
        self.flush()
        data = self._data[: self._n]
        return {name: data[:, i].copy() for i, name in enumerate(COLUMNS)}
