"""The N3-style flight controller's control law: attitude-thrust setpoints and their checks, the inner
loop, its own hover and landing controller, modes and failsafe, gains from the profile. The servers that
carry it on a command link are `emulator.servers`; the vehicle it flies, `emulator.vehicle`."""

from emulator.fc.flight_controller import FcConfig, FlightController
from emulator.fc.hold import HoldGains
from emulator.fc.inner_loop import InnerLoop, InnerLoopGains
from emulator.fc.modes import CommandResult, FcEvent, FcState, LandedState
from emulator.fc.n3 import AttitudeThrustTarget, N3Setpoint, SetpointRejected
from emulator.fc.tuning import FcGains, fc_gains

__all__ = [
    "AttitudeThrustTarget",
    "CommandResult",
    "FcConfig",
    "FcEvent",
    "FcGains",
    "FcState",
    "FlightController",
    "HoldGains",
    "InnerLoop",
    "InnerLoopGains",
    "LandedState",
    "N3Setpoint",
    "SetpointRejected",
    "fc_gains",
]
