"""Projection Parameters (PP): where each point of a path's SOM grid lies in each camera's image
of an adjusted pass, with its 1-sigma from the adjustment.

For every 1.1 km grid point of the chosen blocks (:class:`misrgraph.misr.som.SomGrid`) and every
camera (one band, red by default) the PP hold the image position of the point at ellipsoidal
height ``h`` as a quadratic in ``h``::

    line(h)   = line0   + dline_dh   * h + d2line_dh2   * h**2
    sample(h) = sample0 + dsample_dh * h + d2sample_dh2 * h**2

``line`` is the continuous image line at which the point crosses the band's array centre,
``(t* - t0) / dt_line`` (the exposure that images it is the nearest whole line), ``sample`` the
sample there; both come from the adjusted geometry (supplied navigation minus the estimated
attitude and ephemeris errors, camera corrected) by the same collinearity the adjustment used.
Keeping the height free makes the PP independent of any one DEM: a user evaluates them at the
height of the DEM posting of their choice. At 275 m, interpolate the six coefficient grids
bilinearly to the 275 m point and apply its own height (:meth:`ProjectionParameters.image_coords`);
the terrain parallax (up to ~3 pixels per km of height in the D cameras) is then exact to the
quadratic's error (< 0.005 pixel over 0..6 km, tested), the interpolation to the grid's
smoothness.

**Uncertainty.** The image position's error is linear in the navigation error at the crossing
time ``t*``: the attitude error (3 angles) and the position error (3 orbital axes), both linear
in the adjustment's variables (the Hermite knots through their weights at ``t*``, the eq. 19
segment parameters through its design), and in the camera corrections where the adjustment
estimated them. So ``Cov(line, sample) = J M Sigma M^T J^T`` with ``Sigma`` the joint posterior
covariance of knots, ephemeris and camera variables, ``M`` those linear maps and ``J`` the
derivative of the image position (central differences through the projection), plus the attitude
jitter the knots cannot follow (``unresolved_attitude_rad`` per angle). The covariance is
computed on a sub-grid (every ``sigma_step``-th point, 8.8 km at the default 8) and interpolated:
it varies over tens of kilometres. The horizontal 1-sigma in metres (``sigma_m``, the radial RMS
``sqrt(trace)`` of the ground covariance) maps it through the local ground-to-image derivative.
DEM error is not included: the PP are exact for whatever height they are evaluated at.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import distance_transform_edt

from factors.collinearity import camera_param_scale
from misrgraph.errors import InputError
from misrgraph.estimate.adjust import AdjustResult, corrected_geometry
from misrgraph.estimate.graph import calibrated_camera_sigma
from misrgraph.io.passes import OrbitPass
from misrgraph.io.products import PP_COEFFICIENTS, PP_SIGMAS, ProjectionParameters
from misrgraph.misr.som import N_BLOCKS, SomGrid
from misrgraph.model.constants import BANDS, CAMERAS, N_PIXELS
from misrgraph.model.frames import enu_basis, geodetic_to_ecef
from misrgraph.model.geolocation import PassGeometry

__all__ = ["PP_HEIGHTS_M", "compute_pp", "crossing", "image_derivatives", "ground_derivatives", "navigation_map_at"]

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

#: The PP are computed this many pixels beyond the array's edges (so that the height quadratic
#: holds where terrain parallax moves a point across the edge); :meth:`image_coords` and the
#: "seen" fractions apply the array's bounds to the final position.
EDGE_MARGIN_PX = 50.0
#: Ellipsoidal heights (m) at which the image position is computed to fit the height quadratic.
PP_HEIGHTS_M = (0.0, 3000.0, 6000.0)


# ---------------------------------------------------------------------------- projection
def crossing(
    geo: PassGeometry,
    cam: int,
    band: int,
    ground: Array,
    t_guess: Array,
    iterations: int = 6,
    tol_s: float = 1e-7,
    margin_px: float = 0.0,
) -> tuple[Array, Array, Array]:
    """Crossing time ``t*`` (s), continuous line and sample of ECEF ``ground`` (N, 3) in one
    camera/band, refined from ``t_guess`` (N,) by secant steps on the detector-x residual
    (``x(t) + k = 0``; smooth in ``t``, so a guess within a second converges in 3-4 steps).
    Points whose guess is NaN, that leave the pass span, or whose sample lies more than
    ``margin_px`` beyond the array's edges are NaN."""
    n = ground.shape[0]
    t = np.asarray(t_guess, dtype=float).copy()
    ok = np.isfinite(t)
    c = np.full(n, cam)
    b = np.full(n, band)
    k = geo.camera.k[cam, band]
    t_lo, t_hi = geo.ephemeris.span
    ok &= (t >= t_lo) & (t <= t_hi)
    idx = np.flatnonzero(ok)
    tt = t[idx]
    h_step = 1e-3
    for _ in range(iterations):
        f0 = geo._along_cross(c[idx], b[idx], ground[idx], tt)[0] + k
        f1 = geo._along_cross(c[idx], b[idx], ground[idx], np.clip(tt + h_step, t_lo, t_hi))[0] + k
        step = -f0 * h_step / (f1 - f0)
        tt = np.clip(tt + step, t_lo, t_hi)
        if np.all(np.abs(step) < tol_s):
            break
    t[:] = np.nan
    t[idx] = tt
    x, y, depth = geo._along_cross(c[idx], b[idx], ground[idx], tt)
    good = (np.abs(x + k) < geo.camera.dx * 1e-3) & (depth > 0)
    assert geo.t0 is not None
    line = np.full(n, np.nan)
    sample = np.full(n, np.nan)
    line[idx] = np.where(good, (tt - geo.t0[cam, band]) / geo.camera.line_time, np.nan)
    sample[idx] = np.where(good, geo.camera.sample_from_focal_plane_y(c[idx], b[idx], y), np.nan)
    t[idx] = np.where(good, tt, np.nan)
    bad = ~((sample >= -0.5 - margin_px) & (sample <= N_PIXELS - 0.5 + margin_px))
    return np.where(bad, np.nan, t), np.where(bad, np.nan, line), np.where(bad, np.nan, sample)


