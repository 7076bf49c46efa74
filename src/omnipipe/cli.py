"""The ``omnipipe`` command line: a thin wrapper around each stage's ``run``.

Each stage that has a command offers a module with ``register(subparsers)``; the
parser it adds sets ``func(args) -> int``. Every :class:`OmnipipeError` becomes a
one-line message on stderr and exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys

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


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``omnipipe`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except OmnipipeError as exc:
        print(f"omnipipe {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"omnipipe {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
