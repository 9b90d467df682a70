"""The RL environment's observations through the link: what the onboard program would estimate from the
mocap stream as the UWB radio delivers it, compiled over the environment's rows.

Every vehicle is exposed at the tracker's rate (120 Hz by default; its pose at an exposure interpolated
between the states at the ends of the control step, which the environment holds: against the states of
the physics steps in between, within 0.06 mm and 2.4 mrad under commands that jump by 0.3 rad every
step, beside the tracker's noise of 0.2 mm and 1 mrad): the pose as the tracker measures it
(`emulator.mocap`'s `measured_pose`: position and attitude noise), rounded as the LinkTrack frame
carries it (float32 values, microsecond stamps), sent after the camera latency and the processing time,
then over the radio (the channel model's latency with its jitter, order kept, Gilbert-Elliott and
independent loss, the frame's air time) and the UART into the onboard computer. Frames that have
arrived by the control step go, in order, into the onboard program's filter
(`policies.onboard.estimator`: `filter_update`, `prediction_horizon_s`, `predicted`); the policy sees
the estimate predicted to the step plus the control lead, the attitude of the latest frame, through the
same `e2e_state_row` as the pilot. One definition of each: the tracker's, the channel's and the
program's arithmetic, plain floats compiled here.

A pose the tracker cannot see (not finite, outside its volume: `emulator.mocap.trackable`) sends no
frame, and the estimate ages on the last one. Not modelled: occlusions (a config with
``occlusion_prob`` > 0 is refused), the reader's checks of a frame (every frame is a good one here),
and the gap's own pose (the planner's inputs are the plan's, fixed at the reset).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from emulator.mocap import MocapConfig, measured_pose, trackable
from emulator.uwb import UwbConfig
from hil.link.channel import delivery_s, next_burst_state
from hil.link.linktrack import BodySample, MocapPacket, encode_mocap_frame
from hil.rl.observe import euler_angles, write_inputs
from policies.onboard.estimator import EstimatorConfig, filter_update, predicted, prediction_horizon_s

QUEUE = 32  # frames in flight a row can hold (at 120 Hz: 260 ms of latency)
#: the draws each exposure takes: 6 normals (noise), 1 exponential (processing), 1 normal (jitter),
#: 3 uniforms (the burst state, the burst loss, the independent loss)
DRAWS = 11

_measured = njit(cache=True)(measured_pose)
_trackable = njit(cache=True)(trackable)
_update = njit(cache=True)(filter_update)
_horizon = njit(cache=True)(prediction_horizon_s)
_predicted = njit(cache=True)(predicted)
_burst = njit(cache=True)(next_burst_state)
_delivery = njit(cache=True)(delivery_s)


@dataclass(frozen=True)
class LinkModel:
    """The link the observations come through: the tracker, the radio and the onboard filter, each with
    the harness's defaults (`MocapConfig`, `UwbConfig`, `EstimatorConfig`)."""

    mocap: MocapConfig = field(default_factory=MocapConfig)
    uwb: UwbConfig = field(default_factory=UwbConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)

    def __post_init__(self) -> None:
        if self.mocap.occlusion_prob > 0:
            raise ValueError("the RL environment's link model has no occlusions: set mocap occlusion_prob 0")

    def frame_bytes(self) -> int:
        """Bytes of one LinkTrack frame with the vehicle and the gap (what the radio and the UART carry)."""
        body = BodySample(body_id=1, stamp_s=0.0, pos_m=(0.0, 0.0, 0.0), quat_wxyz=(1.0, 0.0, 0.0, 0.0))
        return len(encode_mocap_frame(MocapPacket(frame_no=0, bodies=(body, body))))

    def packed(self) -> np.ndarray:
        """The constants the kernel reads (see `link_observe_rows`)."""
        m, u, e = self.mocap, self.uwb, self.estimator
        n = self.frame_bytes()
        return np.array([m.pos_noise_m, m.att_noise_rad, m.camera_latency_s, m.processing_s, u.latency_s,
                         u.jitter_s, u.loss_prob, u.burst_enter_prob, u.burst_exit_prob, u.burst_loss_prob,
                         u.air_time_s(n) + u.uart_time_s(n), e.pos_noise_m, e.jerk_psd, e.delay_window_s,
                         e.latency_s, e.reset_after_s, m.period_s])

    def exposures_per_step(self, dt_s: float) -> int:
        """The most exposures a control step of ``dt_s`` (s) holds."""
        return math.ceil(dt_s / self.mocap.period_s - 1e-9)


