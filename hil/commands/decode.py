"""`hil decode`: a command link's raw capture (a .tlog of `hil fc --tlog` or a run's run.tlog), frame by
frame: MAVLink messages or DJI OPEN-protocol frames, each with its time."""

from __future__ import annotations

import argparse
import sys

from hil.link import dji_open
from hil.link.mavlink import decode_frame
from hil.link.tlog import read_tlog


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decode", help="print a command link's capture (.tlog) frame by frame")
    p.add_argument("file", metavar="FILE", help="a .tlog (MAVLink or DJI OPEN frames)")
    p.add_argument("--limit", type=int, default=None, metavar="N", help="print the first N frames only")
    p.set_defaults(func=main)


def describe(frame: bytes) -> str:
    """One line about one captured frame of either protocol."""
    if frame[0] == dji_open.SOF:
        if dji_open.crc32(frame) != 0:
            return "DJI OPEN frame with a bad CRC32"
        return "DJI " + dji_open.describe(frame)
    try:
        return "MAVLink " + str(decode_frame(frame))
    except Exception as exc:  # a frame pymavlink cannot read: say so, go on
        return f"MAVLink frame not decoded ({type(exc).__name__}): {frame.hex(' ')}"


def main(args: argparse.Namespace) -> int:
    try:
        frames = read_tlog(args.file)
    except (OSError, ValueError) as exc:
        print(f"hil decode: {exc}", file=sys.stderr)
        return 2
    t0 = frames[0][0] if frames else 0
    try:
        for k, (stamp_us, frame) in enumerate(frames):
            if args.limit is not None and k >= args.limit:
                break
            print(f"{(stamp_us - t0) * 1e-6:10.6f}  {len(frame):4d} B  {describe(frame)}")
    except BrokenPipeError:  # (a reader that stopped early: `| head`)
        sys.stderr.close()
    return 0
