"""The FC's MAVLink endpoint in lockstep over an in-memory link: heartbeat, commands, setpoints,
telemetry, signing, and a byte-for-byte deterministic .tlog."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from emulator.fc import FcConfig, FcState
from emulator.profile import GRAVITY_M_S2, load_profile
from emulator.servers.mavlink_server import MAX_MESSAGES_PER_POLL, MavlinkServer
from emulator.vehicle import EmulatedVehicle
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import (
    PX4_AUTO_LOITER,
    PX4_MAIN_AUTO,
    PX4_MAIN_OFFBOARD,
    MavlinkCodec,
    mav,
    px4_custom_mode,
    px4_mode_parts,
    quat_from_euler,
)
from hil.link.tlog import TlogWriter, read_tlog

PROFILE = load_profile("n3_tx2")
HOVER = PROFILE.mass_kg * GRAVITY_M_S2 / PROFILE.n3_full_thrust_n  # SET_ATTITUDE_TARGET thrust 0..1
KEY = bytes(range(32))


class Bench:
    """FC server and a client codec on one SimClock, advanced in 1 ms lockstep."""

    def __init__(
        self,
        signing_key: bytes | None = None,
        client_key: bytes | None = None,
        tlog: Path | None = None,
        config: FcConfig | None = None,
    ) -> None:
        self.clock = SimClock()
        fc_end, gcs_end = MemoryTransport.pair()
        self.tlog = TlogWriter(tlog, epoch_unix_s=1.7e9) if tlog else None
        self.vehicle = EmulatedVehicle(PROFILE, config=config)
        self.server = MavlinkServer(
            self.vehicle,
            MavlinkCodec(fc_end, self.clock, 1, 1, signing_key=signing_key, recorder=self.tlog),
        )
        self.client = MavlinkCodec(gcs_end, self.clock, 255, 190, signing_key=client_key)
        self.received: list = []

    def run(self, duration_s: float) -> list:
        """Advance; returns the messages the client received meanwhile."""
        got = []
        end = self.clock.now_s() + duration_s
        while self.clock.now_s() < end - 1e-9:
            self.clock.advance_to(round(self.clock.now_s() + 0.001, 6))
            now = self.clock.now_s()
            self.server.poll(now)
            self.vehicle.step_to(now)
            got.extend(self.client.receive())
        self.received.extend(got)
        return got

    def send(self, msg) -> None:
        self.client.send(msg)

    def command(self, command: int, *params: float, target: int = 1) -> list:
        p = list(params) + [0.0] * (7 - len(params))
        self.send(self.client.mav.command_long_encode(target, 1, command, 0, *p))
        return [m for m in self.run(0.01) if m.get_type() == "COMMAND_ACK" and m.command == command]

    def attitude(
        self,
        roll: float = 0.0,
        pitch: float = 0.0,
        yaw: float = 0.0,
        thrust: float = HOVER,
        type_mask: int = 7,
        target: int = 1,
        q=None,
    ):
        q = list(quat_from_euler(roll, pitch, yaw)) if q is None else q
        return self.client.mav.set_attitude_target_encode(0, target, 1, type_mask, q, 0.0, 0.0, 0.0, thrust)

    def stream(self, duration_s: float, rate_hz: float = 50.0, **kw) -> list:
        got = []
        for _ in range(round(duration_s * rate_hz)):
            self.send(self.attitude(**kw))
            got += self.run(1.0 / rate_hz)
        return got


def of_type(msgs: list, name: str) -> list:
    return [m for m in msgs if m.get_type() == name]


def test_heartbeat_is_a_px4_quadrotor_and_telemetry_streams_at_their_rates():
    b = Bench()
    got = b.run(2.0)
    hb = of_type(got, "HEARTBEAT")
    assert len(hb) == 2
    assert hb[0].autopilot == mav.MAV_AUTOPILOT_PX4 and hb[0].type == mav.MAV_TYPE_QUADROTOR
    assert hb[0].base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb[0].base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb[0].system_status == mav.MAV_STATE_STANDBY
    assert len(of_type(got, "ATTITUDE")) == pytest.approx(100, abs=2)
    assert len(of_type(got, "LOCAL_POSITION_NED")) == pytest.approx(60, abs=2)
    for name in ("ATTITUDE_QUATERNION", "HIGHRES_IMU", "SYS_STATUS", "BATTERY_STATUS", "EXTENDED_SYS_STATE"):
        assert of_type(got, name), name
    ext = of_type(got, "EXTENDED_SYS_STATE")[-1]
    assert ext.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    imu = of_type(got, "HIGHRES_IMU")[-1]
    assert imu.zacc == pytest.approx(-GRAVITY_M_S2, abs=0.05)  # FRD: resting reads -g on z
    att = of_type(got, "ATTITUDE")[-1]
    assert att.yaw == pytest.approx(0.0, abs=1e-6)  # resting vehicle heads north
    lpn = of_type(got, "LOCAL_POSITION_NED")[-1]
    assert lpn.z == pytest.approx(-0.5 * PROFILE.body_box_m[2], abs=1e-3)  # NED: up is negative


def test_arm_offboard_climb_and_hold_through_commands_and_setpoints():
    b = Bench()
    b.run(0.1)
    [ack] = b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack.result == mav.MAV_RESULT_ACCEPTED and ack.target_system == 255
    b.send(b.attitude(thrust=0.7 * HOVER))
    b.run(0.02)
    [ack] = b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)  # one setpoint: not a stream yet
    assert ack.result == mav.MAV_RESULT_DENIED
    assert any("2 Hz" in m.text for m in of_type(b.received, "STATUSTEXT"))
    b.stream(0.2, thrust=0.7 * HOVER)
    [ack] = b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    got = b.stream(1.0, thrust=1.3 * HOVER)
    hb = of_type(got, "HEARTBEAT")[-1]
    assert px4_mode_parts(hb.custom_mode) == (PX4_MAIN_OFFBOARD, 0)
    assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    lpn = of_type(got, "LOCAL_POSITION_NED")[-1]
    assert lpn.vz < -1.0  # climbing (NED)
    assert of_type(got, "EXTENDED_SYS_STATE")[-1].landed_state == mav.MAV_LANDED_STATE_IN_AIR
    [ack] = b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_AUTO, PX4_AUTO_LOITER)  # MAVSDK's offboard stop
    assert ack.result == mav.MAV_RESULT_ACCEPTED and b.vehicle.fc.state is FcState.HOLD
    [ack] = b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0)
    assert ack.result == mav.MAV_RESULT_DENIED  # in the air


def test_failsafe_is_announced_in_heartbeat_and_statustext_within_the_timeout():
    b = Bench(config=FcConfig(failsafe_timeout_s=0.3))
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(0.2, thrust=1.2 * HOVER)
    b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)
    b.stream(0.5, thrust=1.2 * HOVER)
    t_last = b.clock.now_s() - 0.02  # the last setpoint went out one period ago
    got = b.run(0.5)
    texts = [m for m in of_type(got, "STATUSTEXT") if "Failsafe" in m.text]
    assert texts and texts[0].severity == mav.MAV_SEVERITY_CRITICAL
    hb = [m for m in of_type(got, "HEARTBEAT") if m.custom_mode != px4_custom_mode(PX4_MAIN_OFFBOARD)]
    assert hb and hb[0].system_status == mav.MAV_STATE_CRITICAL
    ev = b.vehicle.fc.events[-1]
    assert ev.to_state is FcState.FAILSAFE_HOVER and 0.3 < ev.time_s - t_last <= 0.3 + 0.1


def test_a_setpoint_read_late_is_logged_at_the_time_the_fc_counts_its_failsafe_from(tmp_path):
    """In real time an FC's poll reads the clock, then the link: a read held up (a busy host) logs the
    setpoint at the poll's time, the one the failsafe timeout runs from, not later (the .tlog then shows
    the failsafe a full timeout after the last setpoint, as the FC counted it)."""
    b = Bench(tlog=tmp_path / "fc.tlog")
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(0.2, thrust=HOVER)
    b.send(b.attitude(thrust=1.1 * HOVER))
    poll_s = b.clock.now_s()
    b.clock.advance_to(round(poll_s + 0.02, 6))  # the read comes 20 ms after the poll read the clock
    b.server.poll(poll_s)
    assert b.vehicle.fc.last_setpoint_s == poll_s
    b.tlog.close()
    stamps = [t for t, f in read_tlog(tmp_path / "fc.tlog")
              if mav.MAVLink(None).decode(bytearray(f)).get_type() == "SET_ATTITUDE_TARGET"]
    assert stamps[-1] == round((1.7e9 + poll_s) * 1e6)


def test_request_message_interval_ping_and_timesync_are_answered():
    b = Bench()
    assert b.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)[0].result == 0
    assert b.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION)[0].result == 0
    av, home = of_type(b.received, "AUTOPILOT_VERSION"), of_type(b.received, "HOME_POSITION")
    assert av and av[0].capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert home and home[0].latitude != 0
    [ack] = b.command(mav.MAV_CMD_REQUEST_MESSAGE, 9999)
    assert ack.result == mav.MAV_RESULT_UNSUPPORTED
    [ack] = b.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 100_000)  # 10 Hz
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    assert len(of_type(b.run(1.0), "ATTITUDE")) == pytest.approx(10, abs=1)
    b.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, -1)
    assert not of_type(b.run(0.5), "ATTITUDE")
    [ack] = b.command(12345)
    assert ack.result == mav.MAV_RESULT_UNSUPPORTED
    b.send(b.client.mav.ping_encode(123456, 7, 0, 0))
    b.send(b.client.mav.timesync_encode(0, 42))
    got = b.run(0.01)
    [ping] = of_type(got, "PING")
    assert (ping.seq, ping.time_usec, ping.target_system) == (7, 123456, 255)
    [ts] = of_type(got, "TIMESYNC")
    assert ts.ts1 == 42 and ts.tc1 == pytest.approx(b.clock.now_s() * 1e9, abs=2e7)


def test_bad_setpoints_and_foreign_commands_are_counted_and_answered():
    b = Bench()
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    bad = [
        b.attitude(thrust=math.nan),
        b.attitude(thrust=1.5),
        b.attitude(thrust=-0.1),
        b.attitude(q=[math.nan, 0, 0, 0]),
        b.attitude(q=[math.inf, 0, 0, 0]),
        b.attitude(q=[0.0, 0, 0, 0]),
        b.attitude(type_mask=128),  # rates only: N3 flies angles
        b.attitude(type_mask=64 | 7),  # thrust ignored
    ]
    for msg in bad:
        b.send(msg)
        b.run(1.1)  # past the STATUSTEXT rate limit
    s = b.server.stats
    assert s.setpoints_rejected == len(bad) and s.setpoints_applied == 0
    texts = [m.text for m in of_type(b.received, "STATUSTEXT") if "Setpoint rejected" in m.text]
    assert len(texts) == len(bad)
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, target=7)  # another vehicle's command: no answer
    assert s.foreign_target == 1
    b.send(b.attitude(target=9))
    b.run(0.01)
    assert s.foreign_target == 2 and s.setpoints_applied == 0
    [ack] = b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, math.nan)
    assert ack.result == mav.MAV_RESULT_DENIED
    [ack] = b.command(mav.MAV_CMD_DO_SET_MODE, 129, math.inf)
    assert ack.result == mav.MAV_RESULT_DENIED
    [ack] = b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD + 1)  # acro: not an N3 mode
    assert ack.result == mav.MAV_RESULT_DENIED
    assert b.vehicle.fc.state is FcState.HOLD


def test_signing_rejects_unsigned_and_wrongly_signed_commands_and_accepts_signed_ones():
    unsigned = Bench(signing_key=KEY)
    assert unsigned.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == []
    assert unsigned.server.codec.stats.unsigned_refused == 1 and unsigned.vehicle.fc.state is FcState.DISARMED
    wrong = Bench(signing_key=KEY, client_key=bytes(32))
    assert wrong.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == []
    wrong.send(wrong.attitude())
    wrong.run(0.01)
    assert wrong.server.codec.stats.bad_signature == 2 and wrong.server.stats.setpoints_applied == 0
    good = Bench(signing_key=KEY, client_key=KEY)
    [ack] = good.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack.result == mav.MAV_RESULT_ACCEPTED and good.vehicle.fc.state is FcState.HOLD
    beat = of_type(good.received, "HEARTBEAT")[0].get_msgbuf()  # the FC signs what it sends
    assert beat[2] & mav.MAVLINK_IFLAG_SIGNED and good.client.stats.signing_refused == 0


def fly_recorded(path: Path) -> None:
    b = Bench(tlog=path)
    b.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    b.stream(0.2, thrust=HOVER)
    b.command(mav.MAV_CMD_DO_SET_MODE, 129, PX4_MAIN_OFFBOARD)
    b.stream(0.5, thrust=1.2 * HOVER, roll=0.2)
    b.tlog.close()


def test_tlog_has_both_directions_and_is_byte_for_byte_deterministic(tmp_path):
    fly_recorded(tmp_path / "a.tlog")
    fly_recorded(tmp_path / "b.tlog")
    a = (tmp_path / "a.tlog").read_bytes()
    assert a == (tmp_path / "b.tlog").read_bytes()
    frames = read_tlog(tmp_path / "a.tlog")
    stamps = [t for t, _ in frames]
    assert stamps == sorted(stamps) and stamps[0] >= 1.7e15
    parser = mav.MAVLink(None)
    types = {parser.decode(bytearray(f)).get_type() for _, f in frames}
    assert {"SET_ATTITUDE_TARGET", "COMMAND_LONG", "COMMAND_ACK", "HEARTBEAT", "ATTITUDE"} <= types


def test_a_flood_is_taken_over_several_passes_and_nothing_is_lost():
    b, most = Bench(), MAX_MESSAGES_PER_POLL
    n = 2 * most + 100
    for i in range(n):
        value = 0.5 + i % 4 / 4
        b.send(b.client.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", value, mav.MAV_PARAM_TYPE_REAL32))
    b.run(0.001)  # one pass: the bound
    assert b.server.stats.params_set == most
    b.run(0.002)  # two more: the rest
    assert b.server.stats.params_set == n
    assert b.server.stats.intake_deferred == (n - most) + (n - 2 * most)  # each pass's wait counted
