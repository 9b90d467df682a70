"""`hil decode`: a command link's raw capture (a .tlog of `hil fc --tlog` or a run's run.tlog), frame by
frame: MAVLink messages or DJI OPEN-protocol frames, each with its time and its sender, past damaged spots
(each reported, exit 0 with a warning), filtered by type, as text or JSON lines."""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.link import dji_open
from hil.link.mavlink import decode_frame, mav
from hil.link.tlog import scan_tlog

#: DJI OPEN frames the FC sends (besides every ACK): pushed flight data, and the lockstep's tick
FC_SENT_DJI: frozenset[tuple[int, int]] = frozenset(
    {(dji_open.SET_BROADCAST, dji_open.CMD_FLIGHT_DATA), (dji_open.SET_BROADCAST, dji_open.CMD_CONTROL_LOST),
     (dji_open.SET_BROADCAST, dji_open.CMD_SUBSCRIPTION_DATA), (dji_open.SET_HIL, dji_open.CMD_HIL_TICK)}
)


SHOW_SKIPPED_BYTES = 16  # of a damaged spot, its first bytes are shown


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decode", help="print a command link's capture (.tlog) frame by frame")
    p.add_argument("file", metavar="FILE", help="a .tlog (MAVLink or DJI OPEN frames)")
    p.add_argument("--limit", type=int, default=None, metavar="N", help="print the first N frames only")
    p.add_argument("--types", default=None, metavar="T1,T2",
                   help="only these types (MAVLink message names, DJI OPEN command names such as SETPOINT, "
                        "FLIGHT_DATA, ACK; shell wildcards, case ignored)")
    p.add_argument("--json", action="store_true", help="one JSON object a line (frames, and damaged spots)")
    p.set_defaults(func=main)


@dataclass(frozen=True)
class Decoded:
    """One captured frame read: protocol, type name, sender ('fc' or 'peer'), one line and the fields."""

    protocol: str
    type: str
    sender: str
    text: str
    fields: dict[str, Any]


def decode(frame: bytes) -> Decoded:
    """A captured frame (CRC checked) of either protocol, read. The sender of a MAVLink frame is its
    source component (MAV_COMP_ID_AUTOPILOT1: the FC); of a DJI OPEN frame, its kind (the FC sends the
    ACKs and the pushed data)."""
    if frame[0] == dji_open.SOF:
        return _decode_dji(frame)
    try:
        msg = decode_frame(frame)
    except Exception as exc:  # a frame pymavlink cannot read: say so, go on
        return Decoded("mavlink", "UNDECODED", "?", f"MAVLink frame not decoded ({type(exc).__name__}): "
                       f"{frame.hex(' ')}", {})
    sender = "fc" if msg.get_srcComponent() == mav.MAV_COMP_ID_AUTOPILOT1 else "peer"
    fields = {k: v for k, v in msg.to_dict().items() if k != "mavpackettype"}
    fields.update(src_system=msg.get_srcSystem(), src_component=msg.get_srcComponent(), seq=msg.get_seq(),
                  signed=bool(frame[0] == 0xFD and frame[2] & mav.MAVLINK_IFLAG_SIGNED))
    return Decoded("mavlink", msg.get_type(), sender, "MAVLink " + str(msg), fields)


def _decode_dji(frame: bytes) -> Decoded:
    f = dji_open.decode(frame)
    if f.is_ack:
        kind, sender = "ACK", "fc"
    else:
        name = dji_open.COMMAND_NAMES.get((f.cmd_set, f.cmd_id))
        kind = name.upper().replace(" ", "_").replace("/", "_") if name else \
            f"0X{f.cmd_set:02X}_0X{f.cmd_id:02X}"
        sender = "fc" if (f.cmd_set, f.cmd_id) in FC_SENT_DJI else "peer"
    fields = {"session": f.session, "seq": f.seq, "ack": f.is_ack, "enc": f.enc, "data": f.data.hex()}
    return Decoded("dji_open", kind, sender, "DJI " + dji_open.describe(frame), fields)


def _wanted(types: str | None) -> list[str] | None:
    return None if types is None else [t.strip().upper() for t in types.split(",") if t.strip()]


def _json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as None and bytes as hex (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex()
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def main(args: argparse.Namespace) -> int:
    try:
        data = Path(args.file).read_bytes()
        scan = scan_tlog(data)
    except OSError as exc:
        print(f"hil decode: {args.file}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    wanted = _wanted(args.types)
    # each damaged spot, printed where it was: before the first record after it
    spots = dict(scan.skipped)
    offsets = iter(sorted(spots))
    next_spot = next(offsets, None)
    t0 = scan.records[0][0] if scan.records else 0
    shown = 0
    try:
        pos = 0
        for stamp_us, frame in scan.records:
            while next_spot is not None and next_spot <= pos:
                _print_skip(data, next_spot, spots[next_spot], args.json)
                pos = next_spot + spots[next_spot]
                next_spot = next(offsets, None)
            pos += 8 + len(frame)
            if args.limit is not None and shown >= args.limit:
                next_spot = None
                break
            d = decode(frame)
            if wanted is not None and not any(fnmatch.fnmatchcase(d.type, w) for w in wanted):
                continue
            shown += 1
            t = (stamp_us - t0) * 1e-6
            if args.json:
                print(json.dumps({"time_s": round(t, 6), "stamp_us": stamp_us, "bytes": len(frame),
                                  "from": d.sender, "protocol": d.protocol, "type": d.type,
                                  "fields": {k: _json_safe(v) for k, v in d.fields.items()}}))
            else:
                print(f"{t:10.6f}  {len(frame):4d} B  {d.sender:<4}  {d.text}")
        while next_spot is not None:
            _print_skip(data, next_spot, spots[next_spot], args.json)
            next_spot = next(offsets, None)
    except BrokenPipeError:  # (a reader that stopped early: `| head`)
        sys.stderr.close()
        return 0
    if scan.skipped:
        print(f"hil decode: warning: {args.file}: {len(scan.skipped)} damaged spot(s), "
              f"{scan.skipped_bytes} bytes skipped; every good frame around them printed", file=sys.stderr)
    return 0


def _print_skip(data: bytes, offset: int, size: int, as_json: bool) -> None:
    """A damaged spot: where, how long, and its first bytes."""
    head = data[offset : offset + min(size, SHOW_SKIPPED_BYTES)].hex(" ")
    if size > SHOW_SKIPPED_BYTES:
        head += " ..."
    if as_json:
        print(json.dumps({"skipped_bytes": size, "offset": offset, "head": head}))
    else:
        print(f"{'':10}  skipped {size} bytes at byte {offset} (no record with a good CRC): {head}")
