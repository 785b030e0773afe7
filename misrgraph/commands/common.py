"""What every command shares: the consoles, the one error boundary, ``--config`` and ``--json``,
progress bars, output-location checks and the tables more than one command prints.

A command module holds its command functions only; :mod:`misrgraph.commands.cli` registers them.
Every failure ends in one line on stderr, ``misrgraph: error: ...``, and an exit status:

====  ==========================================================================================
code  meaning
====  ==========================================================================================
0     success
1     a computation failed (no convergence, a failed campaign task) or an output could not be
      written (full disk, read-only place); the line names the path
2     bad input: an option's value, an input file (missing, malformed, wrong kind), a problem
      the input cannot determine, a missing optional dependency
130   interrupted (Ctrl-C)
====  ==========================================================================================
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table

from misrgraph.errors import InputError, MisrGraphError, OutputError

__all__ = [
    "console",
    "err_console",
    "fail",
    "handle_errors",
    "set_debug",
    "exit_hard_on_output_errors",
    "configure_logging",
    "merge_config",
    "print_json",
    "check_output",
    "progress_bar",
    "mode_or_sigma",
    "parse_comma_list",
    "print_coregistration",
    "CONFIG_HELP",
    "NOISE_HELP",
    "load_noise",
    "adjust_config",
]

console = Console()
err_console = Console(stderr=True)

#: The help text of every command's ``--config`` option (the dataclass is named by the command).
CONFIG_HELP = "JSON file of {cls} fields; its values replace the options' (unknown keys are refused)."

#: The help text of every command's ``--noise-model`` option
NOISE_HELP = (
    "Noise-model file (JSON; 'misrgraph noise init' writes the defaults): the levels the estimator assumes. "
    "Default: the pre-flight levels."
)


def adjust_config(fields: dict[str, Any], config: Optional[Path], noise_model: Optional[Path]) -> Any:
    """The :class:`~misrgraph.estimate.adjust.AdjustConfig` of a command: its options' ``fields``,
    then the ``--config`` file's, then the ``--noise-model`` file's levels."""
    from misrgraph.estimate.adjust import AdjustConfig

    merge_config(fields, config)
    cfg = AdjustConfig.from_dict(fields)
    noise = load_noise(noise_model)
    return cfg if noise is None else cfg.with_noise(noise)


def load_noise(path: Optional[Path]) -> Any:
    """The :class:`~misrgraph.model.noise.NoiseModel` in ``path``, or None."""
    if path is None:
        return None
    from misrgraph.io.noise import read_noise_model

    return read_noise_model(path)[0]


_STATE = {"debug": False, "hard_exit": False}


def set_debug(debug: bool) -> None:
    """``misrgraph --debug``: errors propagate with their traceback instead of one line."""
    _STATE["debug"] = bool(debug)


def configure_logging(verbose: bool) -> None:
    """Log at INFO with ``--verbose``, else WARNING, on stderr; HDF5 objects that fail to close
    after a failed write are logged at DEBUG instead of printed as tracebacks."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    if _STATE.get("hooks"):  # once per process, however many commands it runs
        return
    _STATE["hooks"] = True
    default_hook = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if "h5py" in repr(getattr(unraisable, "object", "")):
            logging.getLogger("misrgraph").debug("h5py: %s", unraisable.exc_value)
            return
        default_hook(unraisable)

    sys.unraisablehook = hook
    default_excepthook = sys.excepthook

    def excepthook(kind: Any, value: Any, tb: Any) -> None:
        # Cython prints a deallocation failure through sys.excepthook before the unraisable hook
        frames, t = [], tb
        while t is not None:
            frames.append(t.tb_frame.f_code.co_filename)
            t = t.tb_next
        if frames and "h5py" in frames[-1] and "_objects" in frames[-1]:
            logging.getLogger("misrgraph").debug("h5py: %s", value)
            return
        default_excepthook(kind, value, tb)

    sys.excepthook = excepthook


def exit_hard_on_output_errors() -> None:
    """In the console script: after an output error, end the process at once (HDF5 would otherwise
    try to flush the failed file again at interpreter exit, onto the same full disk)."""
    _STATE["hard_exit"] = True


