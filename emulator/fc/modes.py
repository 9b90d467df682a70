"""The FC's state machine: arming, control authority, failsafe states, and the record of transitions."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class FcState(Enum):
    """What the flight controller is doing. Later fault scenarios read these from `FcEvent`s."""

    DISARMED = "disarmed"  # motors off
    HOLD = "hold"  # armed, no offboard authority: idle on the ground, hover in the air
    OFFBOARD = "offboard"  # armed, flying the onboard computer's attitude-thrust setpoints
    LAND = "land"  # commanded landing, disarms on touchdown
    FAILSAFE_HOVER = "failsafe_hover"  # setpoints lost: hover in place for a while ...
    FAILSAFE_LAND = "failsafe_land"  # ... then land and disarm
    TAKEOFF = "takeoff"  # the FC's own take-off: motors spin up, climb to the take-off height, then HOLD
    GO_HOME = "go_home"  # the FC flies back over its home point (where it armed) at its height, then LAND

    @property
    def armed(self) -> bool:
        return self is not DISARMED

    @property
    def failsafe(self) -> bool:
        return self is FAILSAFE_HOVER or self is FAILSAFE_LAND


#: the members as module names, for code that compares a state per tick or per message (import these):
#: an enum class's attribute goes through its metaclass's ``__getattr__`` hook, about 850 instructions a
#: lookup, a module global's about 50
DISARMED, HOLD, OFFBOARD, LAND = FcState.DISARMED, FcState.HOLD, FcState.OFFBOARD, FcState.LAND
FAILSAFE_HOVER, FAILSAFE_LAND = FcState.FAILSAFE_HOVER, FcState.FAILSAFE_LAND
TAKEOFF, GO_HOME = FcState.TAKEOFF, FcState.GO_HOME


@dataclass(frozen=True)
class FcEvent:
    """One state transition at simulated time ``time_s`` (s), with its reason."""

    time_s: float
    from_state: FcState
    to_state: FcState
    reason: str


@dataclass(frozen=True)
class CommandResult:
    """The answer to a command (arm, mode change): accepted, or refused with a reason."""

    accepted: bool
    reason: str = ""


ACCEPTED = CommandResult(True)


class StateMachine:
    """Holds the current FcState and records every transition as an FcEvent."""

    def __init__(self, initial: FcState = FcState.DISARMED) -> None:
        self.state = initial
        self.since_s = 0.0
        self.events: list[FcEvent] = []

    def go(self, to_state: FcState, time_s: float, reason: str) -> bool:
        """Move to ``to_state`` (no-op if already there); True if a transition happened."""
        if to_state is self.state:
            return False
        self.events.append(FcEvent(time_s, self.state, to_state, reason))
        self.state = to_state
        self.since_s = time_s
        return True


class LandedState(Enum):
    """MAVLink's landed state as the FC detects it (EXTENDED_SYS_STATE.landed_state)."""

    ON_GROUND = 1
    IN_AIR = 2
    LANDING = 4
