"""The `hil` command line: discovers its subcommands in `hil.commands`."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import hil
import hil.commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hil", description="crossgap-hil: HIL harness and N3-style FC emulator"
    )
    parser.add_argument("--version", action="version", version=f"crossgap-hil {hil.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = [
        f"hil.commands.{m.name}"
        for m in pkgutil.iter_modules(hil.commands.__path__)
        if not m.name.startswith("_")
    ]
    for name in sorted(modules):
        importlib.import_module(name).register(sub)
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
