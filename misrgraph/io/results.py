"""Summaries of results: capped lists for JSON summaries, and result-file attributes."""

from __future__ import annotations

import os
from typing import Any

from misrgraph.io.h5 import open_h5

__all__ = ["summarise_result_file", "capped_list", "JSON_LIST_CAP"]

#: Entries of a list that grows with the data (blunders, rejected observations) shown in a summary.
JSON_LIST_CAP = 20


def capped_list(
    items: list[dict[str, Any]],
    full_list: str | None,
    key: str = "normalised_residual",
    group_by: tuple[str, ...] = (),
    cap: int = JSON_LIST_CAP,
) -> dict[str, Any]:
    """A summary of a list that grows with the data: ``count``, counts per value of each field
    in ``group_by``, the ``cap`` entries with the largest ``key`` (``largest``, descending) and
    ``full_list``, where the whole list is (``FILE:/dataset``; None if nothing was written)."""
    ranked = sorted(items, key=lambda e: -abs(float(e[key]))) if items and key in items[0] else list(items)
    out: dict[str, Any] = {"count": len(items)}
    for field in group_by:
        counts: dict[str, int] = {}
        for e in items:
            counts[str(e[field])] = counts.get(str(e[field]), 0) + 1
        out[f"by_{field}"] = counts
    out["largest"] = ranked[:cap]
    out["shown"] = min(cap, len(items))
    out["full_list"] = full_list
    return out


def summarise_result_file(path: str | os.PathLike[str], kind: str) -> dict[str, Any]:
    """Root attributes of a result file (kind-specific readers add more)."""
    with open_h5(path, kind) as f:
        return {
            k: (v.decode() if isinstance(v, bytes) else v.item() if hasattr(v, "item") else v)
            for k, v in f.attrs.items()
            if k not in ("misrgraph_kind", "format_version")
        }