(L_POS_SD, L_ATT_SD, L_CAMERA_S, L_PROCESSING_S, L_LATENCY_S, L_JITTER_S, L_LOSS, L_BURST_ENTER, L_BURST_EXIT,
 L_BURST_LOSS, L_WIRE_S, L_KF_NOISE_M, L_KF_JERK, L_KF_WINDOW_S, L_KF_LATENCY_S, L_KF_RESET_S,
 L_PERIOD_S) = range(17)


class LinkRows:
    """Per row: the frames in flight and the onboard filter's state (arrays the kernel advances)."""

    def __init__(self, n: int, model: LinkModel) -> None:
        self.consts = model.packed()
        self.kx = np.zeros((n, 9))  # the filter's state: p, v, a of x, y, z
        self.kp = np.zeros((n, 6))  # its covariance
        #: the latest frame's stamp (s), its arrival (s), arrival - stamp (s), that delay's running mean (s),
        #: and the radio's last arrival (s: it keeps the order)
        self.kt = np.zeros((n, 5))
        self.quat = np.zeros((n, 4))  # the latest frame's attitude
        self.bad = np.zeros(n, np.bool_)  # the radio's burst state
        self.q_stamp = np.zeros((n, QUEUE))
        self.q_arrival = np.zeros((n, QUEUE))
        self.q_values = np.zeros((n, QUEUE, 7))
        self.q_head = np.zeros(n, np.int64)
        self.q_count = np.zeros(n, np.int64)
        self.lost = np.zeros(n, np.int64)  # frames the radio lost (per row, since its reset)
        self.next_exposure_s = np.zeros(n)  # each row's next exposure (s, its episode time)
        self.before = np.zeros((n, 10))  # each row's pose at the start of the control step (`save`)

    def save(self, x: np.ndarray) -> None:
        """Keep the poses of the state rows ``x`` before a control step: exposures within it are
        interpolated from them and the poses after it."""
        self.before[:] = x[:, 0:10]

    def reset(self, rows: np.ndarray, x: np.ndarray, t_s: float) -> None:
        """Rows ``rows`` start hovering at the state rows ``x`` at episode time ``t_s``: the filter settled
        on that pose and the frames of it in flight, as after a long hover (`link_reset_rows`)."""
        self.q_head[rows] = 0
        self.q_count[rows] = 0
        link_reset_rows(rows, x, t_s, self.consts, self.kx, self.kp, self.kt, self.quat, self.next_exposure_s,
                        self.q_stamp, self.q_arrival, self.q_values, self.q_count)
        self.before[rows] = x[rows, 0:10]
        self.bad[rows] = False
        self.lost[rows] = 0


