"""Recording a run on the emulator side: world samples (crossing, clearance, collisions, lab bounds)
and the time-series columns of timeseries.npz, into preallocated arrays.

Sampled every 10 ms of sim time, every 1 ms while the body is within reach of the wall.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from emulator.fc import FlightController, MavlinkServer
from emulator.fc.n3 import AttitudeThrustTarget
from emulator.mocap_link import MocapLinkServer
from emulator.physics.state import POS, QUAT
from emulator.profile import VehicleProfile
from emulator.world import CrossingTracker, Obstacle, World
from hil.link.mavlink import euler_from_quat, quat_enu_flu_to_ned_frd_tuple

SAMPLE_S = 0.01  # away from the wall (s)
NEAR_WALL_SAMPLE_S = 0.001  # within NEAR_WALL_M of the gap plane (s)
NEAR_WALL_M = 0.6
GROUND_HIT_SPEED_M_S = 1.0  # touching the ground slower than this is a landing, not a crash
RATE_WINDOW_S = 1.0

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
)
#: what `Recorder.sample` keeps for `Recorder.flush`: t, state, offset along the gap normal (m), FC
#: target, FC state, setpoints applied, mocap frames written, command frames lost, mocap packets lost
_Sample = tuple[float, np.ndarray, float, AttitudeThrustTarget | None, str, int, int, int, int]
_NO_COMMAND = (math.nan,) * 4  # no FC target yet
_OBSTACLES = tuple(World.obstacle(code) for code in range(4))  # by `ObstacleCode`
FC_STATE_CODES = {"disarmed": 0, "hold": 1, "offboard": 2, "land": 3, "failsafe_hover": 4, "failsafe_land": 5}


@dataclass(frozen=True)
class Collision:
    """The first collision that counts: what, when (sim s), where (m) and how fast (m/s)."""

    obstacle: str
    time_s: float
    pos_m: tuple[float, float, float]
    speed_m_s: float


class Recorder:
    """World checks and time-series rows for one run of at most ``duration_s`` (s)."""

    def __init__(self, world: World, profile: VehicleProfile, duration_s: float) -> None:
        self.world = world
        self.profile = profile
        self._tracker = CrossingTracker(world)
        self.next_sample_s = 0.0
        cap = int(duration_s / SAMPLE_S) + 2000
        self._cap = cap
        self._data = np.full((cap, len(COLUMNS)), np.nan)
        self._n = 0  # rows recorded, the last ``len(self._rows)`` of them not yet in ``_data``
        self._rows: list[tuple[float, ...]] = []
        self._collision: Collision | None = None
        self._max_outside_lab_m = 0.0
        self._attitude_error_deg_at_crossing: float | None = None
        self._crossings_seen = 0
        #: samples taken and not yet checked and recorded (see `sample`)
        self._pending: list[_Sample] = []
        #: (t, setpoints applied, mocap frames written)
        self._rate_hist: deque[tuple[float, int, int]] = deque()
        self._gap_axes = world.gap.axes()
        self._gap_centre = np.asarray(world.gap.centre_m)
        self._lab_min = np.asarray(world.lab.min_m)
        self._lab_max = np.asarray(world.lab.max_m)
        self._lab_min_t = tuple(float(v) for v in world.lab.min_m)
        self._lab_max_t = tuple(float(v) for v in world.lab.max_m)
        self._gap_centre_t = tuple(float(v) for v in world.gap.centre_m)
        self._gap_e1_t = tuple(float(v) for v in self._gap_axes[1])
        self._thrust_coeff = float(profile.thrust_coeff_n_s2)
        self._full_thrust_n = profile.n3_full_thrust_n

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
    def attitude_error_at_crossing_deg(self) -> float | None:
        """The attitude error at the first crossing of the gap plane (deg), None if none."""
        self.flush()
        return self._attitude_error_deg_at_crossing

    # --- sampling -------------------------------------------------------------------------------
    def sample(
        self,
        t: float,
        x: np.ndarray,
        fc: FlightController,
        server: MavlinkServer,
        mocap: MocapLinkServer,
    ) -> None:
        """Take the sample at sim time ``t`` (s) of the state ``x`` (a flat `VehicleState.to_vector`
        copy, kept): what the row needs is copied now and ``next_sample_s`` set; the world checks and
        the row itself wait for `flush` (the lockstep loop calls it while the onboard program works on
        a tick; results and `columns` call it first)."""
        px, py, pz = x[POS].tolist()
        c, e1 = self._gap_centre_t, self._gap_e1_t
        n_wall = (px - c[0]) * e1[0] + (py - c[1]) * e1[1] + (pz - c[2]) * e1[2]
        self.next_sample_s = t + (NEAR_WALL_SAMPLE_S if abs(n_wall) < NEAR_WALL_M else SAMPLE_S)
        to_fc = server.codec.transport.to_fc
        self._pending.append((t, x, n_wall, fc.target, fc.state.value, server.stats.setpoints_applied,
                              mocap.frames_written, to_fc.frames_lost + to_fc.frames_dropped_fault,
                              mocap.radio.stats.lost))

    def flush(self) -> None:
        """Check and record the samples taken since the last call."""
        pending = self._pending
        if pending:
            for p in pending:
                self._record(*p)
            pending.clear()
            rows = self._rows
            if rows:  # into the table in one assignment
                self._data[self._n - len(rows) : self._n] = rows
                rows.clear()

    def _record(self, t: float, x: np.ndarray, n_wall: float, tg: AttitudeThrustTarget | None,
                fc_state: str, applied: int, frames: int, command_lost: int, mocap_lost: int) -> None:
        pos, quat = x[POS], x[QUAT]
        # the simulated state is finite: no validation
        code, clr_m, in_slab, _ = self.world.check_state_values(pos, quat)
        hit = _OBSTACLES[code]
        if t > 0:
            tracker = self._tracker
            crossing = tracker.add_checked(t, pos, hit, clr_m, in_slab, n_wall)
            if crossing is not None and self._crossings_seen == 0:
                self._attitude_error_deg_at_crossing = self._attitude_error_deg(quat)
            self._crossings_seen = tracker.crossing_count
        (px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, *rotors) = x.tolist()
        if hit is not None and self._collision is None:
            speed = math.sqrt(vx * vx + vy * vy + vz * vz)
            if hit is not Obstacle.GROUND or speed >= GROUND_HIT_SPEED_M_S:
                self._collision = Collision(str(hit), t, (px, py, pz), speed)
        lo, hi = self._lab_min_t, self._lab_max_t
        outside = max(lo[0] - px, lo[1] - py, lo[2] - pz, px - hi[0], py - hi[1], pz - hi[2], 0.0)
        if outside > self._max_outside_lab_m:
            self._max_outside_lab_m = outside
        if self._n >= self._cap:
            return
        hist = self._rate_hist
        hist.append((t, applied, frames))
        while len(hist) > 1 and hist[0][0] < t - RATE_WINDOW_S:
            hist.popleft()
        h0 = hist[0]
        span = max(t - h0[0], 1e-9)
        cmd_rate = (applied - h0[1]) / span if t > 0 else 0.0
        mocap_rate = (frames - h0[2]) / span if t > 0 else 0.0
        roll, pitch, yaw = euler_from_quat(quat_enu_flu_to_ned_frd_tuple(qw, qx, qy, qz))
        degrees = math.degrees
        if tg is not None:
            cmd = (
                degrees(tg.roll_rad),
                degrees(tg.pitch_rad),
                degrees(tg.yaw_rad) if tg.yaw_rate_rad_s is None else math.nan,
                100.0 * tg.thrust_n / self._full_thrust_n,
            )
        else:
            cmd = _NO_COMMAND
        kf = self._thrust_coeff
        # one row (columns as in COLUMNS), written to the table by `flush`
        self._rows.append((
            t,
            px,
            py,
            pz,
            vx,
            vy,
            vz,
            degrees(roll),
            degrees(pitch),
            degrees(yaw),
            *cmd,
            clr_m if in_slab else math.nan,
            cmd_rate,
            mocap_rate,
            command_lost,
            mocap_lost,
            FC_STATE_CODES.get(fc_state, -1),
            sum([kf * (w * w) for w in rotors]),
            math.sqrt(wx * wx + wy * wy + wz * wz),
        ))
        self._n += 1

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
