"""The onboard program's OPEN-protocol client against the emulator's server over memory links: it
activates and gets its flight data, reports a refused activation and an RC out of F mode, obtains
control, arms and flies setpoints as the program's requests ask, and reads lockstep ticks."""

from __future__ import annotations

import math

from emulator.fc import FcState
from emulator.profile import load_profile
from emulator.servers.dji_open_server import DjiOpenServer, DjiServerConfig
from emulator.vehicle import EmulatedVehicle
from hil.link import MemoryTransport, SimClock
from hil.link.dji_open import OpenCodec
from hil.link.lockstep import dji_tick_frames
from hil.link.mavlink import mav
from policies.onboard.dji_command_link import DjiCommandLink

PROFILE = load_profile("n3_tx2")


class Rig:
    def __init__(self, config: DjiServerConfig | None = None) -> None:
        self.clock = SimClock()
        self.fc_end, ob_end = MemoryTransport.pair()
        self.vehicle = EmulatedVehicle(PROFILE)
        self.server = DjiOpenServer(self.vehicle, OpenCodec(self.fc_end, self.clock), config)
        self.link = DjiCommandLink(ob_end, self.clock)

    def run(self, duration_s: float, setpoints: bool = False) -> None:
        end = self.clock.now_s() + duration_s
        while self.clock.now_s() < end - 1e-9:
            self.clock.advance_to(round(self.clock.now_s() + 0.001, 6))
            now = self.clock.now_s()
            if self.link.status is None:
                self.link.request_heartbeat()
            if setpoints and round(now * 1000) % 10 == 0:
                hover = PROFILE.mass_kg * 9.81 / PROFILE.n3_full_thrust_n
                self.link.send_attitude_target(0.0, 0.0, 0.0, hover * 1.2)
            self.server.poll(now)
            self.vehicle.step_to(now)
            self.link.read()


def test_the_client_activates_obtains_control_arms_and_flies():
    rig = Rig()
    rig.run(0.2)
    assert rig.link.activated and rig.link.status is not None and not rig.link.status.armed
    assert rig.link.heartbeat_age_s(rig.clock.now_s()) < 0.15
    rig.link.request_offboard()
    rig.run(0.2, setpoints=True)
    assert rig.link.acks[mav.MAV_CMD_DO_SET_MODE].accepted and rig.link.status.offboard
    rig.link.request_arm()
    rig.run(1.0, setpoints=True)
    assert rig.link.acks[mav.MAV_CMD_COMPONENT_ARM_DISARM].accepted and rig.link.status.armed
    assert rig.vehicle.fc.state is FcState.OFFBOARD and rig.vehicle.state.pos_m[2] > 0.2
    # the setpoint reaches the FC as the N3's NED degrees: yaw 0 in ENU (east) is heading 90 deg
    assert math.isclose(math.degrees(rig.vehicle.fc.target.yaw_rad), 90.0, abs_tol=1e-3)
    rig.link.request_hold()
    rig.run(0.2)
    assert rig.link.acks[mav.MAV_CMD_DO_SET_MODE].accepted and rig.link.status.holding
    assert rig.vehicle.fc.state is FcState.HOLD


def test_a_refused_activation_and_an_rc_out_of_f_mode_are_reported():
    rig = Rig(DjiServerConfig(activation_code=6))
    rig.run(1.2)
    assert not rig.link.activated and rig.link.status is None
    assert rig.link.activation_code == 6 and "activation refused: code 6" in rig.link.status_texts
    assert rig.server.stats.commands_denied >= 2  # asked again after a refusal
    rig = Rig(DjiServerConfig(rc_mode="P"))
    rig.run(0.2)
    rig.link.request_offboard()
    rig.run(0.2)
    assert not rig.link.acks[mav.MAV_CMD_DO_SET_MODE].accepted
    assert "control refused: the RC is not in F mode" in rig.link.status_texts


def test_lockstep_ticks_and_their_mocap_totals_are_read_and_answered():
    rig = Rig()
    rig.link.lockstep = True
    rig.fc_end.send(dji_tick_frames(0.01, 1234) + dji_tick_frames(0.02, 2345))
    rig.link.read()
    assert rig.link.take_ticks() == [0.01] and rig.link.mocap_announced == 1234
    rig.link.answer_tick(0.01)
    rig.link.read()
    assert rig.link.take_ticks() == [0.02] and rig.link.mocap_announced == 2345
