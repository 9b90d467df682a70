"""`hil onboard`: the onboard program (the system under test) on a command link and a mocap link."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    # (here, not at the top: every `hil` call imports each command module to build its parser; the
    # onboard program only for this command)
    from policies.onboard.cli import add_arguments

    p = sub.add_parser("onboard", help="run the onboard program: mocap -> pilot -> setpoints to the FC")
    add_arguments(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from policies.onboard.cli import run  # (the onboard program only for this command: see register)

    return run(args, "hil onboard")
