"""JSBSimBackend: the quadrotor's rigid body integrated by JSBSim, rotor forces computed in Python.

Each ``dt_s`` step: the four first-order motor models advance (exact discretisation of
``dw/dt = (w_cmd - w) / tau`` with ``w_cmd = sqrt(u) * w_max``), then the four rotor thrusts
``k_f w^2`` (applied by JSBSim at the rotor positions, so it forms the roll/pitch torques itself), the
rotor drag torques ``-spin k_m w^2`` plus angular damping ``-c_w * omega`` (one body moment), the body
drag ``-c * v_body`` and the world disturbance force are written into the model's
``<external_reactions>``, and JSBSim runs one frame. Forces use the rotor speeds after the motor update
and the velocities at the start of the step.

Ground: JSBSim spring-damper contacts at the eight corners of the body box (gear points in the
XML, see `emulator.physics.jsbsim_aircraft.ground_contacts`), so the box rests with its bottom at
z = 0 and lands on any face. Unlike the native clamp, a landing bounces a little (restitution about
0.4) and sinks the box a few centimetres at 10 m/s; it cannot tunnel. A reset state whose box
corner is below ground is lifted onto it.

Frames: JSBSim runs on a large non-rotating sphere; the world ENU origin is the tangent point at
latitude 0, longitude 0, where ENU = (ECEF y, ECEF z, ECEF x - R). Attitude and rates are converted
from JSBSim's local NED / body FRD to world ENU / body FLU.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import weakref
from pathlib import Path

import jsbsim
import numpy as np

from emulator.physics.jsbsim_aircraft import FT_M, LBF_N, PLANET_RADIUS_M, aircraft_xml, box_corners_flu_m
from emulator.physics.state import VehicleState
from emulator.profile import GRAVITY_M_S2, ROTOR_SPIN, VehicleProfile

_R_FT = PLANET_RADIUS_M / FT_M
_FT_LBF = FT_M * LBF_N  # N m per ft lbf
_SQRT_HALF = math.sqrt(0.5)


def _qmul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


_Q_ENU_NED = (0.0, _SQRT_HALF, _SQRT_HALF, 0.0)  # maps NED vectors to ENU (pi about (1,1,0)/sqrt 2)
_Q_FRD_FLU = (0.0, 1.0, 0.0, 0.0)  # maps FLU vectors to FRD (pi about x)


def quat_enu_flu_from_euler_ned(phi: float, theta: float, psi: float) -> tuple[float, float, float, float]:
    """Body FLU -> world ENU quaternion (w, x, y, z) from NED/FRD Euler angles (rad, ZYX order)."""
    cr, sr = math.cos(phi / 2), math.sin(phi / 2)
    cp, sp = math.cos(theta / 2), math.sin(theta / 2)
    cy, sy = math.cos(psi / 2), math.sin(psi / 2)
    q_ned_frd = (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )
    q = _qmul(_qmul(_Q_ENU_NED, q_ned_frd), _Q_FRD_FLU)
    if q[0] < 0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return q


def euler_ned_from_rotation_enu_flu(r_enu_flu: np.ndarray) -> tuple[float, float, float]:
    """NED/FRD Euler angles (phi, theta, psi; rad) of a body FLU -> world ENU rotation matrix."""
    p = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    r = p @ r_enu_flu @ np.diag([1.0, -1.0, -1.0])  # body FRD -> NED
    theta = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    if abs(r[2, 0]) > 1.0 - 1e-12:  # gimbal lock: put all the heading into psi
        return 0.0, theta, math.atan2(-float(r[0, 1]), float(r[1, 1]))
    return math.atan2(float(r[2, 1]), float(r[2, 2])), theta, math.atan2(float(r[1, 0]), float(r[0, 0]))


class JSBSimBackend:
    """One quadrotor stepped by JSBSim at a fixed ``dt_s`` (s); see the module docstring."""

    name = "jsbsim"

    def __init__(self, profile: VehicleProfile, dt_s: float = 0.001) -> None:
        if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and 0.0 < dt_s <= 0.05):
            raise ValueError(f"dt_s must be a number in (0, 0.05] s, got {dt_s!r}")
        self.profile = profile
        self.dt_s = float(dt_s)
        self._closed = False
        self._root = Path(tempfile.mkdtemp(prefix="crossgap-jsbsim-"))
        self._cleanup = weakref.finalize(self, shutil.rmtree, str(self._root), True)
        files = aircraft_xml(profile, GRAVITY_M_S2, self.dt_s)
        folder = self._root / "aircraft" / files.name
        folder.mkdir(parents=True)
        (folder / f"{files.name}.xml").write_text(files.xml)
        jsbsim.FGJSBBase().debug_lvl = 0
        fdm = jsbsim.FGFDMExec(str(self._root))
        fdm.set_debug_level(0)
        fdm.disable_output()
        if not fdm.load_model(files.name):
            self._cleanup()
            raise RuntimeError(f"JSBSim could not load the generated model for profile '{profile.name}'")
        fdm.set_dt(self.dt_s)
        self._fdm: jsbsim.FGFDMExec | None = fdm
        self._pm = fdm.get_property_manager()
        node = self._node
        self._set_rotor = [node(f"external_reactions/rotor{i}/magnitude").set_double_value for i in range(4)]
        for name in ("drag", "disturbance"):
            node(f"external_reactions/{name}/magnitude").set_double_value(1.0)
        node("external_reactions/torque/magnitude-lbsft").set_double_value(1.0)
        self._set_drag = [node(f"external_reactions/drag/{a}").set_double_value for a in "xyz"]
        self._set_dist = [node(f"external_reactions/disturbance/{a}").set_double_value for a in "xyz"]
        self._set_torque = [node(f"external_reactions/torque/{a}").set_double_value for a in "lmn"]
        self._get_uvw = [node(f"velocities/{a}-fps").get_double_value for a in "uvw"]
        self._get_pqr = [node(f"velocities/{a}-rad_sec").get_double_value for a in "pqr"]
        self._get_ned_vel = [
            node(f"velocities/v-{a}-fps").get_double_value for a in ("north", "east", "down")
        ]
        self._get_ecef = [node(f"position/ecef-{a}-ft").get_double_value for a in "xyz"]
        self._get_euler = [node(f"attitude/{a}-rad").get_double_value for a in ("phi", "theta", "psi")]

        p = profile
        self._w_max = p.max_rotor_speed_rad_s
        self._alpha = 1.0 - math.exp(-self.dt_s / p.motor_time_constant_s)
        self._kf_lbf = p.thrust_coeff_n_s2 / LBF_N
        self._km = p.drag_torque_coeff_nm_s2
        self._lin_drag = p.linear_drag_n_s_m
        self._ang_drag = p.angular_drag_nm_s_rad
        self._w = [0.0, 0.0, 0.0, 0.0]
        self._torque_frd_nm = (0.0, 0.0, 0.0)  # the external torque, body FRD
        self._corners_flu_m = box_corners_flu_m(p)
        self._t0_s = 0.0
        self._steps = 0
        self._accel = (0.0, 0.0, 0.0)
        self._cached: VehicleState | None = None
        self.reset(VehicleState(pos_m=np.array([0.0, 0.0, p.body_box_m[2] / 2.0])))

    # --- PhysicsBackend -------------------------------------------------------------------
    def reset(self, state: VehicleState) -> None:
        """Put the vehicle in ``state``; its ``time_s`` becomes the backend's clock."""
        fdm = self._live()
        v = state.to_vector()
        if not (np.all(np.isfinite(v)) and math.isfinite(state.time_s)):
            raise ValueError("reset state has non-finite values")
        if np.any(state.rotor_speed_rad_s < 0):
            raise ValueError("reset state: rotor speeds must be >= 0 rad/s")
        qn = float(np.linalg.norm(state.quat_wxyz))
        if qn < 1e-9:
            raise ValueError("reset state: attitude quaternion has zero length")
        rot = VehicleState(quat_wxyz=state.quat_wxyz / qn).rotation_matrix()
        phi, theta, psi = euler_ned_from_rotation_enu_flu(rot)
        e, n, u = (float(x) for x in state.pos_m)
        ve, vn, vu = (float(x) / FT_M for x in state.vel_m_s)
        # A box corner below the ground would meet a huge spring force: lift the vehicle onto the
        # ground instead and drop any downward speed.
        depth_m = -(u + min(float(rot[2] @ c) for c in self._corners_flu_m))
        if depth_m > 0.0:
            u += depth_m
            vu = max(vu, 0.0)
        x_ecef = PLANET_RADIUS_M + u
        wx, wy, wz = (float(x) for x in state.omega_rad_s)
        ic = {
            "lat-gc-rad": math.atan2(n, math.hypot(x_ecef, e)),
            "long-gc-rad": math.atan2(e, x_ecef),
            "terrain-elevation-ft": 0.0,
            "h-sl-ft": (math.sqrt(x_ecef**2 + e**2 + n**2) - PLANET_RADIUS_M) / FT_M,
            "phi-rad": phi,
            "theta-rad": theta,
            "psi-true-rad": psi,
            "vn-fps": vn,
            "ve-fps": ve,
            "vd-fps": -vu,
            "p-rad_sec": wx,
            "q-rad_sec": -wy,
            "r-rad_sec": -wz,
        }
        for key, value in ic.items():
            self._node(f"ic/{key}").set_double_value(value)
        # Forces of the new state go in before the IC run, so that the multistep integrators start
        # from the right derivatives.
        self._w = [float(x) for x in state.rotor_speed_rad_s]
        v_frd_fps = (rot.T @ np.array([ve, vn, vu])) * np.array([1.0, -1.0, -1.0])
        self._apply_forces(*(float(x) for x in v_frd_fps), wx, -wy, -wz)
        if not fdm.run_ic():
            raise RuntimeError("JSBSim rejected the initial condition")
        self._t0_s = float(state.time_s)
        self._steps = 0
        self._accel = tuple(float(a) for a in state.accel_m_s2)
        self._cached = None

    def step(self, motor_cmd: np.ndarray, n_steps: int = 1) -> None:
        """Hold throttle ``motor_cmd`` (4,) for ``n_steps`` steps of ``dt_s``.

        As in the native backend, throttles clip to [0, 1] and a non-finite throttle counts as 0
        (motor off); a command of the wrong shape raises ValueError.
        """
        fdm = self._live()
        cmd = np.asarray(motor_cmd, dtype=np.float64)
        if cmd.shape != (4,):
            raise ValueError(f"motor_cmd: expected 4 throttles, got shape {cmd.shape}")
        if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
            raise ValueError(f"n_steps must be a non-negative integer, got {n_steps!r}")
        w_cmd = [math.sqrt(min(1.0, float(u)) if u > 0.0 else 0.0) * self._w_max for u in cmd]
        alpha, w = self._alpha, self._w
        get_u, get_v, get_w = self._get_uvw
        get_p, get_q, get_r = self._get_pqr
        v_before = None
        for k in range(n_steps):
            if k == n_steps - 1:
                v_before = self._ned_velocity_m_s()
            for i in range(4):
                w[i] += (w_cmd[i] - w[i]) * alpha
            self._apply_forces(get_u(), get_v(), get_w(), get_p(), get_q(), get_r())
            fdm.run()
        self._steps += n_steps
        self._cached = None
        if v_before is not None:
            v_after = self._ned_velocity_m_s()
            self._accel = tuple((a - b) / self.dt_s for a, b in zip(v_after, v_before, strict=True))

    def set_external_force(self, force_world_n: np.ndarray) -> None:
        """A disturbance force in world ENU (N), held until changed."""
        self._live()
        f = np.asarray(force_world_n, dtype=np.float64)
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            raise ValueError(f"force_world_n must be 3 finite numbers (N), got {force_world_n!r}")
        fe, fn, fu = (float(x) / LBF_N for x in f)
        self._set_dist[0](fn)
        self._set_dist[1](fe)
        self._set_dist[2](-fu)

    def set_external_torque(self, torque_body_nm: np.ndarray) -> None:
        """A disturbance torque in body FLU (N m), held until changed."""
        self._live()
        m = np.asarray(torque_body_nm, dtype=np.float64)
        if m.shape != (3,) or not np.all(np.isfinite(m)):
            raise ValueError(f"torque_body_nm must be 3 finite numbers (N m), got {torque_body_nm!r}")
        self._torque_frd_nm = (float(m[0]), -float(m[1]), -float(m[2]))  # FLU -> FRD

    @property
    def time_s(self) -> float:
        """The backend's clock (s)."""
        return self._t0_s + self._steps * self.dt_s

    @property
    def state(self) -> VehicleState:
        """The current state in world ENU / body FLU (SI units)."""
        if self._cached is not None:
            return self._cached
        self._live()
        x, y, z = (g() * FT_M for g in self._get_ecef)
        phi, theta, psi = (g() for g in self._get_euler)
        p, q, r = (g() for g in self._get_pqr)
        ve, vn, vu = self._ned_velocity_m_s()
        ax, ay, az = self._accel  # ENU, from the NED velocity difference
        self._cached = VehicleState(
            time_s=self.time_s,
            pos_m=np.array([y, z, x - PLANET_RADIUS_M]),
            vel_m_s=np.array([ve, vn, vu]),
            quat_wxyz=np.array(quat_enu_flu_from_euler_ned(phi, theta, psi)),
            omega_rad_s=np.array([p, -q, -r]),
            rotor_speed_rad_s=np.array(self._w),
            accel_m_s2=np.array([ax, ay, az]),
        )
        return self._cached

    def close(self) -> None:
        """Release JSBSim and remove the temporary model directory; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._fdm = None
        self._cleanup()

    def __enter__(self) -> JSBSimBackend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- helpers --------------------------------------------------------------------------
    def _apply_forces(self, u_fps: float, v_fps: float, w_fps: float, p: float, q: float, r: float) -> None:
        """Write rotor, drag and torque reactions for the current rotor speeds, body FRD velocity
        (ft/s) and body FRD rates (rad/s)."""
        kf, km = self._kf_lbf, self._km
        yaw_n_m = 0.0
        for i, wi in enumerate(self._w):
            self._set_rotor[i](kf * wi * wi)
            yaw_n_m -= ROTOR_SPIN[i] * km * wi * wi
        cx, cy, cz = self._lin_drag
        dx, dy, dz = self._ang_drag
        set_drag, set_torque = self._set_drag, self._set_torque
        # FLU drag -c * v_flu is -c * v_frd in FRD axes, axis by axis.
        set_drag[0](-cx * u_fps * FT_M / LBF_N)
        set_drag[1](-cy * v_fps * FT_M / LBF_N)
        set_drag[2](-cz * w_fps * FT_M / LBF_N)
        ext_x, ext_y, ext_z = self._torque_frd_nm
        set_torque[0]((ext_x - dx * p) / _FT_LBF)
        set_torque[1]((ext_y - dy * q) / _FT_LBF)
        set_torque[2]((ext_z - yaw_n_m - dz * r) / _FT_LBF)

    def _node(self, path: str) -> jsbsim.FGPropertyNode:
        node = self._pm.get_node(path)
        if node is None:
            raise RuntimeError(f"JSBSim model has no property '{path}'")
        return node

    def _live(self) -> jsbsim.FGFDMExec:
        if self._fdm is None:
            raise RuntimeError("JSBSimBackend is closed")
        return self._fdm

    def _ned_velocity_m_s(self) -> tuple[float, float, float]:
        """Velocity in world ENU (m/s) from JSBSim's local NED (ft/s)."""
        vn, ve, vd = (g() for g in self._get_ned_vel)
        return ve * FT_M, vn * FT_M, -vd * FT_M
