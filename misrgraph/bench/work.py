"""The working directory of a bench study: the user's (kept, so that a rerun reuses its inputs)
or a temporary one removed when the study ends, also when it fails."""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path
from typing import Iterator

__all__ = ["bench_workdir"]


@contextlib.contextmanager
def bench_workdir(workdir: str | Path | None, prefix: str = "misrgraph-bench-") -> Iterator[Path]:
    """``workdir`` (created if missing), or a new temporary directory named ``prefix...``."""
    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)
        yield Path(workdir)
        return
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        yield Path(tmp)
