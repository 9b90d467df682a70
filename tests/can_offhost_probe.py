"""Run in a network namespace of its own (``unshare -n``, by tests/test_can_loopback.py): the ESC bus on
each default cross-process bus with an outside dronecan node (tests/esc_node_external.py) standing in
for ESC 3, while a TUN device, the namespace's default route, takes every packet that would leave the
machine. Prints JSON: what each bus carried, and what reached the TUN device during the runs and after
one plain datagram to a group through the default route (the control: the capture sees a leak).

    python can_offhost_probe.py SECONDS
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from emulator.esc.bus import Bridge, EscBus, EscBusConfig

TUNSETIFF, IFF_TUN, IFF_NO_PI = 0x400454CA, 0x0001, 0x1000
TUN = "offhost0"
NODE = Path(__file__).with_name("esc_node_external.py")


def open_tun() -> int:
    """A TUN device as the default route of this namespace (IPv6 off on it: no router solicitations)."""
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
    fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", TUN.encode(), IFF_TUN | IFF_NO_PI))
    Path(f"/proc/sys/net/ipv6/conf/{TUN}/disable_ipv6").write_text("1\n")
    for cmd in ("ip link set lo up", f"ip link set {TUN} up", f"ip addr add 10.77.0.2/24 dev {TUN}",
                f"ip route add default via 10.77.0.1 dev {TUN}"):
        subprocess.run(cmd.split(), check=True)
    return fd


def captured(fd: int) -> list[dict]:
    """The packets that reached the TUN device since the last call (IPv4 headers' fields)."""
    out = []
    while True:
        try:
            p = os.read(fd, 65536)
        except BlockingIOError:
            return out
        version = p[0] >> 4
        if version == 4:
            out.append({"proto": p[9], "dst": ".".join(map(str, p[16:20])), "len": len(p)})
        else:
            out.append({"version": version, "len": len(p)})


CONTACT_WAIT_S = 60.0  # the longest the FC's side waits for the outside node's first frame (s)


def run_bus(spec: str, seconds: float) -> dict:
    """The FC's node and ESCs 0-2 on ``spec``, ESC 3 a dronecan node in another process, for ``seconds``."""
    w_max = 1000.0
    esc = EscBus(EscBusConfig(external=(23,)), np.random.default_rng(0), 0.0, lambda *a: None,
                 lambda *a: None, Bridge(spec, 1_000_000))
    esc.max_rotor_speed_rad_s = w_max
    ext = subprocess.Popen([sys.executable, str(NODE), spec, "23", "3", str(seconds + CONTACT_WAIT_S + 10),
                            str(w_max)], stdout=subprocess.PIPE, text=True)
    assert ext.stdout is not None and ext.stdout.readline().strip() == "ready"
    start, contact = time.monotonic(), None
    # ``seconds`` counted from the first frame back from the outside node: the bus's kernels compile on
    # their first frames (a cold cache takes longer than the window)
    while (t := time.monotonic() - start) < CONTACT_WAIT_S and (contact is None or t - contact < seconds):
        esc.bus.take_external(t)
        esc.command(np.full(4, 0.25), t)
        esc.poll(t, np.full(4, 500.0), False)
        if contact is None and esc.bus.stats.external_in:  # (after the step: its kernels compiled on it)
            contact = time.monotonic() - start
        time.sleep(0.0025)
    stats = esc.bus.stats.as_dict()
    esc.close()
    ext.terminate()
    seen = json.loads(ext.communicate(timeout=20)[0].strip().splitlines()[-1])
    return {"external_in": stats["external_in"], "external_out": stats["external_out"],
            "node_raw_commands": seen["raw_commands"], "throttle_3": float(esc.throttle[3])}


def main() -> None:
    seconds = float(sys.argv[1])
    fd = open_tun()
    time.sleep(0.2)
    before = captured(fd)  # (the device's own start, if anything)
    n = os.getpid() % 200 + 20
    buses = {spec: run_bus(spec, seconds) for spec in (f"mcast:{n}", f"udp_multicast:239.74.{n}.5")}
    time.sleep(0.2)
    leaked = captured(fd)
    control = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # (no options: the default route)
    control.sendto(b"control", (f"239.65.82.{n}", 57732))
    time.sleep(0.2)
    print(json.dumps({"before": before, "buses": buses, "leaked": leaked, "control": captured(fd)}))


if __name__ == "__main__":
    main()
