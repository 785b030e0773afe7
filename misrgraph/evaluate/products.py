"""Scoring Projection Parameters (and the Reference Orbit Imagery made with them,
:func:`score_roi`) against the simulator's truth.

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

from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import InputError
from misrgraph.io.passes import OrbitPass
from misrgraph.io.products import ProjectionParameters
from misrgraph.io.truth import PassTruth
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.frames import enu_basis, geodetic_to_ecef
from misrgraph.products.pp import crossing, ground_derivatives

__all__ = ["score_pp", "score_roi", "score_roi_matches", "truth_hidden"]

Array = NDArray[np.float64]


def score_pp(
    pp: ProjectionParameters,
    orbit_pass: OrbitPass,
    truth: PassTruth,
    step: int = 8,
    supplied_camera: CameraModel | None = None,
) -> dict[str, Any]:
    """``{"pp_error_m": {camera: {"n", "rms", "predicted_rms", "rms_over_predicted", "nees",
    "error_px_rms"[, "supplied_rms"]}}, "pp_error_by_block": {camera: {block: {"n", "rms",
    "predicted_rms", "error_px_rms", "predicted_px_rms"}}}}`` (module docstring; ``rms`` m,
    ``*_px_rms`` the pixel error and the RMS of its predicted 1-sigma ``sqrt(sigma_line^2 +
    sigma_sample^2)``); with ``supplied_camera`` also the RMS error the same grid points would
    have with the supplied navigation (no adjustment)."""
    true_geo = truth.geometry(orbit_pass)
    supplied_geo = orbit_pass.geometry(supplied_camera) if supplied_camera is not None else None
    grid = pp.grid
    bi = BANDS.index(pp.band)
    sub = (slice(None, None, step), slice(None, None, step))
    seen = pp.seen()
    per_cam: dict[str, dict[str, list[Array]]] = {
        c: {"e_m": [], "s_m": [], "nees": [], "e_px": [], "sup_m": [], "s_px": []} for c in pp.cameras
    }
    blocks_of: dict[str, list[int]] = {c: [] for c in pp.cameras}
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
            ci = CAMERAS.index(name)  # the geometry's camera index (the PP may hold a subset)
            t_guess = true_geo.t0[ci, bi] + ln_pp[ok] * true_geo.camera.line_time
            _, ln_t, sm_t = crossing(true_geo, ci, bi, g[ok], t_guess)
            e = np.stack([ln_pp[ok] - ln_t, sm_pp[ok] - sm_t], -1)
            # the ground displacement that moves the true image position onto the PP's
            d_en = ground_derivatives(true_geo, ci, bi, g[ok], enu[ok], t_guess)
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
            per_cam[name]["s_px"].append(np.hypot(sl, ss))
            blocks_of[name].append(int(block))
            if supplied_geo is not None:
                _, ln_s, sm_s = crossing(supplied_geo, ci, bi, g[ok], t_guess)
                e_s = np.stack([ln_s - ln_t, sm_s - sm_t], -1)[good]
                e_s_en = np.linalg.solve(d_en, e_s[..., None])[..., 0]
                per_cam[name]["sup_m"].append(np.hypot(e_s_en[:, 0], e_s_en[:, 1]))
    out: dict[str, Any] = {}
    for name, v in per_cam.items():
        if not v["e_m"]:
            continue
        e_m, s_m = np.concatenate(v["e_m"]), np.concatenate(v["s_m"])
        rms, pred = float(np.sqrt(np.mean(e_m**2))), float(np.sqrt(np.nanmean(s_m**2)))
        out[name] = {
            "n": int(e_m.size),
            "rms": rms,
            "predicted_rms": pred,
            "rms_over_predicted": rms / pred,
            "nees": float(np.mean(np.concatenate(v["nees"]))),
            "error_px_rms": float(np.sqrt(np.mean(np.concatenate(v["e_px"]) ** 2))),
        }
        if v["sup_m"]:
            sup = np.concatenate(v["sup_m"])
            out[name]["supplied_rms"] = float(np.sqrt(np.nanmean(sup**2)))
    by_block: dict[str, dict[int, dict[str, float]]] = {}
    for name, v in per_cam.items():
        for b, e_m, s_m, e_px, s_px in zip(blocks_of[name], v["e_m"], v["s_m"], v["e_px"], v["s_px"]):
            if e_m.size:
                by_block.setdefault(name, {})[b] = {
                    "n": int(e_m.size),
                    "rms": float(np.sqrt(np.mean(e_m**2))),
                    "predicted_rms": float(np.sqrt(np.nanmean(s_m**2))),
                    "error_px_rms": float(np.sqrt(np.mean(e_px**2))),
                    "predicted_px_rms": float(np.sqrt(np.nanmean(s_px**2))),
                }
    return {"pp_error_m": out, "pp_error_by_block": by_block}


def _seen_ground(
    geo: Any, cam: int, band: int, line: Array, sample: Array, surface: Callable[[Array, Array], Array]
) -> Array:
    """The true ground ``(N, 3)`` ECEF that image positions show: the first crossing of their rays
    with ``surface`` from the camera (:func:`misrgraph.model.geolocation.cast_seen`)."""
    from misrgraph.model.geolocation import cast_seen

    n = line.size
    origin, direction = geo.pixel_rays(np.full(n, cam), np.full(n, band), line, sample, np.full(n, np.nan))
    return cast_seen(origin, direction, surface)


def truth_hidden(
    geo: Any,
    cam: int,
    band: int,
    ground: Array,
    surface: Callable[[Array, Array], Array],
    min_distance_m: float = 137.5,
) -> NDArray[np.bool_]:
    """``(N,)`` bool: which ECEF points ``ground (N, 3)`` on the true ``surface`` camera ``cam``
    cannot see under the geometry ``geo`` -- the ray from the camera at the moment it images the
    point meets the surface first more than ``min_distance_m`` (half a 275 m pixel) before it.
    Points the camera never images are False."""
    from misrgraph.model.geolocation import hidden_in_image

    cams = np.full(ground.shape[0], cam)
    ip = geo.ground_to_pixel(cams, np.full(cams.size, band), ground, continuous=True)
    return hidden_in_image(geo, cams, band, ip, ground, surface, min_distance_m)


def _seen_error(
    grid: Any,
    block: int,
    geo: Any,
    pp: ProjectionParameters,
    cam: str,
    pl: NDArray[np.int64],
    ps: NDArray[np.int64],
    heights: NDArray[np.float32],
    surface: Callable[[Array, Array], Array],
) -> tuple[Array, Array, Array]:
    """The true geolocation error ``(n, 2)`` (SOM line, sample; 275 m px; NaN where the PP do not
    image the point) of what camera ``cam``'s image, resampled by ``pp`` at the SOM DEM's
    ``heights``, shows at grid points ``(pl, ps)`` of ``block``: where the true geometry ``geo``'s
    ray through the PP's image position first meets the true ``surface``, less the grid point.
    Also the PP's image line and sample ``(n,)``."""
    from misrgraph.model.frames import ecef_to_geodetic

    ln, sm = pp.image_coords(cam, block, pl.astype(float), ps.astype(float), heights[pl, ps], resolution_m=275)
    ok = np.isfinite(ln) & np.isfinite(sm)
    e = np.full((pl.size, 2), np.nan)
    if ok.any():
        g = _seen_ground(geo, CAMERAS.index(cam), BANDS.index(pp.band), ln[ok], sm[ok], surface)
        lat, lon, _ = ecef_to_geodetic(g)
        b, gl, gs = grid.latlon_to_bls(lat, lon, strict=False)
        e[ok] = np.stack([gl + (b - block) * grid.nline - pl[ok], gs - ps[ok]], 1)
    return e, ln, sm