def _perturbed(
    geo: PassGeometry, d_att: Array | None = None, d_pos: Array | None = None, camera: Any = None
) -> PassGeometry:
    """``geo`` with a constant extra attitude (rad, roll/pitch/yaw) or orbital-frame position (m)
    correction, or another camera model."""
    att0, pos0 = geo.attitude_delta, geo.position_delta

    def att(t: Array) -> Array:
        base = np.zeros((np.size(t), 3)) if att0 is None else np.asarray(att0(t)).reshape(-1, 3)
        return base + (0.0 if d_att is None else d_att)

    def pos(t: Array) -> Array:
        base = np.zeros((np.size(t), 3)) if pos0 is None else np.asarray(pos0(t)).reshape(-1, 3)
        return base + (0.0 if d_pos is None else d_pos)

    return PassGeometry(
        geo.ephemeris,
        geo.attitude,
        geo.camera if camera is None else camera,
        earth=geo.earth,
        t0=geo.t0,
        attitude_delta=att,
        position_delta=pos,
    )


#: Central-difference steps: 1 arcsec of attitude, 1 m of position.
_D_ANGLE = np.pi / 180 / 3600
_D_POS = 1.0


def _central_differences(
    geo_at: Callable[[int, float], PassGeometry], n: int, step: float, cam: int, band: int, ground: Array, t_star: Array
) -> Array:
    """``d(line, sample) / d(parameter j)`` (N, 2, n) by central differences, where
    ``geo_at(j, +-step)`` is the geometry with parameter ``j`` moved by that much."""
    out = np.full((ground.shape[0], 2, n), np.nan)
    for j in range(n):
        plus, minus = (np.stack(crossing(geo_at(j, s), cam, band, ground, t_star)[1:], -1) for s in (step, -step))
        out[:, :, j] = (plus - minus) / (2 * step)
    return out


def _unit(j: int, value: float, n: int = 3) -> Array:
    v = np.zeros(n)
    v[j] = value
    return v


def image_derivatives(geo: PassGeometry, cam: int, band: int, ground: Array, t_star: Array) -> Array:
    """``d(line, sample) / d(roll, pitch, yaw, along, cross, radial)`` (N, 2, 6) in pixels per rad
    and per metre, by central differences through :func:`crossing` (constant perturbations: the
    crossing time moves by milliseconds, over which the navigation error is constant)."""
    att = _central_differences(lambda j, s: _perturbed(geo, d_att=_unit(j, s)), 3, _D_ANGLE, cam, band, ground, t_star)
    pos = _central_differences(lambda j, s: _perturbed(geo, d_pos=_unit(j, s)), 3, _D_POS, cam, band, ground, t_star)
    return np.concatenate([att, pos], axis=2)


