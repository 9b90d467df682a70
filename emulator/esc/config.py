"""The ESC bus's settings (`EscBusConfig`), apart from the bus model so that the FC's parameters can name
them without loading the model (`emulator.esc.bus`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

ESC_STATUS_RATE_HZ = 50.0  # how often each ESC reports esc.Status
ACTIONS = ("report", "land", "disarm")  # what the FC does about a failed ESC, in the model's numbering


@dataclass(frozen=True)
class EscBusConfig:
    """The ESC bus: its wire, its nodes and what the FC does about a failed ESC (SI units)."""

    bitrate_bps: int = 1_000_000
    command_rate_hz: float = 400.0  # RawCommand (and the FC's loop) rate
    status_rate_hz: float = ESC_STATUS_RATE_HZ
    fc_node_id: int = 10
    esc_node_ids: tuple[int, ...] = (20, 21, 22, 23)  # ESC index i (the FC's motor i) is this node
    #: ESC node ids served by a node outside this process (their motor follows its esc.Status rpm)
    external: tuple[int, ...] = ()
    loss: float = 0.0  # fraction of frames lost (never reach a receiver)
    corruption: float = 0.0  # fraction of frames hit by a bit error (an error frame, then resent)
    status_timeout_s: float = 0.1  # an ESC silent this long is reported failed
    failsafe_action: str = "report"  # on a failed ESC: report, land or disarm

    def __post_init__(self) -> None:
        if not 10_000 <= self.bitrate_bps <= 1_000_000:
            raise ValueError(f"ESC bus bitrate must be 10 kbit/s..1 Mbit/s, got {self.bitrate_bps}")
        for name in ("command_rate_hz", "status_rate_hz", "status_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"EscBusConfig.{name} must be a positive number, got {v!r}")
        for name in ("loss", "corruption"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v < 1.0):
                raise ValueError(f"EscBusConfig.{name} must be in [0, 1), got {v!r}")
        ids = (self.fc_node_id, *self.esc_node_ids)
        if len(self.esc_node_ids) != 4 or len(set(ids)) != len(ids) or not all(1 <= i <= 127 for i in ids):
            raise ValueError(f"node ids must be 1..127 and distinct, four ESCs: fc {self.fc_node_id}, "
                             f"escs {self.esc_node_ids}")
        for nid in self.external:
            if nid not in self.esc_node_ids:
                raise ValueError(f"external ESC node {nid} is none of the ESC node ids {self.esc_node_ids}")
        if self.failsafe_action not in ACTIONS:
            raise ValueError(f"failsafe_action must be report, land or disarm, got {self.failsafe_action!r}")
