"""The demo a newcomer runs first (``make demo``): every stage that exists, on simulated data.

Each stage is a plain function call to the same ``run_*`` functions the CLI uses. Stages that
are not implemented yet are listed as such, so the demo always says what it did and did not do.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["run_demo", "STAGES"]

log = logging.getLogger(__name__)


def _stage_sensitivity(out: Path, state: dict[str, Any]) -> str:
    from misrgraph.sensitivity import run_sensitivity

    res = run_sensitivity(arcsec=10.0, pixel=0.0, band="red")
    df, an = res["cameras"]["Df"], res["cameras"]["An"]
    return (f"+10 arcsec pitch moves Df {df['pitch']['along_m']:.0f} m and An {an['pitch']['along_m']:.0f} m "
            f"along track (pixel 0, red)")


def _stage_round_trip(out: Path, state: dict[str, Any]) -> str:
    import numpy as np

    from misrgraph.sensitivity import reference_geometry

    geo = reference_geometry()
    rng = np.random.default_rng(0)
    worst = 0.0
    for c in range(9):
        n = geo.lines_in_pass(c, 2)
        line = np.floor(rng.uniform(0.4, 0.6, 50) * n)
        s = rng.uniform(0, 1503, 50)
        g = geo.pixel_to_ground(c, 2, line, s)
        ln, sm, vis, _, _ = geo.ground_to_pixel(c, 2, g)
        worst = max(worst, float(np.max(np.hypot(ln - line, sm - s))))
    return f"pixel -> ground -> pixel round trip, 9 cameras x 50 pixels: worst {worst:.1e} px"


STAGES: list[tuple[str, Callable[[Path, dict[str, Any]], str] | None]] = [
    ("forward model sensitivity", _stage_sensitivity),
    ("geolocation round trip", _stage_round_trip),
    ("simulate scenario", None),
    ("calibrate cameras", None),
    ("adjust a pass", None),
    ("incremental update", None),
    ("rerun recording", None),
]


def run_demo(out: str | Path, progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Run every available stage; return one record per stage (name, status, summary, seconds)."""
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    state: dict[str, Any] = {}
    records = []
    for name, fn in STAGES:
        if progress:
            progress(name)
        if fn is None:
            records.append({"stage": name, "status": "not yet implemented", "summary": "", "seconds": 0.0})
            continue
        t0 = time.perf_counter()
        summary = fn(out_dir, state)
        records.append({"stage": name, "status": "done", "summary": summary, "seconds": time.perf_counter() - t0})
        log.info("%s: %s", name, summary)
    return records
