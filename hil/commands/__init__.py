"""Subcommands of `hil`: one module each, with ``register(subparsers)`` setting ``func``."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def port_number(text: str) -> int:
    """An argparse type: a TCP port, 0 (any free one) to 65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a port is a whole number, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0 (any free one) to 65535, got {port}")
    return port


def output_folder(path: str | Path, command: str) -> Path | None:
    """``path`` made (with its parents) as ``command``'s output folder and checked writable, before any
    work is done; None after saying on stderr why it cannot be (the command then exits with 2)."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"{command}: cannot make the output folder {out}: {exc.strerror or exc}", file=sys.stderr)
        return None
    if not os.access(out, os.W_OK | os.X_OK):
        print(f"{command}: cannot write into the output folder {out}", file=sys.stderr)
        return None
    return out


def say_if_compiling(command: str) -> None:
    """On stderr, when the emulator's kernels are not cached yet: the first run compiles them (seconds of
    silence otherwise, before the first line of a run or `hil fc`'s endpoints)."""
    # (here, not at the top: every `hil` call imports this package; the emulator only for runs)
    from emulator.kernel_cache import cold

    folder = cold()
    if folder is not None:
        print(f"{command}: compiling the emulator's kernels once, about 10-20 s (cached in {folder} for "
              "the next runs)", file=sys.stderr, flush=True)
