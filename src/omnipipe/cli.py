"""The ``omnipipe`` command line: a thin wrapper around each stage's ``run``.

Each stage that has a command offers a module with ``register(subparsers)``; the
parser it adds sets ``func(args) -> int``. Every :class:`OmnipipeError` becomes a
one-line message on stderr and exit code 1. Ctrl-C exits 130 and SIGTERM 143, after
the ``with`` blocks have removed their temporary output folders (one line each).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from omnipipe import __version__
from omnipipe.errors import OmnipipeError

# Modules that add sub-commands, in the order they appear in --help.
COMMAND_MODULES = (
    "omnipipe.sim.cli",
    "omnipipe.pipeline.cli",
    "omnipipe.baseline.cli",
    "omnipipe.evaluation.cli",
)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every registered sub-command."""
    parser = argparse.ArgumentParser(
        prog="omnipipe",
        description="3-D pipe models from an omni-directional rangefinder (camera + hyperboloid mirror + laser ring).",
    )
    parser.add_argument("--version", action="version", version=f"omnipipe {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


class Terminated(BaseException):
    """SIGTERM arrived: unwinds the stack like KeyboardInterrupt, so that every
    ``with`` block (temporary output folders) cleans up."""


@contextmanager
def _sigterm_raises() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` in this process during the block.

    Forked worker processes inherit the handler; in them it falls back to the
    default action (die), as before.
    """
    owner = os.getpid()

    def handler(signum: int, frame: object) -> None:
        if os.getpid() != owner:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``omnipipe`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with _sigterm_raises():
            return int(args.func(args) or 0)
    except OmnipipeError as exc:
        _close_bars()
        print(f"omnipipe {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        _close_bars()
        print(f"omnipipe {args.command}: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        _close_bars()
        print(f"omnipipe {args.command}: terminated", file=sys.stderr)
        return 143


def _close_bars() -> None:
    """End open progress bars' lines, so the error starts a line of its own."""
    progress = sys.modules.get("omnipipe.pipeline.cli")
    if progress is not None:
        progress.close_progress_bars()


if __name__ == "__main__":
    sys.exit(main())