def _camera_derivatives(
    geo: PassGeometry, cam: int, band: int, ground: Array, t_star: Array, params: tuple[str, ...]
) -> Array:
    """``d(line, sample) / d(camera correction)`` (N, 2, P) for camera ``cam``'s ``params``, per
    unit of the adjustment's variables (:data:`factors.collinearity.CAMERA_PARAM_SCALE`), by central
    differences of steps that move an image point by ~0.05 pixel."""
    step_si = calibrated_camera_sigma(geo.camera, cam, params, 0.05, 0.05)
    scale = camera_param_scale(params)
    out = np.empty((ground.shape[0], 2, len(params)))
    for j, p in enumerate(params):
        d = _central_differences(
            lambda _, s: _perturbed(geo, camera=geo.camera.corrected({cam: [s]}, (p,))),
            1,
            float(step_si[j]),
            cam,
            band,
            ground,
            t_star,
        )
        out[:, :, j] = d[:, :, 0] * scale[j]
    return out


def ground_derivatives(
    geo: PassGeometry, cam: int, band: int, ground: Array, enu: Array, t_guess: Array, step_m: float = 10.0
) -> Array:
    """``d(line, sample) / d(east, north)`` (N, 2, 2) in pixels per metre at ECEF ``ground`` (N, 3)
    with local ``enu`` bases (N, 3, 3), by central differences of ``step_m``; NaN where a displaced
    point leaves the view."""

    def image(q: int, sign: float) -> Array:
        return np.stack(crossing(geo, cam, band, ground + sign * step_m * enu[:, :, q], t_guess)[1:], -1)

    return np.stack([(image(q, 1.0) - image(q, -1.0)) / (2 * step_m) for q in range(2)], axis=2)


# ---------------------------------------------------------------------------- covariance
@dataclass
class _Posterior:
    """The joint posterior of the navigation (and camera) variables of an adjusted pass."""

    keys: list[int]
    cov: Array
    knot_slices: list[slice]  # per angle, into the state (value, rate) pairs knot-major
    eph_slice: slice
    camera_slices: dict[int, slice]  # camera index -> its corrections (in the order of camera_params)
    jitter_rad: float
    camera_params: tuple[str, ...] = ("delta", "beta", "epsilon")


def _posterior(res: AdjustResult) -> _Posterior:
    pg = res.pass_graph
    keys: list[int] = []
    knot_slices = []
    for a in range(3):
        kk = pg.knot_keys(a)
        knot_slices.append(slice(2 * len(keys), 2 * (len(keys) + len(kk))))
        keys.extend(kk)
    n = 2 * len(keys)
    ek = pg.ephemeris_keys()
    eph_slice = slice(n, n + 6 * len(ek))
    keys.extend(ek)
    n += 6 * len(ek)
    camera_slices: dict[int, slice] = {}
    dim = len(pg.camera_params)
    for code, key in sorted(pg.camera_keys.items()):
        if code >= 1000:
            log.warning("camera variable %d (a temperature bin's) is not propagated into the PP uncertainty", code)
            continue
        camera_slices[int(code)] = slice(n, n + dim)
        keys.append(key)
        n += dim
    cov = res.marginals.joint_of(keys)
    return _Posterior(
        keys,
        0.5 * (cov + cov.T),
        knot_slices,
        eph_slice,
        camera_slices,
        res.unresolved_attitude_rad,
        tuple(pg.camera_params),
    )


