"""MISR space at the command line: convert a point between block/line/sample, geodetic and SOM
coordinates (``misrgraph som convert``), and orbit <-> path <-> time (``misrgraph som orbit``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from misrgraph.errors import InputError
from misrgraph.misr.orbits import format_utc, orbit_time_range, orbit_to_path, parse_utc, time_to_orbit
from misrgraph.misr.som import SomGrid

__all__ = ["run_som_convert", "run_som_orbit"]

_FORMS = {"block/line/sample": ("block", "line", "sample"), "lat/lon": ("lat", "lon"), "SOM x/y": ("som_x", "som_y")}


def run_som_convert(
    path: int,
    resolution_m: int = 1100,
    *,
    block: int | None = None,
    line: float | None = None,
    sample: float | None = None,
    lat: float | None = None,
    lon: float | None = None,
    som_x: float | None = None,
    som_y: float | None = None,
) -> dict[str, Any]:
    """One point in every form, from exactly one complete form of input.

    Returns ``{"path", "resolution_m", "block", "line", "sample", "lat", "lon", "som_x", "som_y"}``
    (degrees, metres, fractional pixels with -0.5 the edge of the first pixel). A point on no
    block of the path (possible from lat/lon or SOM x/y) has ``block``, ``line`` and ``sample``
    null and ``on_grid`` false."""
    given = {"block": block, "line": line, "sample": sample, "lat": lat, "lon": lon, "som_x": som_x, "som_y": som_y}
    complete = [name for name, keys in _FORMS.items() if all(given[k] is not None for k in keys)]
    partial = [
        name for name, keys in _FORMS.items() if any(given[k] is not None for k in keys) and name not in complete
    ]
    if len(complete) != 1 or partial:
        got = ", ".join(k for k, v in given.items() if v is not None) or "nothing"
        raise InputError(
            "point", got, "exactly one of --block/--line/--sample, --lat/--lon or --som-x/--som-y, complete"
        )
    grid = SomGrid(path, resolution_m)
    form = complete[0]
    if form == "block/line/sample":
        x, y = grid.bls_to_somxy(block, line, sample)
        b, ln, s = np.asarray(block), np.asarray(line, dtype=float), np.asarray(sample, dtype=float)
        la, lo = grid.somxy_to_latlon(x, y)
    else:
        if form == "lat/lon":
            la, lo = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
            x, y = grid.latlon_to_somxy(la, lo)
        else:
            x, y = np.asarray(som_x, dtype=float), np.asarray(som_y, dtype=float)
            la, lo = grid.somxy_to_latlon(x, y)
        b, ln, s = grid.somxy_to_bls(x, y, strict=False)
    on_grid = int(b) != 0
    return {
        "path": grid.path,
        "resolution_m": grid.resolution_m,
        "block": int(b) if on_grid else None,
        "line": float(ln) if on_grid else None,
        "sample": float(s) if on_grid else None,
        "lat": float(la),
        "lon": float(lo),
        "som_x": float(x),
        "som_y": float(y),
        "on_grid": on_grid,
    }


def run_som_orbit(orbit: int | None = None, time: str | None = None) -> dict[str, Any]:
    """``{"orbit", "path", "start", "end"}`` of an orbit number or of the orbit flying at a UTC
    time (exactly one of the two); times ISO-8601 UTC to the second."""
    if (orbit is None) == (time is None):
        raise InputError("orbit/time", {"orbit": orbit, "time": time}, "exactly one of --orbit or --time")
    if orbit is None:
        orbit = time_to_orbit(parse_utc(time, "--time"))
    start, end = orbit_time_range(orbit)
    return {"orbit": int(orbit), "path": int(orbit_to_path(orbit)), "start": format_utc(start), "end": format_utc(end)}