@njit(cache=True)
def link_reset_rows(rows, x, t_s, c, kx, kp, kt, quat, next_exposure_s, q_stamp, q_arrival, q_values,
                    q_count):  # pragma: no cover
    """Each of ``rows`` as after a long hover at its state row of ``x`` (see `LinkRows.reset`): its filter
    after 100 exact frames a tracker's period apart, the last one exposed at ``t_s`` - the mean latency
    and arriving at ``t_s``; the frames exposed since, up to ``t_s``, in flight (exact, at the mean
    latency; ``q_count`` of the rows 0 before); the next exposure a period after the last of them."""
    delay = c[L_CAMERA_S] + c[L_PROCESSING_S] + c[L_LATENCY_S] + c[L_WIRE_S]  # the mean arrival - stamp
    period = c[L_PERIOD_S]
    for j in range(rows.shape[0]):
        i = rows[j]
        xs = (0.0,) * 9
        ps = (0.0,) * 6
        mean = 0.0
        for k in range(100):
            xs, ps, mean = _update(xs, ps, mean, k == 0, period, delay, x[i, 0], x[i, 1], x[i, 2],
                                   c[L_KF_NOISE_M], c[L_KF_JERK], c[L_KF_WINDOW_S])
        for k in range(9):
            kx[i, k] = xs[k]
        for k in range(6):
            kp[i, k] = ps[k]
        kt[i, 0], kt[i, 1], kt[i, 2], kt[i, 3], kt[i, 4] = t_s - delay, t_s, delay, mean, t_s
        for k in range(4):
            quat[i, k] = x[i, 6 + k]
        qw, qx, qy, qz = x[i, 6], x[i, 7], x[i, 8], x[i, 9]
        m = _measured(x[i, 0], x[i, 1], x[i, 2], qw, qx, qy, qz, qw * qw + qx * qx + qy * qy + qz * qz, 0.0,
                      0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        te = t_s - delay + period
        while te <= t_s + 1e-9 and q_count[i] < q_stamp.shape[1]:
            n = q_count[i]
            q_stamp[i, n] = round(te * 1e6) * 1e-6
            q_arrival[i, n] = te + delay
            for k in range(7):
                q_values[i, n, k] = np.float32(m[k])
            kt[i, 4] = te + delay - c[L_WIRE_S]
            q_count[i] += 1
            te += period
        next_exposure_s[i] = te


@njit(cache=True, inline="always")
def _filter_state(kx, i):  # pragma: no cover
    """Row ``i`` of the filter states as the tuple `filter_update` takes."""
    return (kx[i, 0], kx[i, 1], kx[i, 2], kx[i, 3], kx[i, 4], kx[i, 5], kx[i, 6], kx[i, 7], kx[i, 8])


@njit(cache=True, parallel=True)
def link_observe_rows(x, before, now_s, dt_s, draws, c, lead_s, row_start, row_yaw, t_approach_s, kx, kp,
                      kt, quat, bad, next_exposure_s, q_stamp, q_arrival, q_values, q_head, q_count, lost,
                      pred_pos, pred_vel, obs):  # pragma: no cover
    """Every row: expose it at the tracker's instants within the control step that ends at ``now_s`` (N,)
    (s, its episode time; the step began ``dt_s`` earlier at the poses ``before`` (N, 10) and ends at the
    state rows ``x``), each exposure with its `DRAWS` of the row's ``draws`` (N, k x DRAWS) from the
    seeded Generator, send the frames (or lose them), deliver the frames that have arrived into the
    filter, and write the estimate ``lead_s`` ahead into ``pred_pos``, ``pred_vel`` (N, 3) and the policy's
    first 13 inputs into ``obs`` (N, 29) (`hil.rl.observe.observe_rows`'s columns)."""
    nq = q_stamp.shape[1]
    period = c[L_PERIOD_S]
    for i in prange(x.shape[0]):
        t = now_s[i]
        e = 0
        while next_exposure_s[i] <= t + 1e-9 and (e + 1) * DRAWS <= draws.shape[1]:
            te = next_exposure_s[i]
            next_exposure_s[i] = te + period
            d = draws[i, e * DRAWS:(e + 1) * DRAWS]
            e += 1
            # --- the tracker: the pose at the exposure, rounded as LinkTrack carries it ----------
            f = min(max((te - (t - dt_s)) / dt_s, 0.0), 1.0)  # where in the step (0: its start)
            dot = (before[i, 6] * x[i, 6] + before[i, 7] * x[i, 7] + before[i, 8] * x[i, 8]
                   + before[i, 9] * x[i, 9])
            sgn = -1.0 if dot < 0.0 else 1.0  # (the start's quaternion on the end's side)
            px = before[i, 0] + f * (x[i, 0] - before[i, 0])
            py = before[i, 1] + f * (x[i, 1] - before[i, 1])
            pz = before[i, 2] + f * (x[i, 2] - before[i, 2])
            qw = sgn * before[i, 6] + f * (x[i, 6] - sgn * before[i, 6])
            qx = sgn * before[i, 7] + f * (x[i, 7] - sgn * before[i, 7])
            qy = sgn * before[i, 8] + f * (x[i, 8] - sgn * before[i, 8])
            qz = sgn * before[i, 9] + f * (x[i, 9] - sgn * before[i, 9])
            sq = qw * qw + qx * qx + qy * qy + qz * qz
            m = _measured(px, py, pz, qw, qx, qy, qz, sq, c[L_POS_SD], c[L_ATT_SD], d[0], d[1], d[2], d[3],
                          d[4], d[5])
            stamp = round(te * 1e6) * 1e-6
            ready = te + c[L_CAMERA_S] + (c[L_PROCESSING_S] * d[6] if c[L_PROCESSING_S] > 0 else 0.0)
            # --- the radio: burst state, losses, latency with jitter (order kept), air and UART time
            if c[L_BURST_ENTER] > 0:
                bad[i] = _burst(bad[i], d[8], c[L_BURST_ENTER], c[L_BURST_EXIT])
            gone = (bad[i] and d[9] < c[L_BURST_LOSS]) or (c[L_LOSS] > 0 and d[10] < c[L_LOSS])
            if not _trackable(px, py, pz, sq):  # (a frame flagged invalid: the program skips it)
                continue
            if gone or q_count[i] == nq:  # (a full queue: 32 frames in flight, 260 ms behind)
                lost[i] += 1
                continue
            jitter = c[L_JITTER_S] * d[7] if c[L_JITTER_S] > 0 else 0.0  # (as normal(0, sd) of the draw)
            arrival = kt[i, 4] = _delivery(ready, c[L_LATENCY_S], jitter, kt[i, 4])
            slot = (q_head[i] + q_count[i]) % nq
            q_stamp[i, slot] = stamp
            q_arrival[i, slot] = arrival + c[L_WIRE_S]
            for k in range(7):
                q_values[i, slot, k] = np.float32(m[k])
            q_count[i] += 1
        # --- the onboard program: the frames that have arrived, in order, into its filter --------
        while q_count[i] > 0 and q_arrival[i, q_head[i]] <= t:
            h = q_head[i]
            s, a = q_stamp[i, h], q_arrival[i, h]
            if s > kt[i, 0]:
                dt = s - kt[i, 0]
                restart = not (0.0 < dt <= c[L_KF_RESET_S])
                v = q_values[i, h]
                ps = (kp[i, 0], kp[i, 1], kp[i, 2], kp[i, 3], kp[i, 4], kp[i, 5])
                xs, ps, kt[i, 3] = _update(_filter_state(kx, i), ps, kt[i, 3], restart, dt, a - s, v[0], v[1],
                                           v[2], c[L_KF_NOISE_M], c[L_KF_JERK], c[L_KF_WINDOW_S])
                for k in range(9):
                    kx[i, k] = xs[k]
                for k in range(6):
                    kp[i, k] = ps[k]
                kt[i, 0], kt[i, 1], kt[i, 2] = s, a, a - s
                n = math.sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6])
                for k in range(4):
                    quat[i, k] = v[3 + k] / n
            q_head[i] = (h + 1) % nq
            q_count[i] -= 1
        # --- the policy's inputs: the estimate predicted to the step plus the control lead ---------
        hz = _horizon(t + lead_s - kt[i, 1], c[L_KF_LATENCY_S], kt[i, 2], kt[i, 3], c[L_KF_RESET_S])
        px, py, pz, vx, vy, vz = _predicted(_filter_state(kx, i), hz)
        pred_pos[i, 0], pred_pos[i, 1], pred_pos[i, 2] = px, py, pz
        pred_vel[i, 0], pred_vel[i, 1], pred_vel[i, 2] = vx, vy, vz
        roll, pitch, yaw = euler_angles(quat[i])
        write_inputs(obs[i], px, py, pz, vx, vy, vz, roll, pitch, yaw, row_start[i], row_yaw[i], t + lead_s,
                     t_approach_s[i])