def score_roi_matches(
    block: int,
    passes: list[tuple[OrbitPass, PassTruth, ProjectionParameters]],
    heights: NDArray[np.float32],
    cameras: tuple[str, ...],
    surface: Callable[[Array, Array], Array],
    matches: list[Any],
) -> dict[str, dict[str, dict[str, float | int]]]:
    """The truth at the very points co-registration matched and kept (simulated passes only): per
    camera and kind (:class:`misrgraph.products.roi.PairMatches`, pairs of at least 3), the
    pooled radial RMS of the true misregistration there, ``truth_px`` -- what the matched
    ``excess_px`` estimates -- and of the matching error (matched offset less the true one),
    ``error_px``, with the RMS of its components over their LSM 1-sigma, ``error_over_sigma``,
    and ``matches``; ``rejected`` (the matches rejected as inconsistent) and, if any, their
    matching error ``rejected_error_px`` (large if the rejection is right). A pair's true offset
    at a grid point is the reference image's error less the other's (:func:`_seen_error`): the
    reference shows there the ground the other shows at the point plus the offset. Points either
    image does not show are left out."""
    from misrgraph.misr.som import SomGrid

    grid = SomGrid(int(passes[0][2].path), 275)
    need: dict[tuple[int, int], list[NDArray[np.int64]]] = {}
    matches = [m for m in matches if m.usable]
    for m in matches:
        need.setdefault(m.ref, []).append(m.points)
        need.setdefault(m.other, []).append(m.points)
    err: dict[tuple[int, int], dict[tuple[int, int], Array]] = {}
    for (k, c), pts in need.items():
        u = np.unique(np.concatenate(pts), axis=0)
        orbit_pass, truth, pp = passes[k]
        e, _, _ = _seen_error(
            grid, block, truth.geometry(orbit_pass), pp, cameras[c], u[:, 0], u[:, 1], heights, surface
        )
        err[(k, c)] = {(int(r), int(q)): e[i] for i, (r, q) in enumerate(u)}
    acc: dict[tuple[str, str], list[Array]] = {}
    for m in matches:
        t = np.array([err[m.ref][(int(r), int(q))] - err[m.other][(int(r), int(q))] for r, q in m.points])
        ok = np.isfinite(t).all(1)
        acc.setdefault((m.camera, m.kind), []).append(np.column_stack([t[ok], m.offsets[ok], m.kept[ok]]))
    out: dict[str, dict[str, dict[str, float | int]]] = {}
    for (cam, kind), rows in acc.items():
        a = np.concatenate(rows)
        kept, gone = a[a[:, 6] > 0], a[a[:, 6] == 0]
        if kept.shape[0] == 0:
            continue
        t, d, sd = kept[:, :2], kept[:, 2:4], kept[:, 4:6]
        st: dict[str, float | int] = {
            "truth_px": float(np.sqrt(np.mean(np.sum(t**2, 1)))),
            "error_px": float(np.sqrt(np.mean(np.sum((d - t) ** 2, 1)))),
            "error_over_sigma": float(np.sqrt(np.mean(((d - t) / sd) ** 2))),
            "matches": int(kept.shape[0]),
            "rejected": int(gone.shape[0]),
        }
        if gone.shape[0]:
            st["rejected_error_px"] = float(np.sqrt(np.mean(np.sum((gone[:, 2:4] - gone[:, :2]) ** 2, 1))))
        out.setdefault(cam, {})[kind] = st
    return out


