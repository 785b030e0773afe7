"""Summaries of result files written by calibration and adjustment (filled in as they land)."""

from __future__ import annotations

import os
from typing import Any

from misrgraph.h5io import open_h5

__all__ = ["summarise_result_file"]


def summarise_result_file(path: str | os.PathLike[str], kind: str) -> dict[str, Any]:
    """Root attributes of a result file (kind-specific readers add more)."""
    with open_h5(path, kind) as f:
        return {k: (v.decode() if isinstance(v, bytes) else v.item() if hasattr(v, "item") else v)
                for k, v in f.attrs.items() if k not in ("misrgraph_kind", "format_version")}
