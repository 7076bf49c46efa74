"""The single exception hierarchy of omnipipe.

Every error that a user can cause (bad files, bad values, impossible requests)
is an :class:`OmnipipeError`. The CLI prints its message on one line and exits
with code 1; anything else escaping is a bug.
"""

from __future__ import annotations


class OmnipipeError(Exception):
    """Base class of every error omnipipe raises on purpose."""


class ConfigError(OmnipipeError):
    """A configuration or calibration value is missing or invalid.

    Args:
        field: dotted name of the offending field, e.g. ``"camera.f"``.
        message: what is wrong with it.
        source: the file it came from, if any.
    """

    def __init__(self, field: str, message: str, source: str | None = None) -> None:
        self.field = field
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{field}: {message}")


class DatasetError(OmnipipeError):
    """A dataset directory, frame or ground-truth file is missing or unreadable."""


class ShapeError(OmnipipeError):
    """An array handed to a public function has the wrong shape or type."""


class ReconstructionError(OmnipipeError):
    """A pipeline stage could not produce a usable result from valid input."""


class OutputError(OmnipipeError):
    """An output location cannot be written (exists, not writable, ...)."""


def one_line(text: str) -> str:
    """``text`` on one line: every run of whitespace (newlines of a YAML parser's
    context, indentation) becomes one space. Every message the CLI prints or an index
    lists goes through here."""
    return " ".join(str(text).split())


def yaml_reason(exc: BaseException) -> str | None:
    """``"PROBLEM (line L, column C)"`` of a YAML parser's error (PyYAML's or ruamel's
    ``MarkedYAMLError``: lines and columns 1-based) found in ``exc`` or what caused it,
    without the parser's multi-line context; None if there is none."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        problem = getattr(cause, "problem", None)
        if isinstance(problem, str) and problem:
            mark = getattr(cause, "problem_mark", None)
            where = ""
            if mark is not None and hasattr(mark, "line") and hasattr(mark, "column"):
                where = f" (line {int(mark.line) + 1}, column {int(mark.column) + 1})"
            return one_line(problem + where)
        cause = cause.__cause__ or cause.__context__
    return None