def fail(message: str, code: int = 2) -> None:
    """Print ``misrgraph: error: MESSAGE`` on stderr and exit with ``code``."""
    err_console.print(f"misrgraph: error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _io_message(exc: OSError) -> str | None:
    """One line for an operating-system write failure that no writer caught: the path (when the
    error names one) and the reason, no library detail; ``None`` for any other OSError."""
    from misrgraph.io.h5 import is_write_failure, os_reason  # h5py: not at start-up

    if not is_write_failure(exc):
        return None
    return f"{exc.filename or 'output'}: cannot write ({os_reason(exc)})"


def handle_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator, the one error boundary of every command: any failure ends with one line on
    stderr naming what went wrong (exit codes: see the module docstring). ``misrgraph --debug``
    re-raises instead, with the traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except MisrGraphError as exc:
            if _STATE["debug"]:
                raise
            if isinstance(exc, OutputError) and _STATE["hard_exit"]:
                err_console.print(f"misrgraph: error: {exc}", markup=False, highlight=False, soft_wrap=True)
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(exc.exit_code)
            fail(str(exc), exc.exit_code)
        except KeyboardInterrupt:
            fail("interrupted", 130)
        except OSError as exc:
            if _STATE["debug"]:
                raise
            line = _io_message(exc)
            if line is None:
                fail(
                    f"internal error in {fn.__name__} ({exc.__class__.__name__}: {exc}). "
                    "Rerun with 'misrgraph --debug ...' for the traceback",
                    1,
                )
            fail(line, 1)
        except Exception as exc:
            if _STATE["debug"]:
                raise
            fail(
                f"internal error in {fn.__name__} ({exc.__class__.__name__}: {exc}). "
                "Rerun with 'misrgraph --debug ...' for the traceback",
                1,
            )

    return wrapper


def merge_config(fields: dict[str, Any], config: Optional[Path]) -> None:
    """Update ``fields`` from a ``--config`` JSON file (its keys win over the options)."""
    if config is None:
        return
    try:
        data = json.loads(config.read_text())
    except OSError as exc:
        raise InputError("--config", str(config), f"a readable JSON file ({os.strerror(exc.errno or 0)})") from None
    except json.JSONDecodeError as exc:
        raise InputError("--config", str(config), f"a JSON object (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(data, dict):
        raise InputError("--config", str(config), "a JSON object of field names and values")
    fields.update(data)


def print_json(obj: Any) -> None:
    """The machine-readable output of ``--json``: indented JSON on stdout."""
    sys.stdout.write(json.dumps(obj, indent=2, sort_keys=False) + "\n")


def check_output(path: Optional[Path], option: str) -> None:
    """Refuse, before any work, an output location that cannot be written
    (:func:`misrgraph.io.h5.check_writable`); ``None`` is accepted (no output)."""
    if path is not None:
        from misrgraph.io.h5 import check_writable  # h5py: not at start-up

        check_writable(path, option)


@contextlib.contextmanager
def progress_bar(description: str, disable: bool = False, counts: bool = False) -> Iterator[Callable[..., None]]:
    """A progress bar on stderr; yields ``update(description, done, total)``.

    ``counts`` shows ``done/total`` as well; ``disable`` (for ``--json``) shows nothing.
    """
    columns = [TextColumn("{task.description}"), BarColumn()]
    if counts:
        columns.append(MofNCompleteColumn())
    columns.append(TimeElapsedColumn())
    with Progress(*columns, console=err_console, disable=disable) as bar:
        task = bar.add_task(description, total=None)

        def update(desc: str, done: int, total: int | None) -> None:
            bar.update(task, description=desc, completed=done, total=None if total is None else max(total, 1))

        yield update


def mode_or_sigma(option: str, value: str, modes: tuple[str, ...], unit: str) -> float | str:
    """A named setting of an option, or its 1 sigma as a number.

    Raises
    ------
    InputError
        When ``value`` is neither one of ``modes`` nor a number.
    """
    if value in modes:
        return value
    try:
        return float(value)
    except ValueError:
        raise InputError(option, value, f"{', '.join(modes)} or a 1 sigma in {unit} (0: off)") from None


def parse_comma_list(option: str, value: str, kind: Callable[[str], Any], example: str) -> tuple:
    """``"a,b,c"`` as a tuple of ``kind``; an :class:`InputError` naming ``option`` otherwise."""
    try:
        return tuple(kind(x.strip()) for x in value.split(",") if x.strip())
    except ValueError:
        raise InputError(option, value, f"a comma-separated list such as {example}") from None


def print_coregistration(
    title: str,
    cameras: list[str],
    matched: dict[str, float],
    truth: dict[str, dict[str, float]],
    predicted: dict[str, dict[str, float]] | None = None,
) -> None:
    """The ROI's co-registration per camera (pixels, worst block): matched on the ROI (beyond
    matching noise, a block's pairs pooled), what the adjustment's own uncertainty allows and,
    when simulated, the truth against An and between passes (pooled as the matches are) and of
    the worst single pair of images."""
    table = Table(title=title)
    for col in (
        "camera",
        "matched, beyond noise",
        "allowed: vs An",
        "allowed: between passes",
        "truth: vs An",
        "truth: between passes",
        "truth: worst pair",
    ):
        table.add_column(col, justify="right")

    def fmt(v: float | None) -> str:
        return "-" if v is None else f"{v:.3f}"

    predicted = predicted or {}
    for cam in cameras:
        worst = [v for k in ("between_cameras_px", "between_passes_px") if (v := truth.get(k, {}).get(cam)) is not None]
        table.add_row(
            cam,
            fmt(matched.get(cam)),
            fmt(predicted.get(cam, {}).get("vs_An")),
            fmt(predicted.get(cam, {}).get("between_passes")),
            fmt(truth.get("between_cameras_pooled_px", {}).get(cam)),
            fmt(truth.get("between_passes_pooled_px", {}).get(cam)),
            fmt(max(worst) if worst else None),
        )
    console.print(table)