def score_roi(
    block: int,
    passes: list[tuple[OrbitPass, PassTruth, ProjectionParameters]],
    heights: NDArray[np.float32],
    cameras: tuple[str, ...],
    surface: Callable[[Array, Array], Array],
    n_points: int = 300,
    seed: int = 0,
    reference: int | None = None,
    obscured: NDArray[np.bool_] | None = None,
) -> dict[str, dict[str, Any]]:
    """The ROI's true misregistration on ``block`` (simulated passes only), in 275 m pixels.

    At ``n_points`` random grid points (fixed ``seed``) and for each pass, the ground point a
    resampled image shows there is where the *true* geometry's ray through the image position the
    PP give (at the SOM DEM's height ``heights (512, 2048)``) first meets the true ``surface``; its
    SOM (line, sample) minus the grid point is that camera's geolocation error, and its difference
    from An's (same pass) or from its own in another pass is the co-registration error. Points the
    ROI flags as obscured by terrain (``obscured (P, C, 512, 2048)``, per pass and camera of
    ``cameras``; :mod:`misrgraph.products.terrain`) are left out. Returns ``{"geolocation_px":
    {camera: worst RMS over passes}, "between_cameras_px": {camera: worst RMS against An over
    passes}, "between_passes_px": {camera: worst RMS over pairs of passes}, "geolocation_pooled_px",
    "between_cameras_pooled_px" and "between_passes_pooled_px" (the RMS over every pair's points
    pooled, as :func:`misrgraph.products.roi.coregistration` pools its matches), "obscured": {camera:
    {"points", "flagged", "hidden", "missed", "false"}}}`` -- what matching on the ROI measures,
    without the matching error; ``obscured`` counts, over passes and points the camera images,
    those the ROI flags, those the truth hides (:func:`truth_hidden`), the hidden ones not flagged
    and the flagged ones not hidden. With ``reference`` (a pass index: the block's pass, as
    :func:`misrgraph.products.roi.coregistration` compares) the pairs of passes are each pass
    with that one."""
    from misrgraph.misr.som import SomGrid

    rng = np.random.default_rng(seed)
    grid = SomGrid(int(passes[0][2].path), 275)
    pl = rng.integers(8, grid.nline - 8, n_points)
    ps = rng.integers(8, grid.nsample - 8, n_points)
    if obscured is not None and obscured.shape != (len(passes), len(cameras), grid.nline, grid.nsample):
        raise InputError(
            "obscured",
            obscured.shape,
            f"(passes, cameras, lines, samples) = {(len(passes), len(cameras), grid.nline, grid.nsample)}",
        )
    lat_g, lon_g = grid.bls_to_latlon(np.full(n_points, block), pl, ps)
    ground_true = geodetic_to_ecef(lat_g, lon_g, np.asarray(surface(lat_g, lon_g), dtype=float))
    err: dict[tuple[int, str], Array] = {}
    counts: dict[str, dict[str, int]] = {
        c: {"points": 0, "flagged": 0, "hidden": 0, "missed": 0, "false": 0} for c in cameras
    }
    for k, (orbit_pass, truth, pp) in enumerate(passes):
        geo = truth.geometry(orbit_pass)
        bi = BANDS.index(pp.band)
        for j, cam in enumerate(cameras):
            e, ln, sm = _seen_error(grid, block, geo, pp, cam, pl, ps, heights, surface)
            ok = np.isfinite(ln) & np.isfinite(sm)
            if ok.any():
                ci = CAMERAS.index(cam)
                flagged = obscured[k, j][pl, ps][ok] if obscured is not None else np.zeros(int(ok.sum()), bool)
                hidden = truth_hidden(geo, ci, bi, ground_true[ok], surface)
                c = counts[cam]
                c["points"] += int(ok.sum())
                c["flagged"] += int(flagged.sum())
                c["hidden"] += int(hidden.sum())
                c["missed"] += int((hidden & ~flagged).sum())
                c["false"] += int((flagged & ~hidden).sum())
                e[np.flatnonzero(ok)[flagged]] = np.nan  # the ROI leaves these out
            err[(k, cam)] = e

    def squares(pairs: list[tuple[Array, Array | None]]) -> list[Array]:
        out = []
        for a, b in pairs:
            d = a if b is None else a - b
            fin = np.isfinite(d).all(1)
            if fin.sum() >= 3:
                out.append(np.sum(d[fin] ** 2, 1))
        return out

    def worst(pairs: list[tuple[Array, Array | None]]) -> float | None:
        vals = [float(np.sqrt(np.mean(q))) for q in squares(pairs)]
        return max(vals) if vals else None

    def pooled(pairs: list[tuple[Array, Array | None]]) -> float | None:
        sq = squares(pairs)
        return float(np.sqrt(np.mean(np.concatenate(sq)))) if sq else None

    n_p = len(passes)
    out: dict[str, dict[str, Any]] = {
        "geolocation_px": {},
        "between_cameras_px": {},
        "between_passes_px": {},
        "geolocation_pooled_px": {},
        "between_cameras_pooled_px": {},
        "between_passes_pooled_px": {},
        "obscured": counts,
    }
    for cam in cameras:
        for kind, pairs in (
            ("geolocation_px", [(err[(k, cam)], None) for k in range(n_p)]),
            (
                "between_cameras_px",
                [(err[(k, cam)], err[(k, "An")]) for k in range(n_p)] if cam != "An" and "An" in cameras else [],
            ),
            (
                "between_passes_px",
                [(err[(k, cam)], err[(q, cam)]) for k in range(n_p) for q in range(k)]
                if reference is None
                else [(err[(k, cam)], err[(reference, cam)]) for k in range(n_p) if k != reference],
            ),
        ):
            w, p = worst(pairs), pooled(pairs)
            if w is not None:
                out[kind][cam] = w
                out[kind.replace("_px", "_pooled_px")][cam] = p
    return out
