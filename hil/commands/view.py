"""`hil view RUN_DIR`: replay a finished run folder in the live view's page, with a time slider, until
Ctrl-C (or, with ``--mcap``, write it as an MCAP recording); exit 2 when the folder holds no finished run."""

from __future__ import annotations

import argparse
import sys

from hil.commands import port_number


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="replay a finished run folder in the browser (time slider)")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (summary.json, timeseries.npz)")
    p.add_argument("--port", type=port_number, default=0, help="port on 127.0.0.1 (default: a free one)")
    p.add_argument("--mcap", action="store_true",
                   help="write the run as RUN_DIR/run.mcap (Foxglove) and exit instead of serving it")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    # (here, not at the top: the view server's imports only for this command; every `hil` call
    # imports each command module to build its parser)
    from hil.view import ViewServer
    from hil.view.replay import ReplayError
    from hil.view.server import serve_until_stopped

    if args.mcap:
        from hil.report.mcap_log import write_mcap  # (the mcap writer only with --mcap)

        try:
            print(f"mcap: {write_mcap(args.run_dir)}")
        except (OSError, ValueError, KeyError) as exc:
            print(f"hil view: {args.run_dir} holds no finished run: {exc}", file=sys.stderr)
            return 2
        return 0
    try:
        view = ViewServer(port=args.port)
    except OSError as exc:
        print(f"hil view: cannot serve on 127.0.0.1:{args.port}: {exc}", file=sys.stderr)
        return 2
    try:
        data = view.replay(args.run_dir)
    except ReplayError as exc:
        view.close()
        print(f"hil view: {exc}", file=sys.stderr)
        return 2
    print(f"view: {view.url} (replay of {args.run_dir}); Ctrl-C to stop", flush=True)
    refused = f": refused before take-off: {data['refused']}" if data["refused"] else ""
    print(f"  {data['verdict']}{refused}")
    for c in data["failed_checks"]:  # why it failed, and when
        when = "" if c["time_s"] is None else f" at t={c['time_s']:.3f} s"
        print(f"  failed {c['name']}: expected {c['expected']}, observed {c['observed']}{when}", flush=True)
    serve_until_stopped(view)
    return 0
