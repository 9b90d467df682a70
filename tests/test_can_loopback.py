"""The cross-process CAN buses stay on this machine: nothing of a run on the default buses (the FC's
side, and an outside dronecan node on each) leaves through a network interface, seen by a capture in
a network namespace of the test's own whose default route is a TUN device; and the sockets' multicast
settings as the kernel holds them."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from emulator.esc.bus import Bridge
from hil.link.can_dronecan import McastDriver

PROBE = Path(__file__).with_name("can_offhost_probe.py")


def _unshare() -> list[str]:
    """The command that runs a process in a new network namespace (as root, or in a user namespace of
    its own where the kernel lets an unprivileged user make one)."""
    if shutil.which("unshare") is None or shutil.which("ip") is None or not os.path.exists("/dev/net/tun"):
        pytest.skip("needs unshare, ip (iproute2) and /dev/net/tun to capture in a namespace of its own")
    cmd = ["unshare", "-n"] if os.geteuid() == 0 else ["unshare", "-rn"]
    if subprocess.run([*cmd, "true"], capture_output=True).returncode != 0:
        pytest.skip(f"{' '.join(cmd)} is not permitted here: no network namespace to capture in")
    return cmd


@pytest.mark.realtime  # (the FC's side polls the bus on the wall clock, the outside node in its own process)
def test_no_frame_of_the_default_buses_leaves_the_loopback_interface():
    run = subprocess.run([*_unshare(), sys.executable, str(PROBE), "3"], capture_output=True, text=True,
                         timeout=180, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout.strip().splitlines()[-1])
    for spec, bus in got["buses"].items():  # the buses worked, both ways, between the two processes
        assert bus["external_out"] > 20 and bus["node_raw_commands"] > 20, spec
        # (ESC 3's motor at the outside node's rpm for the FC's 0.25: its esc.Status came back)
        assert bus["external_in"] > 20 and bus["throttle_3"] == pytest.approx(0.25, abs=0.01), spec
    assert got["leaked"] == []  # not a frame, not an IGMP report through the default route
    # ... where a plain datagram to a group does leave: the capture sees what leaves
    assert any(p.get("proto") == 17 and p["dst"].startswith("239.65.82.") for p in got["control"])


@pytest.mark.parametrize("spec", ["mcast:3", "udp_multicast:239.74.163.2"])
def test_the_default_buses_send_on_loopback_with_ttl_0(spec):
    bridge, driver = Bridge(spec, 1_000_000), McastDriver(spec)
    try:
        for sock in (bridge.mcast, driver.socket):
            opts = sock.multicast_options()
            assert opts["interface"] == "127.0.0.1" and opts["ttl"] == 0 and opts["loop"]
            assert opts["source"][0] == "127.0.0.1"
    finally:
        bridge.close()
        driver.close()


def test_a_lab_network_is_asked_for_by_its_interfaces_address():
    bridge = Bridge("mcast:3@127.0.0.1", 1_000_000)  # (the loopback's own address: still TTL 0)
    try:
        assert bridge.mcast.multicast_options()["ttl"] == 0
    finally:
        bridge.close()
    with pytest.raises(OSError, match=r"cannot open the CAN bus 'mcast:3@192\.0\.2\.77'"):
        Bridge("mcast:3@192.0.2.77", 1_000_000)  # (an address no interface of this machine has)
