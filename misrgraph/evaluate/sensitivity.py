"""Ground displacement caused by attitude and ephemeris errors (the seed's Table 3 study).

For each camera, the nominal ground point of sample ``S`` (band ``B``) is geolocated on the
WGS84 ellipsoid at the middle of a standard Terra-like descending pass (path 37, June 2001, the
spacecraft near the equator), once with perfect navigation and once with a perturbation; the
displacement is expressed in the local horizontal frame at the nominal point.

Sign conventions:

* ``along_m``: positive in the flight direction (the orbital +x axis projected on the local
  horizontal plane); ``cross_m``: positive to the right of the flight direction (orbital +y).
* Attitude: ``+A`` arcsec added to the true roll, pitch or yaw (eq. 5 angles, spacecraft ->
  orbital ``Rz(yaw) Ry(pitch) Rx(roll)``). +pitch tips the boresight forward, +roll tips it to
  the left (-y), +yaw turns it counter-clockwise seen from above the spacecraft.
* Ephemeris: ``+M`` metres of spacecraft position error along (+x), cross (+y, right) and
  radial (up, i.e. -z of the orbital frame), the attitude staying fixed relative to the orbital
  frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from misrgraph.errors import InputError
from misrgraph.model.camera import CameraModel, validate_pixel_inputs
from misrgraph.model.constants import ANGLES, ARCSEC, CAMERAS
from misrgraph.model.geolocation import PassGeometry
from misrgraph.model.nominal import nominal_camera_model
from misrgraph.model.orbit import AttitudeSeries, terra_like_orbit

__all__ = ["run_sensitivity", "reference_geometry", "table3_markdown"]


def reference_geometry(camera: CameraModel | None = None) -> PassGeometry:
    """The standard reference pass used by the sensitivity study (perfect navigation)."""
    eph = terra_like_orbit(epoch_date="2001-06-15", path=37, start_lat_deg=60.0, duration_s=1800.0)
    return PassGeometry(eph, AttitudeSeries.zeros(eph.t), camera or nominal_camera_model())


def _const(vec: np.ndarray):
    return lambda t: np.broadcast_to(vec, (np.size(t), 3))


def run_sensitivity(
    arcsec: float = 10.0,
    pixel: float = 0.0,
    band: str = "red",
    ephemeris_m: float | None = None,
    cameras: tuple[str, ...] = CAMERAS,
    camera_model: CameraModel | None = None,
) -> dict[str, Any]:
    """Ground displacement (m) per camera for +``arcsec`` of yaw, pitch and roll at ``pixel``.

    Returns ``{"arcsec", "pixel", "band", "cameras": {cam: {"yaw"|"pitch"|"roll":
    {"along_m", "cross_m"}}}}`` and, with ``ephemeris_m``, per camera also ``"ephemeris":
    {"along"|"cross"|"radial": {"along_m", "cross_m"}}``.
    """
    if not np.isfinite(arcsec):
        raise InputError("arcsec", arcsec, "a finite number of arcseconds")
    b_idx = None
    for cam in cameras:
        _, b_idx = validate_pixel_inputs(cam, band, pixel)
    if ephemeris_m is not None and not np.isfinite(ephemeris_m):
        raise InputError("ephemeris_m", ephemeris_m, "a finite number of metres")
    base = reference_geometry(camera_model)
    t_mid = 0.5 * (base.ephemeris.t[0] + base.ephemeris.t[-1])
    out: dict[str, Any] = {"arcsec": float(arcsec), "pixel": float(pixel), "band": band, "cameras": {}}
    if ephemeris_m is not None:
        out["ephemeris_m"] = float(ephemeris_m)
    for cam in cameras:
        c = CAMERAS.index(cam)
        line = (t_mid - base.t0[c, b_idx]) / base.camera.line_time
        g0 = base.pixel_to_ground(c, b_idx, line, pixel)
        along, cross, _ = base.track_frame(g0, base.line_time(c, b_idx, line))
        entry: dict[str, Any] = {}
        perturb: list[tuple[str, str, np.ndarray]] = []
        for i, ang in enumerate(ANGLES):
            v = np.zeros(3)
            v[i] = arcsec * ARCSEC
            perturb.append(("att", ang, v))
        if ephemeris_m is not None:
            for name, v in (("along", [1, 0, 0]), ("cross", [0, 1, 0]), ("radial", [0, 0, -1])):
                perturb.append(("eph", name, float(ephemeris_m) * np.array(v, float)))
        for kind, name, v in perturb:
            geo = PassGeometry(
                base.ephemeris,
                base.attitude,
                base.camera,
                base.earth,
                base.t0,
                attitude_delta=_const(v) if kind == "att" else None,
                position_delta=_const(v) if kind == "eph" else None,
            )
            g1 = geo.pixel_to_ground(c, b_idx, line, pixel)
            d = (g1 - g0)[0]
            res = {"along_m": float(d @ along[0]), "cross_m": float(d @ cross[0])}
            if kind == "att":
                entry[name] = res
            else:
                entry.setdefault("ephemeris", {})[name] = res
        out["cameras"][cam] = {k: entry[k] for k in ("yaw", "pitch", "roll")} | (
            {"ephemeris": entry["ephemeris"]} if "ephemeris" in entry else {}
        )
    return out


def table3_markdown(arcsec: float = 10.0, pixel: float = 0.0, band: str = "red") -> str:
    """The seed's Table 3 for every camera as a Markdown table, computed with the nominal model.

    Columns are the along- and cross-track ground displacement (m) for ``+arcsec`` of yaw, pitch
    and roll at sample ``pixel`` of ``band``, with the sign conventions of this module.
    """
    res = run_sensitivity(arcsec=arcsec, pixel=pixel, band=band)
    head = "| camera | " + " | ".join(f"{a} along (m) | {a} cross (m)" for a in ("yaw", "pitch", "roll")) + " |"
    rows = [head, "|---" * 7 + "|"]
    for cam, v in res["cameras"].items():
        cells = [f"{v[a][d]:.1f}" for a in ("yaw", "pitch", "roll") for d in ("along_m", "cross_m")]
        rows.append(f"| {cam} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"
