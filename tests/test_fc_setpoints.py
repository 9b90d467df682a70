"""The FC's setpoint intake: SET_ATTITUDE_TARGET -> N3 setpoint -> FC target, decoded or read from
undecoded frames, against the rules they replaced (the references below, kept verbatim), and a whole
arm-offboard-climb through the frame path."""

from __future__ import annotations

import math
import struct
from dataclasses import astuple

import numpy as np
import pytest

from emulator.fc import FcState
from emulator.fc.n3 import (
    ATTITUDE_THRUST_YAW_ANGLE,
    ATTITUDE_THRUST_YAW_RATE,
    YAW_RATE,
    AttitudeThrustTarget,
    N3Setpoint,
    SetpointRejected,
    check_flag,
    limit_tilt,
    tilt_of,
    to_target,
    wrap_pi,
)
from emulator.profile import GRAVITY_M_S2, VehicleProfile, load_profile
from emulator.servers.mavlink_server import RAW_MSG_IDS, MavlinkServer, attitude_target_values
from emulator.vehicle import EmulatedVehicle
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import (
    PX4_MAIN_OFFBOARD,
    MavlinkCodec,
    MAVLinkMessage,
    decode_frame,
    euler_from_quat,
    mav,
    quat_from_euler,
)

PROFILE = load_profile("n3_tx2")
HOVER = PROFILE.mass_kg * GRAVITY_M_S2 / PROFILE.n3_full_thrust_n
SPECIAL = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1.0, -1.0, 1e30, -1e30, 1e-300, 0.5, 90.0, 100.0]


# --- references: the replaced code ---------------------------------------------------------------
def _ref_check_flag(flag: int) -> None:
    names_h = {0x00: "ANGLE", 0x40: "VELOCITY", 0x80: "POSITION", 0xC0: "ANGULAR_RATE"}
    names_v = {0x00: "VELOCITY", 0x10: "POSITION", 0x20: "THRUST", 0x30: "RESERVED"}
    if not isinstance(flag, int) or not 0 <= flag <= 0xFF:
        raise SetpointRejected(f"control flag must be a byte, got {flag!r}")
    if flag & 0xC0 != 0x00:
        raise SetpointRejected(f"horizontal {names_h[flag & 0xC0]} unsupported, use ANGLE")
    if flag & 0x30 != 0x20:
        raise SetpointRejected(f"vertical {names_v[flag & 0x30]} unsupported, use THRUST")
    if flag & 0x06 != 0x00:
        raise SetpointRejected("BODY frame unsupported with ANGLE, use GROUND")


def _ref_to_target(sp: N3Setpoint, profile: VehicleProfile) -> AttitudeThrustTarget:
    _ref_check_flag(sp.flag)
    values = (sp.roll_deg, sp.pitch_deg, sp.thrust_percent, sp.yaw)
    if not (
        values[0].__class__ is values[1].__class__ is values[2].__class__ is values[3].__class__ is float
        and math.isfinite(sum(values))
    ) and not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
        raise SetpointRejected(f"non-finite setpoint {values}")
    if not 0.0 <= sp.thrust_percent <= 100.0:
        raise SetpointRejected(f"thrust {sp.thrust_percent:.1f} % outside 0..100 %")
    if abs(sp.roll_deg) > 90.0 or abs(sp.pitch_deg) > 90.0:
        raise SetpointRejected(f"roll/pitch {sp.roll_deg:.0f}/{sp.pitch_deg:.0f} deg beyond 90")
    roll, pitch = limit_tilt(
        math.radians(sp.roll_deg), math.radians(sp.pitch_deg), math.radians(profile.max_tilt_deg)
    )
    thrust_n = profile.thrust_percent_to_force_n(sp.thrust_percent)
    if sp.flag & YAW_RATE:
        limit = math.radians(profile.max_yaw_rate_deg_s)
        rate = max(-limit, min(limit, math.radians(sp.yaw)))
        return AttitudeThrustTarget(roll, pitch, 0.0, rate, thrust_n)
    return AttitudeThrustTarget(roll, pitch, wrap_pi(math.radians(sp.yaw)), None, thrust_n)


