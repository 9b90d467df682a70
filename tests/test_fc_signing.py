"""`hil fc --signing-key` against pymavlink as an outside client over UDP: unsigned, wrongly signed,
replayed and stale PARAM_SET / COMMAND_LONG / SET_ATTITUDE_TARGET are refused and change nothing, each
counted by kind in the summary; the same messages signed with the key are applied."""

from __future__ import annotations

import time

from pymavlink import mavutil
from test_fc_mavsdk import HOVER, start_fc, stop_fc

from hil.link.mavlink import SIGNING_EPOCH_UNIX_S, mav, quat_from_euler

KEY = bytes(range(1, 33))


def packer(key: bytes | None, link_id: int = 0, age_s: float = 0.0) -> mav.MAVLink:
    """pymavlink's packer as a ground station sets it up: signing with ``key`` (None: unsigned), its
    timestamps ``age_s`` behind the wall clock."""
    m = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    if key is not None:
        m.signing.secret_key, m.signing.sign_outgoing, m.signing.link_id = key, True, link_id
        m.signing.timestamp = int((time.time() - age_s - SIGNING_EPOCH_UNIX_S) * 1e5)
    return m


def loopback_udpout(host: str, port: int, source_system: int) -> mavutil.mavfile:
    """pymavlink's UDP client to ``host``:``port`` (a loopback address), its own socket bound to the
    loopback too: left unbound, the first send would bind it to every interface."""
    conn = mavutil.mavlink_connection(f"udpout:{host}:{port}", source_system=source_system)
    conn.port.bind(("127.0.0.1", 0))
    return conn


class Station:
    """One UDP socket to the FC (pymavlink's, no key: it reads the FC's signed frames without judging
    them); frames packed elsewhere are written raw."""

    def __init__(self, endpoint: str) -> None:
        _, host, port = endpoint.split(":")
        self.conn = loopback_udpout(host, int(port), 255)

    def write(self, frame: bytes) -> bytes:
        self.conn.write(frame)
        return frame

    def drain(self, seconds: float) -> list:
        got, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is not None:
                got.append(m)
        return got

    def param(self, name: str) -> float:
        """COM_OF_LOSS_T's value in force, asked unsigned (a read needs no signature)."""
        for _ in range(20):
            self.write(packer(None).param_request_read_encode(1, 1, name.encode(), -1).pack(packer(None)))
            for m in self.drain(0.3):
                if m.get_type() == "PARAM_VALUE" and m.param_id == name:
                    return m.param_value
        raise AssertionError(f"no PARAM_VALUE {name}")

    def armed(self) -> bool:
        for m in self.drain(1.5):
            if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1:
                last = m
        return bool(last.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)


def three(m: mav.MAVLink, loss_s: float, arm: float) -> list[bytes]:
    """PARAM_SET COM_OF_LOSS_T, an arm/disarm COMMAND_LONG and a SET_ATTITUDE_TARGET, packed by ``m``."""
    q = list(quat_from_euler(0.0, 0.0, 0.0))
    return [bytes(msg.pack(m)) for msg in (
        m.param_set_encode(1, 1, b"COM_OF_LOSS_T", loss_s, mav.MAV_PARAM_TYPE_REAL32),
        m.command_long_encode(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, arm, 0, 0, 0, 0, 0, 0),
        m.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, HOVER),
    )]


def test_signed_fc_refuses_unsigned_wrong_replayed_and_stale_frames_and_applies_signed_ones():
    proc, endpoint = start_fc("--link", "udp:127.0.0.1:0", "--signing-key", KEY.hex(), "--mocap-link", "none")
    gcs = None
    try:
        gcs = Station(endpoint)
        assert gcs.param("COM_OF_LOSS_T") == 1.0  # reads go unsigned
        for m in (packer(None), packer(bytes(32)), packer(KEY, link_id=1, age_s=120.0)):
            for frame in three(m, 0.5, 1):
                gcs.write(frame)
        assert gcs.param("COM_OF_LOSS_T") == 1.0 and not gcs.armed()  # nothing changed
        good = packer(KEY)
        first = three(good, 0.5, 1)
        for frame in first:
            gcs.write(frame)
        assert gcs.param("COM_OF_LOSS_T") == 0.5 and gcs.armed()  # signed: applied
        for frame in three(good, 0.75, 0)[:2]:  # a newer set and a disarm
            gcs.write(frame)
        assert gcs.param("COM_OF_LOSS_T") == 0.75 and not gcs.armed()
        for frame in first:  # the first three again, byte for byte
            gcs.write(frame)
        assert gcs.param("COM_OF_LOSS_T") == 0.75 and not gcs.armed()
    finally:
        if gcs is not None:
            gcs.conn.close()
        summary = stop_fc(proc)
    link, server = summary["link"], summary["server"]
    assert (link["unsigned_refused"], link["bad_signature"], link["stale_timestamp"], link["replayed"]) == \
        (3, 3, 3, 3)
    assert server["params_set"] == 2 and server["commands_accepted"] == 2
    assert server["setpoints_applied"] + server["setpoints_rejected"] == 1  # the one signed setpoint

