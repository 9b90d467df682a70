"""What every emulated node of the ESC bus answers a tool on the real bus: uavcan.protocol.GetNodeInfo
(name, software and hardware version, unique id, its NodeStatus), GetTransportStats and RestartNode, in
dronecan's DSDL types. The DroneCAN GUI tool, PX4 and ArduPilot ask each node they hear for its
GetNodeInfo to list it by name.

The nodes of one process share one interface (the bus model and its bridge): GetTransportStats answers
that interface's counts, the same from each node. RestartNode is honoured by an ESC while the motors are
disarmed (its uptime and error count start again, as a rebooted ESC's would), refused while armed and
by the FC's node (the flight controller restarts with its process, not over the bus), and refused
without DroneCAN's magic number.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from dronecan import uavcan

FC_NAME = "org.crossgap_hil.n3_fc"
ESC_NAME = "org.crossgap_hil.esc"
HARDWARE_VERSION = (1, 0)  # (an emulated board: one revision)
MODE_OPERATIONAL = 0  # uavcan.protocol.NodeStatus mode


def software_version() -> tuple[int, int]:
    """The harness's (major, minor) version, as installed; (0, 0) when it is not installed."""
    try:
        parts = version("crossgap-hil").split(".")
    except PackageNotFoundError:
        return 0, 0
    return int(parts[0]), int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0


@dataclass(frozen=True)
class NodeIdentity:
    """An emulated node as GetNodeInfo names it. Its 16-byte unique id is derived from its name and node
    id (an emulated node has no chip to read one from): the same node, the same id, run after run."""

    node_id: int
    name: str

    @property
    def unique_id(self) -> bytes:
        return hashlib.blake2b(f"{self.name}/{self.node_id}".encode(), digest_size=16).digest()


@dataclass(frozen=True)
class InterfaceCounts:
    """The process's interface to the bus, as GetTransportStats reports it (counts)."""

    transfers_tx: int
    transfers_rx: int
    transfer_errors: int
    frames_tx: int
    frames_rx: int
    errors: int


class NodeServices:
    """Answers the requests addressed to the nodes in ``identities`` (by node id). ``status_of(node_id,
    t)`` gives a node's (uptime s, health); ``counts()`` the interface's; ``restart(node_id, t)``
    restarts a node and says whether it did (see the module doc)."""

    def __init__(self, identities: dict[int, NodeIdentity],
                 status_of: Callable[[int, float], tuple[int, int]], counts: Callable[[], InterfaceCounts],
                 restart: Callable[[int, float], bool]) -> None:
        self.identities, self.status_of, self.counts, self.restart = identities, status_of, counts, restart
        self.software_version = software_version()
        p = uavcan.protocol
        self._answers: dict[int, tuple[str, Callable[[int, Any, float], Any]]] = {
            p.GetNodeInfo.default_dtid: ("GetNodeInfo", self._node_info),
            p.GetTransportStats.default_dtid: ("GetTransportStats", self._transport_stats),
            p.RestartNode.default_dtid: ("RestartNode", self._restart),
        }
        self.answered: dict[str, int] = {}  # requests answered, by service name

    def answer(self, transfer: Any, t: float) -> Any | None:
        """The response payload to a request ``transfer`` (dronecan's, decoded) at ``t`` (s); None for a
        node not served here or a service it does not answer (it stays silent, as a node does)."""
        node_id = transfer.dest_node_id
        service = self._answers.get(transfer.data_type_id)
        if node_id not in self.identities or service is None:
            return None
        name, fn = service
        self.answered[name] = self.answered.get(name, 0) + 1
        return fn(node_id, transfer.payload, t)

    def _node_info(self, node_id: int, request: Any, t: float) -> Any:
        identity = self.identities[node_id]
        r = uavcan.protocol.GetNodeInfo.Response()
        uptime_s, health = self.status_of(node_id, t)
        r.status.uptime_sec, r.status.health, r.status.mode = uptime_s, health, MODE_OPERATIONAL
        r.software_version.major, r.software_version.minor = self.software_version
        r.hardware_version.major, r.hardware_version.minor = HARDWARE_VERSION
        r.hardware_version.unique_id = list(identity.unique_id)
        r.name = identity.name
        return r

    def _transport_stats(self, node_id: int, request: Any, t: float) -> Any:
        c = self.counts()
        iface = uavcan.protocol.CANIfaceStats(frames_tx=c.frames_tx, frames_rx=c.frames_rx, errors=c.errors)
        return uavcan.protocol.GetTransportStats.Response(
            transfers_tx=c.transfers_tx, transfers_rx=c.transfers_rx, transfer_errors=c.transfer_errors,
            can_iface_stats=[iface])

    def _restart(self, node_id: int, request: Any, t: float) -> Any:
        magic = request.magic_number == uavcan.protocol.RestartNode.Request().MAGIC_NUMBER
        return uavcan.protocol.RestartNode.Response(ok=magic and self.restart(node_id, t))