def navigation_map_at(res: AdjustResult, post: _Posterior, t: Array) -> Array:
    """Linear map ``M (N, 6, n)`` from the posterior state to the (attitude rad, position m) *error*
    at times ``t`` (the geometry's correction is its negative)."""
    m = np.zeros((t.size, 6, post.cov.shape[0]))
    rows = np.arange(t.size)
    for a in range(3):
        i, w = res.attitude.bracket(a, t)
        base = post.knot_slices[a].start
        for col in range(4):  # (a_i, a'_i, a_i+1, a'_i+1): knot i + col // 2, value/rate col % 2
            m[rows, a, base + 2 * (i + col // 2) + col % 2] = w[:, col]
    seg, d = res.ephemeris.design(t)
    for r in range(3):
        for p in range(6):
            m[rows, 3 + r, post.eph_slice.start + 6 * seg + p] = d[:, r, p]
    return m


# ---------------------------------------------------------------------------- the PP
def _fill_nearest(a: Array) -> Array:
    bad = ~np.isfinite(a)
    if not bad.any() or bad.all():
        return a
    idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
    return a[tuple(idx)]


def _upsample(sub: Array, sub_axes: tuple[Array, Array], shape: tuple[int, int], step: int = 1) -> Array:
    """Bilinear interpolation of a sub-grid field (NaN filled by the nearest value) to a grid of
    ``shape`` points every ``step`` grid points (1: the full grid)."""
    f = RegularGridInterpolator(sub_axes, _fill_nearest(sub), bounds_error=False, fill_value=None)
    ln, sm = np.meshgrid(
        np.arange(shape[0], dtype=float) * step, np.arange(shape[1], dtype=float) * step, indexing="ij"
    )
    return f(np.stack([ln, sm], -1))


def compute_pp(
    orbit_pass: OrbitPass,
    res: AdjustResult,
    path: int,
    blocks: NDArray[np.int64],
    band: str = "red",
    sigma_step: int = 8,
    progress: Callable[[str, int, int], None] | None = None,
    cameras: tuple[str, ...] = CAMERAS,
) -> ProjectionParameters:
    """The PP of an adjusted pass on ``path``'s 1.1 km grid over ``blocks`` (module docstring), for
    ``cameras`` (default all nine, in MISR's order).

    ``sigma_step`` (a divisor of 128) sets the sub-grid on which the height coefficients and the
    covariance are computed before bilinear interpolation."""
    if band not in BANDS:
        raise InputError("band", band, BANDS)
    if not cameras or any(c not in CAMERAS for c in cameras) or len(set(cameras)) != len(cameras):
        raise InputError("cameras", cameras, f"distinct names from {', '.join(CAMERAS)}")
    cameras = tuple(c for c in CAMERAS if c in cameras)
    blocks = np.asarray(blocks, dtype=np.int64).ravel()
    if blocks.size == 0 or np.any((blocks < 1) | (blocks > N_BLOCKS)):
        raise InputError("blocks", blocks.tolist(), f"block numbers in 1..{N_BLOCKS}")
    grid = SomGrid(path, 1100)
    if isinstance(sigma_step, bool) or not isinstance(sigma_step, int) or sigma_step < 1 or grid.nline % sigma_step:
        raise InputError("sigma_step", sigma_step, f"a positive divisor of {grid.nline}")
    geo = corrected_geometry(orbit_pass, res.attitude, res.ephemeris, res.camera)
    post = _posterior(res)
    bi = BANDS.index(band)
    nc, nb, nl, ns = len(cameras), blocks.size, grid.nline, grid.nsample
    out = {k: np.full((nc, nb, nl, ns), np.nan) for k in PP_COEFFICIENTS + PP_SIGMAS}
    sub_axes = (np.arange(0, nl, sigma_step, dtype=float), np.arange(0, ns, sigma_step, dtype=float))
    sub = (slice(None, None, sigma_step), slice(None, None, sigma_step))
    hh = np.asarray(PP_HEIGHTS_M)
    vand = np.stack([np.ones(3), hh, hh**2], 1)
    total, done = nb * nc, 0
    for j, block in enumerate(blocks):
        x, y = grid.block_centres(int(block))
        lat, lon = grid.somxy_to_latlon(x, y)
        lat_s, lon_s = lat[sub], lon[sub]
        shape_s = lat_s.shape
        g_heights = [geodetic_to_ecef(lat_s.ravel(), lon_s.ravel(), np.full(lat_s.size, h)) for h in PP_HEIGHTS_M]
        g_full = geodetic_to_ecef(lat.ravel(), lon.ravel(), np.zeros(lat.size))
        enu = enu_basis(lat_s.ravel(), lon_s.ravel())
        for jc, name in enumerate(cameras):
            c = CAMERAS.index(name)  # the geometry's camera index; jc indexes the PP's arrays
            if progress:
                progress(f"PP block {block} {name}", done, total)
            done += 1
            # the sub-grid by the general line search, then every point by secant steps from it
            ip = geo.ground_to_pixel(c, bi, g_heights[0])
            t_s = geo.t0[c, bi] + ip.crossing_line * geo.camera.line_time
            # ground_to_pixel stops at the array's edge; carry the sub-grid a margin beyond it
            t_s = (
                _upsample(t_s.reshape(shape_s), sub_axes, shape_s, step=sigma_step).ravel()
                if np.isnan(t_s).any()
                else t_s
            )
            t_s, l_sub, s_sub = crossing(geo, c, bi, g_heights[0], t_s, margin_px=2 * EDGE_MARGIN_PX)
            if not np.isfinite(t_s).any():
                continue
            t_full_guess = _upsample(t_s.reshape(shape_s), sub_axes, (nl, ns)).ravel()
            _, ln0, sm0 = crossing(geo, c, bi, g_full, t_full_guess, margin_px=EDGE_MARGIN_PX)
            out["line0"][jc, j] = ln0.reshape(nl, ns)
            out["sample0"][jc, j] = sm0.reshape(nl, ns)
            # height quadratic on the sub-grid (height 0 is the crossing just computed)
            ls = [(l_sub, s_sub)] + [
                crossing(geo, c, bi, gh, t_s, margin_px=2 * EDGE_MARGIN_PX)[1:] for gh in g_heights[1:]
            ]
            for which, names in (
                (0, ("line0", "dline_dh", "d2line_dh2")),
                (1, ("sample0", "dsample_dh", "d2sample_dh2")),
            ):
                coef = np.linalg.solve(vand, np.stack([ls[k][which] for k in range(3)], 0))  # (3, n_sub)
                for q in (1, 2):
                    out[names[q]][jc, j] = _upsample(coef[q].reshape(shape_s), sub_axes, (nl, ns))
            # covariance on the sub-grid: the geometry removes the estimated errors (correction =
            # -error), so d(image)/d(knots, segments) is -J M while camera corrections enter with
            # their own sign (their cross-covariance with the navigation makes the sign matter)
            okp = np.isfinite(t_s)
            g0, t0 = g_heights[0][okp], t_s[okp]
            jac = image_derivatives(geo, c, bi, g0, t0)  # (n, 2, 6)
            full_j = -np.einsum("nij,njk->nik", jac, navigation_map_at(res, post, t0))
            if c in post.camera_slices:
                full_j[:, :, post.camera_slices[c]] += _camera_derivatives(geo, c, bi, g0, t0, post.camera_params)
            cov_ls = np.einsum("nij,jk,nlk->nil", full_j, post.cov, full_j) + post.jitter_rad**2 * np.einsum(
                "nij,nlj->nil", jac[:, :, :3], jac[:, :, :3]
            )
            # ground (east, north) per (line, sample): invert d(line, sample)/d(east, north)
            d_en = ground_derivatives(geo, c, bi, g0, enu[okp], t0)
            en_ok = np.isfinite(d_en).all(axis=(1, 2))  # a displaced point can leave the margin
            inv = np.linalg.inv(np.where(en_ok[:, None, None], d_en, np.eye(2)))
            cov_en = np.einsum("nij,njk,nlk->nil", inv, cov_ls, inv)
            fields = {
                "sigma_line": np.sqrt(cov_ls[:, 0, 0]),
                "sigma_sample": np.sqrt(cov_ls[:, 1, 1]),
                "correlation": cov_ls[:, 0, 1] / np.sqrt(cov_ls[:, 0, 0] * cov_ls[:, 1, 1]),
                "sigma_m": np.where(en_ok, np.sqrt(cov_en[:, 0, 0] + cov_en[:, 1, 1]), np.nan),
            }
            for name, v in fields.items():
                sub_field = np.full(t_s.size, np.nan)
                sub_field[okp] = v
                out[name][jc, j] = _upsample(sub_field.reshape(shape_s), sub_axes, (nl, ns))
            unseen = ~np.isfinite(out["line0"][jc, j])
            for name in out:
                out[name][jc, j][unseen] = np.nan
    if progress:
        progress("PP", total, total)
    return ProjectionParameters(
        path=int(path),
        blocks=blocks,
        cameras=cameras,
        band=band,
        pass_id=orbit_pass.pass_id,
        **{k: out[k] for k in out},
    )
