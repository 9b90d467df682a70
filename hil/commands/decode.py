"""`hil decode`: a command link's raw capture (a .tlog of `hil fc --tlog` or a run's run.tlog), frame by
frame (each by its protocol's reader, `hil.link.protocols`: MAVLink messages, DJI OPEN frames), each
with its time and its sender, past damaged spots (each reported, exit 0 with a warning), filtered by
type, as text or JSON lines."""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import sys
from pathlib import Path
from typing import Any

from hil.link.protocols import Decoded, decode
from hil.link.tlog import scan_tlog

__all__ = ["Decoded", "decode", "main", "register"]

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
