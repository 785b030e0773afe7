"""Scoring Projection Parameters against the simulator's truth.

On the PP's covariance sub-grid (every ``step``-th 1.1 km point, where the stored 1-sigma is
exact rather than interpolated) each camera's PP image position at height 0 is compared with
where the *true* geometry (navigation without the injected errors, the true camera) images the
same ground point. The pixel error is mapped to a horizontal ground error through the true
geometry's local ground-to-image derivative, so ``rms`` (metres) is the geolocation error a user
of the PP would make; ``predicted_rms`` is the RMS of the PP's own ``sigma_m`` over the same
points, and ``nees`` the mean of ``e^T C^-1 e / 2`` with ``C`` the stored pixel covariance.
The points of one pass share their navigation error, so one pass's figures scatter far more
than their count suggests: judge honesty over several passes (``misrgraph bench`` style).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from misrgraph.io.passes import OrbitPass
from misrgraph.io.truth import PassTruth
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import BANDS
from misrgraph.model.frames import enu_basis, geodetic_to_ecef
from misrgraph.io.products import ProjectionParameters
from misrgraph.products.pp import crossing, ground_derivatives

__all__ = ["score_pp"]

Array = NDArray[np.float64]


def score_pp(pp: ProjectionParameters, orbit_pass: OrbitPass, truth: PassTruth, step: int = 8,
             supplied_camera: CameraModel | None = None) -> dict[str, Any]:
    """``{"pp_error_m": {camera: {"n", "rms", "predicted_rms", "rms_over_predicted", "nees",
    "error_px_rms"[, "supplied_rms"]}}}`` (module docstring); with ``supplied_camera`` also the
    RMS error the same grid points would have with the supplied navigation (no adjustment)."""
    true_geo = truth.geometry(orbit_pass)
    supplied_geo = orbit_pass.geometry(supplied_camera) if supplied_camera is not None else None
    grid = pp.grid
    bi = BANDS.index(pp.band)
    sub = (slice(None, None, step), slice(None, None, step))
    seen = pp.seen()
    per_cam: dict[str, dict[str, list[Array]]] = {c: {"e_m": [], "s_m": [], "nees": [], "e_px": [], "sup_m": []}
                                                  for c in pp.cameras}
    for j, block in enumerate(pp.blocks):
        x, y = grid.block_centres(int(block), step=step)
        lat, lon = grid.somxy_to_latlon(x, y)
        g = geodetic_to_ecef(lat.ravel(), lon.ravel(), np.zeros(lat.size))
        enu = enu_basis(lat.ravel(), lon.ravel())
        for c, name in enumerate(pp.cameras):
            ln_pp = pp.line0[c, j][sub].ravel()
            sm_pp = pp.sample0[c, j][sub].ravel()
            ok = seen[c, j][sub].ravel() & np.isfinite(pp.sigma_line[c, j][sub].ravel())
            if not ok.any():
                continue
            assert true_geo.t0 is not None
            t_guess = true_geo.t0[c, bi] + ln_pp[ok] * true_geo.camera.line_time
            _, ln_t, sm_t = crossing(true_geo, c, bi, g[ok], t_guess)
            e = np.stack([ln_pp[ok] - ln_t, sm_pp[ok] - sm_t], -1)
            # the ground displacement that moves the true image position onto the PP's
            d_en = ground_derivatives(true_geo, c, bi, g[ok], enu[ok], t_guess)
            good = np.isfinite(e).all(1) & np.isfinite(d_en).all((1, 2))
            e, d_en = e[good], d_en[good]
            e_en = np.linalg.solve(d_en, e[..., None])[..., 0]
            sl = pp.sigma_line[c, j][sub].ravel()[ok][good]
            ss = pp.sigma_sample[c, j][sub].ravel()[ok][good]
            rho = pp.correlation[c, j][sub].ravel()[ok][good]
            cov = np.stack([np.stack([sl**2, rho * sl * ss], -1), np.stack([rho * sl * ss, ss**2], -1)], -2)
            per_cam[name]["e_m"].append(np.hypot(e_en[:, 0], e_en[:, 1]))
            per_cam[name]["s_m"].append(pp.sigma_m[c, j][sub].ravel()[ok][good])
            per_cam[name]["nees"].append(np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0]) / 2.0)
            per_cam[name]["e_px"].append(np.hypot(e[:, 0], e[:, 1]))
            if supplied_geo is not None:
                _, ln_s, sm_s = crossing(supplied_geo, c, bi, g[ok], t_guess)
                e_s = np.stack([ln_s - ln_t, sm_s - sm_t], -1)[good]
                e_s_en = np.linalg.solve(d_en, e_s[..., None])[..., 0]
                per_cam[name]["sup_m"].append(np.hypot(e_s_en[:, 0], e_s_en[:, 1]))
    out: dict[str, Any] = {}
    for name, v in per_cam.items():
        if not v["e_m"]:
            continue
        e_m, s_m = np.concatenate(v["e_m"]), np.concatenate(v["s_m"])
        rms, pred = float(np.sqrt(np.mean(e_m**2))), float(np.sqrt(np.nanmean(s_m**2)))
        out[name] = {"n": int(e_m.size), "rms": rms, "predicted_rms": pred, "rms_over_predicted": rms / pred,
                     "nees": float(np.mean(np.concatenate(v["nees"]))),
                     "error_px_rms": float(np.sqrt(np.mean(np.concatenate(v["e_px"]) ** 2)))}
        if v["sup_m"]:
            sup = np.concatenate(v["sup_m"])
            out[name]["supplied_rms"] = float(np.sqrt(np.nanmean(sup**2)))
    return {"pp_error_m": out}
