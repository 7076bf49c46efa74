"""The ``omnipipe`` command line: a thin wrapper around each stage's ``run``.

Each stage that has a command offers a module with ``register(subparsers)``; the
parser it adds sets ``func(args) -> int``. Every :class:`OmnipipeError` (also a bad
number on the command line, refused while parsing: :mod:`omnipipe.cli_values`) becomes a
one-line message on stderr (:func:`omnipipe.errors.one_line`) and exit code 1. Ctrl-C
exits 130 and SIGTERM 143, after the ``with`` blocks have removed their temporary output
folders and ended their worker processes (one line each).
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
from omnipipe.errors import OmnipipeError, one_line

# Sub-commands in the order they appear in --help: (name, module that registers it,
# one-line help). The help lines are repeated here so that ``omnipipe --help`` answers
# without importing any stage (NumPy, SciPy, OpenCV, numba take ~1-2 s to load);
# tests/test_cli_imports.py checks that they match what each module registers.
COMMANDS: tuple[tuple[str, str, str], ...] = (
    (
        "simulate",
        "omnipipe.sim.cli",
        "render a simulated dataset (with ground truth) of a named scenario",
    ),
    ("reconstruct", "omnipipe.pipeline.cli", "build the measured, textured pipe model from a dataset"),
    ("demo", "omnipipe.pipeline.cli", "simulate the paper's experiment, reconstruct it and print Table I"),
    (
        "batch",
        "omnipipe.pipeline.batch",
        "reconstruct many inspection runs over one executor, with an index.html",
    ),
    (
        "baseline",
        "omnipipe.baseline.cli",
        "optimal baseline (camera-to-laser distance) for given wall distances",
    ),
    ("evaluate", "omnipipe.evaluation.cli", "compare a reconstruction with the dataset's ground truth"),
    (
        "calibrate",
        "omnipipe.calibrate.cli",
        "calibrate a real rig's camera or laser plane from checkerboard images",
    ),
    ("rig", "omnipipe.calibrate.cli", "convert calibrations from other tools into rig.yaml (import-ocam)"),
    ("export-bag", "omnipipe.inputs.export_bag", "write a dataset folder as a ROS 2 bag / MCAP file (or a ROS 1 .bag)"),
)

# Modules that add sub-commands (each offers ``register(subparsers)``), in --help order.
COMMAND_MODULES = tuple(dict.fromkeys(module for _, module, _ in COMMANDS))


def _chosen_command(argv: list[str]) -> str | None:
    """The sub-command named on the command line (first token that is one), or None."""
    names = {name for name, _, _ in COMMANDS}
    for token in argv:
        if token in names:
            return token
        if not token.startswith("-"):
            return None  # an unknown command: argparse reports it
    return None


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The argument parser.

    Only the module of the sub-command named in ``argv`` is imported and registers its
    full parser; the others appear as stubs with their one-line help (enough for
    ``omnipipe --help``). ``argv=None`` registers every sub-command in full.
    """
    parser = argparse.ArgumentParser(
        prog="omnipipe",
        description="3-D pipe models from an omni-directional rangefinder (camera + hyperboloid mirror + laser ring).",
    )
    parser.add_argument("--version", action="version", version=f"omnipipe {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    if argv is None:
        for name in COMMAND_MODULES:
            importlib.import_module(name).register(sub)
        return parser
    chosen = _chosen_command(argv)
    module = next((m for n, m, _ in COMMANDS if n == chosen), None)
    registered: set[str] = set()
    for name, mod, help_line in COMMANDS:
        if name in registered:
            continue
        if mod == module:
            before = set(sub.choices)
            importlib.import_module(mod).register(sub)
            registered |= set(sub.choices) - before
        else:
            sub.add_parser(name, help=help_line)
            registered.add(name)
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
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    try:
        # A bad number or address on the command line raises ConfigError here
        # (omnipipe.cli_values), before any work.
        args = parser.parse_args(argv)
    except OmnipipeError as exc:
        prog = " ".join(["omnipipe", *filter(None, [_chosen_command(argv)])])
        print(f"{prog}: error: {one_line(str(exc))}", file=sys.stderr)
        return 1
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with _sigterm_raises():
            return int(args.func(args) or 0)
    except OmnipipeError as exc:
        _close_bars()
        print(f"omnipipe {args.command}: error: {one_line(str(exc))}", file=sys.stderr)
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