def _ref_setpoint(msg: MAVLinkMessage) -> N3Setpoint:
    if len(msg.q) != 4:  # (added since: a quaternion of another count refused first, by its count)
        raise SetpointRejected(f"attitude quaternion of {len(msg.q)} numbers, expected 4")
    mask = msg.type_mask
    if mask & mav.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE:
        raise SetpointRejected("attitude ignored: N3 flies roll/pitch angles")
    if mask & mav.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE:
        raise SetpointRejected("thrust ignored: N3 needs vertical thrust")
    q = [float(x) for x in msg.q]
    thrust = float(msg.thrust)
    if not (math.isfinite(sum(q)) or all(math.isfinite(x) for x in q)):
        raise SetpointRejected("non-finite attitude quaternion")
    if not math.isfinite(thrust) or not 0.0 <= thrust <= 1.0:
        raise SetpointRejected(f"thrust {thrust:.3g} outside 0..1")
    w, x, y, z = q
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if abs(norm - 1.0) > 0.1:
        raise SetpointRejected(f"quaternion norm {norm:.3g}, expected 1")
    roll, pitch, yaw = euler_from_quat((w / norm, x / norm, y / norm, z / norm))
    if mask & mav.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE:
        flag, yaw_value = ATTITUDE_THRUST_YAW_ANGLE, math.degrees(yaw)
    else:
        rate = float(msg.body_yaw_rate)
        if not math.isfinite(rate):
            raise SetpointRejected("non-finite yaw rate")
        flag, yaw_value = ATTITUDE_THRUST_YAW_RATE, math.degrees(rate)
    return N3Setpoint(flag, math.degrees(roll), math.degrees(pitch), 100.0 * thrust, yaw_value)


def _bits(v: object) -> object:
    """A value compared bit for bit (floats by their bytes: -0.0 and NaN payloads count)."""
    return struct.pack("<d", v) if v.__class__ is float else v


def _outcome(f, *args) -> tuple:
    """("ok", result fields bit for bit) or ("raised", exception type, reason or message)."""
    try:
        r = f(*args)
    except SetpointRejected as exc:
        return "rejected", exc.reason
    except Exception as exc:  # the kind of failure must match too
        return "raised", type(exc).__name__, str(exc)
    if r is None:
        return ("ok",)
    fields = astuple(r) if isinstance(r, AttitudeThrustTarget | N3Setpoint) else tuple(r)
    return ("ok", *(_bits(v) for v in fields))


def _rand(rng: np.random.Generator, scale: float = 1.0) -> float:
    return float(rng.choice(SPECIAL)) if rng.random() < 0.15 else float(rng.normal(0, scale))


def _hostile_targets(rng: np.random.Generator, n: int) -> list[MAVLinkMessage]:
    """SET_ATTITUDE_TARGETs as a codec decodes them (float32 values), hostile ones among them."""
    enc = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    msgs = []
    for k in range(n):
        q = list(quat_from_euler(*rng.normal(0, 0.8, 3)))
        if rng.random() < 0.3:
            q[int(rng.integers(0, 4))] = _rand(rng)
        if rng.random() < 0.1:
            q = [x * float(rng.uniform(0.8, 1.2)) for x in q]
        mask = int(rng.choice([7, 7, 3, 3, 0, 0x80, 0x40, 0x47, int(rng.integers(0, 256))]))
        thrust = _rand(rng, 0.3) + 0.5 if rng.random() < 0.3 else float(rng.uniform(0, 1))
        msg = enc.set_attitude_target_encode(k, 1, 1, mask, q, 0.0, 0.0, _rand(rng, 2.0), thrust)
        msgs.append(decode_frame(bytes(msg.pack(enc))))
    return msgs


def test_attitude_targets_give_the_reference_setpoints_and_targets():
    rng = np.random.default_rng(11)
    msgs = _hostile_targets(rng, 4000)
    # messages built in-process: plain floats beyond float32, other sequences, other lengths
    enc = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    q = quat_from_euler(0.3, -0.2, 1.0)
    for extra in (
        [tuple(q)], [q], [list(q)[:3]], [[*q, 0.0]], [[1, 0, 0, 0]], [[0.5, 0.5, 0.5, 0.5]],
        [[1e308, 1e308, -1e308, 0.0]], [[math.radians(200), 0.0, 0.0, 1.0]],
    ):
        for mask, thrust, rate in ((7, 0.5, 0.0), (3, 1.0, 1e300), (3, 0.0, 2.5), (7, 1.0000001, 0.0)):
            msgs.append(enc.set_attitude_target_encode(0, 1, 1, mask, extra[0], 0.0, 0.0, rate, thrust))
    fc = EmulatedVehicle(PROFILE).fc
    kinds = set()
    for msg in msgs:
        ref = _outcome(_ref_setpoint, msg)
        assert _outcome(attitude_target_values, msg.type_mask, msg.q, msg.thrust, msg.body_yaw_rate) == ref
        if ref[0] != "ok":
            kinds.add(ref[1].split(" ")[0])
            continue
        sp = N3Setpoint(*attitude_target_values(msg.type_mask, msg.q, msg.thrust, msg.body_yaw_rate))
        want = _outcome(_ref_to_target, sp, PROFILE)
        if want[0] == "ok":
            over = tilt_of(math.radians(sp.roll_deg), math.radians(sp.pitch_deg)) > math.radians(
                PROFILE.max_tilt_deg)
            kinds.add("tilt limited" if over else "ok")
        else:
            kinds.add(want[1].split(" ")[0])
        assert _outcome(to_target, sp, PROFILE) == want
        assert _outcome(fc.set_setpoint_values, *astuple(sp), 0.0) == want
    # every way out was taken
    assert {"attitude", "thrust", "non-finite", "quaternion", "roll/pitch", "ok", "tilt limited"} <= kinds


