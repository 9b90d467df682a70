"""The FC's telemetry as a ground station reads it: pymavlink decodes the streamed frames to the vehicle's
state in NED/FRD and to the mode, armed flag and landed state of every FC state."""

from __future__ import annotations

import math

import pytest

from emulator.fc import FcState
from emulator.physics.native import hover_state
from emulator.profile import load_profile
from emulator.servers.mavlink_server import MavlinkServer
from emulator.servers.telemetry import BATTERY_CELLS, CUSTOM_MODE
from emulator.vehicle import EmulatedVehicle
from hil.link import MemoryTransport, SimClock
from hil.link.mavlink import PX4_MAIN_OFFBOARD, MavlinkCodec, mav, px4_custom_mode

PROFILE = load_profile("n3_tx2")


def test_streamed_payloads_decode_to_the_state_and_mode_in_every_fc_state():
    vehicle = EmulatedVehicle(PROFILE, initial_state=hover_state(PROFILE, (0.5, -1.0, 1.5)))
    vehicle.step(5)
    codec = MavlinkCodec(MemoryTransport.pair()[0], SimClock(), 1, 1)
    t, fc = MavlinkServer(vehicle, codec).telemetry, vehicle.fc
    x = t.state_values()
    ground = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    s = vehicle.state
    for state in FcState:
        for offboard_selected in (False, True):
            for landed in (False, True):
                fc.machine.state, fc.offboard_selected, fc.landed = state, offboard_selected, landed
                hb, att, pos, ext = (
                    ground.decode(bytearray(codec.pack_payload(i, p))) for i, p in (
                        (mav.MAVLINK_MSG_ID_HEARTBEAT, t.heartbeat_payload()),
                        (mav.MAVLINK_MSG_ID_ATTITUDE, t.attitude_payload(1.234, x)),
                        (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, t.local_position_ned_payload(5e6, x)),
                        (mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, t.extended_sys_state_payload()),
                    )
                )
                offboard_chosen = state is FcState.DISARMED and offboard_selected
                assert hb.custom_mode == (px4_custom_mode(PX4_MAIN_OFFBOARD) if offboard_chosen
                                          else CUSTOM_MODE[state])
                assert bool(hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED) == state.armed
                assert (hb.system_status == mav.MAV_STATE_CRITICAL) == state.failsafe
                assert ext.landed_state == fc.landed_state.value
    # ENU/FLU -> NED/FRD: north, east, down; a level hover with body x east: heading 90 deg
    assert att.time_boot_ms == 1234 and pos.time_boot_ms == 5_000_000_000 % 2**32  # ms, wrapping
    assert (pos.x, pos.y, pos.z) == pytest.approx((-1.0, 0.5, -s.pos_m[2]), abs=1e-6)
    assert (pos.vx, pos.vy, pos.vz) == pytest.approx((s.vel_m_s[1], s.vel_m_s[0], -s.vel_m_s[2]), abs=1e-6)
    assert s.quat_wxyz.tolist() == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-4)
    assert (att.roll, att.pitch, att.yaw) == pytest.approx((0.0, 0.0, math.pi / 2), abs=1e-3)
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx(
        (s.omega_rad_s[0], -s.omega_rad_s[1], -s.omega_rad_s[2]), abs=1e-6)


def test_battery_drains_with_the_time_armed_between_polls():
    """Each poll counts the time since the poll before it when the FC is armed at that poll: the
    battery's charge falls with that time only, in both MAVLink's SYS_STATUS and the model."""
    vehicle = EmulatedVehicle(PROFILE, initial_state=hover_state(PROFILE, (0.0, 0.0, 1.5)))
    codec = MavlinkCodec(MemoryTransport.pair()[0], SimClock(), 1, 1)
    server = MavlinkServer(vehicle, codec)
    t, fc = server.telemetry, vehicle.fc
    for now in (0.0, 1.0, 2.0):
        server.poll(now)
    full_v, full_pct = t.battery(2.0)
    assert full_pct == 100 and full_v == pytest.approx(BATTERY_CELLS * 4.2)
    fc.arm(2.5)
    server.poll(3.0)  # armed at this poll: counted from the poll before (2.0)
    server.poll(11.0)
    assert t.battery(11.0) == (pytest.approx(BATTERY_CELLS * (3.5 + 0.7 * (1 - 9.0 / 900))), 99)
    server.poll(92.0)
    volts, pct = t.battery(92.0)
    assert pct == 90 and volts == pytest.approx(BATTERY_CELLS * (3.5 + 0.7 * 0.9))
    ground = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    status = ground.decode(bytearray(codec.pack(t.sys_status(92.0, 0))))
    assert status.battery_remaining == 90 and status.voltage_battery == round(volts * 1000)
    fc.landed = True
    assert fc.disarm(95.0).accepted
    server.poll(101.0)  # disarmed at this poll: the time since the poll at 92.0 not counted
    server.poll(500.0)
    assert t.battery(500.0) == (volts, pct)
