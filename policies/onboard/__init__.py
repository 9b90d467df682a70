"""The onboard program (the system under test, as it would run on the TX2): command link, mission state
machine, state estimate and pilots. Reaches the vehicle only through `hil.link` transports."""

from policies.onboard.command_link import CommandLink, FcStatus
from policies.onboard.estimator import EstimatorConfig, PoseEstimator, StateEstimate
from policies.onboard.pilots import Observation, Pilot, PilotContext, make_pilot, pilot_names
from policies.onboard.program import EventLog, OnboardProgram, Phase, ProgramConfig

__all__ = [
    "CommandLink",
    "EstimatorConfig",
    "EventLog",
    "FcStatus",
    "Observation",
    "OnboardProgram",
    "Phase",
    "Pilot",
    "PilotContext",
    "PoseEstimator",
    "ProgramConfig",
    "StateEstimate",
    "make_pilot",
    "pilot_names",
]
