"""Command-line numbers checked when the command line is parsed, with bounds.

Each factory returns an argparse ``type=`` callable for one option. A bad value raises
:class:`~omnipipe.errors.ConfigError` naming the option (not argparse's usage error), so
every command refuses every bad number the same way: one line, exit code 1, before any
work. The same rule for every command's ``--workers``: 1 to
:func:`omnipipe.executor.max_workers` (default: every core).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from omnipipe.errors import ConfigError

# Largest seed accepted: NumPy's generators take any non-negative integer; 2^63 - 1
# keeps it a signed 64-bit number everywhere it is written.
MAX_SEED = 2**63 - 1


def whole(option: str, lo: int, hi: int) -> Callable[[str], int]:
    """A whole number ``lo`` .. ``hi`` for ``option``."""

    def parse(text: str) -> int:
        try:
            value = int(text.strip(), 10)
        except ValueError:
            raise ConfigError(option, f"must be a whole number, got {text!r}") from None
        if not lo <= value <= hi:
            raise ConfigError(option, f"must be from {lo} to {hi}, got {value}")
        return value

    return parse


def number(
    option: str, lo: float, hi: float, *, open_lo: bool = False, unit: str = ""
) -> Callable[[str], float]:
    """A finite number in [``lo``, ``hi``] (``open_lo``: in (``lo``, ``hi``]) for ``option``."""
    suffix = f" {unit}" if unit else ""

    def parse(text: str) -> float:
        try:
            value = float(text.strip())
        except ValueError:
            raise ConfigError(option, f"must be a number, got {text!r}") from None
        if not math.isfinite(value):
            raise ConfigError(option, f"must be a finite number, got {text.strip()}")
        if (value <= lo if open_lo else value < lo) or value > hi:
            low = "> " if open_lo else ">= "
            raise ConfigError(option, f"must be {low}{lo:g} and <= {hi:g}{suffix}, got {value:g}")
        return value

    return parse


def workers(option: str = "--workers") -> Callable[[str], int]:
    """Local worker processes: 1 .. :func:`omnipipe.executor.max_workers`."""

    def parse(text: str) -> int:
        from omnipipe.executor import check_workers

        try:
            value = int(text.strip(), 10)
        except ValueError:
            raise ConfigError(option, f"must be a whole number, got {text!r}") from None
        return check_workers(value, option)

    return parse


def scheduler(text: str) -> str:
    """``--scheduler``: a Dask address ``SCHEME://HOST:PORT`` (checked, not contacted)."""
    from omnipipe.executor import check_scheduler_address

    return check_scheduler_address(text)


def seed(option: str = "--seed") -> Callable[[str], int]:
    """A random seed: 0 .. :data:`MAX_SEED`."""
    return whole(option, 0, MAX_SEED)


def image_size(option: str = "--size") -> Callable[[str], tuple[int, int]]:
    """``WxH`` in pixels, each side 16 .. 8192."""

    def parse(text: str) -> tuple[int, int]:
        try:
            w, h = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise ConfigError(option, f"expected WxH such as 1600x1200, got {text!r}") from None
        if not (16 <= w <= 8192 and 16 <= h <= 8192):
            raise ConfigError(option, f"each side must be 16 to 8192 px, got {w}x{h}")
        return w, h

    return parse
