"""The `hil` command line: discovers its subcommands in `hil.commands`."""

from __future__ import annotations

import argparse
import sys

import hil
from hil.link.registry import Registry

#: the subcommands: one module of `hil.commands` each, added to the parser by its ``register``
COMMANDS = Registry("command", package="hil.commands", attr="register")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hil", description="crossgap-hil: HIL harness and N3-style FC emulator"
    )
    parser.add_argument("--version", action="version", version=f"crossgap-hil {hil.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS.names():
        COMMANDS.load(name)(sub)  # type: ignore[operator]
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
