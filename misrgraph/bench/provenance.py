"""Where a bench result comes from: the command that produced it, the commit and the machine.

Every ``misrgraph bench ...`` result carries a ``provenance`` mapping::

    {"command": "misrgraph bench nees --study adjust --runs 20",
     "bench": "nees",
     "commit": "1a2b3c4d5e6f" (+ "-dirty" when tracked files differ from it; "unknown" outside git),
     "version": "0.1.0",
     "machine": {"cpu": str, "cores": int, "memory_gib": float, "os": str,
                 "python": str, "numpy": str, "gtsam": str},
     "measured_utc": "YYYY-MM-DDTHH:MM:SSZ"}

``misrgraph bench report`` renders stored results with this heading, so that every figure in the
documentation names how it was measured.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from misrgraph.errors import InputError
from misrgraph.io.h5 import atomic_file

__all__ = ["provenance", "finish", "machine", "source_commit"]

_ROOT = Path(__file__).resolve().parents[2]


def source_commit(root: Path = _ROOT) -> str:
    """The git commit of the source tree (short hash, ``-dirty`` if tracked files changed), or
    ``"unknown"`` when the package is not run from a git checkout."""
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = (
            subprocess.run(
                ["git", "-C", str(root), "diff", "--quiet", "HEAD", "--", "misrgraph", "factors"],
                capture_output=True,
                timeout=10,
            ).returncode
            != 0
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("-dirty" if dirty else "") if head else "unknown"


def machine() -> dict[str, Any]:
    """The machine a result was measured on: processor model, cores, memory, OS and versions."""
    from importlib.metadata import PackageNotFoundError, version

    import numpy as np

    try:
        gtsam_version = version("gtsam")
    except PackageNotFoundError:
        gtsam_version = "?"

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        memory = float("nan")
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": round(memory, 1),
        "os": platform.system(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "gtsam": gtsam_version,
    }


def _click_context() -> tuple[Any, Any]:
    """The running command's click context and click's ParameterSource enum: click's own, or the
    copy of click that typer carries (typer >= 0.17); ``(None, None)`` outside a command."""
    import importlib

    for base in ("click", "typer._click"):
        try:
            glob = importlib.import_module(f"{base}.globals")
            core = importlib.import_module(f"{base}.core")
        except ImportError:
            continue
        ctx = glob.get_current_context(silent=True)
        if ctx is not None:
            return ctx, core.ParameterSource
    return None, None


def _command_line() -> tuple[str, str]:
    """``misrgraph bench NAME --opt value ...`` of the running click command (options given on the
    command line only) and the bench's name."""
    ctx, source = _click_context()
    if ctx is None:
        return "(Python API)", "api"
    names, c = [], ctx
    while c is not None and c.parent is not None:  # the root's name is the program's, however started
        names.append(c.info_name)
        c = c.parent
    words = ["misrgraph", *reversed(names)]
    for param in ctx.command.params:
        if ctx.get_parameter_source(param.name) is not source.COMMANDLINE or param.name in ("save", "as_json"):
            continue
        opt = param.opts[0]
        value = ctx.params[param.name]
        if isinstance(value, bool):
            words.append(opt if value else (param.secondary_opts or [opt])[0])
        elif param.param_type_name == "argument":
            words.extend(str(v) for v in (value if isinstance(value, (list, tuple)) else [value]))
        else:
            words += [opt, str(value)]
    return " ".join(words), (names[0] if names else "misrgraph")


def provenance() -> dict[str, Any]:
    """The provenance mapping of a result being produced now (see the module docstring)."""
    from misrgraph import __version__

    command, bench = _command_line()
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    return {
        "command": command,
        "bench": bench,
        "commit": source_commit(),
        "version": __version__,
        "machine": machine(),
        "measured_utc": now,
    }


def finish(result: dict[str, Any], save: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """``result`` with its provenance (first key), written atomically as JSON to ``save`` if given.

    Raises
    ------
    InputError
        When ``result`` is not a mapping (a bench function's bug, named rather than hidden).
    """
    if not isinstance(result, dict):
        raise InputError("bench result", type(result).__name__, "a mapping")
    out = {"provenance": provenance(), **{k: v for k, v in result.items() if k != "provenance"}}
    if save is not None:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(save) as fh:
            fh.write(json.dumps(out, indent=2, sort_keys=False) + "\n")
    return out