def test_setpoint_values_give_the_reference_target_for_any_field_types_and_flags():
    rng = np.random.default_rng(5)
    values = [*SPECIAL, 45, 0, -91, 120, True, np.float64(30.0), np.float64(math.nan), np.int64(7), "x", None]
    cases = [N3Setpoint(flag, 0.0, 0.0, 50.0, 0.0) for flag in range(-1, 257)]
    cases += [N3Setpoint(flag, 0.0, 0.0, 50.0, 0.0) for flag in (32.0, True, np.int64(32), "32", None)]
    for _ in range(3000):
        flag = int(rng.choice([0x20, 0x21, 0x28, 0x29, 0x22, 0x30]))
        f = [values[int(rng.integers(0, len(values)))] if rng.random() < 0.2 else float(rng.normal(0, 60))
             for _ in range(4)]
        f[2] = f[2] if rng.random() < 0.3 else float(rng.uniform(0, 100))
        cases.append(N3Setpoint(flag, *f))
    for sp in cases:
        if isinstance(sp.flag, int) and 0 <= sp.flag <= 0xFF and sp.flag & 0xC0:
            continue  # the velocity and position modes came later: `test_velocity_and_position_flags`
        want = _outcome(_ref_to_target, sp, PROFILE)
        assert _outcome(to_target, sp, PROFILE) == want, sp
        assert _outcome(check_flag, sp.flag) == _outcome(_ref_check_flag, sp.flag)


def test_velocity_and_position_flags_are_flown_with_a_velocity_or_height_and_the_rest_refused():
    accepted = {f for f in range(0x40, 0x100) if _outcome(check_flag, f)[0] != "rejected"}
    want = {h | v | y | fr | st for h in (0x40, 0x80) for v in (0x00, 0x10) for y in (0, 8) for fr in (0, 2)
            for st in (0, 1)}
    assert accepted == want  # angular rate, thrust with a velocity or position, frame bit 0x04: refused
    tg = to_target(N3Setpoint(0x91, 2.0, -1.0, 300.0, 30.0), PROFILE)  # OSDK's positionAndYawCtrl
    assert (tg.horizontal_position, tg.vertical_position, tg.body_frame) == (True, True, False)
    assert (tg.x, tg.y, tg.z) == (2.0, -1.0, 120.0) and tg.yaw_rad == pytest.approx(math.radians(30))
    tg = to_target(N3Setpoint(0x48, 40.0, 0.0, -9.0, 10.0), PROFILE)  # velocity, yaw rate
    assert (tg.x, tg.z) == (30.0, -5.0) and tg.yaw_rate_rad_s == pytest.approx(math.radians(10))


def test_a_yaw_rate_stream_still_starts_from_the_heading():
    fc = EmulatedVehicle(PROFILE).fc
    fc.set_setpoint_values(ATTITUDE_THRUST_YAW_RATE, 0.0, 0.0, 50.0, 10.0, 0.0)
    assert fc._yaw_sp_fresh
    fc._yaw_sp_fresh = False
    fc.set_setpoint_values(ATTITUDE_THRUST_YAW_RATE, 0.0, 0.0, 50.0, 10.0, 0.01)
    assert not fc._yaw_sp_fresh  # still a rate stream
    fc.set_setpoint_values(ATTITUDE_THRUST_YAW_ANGLE, 0.0, 0.0, 50.0, 10.0, 0.02)
    fc.set_setpoint_values(ATTITUDE_THRUST_YAW_RATE, 0.0, 0.0, 50.0, 10.0, 0.03)
    assert fc._yaw_sp_fresh and fc.setpoints_accepted == 4 and fc.last_setpoint_s == 0.03


