"""Exception hierarchy of misrgraph.

Every error the package raises on purpose derives from :class:`MisrGraphError`, so a caller (the
CLI, a notebook, a batch script) can catch one class. Messages are single lines that name the
offending field, the value received and what was expected.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, Iterable

__all__ = [
    "MisrGraphError",
    "InputError",
    "FileFormatError",
    "OutputError",
    "ConvergenceError",
    "DegenerateProblemError",
    "MissingDependencyError",
    "require_extra",
]


class MisrGraphError(Exception):
    """Root of every error raised deliberately by misrgraph.

    ``exit_code`` is the CLI's exit status for it: 2 for bad input (a value, a file, a problem
    the input cannot determine), 1 for a computation that failed.
    """

    exit_code = 1


class InputError(MisrGraphError, ValueError):
    """A user-supplied value is out of range, of the wrong shape or not one of the allowed names.

    Parameters
    ----------
    field : str
        Name of the field / option / argument at fault (e.g. ``"camera"``, ``"--pixel"``).
    value : Any
        The offending value as received.
    expected : str or iterable of str
        Human-readable description of what is allowed (e.g. ``"one of Df, Cf, ..."``), or the
        allowed names.
    """

    exit_code = 2

    def __init__(self, field: str, value: Any, expected: str | Iterable[str]) -> None:
        if not isinstance(expected, str):
            expected = "one of " + ", ".join(str(e) for e in expected)
        self.field = field
        self.value = value
        self.expected = expected
        super().__init__(f"{field}: got {value!r}; expected {expected}")


class FileFormatError(MisrGraphError):
    """An input file is missing, unreadable, of the wrong kind or version, or lacks a field."""

    exit_code = 2

    def __init__(self, path: Any, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class OutputError(MisrGraphError):
    """An output could not be written: a full disk, a read-only or missing place, no permission.

    The message names the path and the operating system's reason, never a library's detail.
    """

    exit_code = 1

    def __init__(self, path: Any, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: cannot write ({reason})")


class ConvergenceError(MisrGraphError):
    """An iterative computation did not converge within its limits."""


class DegenerateProblemError(MisrGraphError):
    """The estimation problem is not well posed (e.g. no observations, a singular system)."""

    exit_code = 2


class MissingDependencyError(MisrGraphError, ImportError):
    """An optional dependency is not installed; the message names the extra that brings it."""

    exit_code = 2

    def __init__(self, module: str, extra: str, purpose: str) -> None:
        self.module = module
        self.extra = extra
        super().__init__(f"{module}: not installed; {purpose} needs it: pip install 'misrgraph[{extra}]'")


def require_extra(module: str, extra: str, purpose: str) -> ModuleType:
    """Import an optional dependency, or raise :class:`MissingDependencyError` naming its extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingDependencyError(module, extra, purpose) from exc
