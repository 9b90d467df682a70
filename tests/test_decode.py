"""`hil decode` on real captures, whole and damaged (a cut tail, one flipped length byte), MAVLink and DJI
OPEN: every undamaged frame printed with its sender, the damage shown, exit 0 with a warning; --types and
--json."""

from __future__ import annotations

import json
from pathlib import Path

from test_fc_mavlink import fly_recorded

from hil.cli import main
from hil.commands.decode import decode as decode_frame
from hil.link import dji_open
from hil.link.tlog import TlogWriter, read_tlog, scan_tlog


def decode(capsys, *args: str) -> tuple[int, list[str], str]:
    code = main(["decode", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out.splitlines(), out.err


def frame_lines(lines: list[str]) -> list[str]:
    return [line for line in lines if "skipped" not in line]


def damage(path: Path, records: list[tuple[int, bytes]], k: int) -> bytes:
    """The capture with record ``k``'s length byte flipped and its last 5 bytes cut off."""
    data = bytearray(path.read_bytes())
    offset = sum(8 + len(f) for _, f in records[:k]) + 8 + 1  # record k's frame, its LEN byte
    data[offset] ^= 0x40
    return bytes(data[:-5])


def test_a_damaged_mavlink_capture_prints_every_undamaged_frame(tmp_path: Path, capsys):
    path = tmp_path / "flight.tlog"
    fly_recorded(path)
    records = read_tlog(path)
    code, whole, err = decode(capsys, path)
    assert code == 0 and len(whole) == len(records) and not err
    assert {line.split()[3] for line in whole} == {"fc", "peer"}  # both senders
    setpoints = [line for line in whole if "SET_ATTITUDE_TARGET" in line]
    assert setpoints and all(" peer  MAVLink SET_ATTITUDE_TARGET" in line for line in setpoints)
    k = len(records) // 2
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(damage(path, records, k))
    code, lines, err = decode(capsys, bad)
    assert code == 0 and "warning" in err and "2 damaged spot(s)" in err
    assert frame_lines(lines) == whole[:k] + whole[k + 1 : -1]  # all but the flipped and the cut one
    assert len([line for line in lines if "skipped" in line]) == 2
    assert len(scan_tlog(bad.read_bytes()).records) == len(records) - 2


def test_types_and_json_lines(tmp_path: Path, capsys):
    path = tmp_path / "flight.tlog"
    fly_recorded(path)
    code, lines, _ = decode(capsys, path, "--types", "command_*,HEARTBEAT")
    assert code == 0 and lines
    assert {line.split()[5] for line in lines} == {"COMMAND_LONG", "COMMAND_ACK", "HEARTBEAT"}
    code, lines, _ = decode(capsys, path, "--json", "--types", "COMMAND_ACK")
    acks = [json.loads(line) for line in lines]
    assert acks and all(a["type"] == "COMMAND_ACK" and a["from"] == "fc" for a in acks)
    assert acks[0]["fields"]["command"] == 400 and acks[0]["fields"]["result"] == 0


def test_a_damaged_dji_open_capture_prints_every_undamaged_frame(tmp_path: Path, capsys):
    path = tmp_path / "open.tlog"
    with TlogWriter(path, epoch_unix_s=1.7e9) as tlog:
        for i in range(6):
            tlog.record(dji_open.encode_command(dji_open.SET_CONTROL, dji_open.CMD_SETPOINT,
                                                dji_open.setpoint_payload(0x22, 1.0, 2.0, 40.0, 0.0), 0, i),
                        i * 0.02)
            tlog.record(dji_open.encode_ack(2, i, dji_open.ack_code(0)), i * 0.02 + 0.01)
    records = read_tlog(path)
    code, whole, _ = decode(capsys, path, "--json")
    frames = [json.loads(line) for line in whole]
    assert [(f["type"], f["from"]) for f in frames[:2]] == [("SETPOINT", "peer"), ("ACK", "fc")]
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(damage(path, records, 4))
    code, lines, err = decode(capsys, bad)
    assert code == 0 and "2 damaged spot(s)" in err
    _, text, _ = decode(capsys, path)
    assert frame_lines(lines) == text[:4] + text[5:-1]
    _, only, _ = decode(capsys, path, "--types", "setpoint")
    assert len(only) == 6 and all("setpoint" in line for line in only)


def test_a_subscription_push_is_the_fc_s_and_a_subscription_request_the_peer_s():
    """The N3 pushes subscribed packages (0x02 0x05); the onboard side asks for them (set 0x0B)."""
    push = dji_open.encode_command(dji_open.SET_BROADCAST, dji_open.CMD_SUBSCRIPTION_DATA, b"\x00" * 9, 0, 1)
    ask = dji_open.encode_command(dji_open.SET_SUBSCRIBE, dji_open.CMD_SUB_VERSION, b"", 2, 7)
    assert (decode_frame(push).sender, decode_frame(ask).sender) == ("fc", "peer")
    assert decode_frame(ask).type == "SUBSCRIPTION_VERSION_MATCH"
