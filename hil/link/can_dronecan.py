"""A dronecan driver on `McastCanSocket`: a dronecan node of your own on a cross-process bus of `hil fc`,
kept to this machine as the bus is (``dronecan.node.Node(McastDriver("mcast:0"), node_id=30)``).

dronecan's own ``mcast:N`` driver joins its group on the default interface and sends there (the frames
reach the network the machine is on), through a helper process that waits up to 10 ms between sends.
"""

from __future__ import annotations

import select
import time

from dronecan.driver.common import AbstractDriver, CANFrame

from hil.link.can_multicast import McastCanSocket, split_interface


class McastDriver(AbstractDriver):
    """dronecan's driver interface over a multicast CAN socket: ``spec`` is ``mcast[:N]`` or
    ``udp_multicast[:GROUP]``, with ``@ADDR`` for a lab network's interface (see `hil.link.can_multicast`)."""

    def __init__(self, spec: str, **_: object) -> None:
        super().__init__()
        bus, interface = split_interface(spec)
        kind, _, arg = bus.partition(":")
        self.socket = McastCanSocket(kind, arg, interface)
        self._waiting: list[tuple[int, bytes]] = []

    def receive(self, timeout: float | None = None) -> CANFrame | None:
        """The next frame from another process, waiting up to ``timeout`` s (None: until one comes)."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._waiting:
            self._waiting, _ = self.socket.receive(64)
            self._waiting.reverse()
            if self._waiting:
                break
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                return None
            select.select([self.socket.fileno()], [], [], left)
        can_id, data = self._waiting.pop()
        frame = CANFrame(can_id, bytearray(data), True)
        self._rx_hook(frame)
        return frame

    def send_frame(self, frame: CANFrame) -> None:
        self._tx_hook(frame)
        self.socket.send(frame.id, bytes(frame.data))

    def close(self) -> None:
        self.socket.close()
