"""The N3-style flight controller: attitude-thrust setpoints, inner loop, modes and failsafe, and its
MAVLink endpoint (PX4-flavoured, so MAVSDK and pymavlink clients work unchanged)."""

from emulator.fc.flight_controller import FcConfig, FlightController
from emulator.fc.hold import HoldGains
from emulator.fc.inner_loop import InnerLoop, InnerLoopGains
from emulator.fc.mavlink_server import MavlinkServer, ServerConfig, ServerStats
from emulator.fc.modes import CommandResult, FcEvent, FcState, LandedState
from emulator.fc.n3 import AttitudeThrustTarget, N3Setpoint, SetpointRejected
from emulator.fc.realtime_runner import RealtimeRunner
from emulator.fc.tuning import FcGains, fc_gains
from emulator.fc.vehicle import EmulatedVehicle, resting_state

__all__ = [
    "AttitudeThrustTarget",
    "CommandResult",
    "EmulatedVehicle",
    "FcConfig",
    "FcEvent",
    "FcGains",
    "FcState",
    "FlightController",
    "HoldGains",
    "InnerLoop",
    "InnerLoopGains",
    "LandedState",
    "MavlinkServer",
    "N3Setpoint",
    "RealtimeRunner",
    "ServerConfig",
    "ServerStats",
    "SetpointRejected",
    "fc_gains",
    "resting_state",
]