class _Pair:
    """One server reading decoded messages, one reading the setpoints as frames (codec raw_ids)."""

    def __init__(self) -> None:
        self.clock = SimClock()
        self.sides = []
        for raw in ((), RAW_MSG_IDS):
            fc_end, peer = MemoryTransport.pair()
            vehicle = EmulatedVehicle(PROFILE)
            server = MavlinkServer(vehicle, MavlinkCodec(fc_end, self.clock, 1, 1, raw_ids=raw))
            applied: list = []
            server.on_setpoint = lambda msg, now, got=applied: got.append((bytes(msg.get_msgbuf()), now))
            self.sides.append((server, peer, applied))

    def feed(self, data: bytes) -> None:
        for _, peer, _ in self.sides:
            peer.send(data)
        self.clock.advance_to(round(self.clock.now_s() + 0.001, 6))
        for server, _, _ in self.sides:
            server.poll(self.clock.now_s())

    def same(self) -> None:
        (a, pa, sa), (b, pb, sb) = self.sides
        assert a.stats == b.stats and a.codec.stats == b.codec.stats
        assert pa.recv() == pb.recv()  # what the FC answered (STATUSTEXTs, telemetry) byte for byte
        assert sa == sb
        ta, tb = a.fc.target, b.fc.target
        assert (ta is None and tb is None) or _outcome(lambda: ta) == _outcome(lambda: tb)
        assert a.fc.last_setpoint_s == b.fc.last_setpoint_s
        assert a.fc.setpoints_accepted == b.fc.setpoints_accepted


def test_setpoints_read_from_frames_act_as_decoded_messages():
    rng = np.random.default_rng(3)
    pair = _Pair()
    raw_taken = []
    server_b = pair.sides[1][0]
    handle = server_b.handle
    server_b.handle = lambda msg, now: (raw_taken.append(msg.__class__ is bytes), handle(msg, now))
    enc = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    msgs = _hostile_targets(rng, 600)
    for k, msg in enumerate(msgs):
        m = msg
        if k % 7 == 0:  # addressed elsewhere
            m = enc.set_attitude_target_encode(0, 9 if k % 2 else 1, 5, 7, msg.q, 0.0, 0.0, 0.0, msg.thrust)
        if k % 11 == 0:  # a short payload (trailing zeros trimmed): type_mask 0, zero target ids
            m = enc.set_attitude_target_encode(0, 0, 0, 0, msg.q, 0.0, 0.0, 0.0, msg.thrust)
        data = bytes(m.pack(enc))
        if k % 50 == 0:  # a command among them, and the arm that lets setpoints count
            data += bytes(enc.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(enc))
        pair.feed(data)
        pair.same()
    assert sum(raw_taken) > 500  # the frame path was taken
    server = pair.sides[0][0]
    assert server.stats.setpoints_applied > 100 and server.stats.setpoints_rejected > 100
    assert server.stats.foreign_target > 30 and server.stats.statustext_suppressed > 100


def test_offboard_climb_through_the_frame_path():
    """A whole arm-offboard-climb over a codec handing setpoints over as frames."""
    clock = SimClock()
    fc_end, gcs_end = MemoryTransport.pair()
    vehicle = EmulatedVehicle(PROFILE)
    server = MavlinkServer(vehicle, MavlinkCodec(fc_end, clock, 1, 1, raw_ids=RAW_MSG_IDS))
    client = MavlinkCodec(gcs_end, clock, 255, 190)
    q = list(quat_from_euler(0.0, 0.0, 0.0))

    def run(s: float) -> None:
        for _ in range(round(s * 1000)):
            clock.advance_to(round(clock.now_s() + 0.001, 6))
            server.poll(clock.now_s())
            vehicle.step_to(clock.now_s())
            client.receive()

    client.send(client.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    for i in range(60):
        client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 1.3 * HOVER))
        if i == 10:
            client.send(client.mav.command_long_encode(1, 1, 176, 0, 129, PX4_MAIN_OFFBOARD, 0, 0, 0, 0, 0))
        run(0.02)
    assert vehicle.fc.state is FcState.OFFBOARD and server.stats.setpoints_applied == 60
    assert vehicle.state.pos_m[2] > 0.3
