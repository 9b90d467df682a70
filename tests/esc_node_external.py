"""An ESC outside the emulator, for the tests: a dronecan node of its own on a DroneCAN bus that stands
in for one ESC. It takes its channel of each RawCommand, answers with esc.Status (the rpm its motor
would turn at: sqrt(throttle) x the full speed), asks each node it hears for its GetNodeInfo, and prints
what it saw on the bus as JSON at the end (the answers and the LogMessages among it).

    python esc_node_external.py URI NODE_ID ESC_INDEX SECONDS FULL_SPEED_RAD_S

URI: a cross-process bus of `hil fc` (``mcast:N`` or ``udp_multicast:GROUP``), joined through
`hil.link.can_dronecan.McastDriver`, on this machine's loopback interface as the FC's side is.

It stops after SECONDS or at SIGTERM, whichever comes first.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import sys
import time

import dronecan
from dronecan import uavcan

from hil.link.can_dronecan import McastDriver


def main() -> None:
    uri, node_id, index, seconds, w_max = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), \
        float(sys.argv[4]), float(sys.argv[5])
    node = dronecan.node.Node(McastDriver(uri), node_id=node_id)
    seen: dict = {"raw_commands": 0, "cmd_max": 0, "status_from": {}, "node_status_from": [], "node_info": {},
                  "log": []}

    def on_raw(e) -> None:
        seen["raw_commands"] += 1
        cmd = e.message.cmd
        u = max(0, cmd[index]) / 8191 if index < len(cmd) else 0.0
        seen["cmd_max"] = max(seen["cmd_max"], cmd[index] if index < len(cmd) else 0)
        rpm = int(math.sqrt(u) * w_max * 60 / (2 * math.pi))
        node.broadcast(uavcan.equipment.esc.Status(error_count=0, voltage=15.0, current=10.0 * u,
                                                  temperature=300.0, rpm=rpm,
                                                  power_rating_pct=int(100 * u), esc_index=index))

    def on_status(e) -> None:
        k = str(e.message.esc_index)
        seen["status_from"][k] = seen["status_from"].get(k, 0) + 1

    def on_node_info(e) -> None:  # (None: no answer in time)
        if e is not None:
            r = e.response
            seen["node_info"][str(e.transfer.source_node_id)] = {
                "name": r.name.decode(), "unique_id": bytes(r.hardware_version.unique_id).hex(),
                "software_version": [r.software_version.major, r.software_version.minor],
                "uptime_s": r.status.uptime_sec}

    def on_node_status(e) -> None:  # a node first heard is asked what it is, as a DroneCAN tool does
        src = e.transfer.source_node_id
        if src not in seen["node_status_from"]:
            seen["node_status_from"].append(src)
            if src != node_id:
                node.request(uavcan.protocol.GetNodeInfo.Request(), src, on_node_info, timeout=2.0)

    def on_log(e) -> None:
        seen["log"].append([e.transfer.source_node_id, e.message.level.value, e.message.text.decode()])

    node.add_handler(uavcan.equipment.esc.RawCommand, on_raw)
    node.add_handler(uavcan.equipment.esc.Status, on_status)
    node.add_handler(uavcan.protocol.NodeStatus, on_node_status)
    node.add_handler(uavcan.protocol.debug.LogMessage, on_log)
    stop = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    print("ready", flush=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end and not stop:
        with contextlib.suppress(dronecan.transport.TransferError):
            node.spin(0.05)  # (answers each frame as it comes: the driver waits on its socket)
    print(json.dumps(seen), flush=True)


if __name__ == "__main__":
    main()
