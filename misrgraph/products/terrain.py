"""Terrain obscuration: the SOM grid points a camera cannot see because terrain nearer the camera
stands in the line of sight.

A point of the 275 m grid at height ``h0`` lies, by the Projection Parameters, at image position
``p(x, h0)`` (``x`` its grid line/sample). The ray that images it rises towards the camera; the
points of that ray at height ``h0 + dh`` lie over grid position ``x + v dh`` with

    v = -J^-1 dp/dh     (275 m grid pixels per metre of height, shape (2,))

where ``J = dp/dx`` (image pixels per grid pixel) and ``dp/dh`` come from the PP's coefficient
grids (:class:`misrgraph.io.products.ProjectionParameters`). Seen from above, the ray leaves the
point along ``u = v / |v|`` and climbs ``1 / |v|`` metres per grid pixel: ``1 / |v|`` is
``275 m / tan(view zenith)``, 97 m in the D cameras, 560 m in Af/Aa. The point is **obscured**
where the DEM rises above the ray somewhere along it::

    obscured(x)  <=>  exists k in 1..K:  H(x + k u) > h0 + k / |v|

with ``H`` the SOM DEM interpolated bilinearly (the neighbouring blocks' heights where the ray
leaves the block) and the march stopping once the ray is above the highest height within reach.
Such a point is imaged at the position of the terrain that hides it: resampled into the ROI
it shows the wrong ground (12-17 pixels off in the D cameras over 1.5 km of relief), so the ROI
leaves it out (:mod:`misrgraph.products.roi`).

The march samples the ray every grid pixel, so a ridge narrower than a posting can slip between
samples; the DEM itself holds nothing narrower. The direction ``v`` is the PP's (the adjusted
geometry's), evaluated on the 1.1 km grid and interpolated: it varies over tens of kilometres.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from misrgraph.errors import InputError
from misrgraph.io.dem import SomDem
from misrgraph.io.products import ProjectionParameters

__all__ = ["view_directions", "march_obscured", "terrain_obscured", "OBSCURATION_MARGIN_PX"]

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

#: How far (275 m pixels) the march follows a ray beyond its block: 64 pixels (17.6 km) is 6.2 km
#: of climb in the D cameras, more than any relief on Earth.
OBSCURATION_MARGIN_PX = 64


def view_directions(pp: ProjectionParameters, camera: str, block: int, heights: NDArray[np.float32]) -> Array:
    """``v (2, nline, nsample)``: for each point of ``block``'s 275 m grid, the horizontal
    displacement (275 m grid lines, samples) per metre of height along the ray that images it in
    ``camera`` (module docstring), NaN where the PP do not reach. ``heights (nline, nsample)``
    (m, ellipsoidal) are the points' heights (NaN counts as 0)."""
    if camera not in pp.cameras:
        raise InputError("camera", camera, pp.cameras)
    hit = np.flatnonzero(pp.blocks == int(block))
    if hit.size == 0:
        raise InputError("block", block, f"one of the PP's blocks {pp.blocks.min()}..{pp.blocks.max()}")
    c, b = pp.cameras.index(camera), int(hit[0])
    scale = pp.resolution_m // 275  # 275 m pixels per PP grid pixel (4)
    nl, ns = pp.line0.shape[2:]
    h = np.asarray(heights, dtype=np.float64)
    if h.shape != (nl * scale, ns * scale):
        raise InputError("heights", h.shape, f"the block's 275 m grid {(nl * scale, ns * scale)}")
    h_pp = np.nan_to_num(h.reshape(nl, scale, ns, scale).mean(axis=(1, 3)), nan=0.0)
    # J: image pixels per 275 m grid pixel, from the height-0 grids (the height's effect on J is
    # second order)
    j_ll, j_ls = (g / scale for g in np.gradient(pp.line0[c, b]))
    j_sl, j_ss = (g / scale for g in np.gradient(pp.sample0[c, b]))
    d_l = pp.dline_dh[c, b] + 2.0 * pp.d2line_dh2[c, b] * h_pp
    d_s = pp.dsample_dh[c, b] + 2.0 * pp.d2sample_dh2[c, b] * h_pp
    det = j_ll * j_ss - j_ls * j_sl
    with np.errstate(divide="ignore", invalid="ignore"):
        v_l = -(j_ss * d_l - j_ls * d_s) / det
        v_s = -(-j_sl * d_l + j_ll * d_s) / det
    # to the 275 m points: the PP point (i, j) is at 275 m position scale * i + (scale - 1) / 2
    li = (np.arange(nl * scale) - (scale - 1) / 2.0) / scale
    si = (np.arange(ns * scale) - (scale - 1) / 2.0) / scale
    coords = np.meshgrid(np.clip(li, 0, nl - 1), np.clip(si, 0, ns - 1), indexing="ij")
    return np.stack([ndimage.map_coordinates(v, coords, order=1, mode="nearest", prefilter=False) for v in (v_l, v_s)])


def march_obscured(
    h_ext: NDArray[np.float32], margin: int, v: Array, max_steps: int | None = None
) -> NDArray[np.bool_]:
    """Which points of a block are obscured (module docstring): ``h_ext (nline + 2 margin,
    nsample + 2 margin)`` heights (m; the block at rows/columns ``margin..``, its surroundings
    around it, NaN unknown: never obscuring) and ``v (2, nline, nsample)`` the rays' horizontal
    displacement per metre (grid pixels/m; NaN: not imaged, never obscured). The march takes at
    most ``max_steps`` (default ``margin``) one-pixel steps. Returns ``(nline, nsample)`` bool."""
    if v.ndim != 3 or v.shape[0] != 2 or h_ext.shape != (v.shape[1] + 2 * margin, v.shape[2] + 2 * margin):
        raise InputError(
            "v, h_ext", (v.shape, h_ext.shape), "(2, nline, nsample) and (nline + 2 margin, nsample + 2 margin)"
        )
    nl, ns = v.shape[1:]
    steps = int(margin if max_steps is None else min(max_steps, margin))
    hz = np.where(np.isfinite(h_ext), h_ext, -np.inf).astype(np.float64)
    h0 = hz[margin : margin + nl, margin : margin + ns]
    speed = np.hypot(v[0], v[1])  # grid pixels per metre of climb
    out = np.zeros((nl, ns), bool)
    if steps == 0:
        return out
    # the highest terrain within reach of each point bounds the climb worth following
    reach = ndimage.maximum_filter(hz, size=2 * steps + 1, mode="constant", cval=-np.inf)[
        margin : margin + nl, margin : margin + ns
    ]
    with np.errstate(invalid="ignore"):
        active = np.isfinite(h0) & (speed > 0) & np.isfinite(speed) & (reach > h0 + 1.0 / speed)
    idx = np.flatnonzero(active)
    if idx.size == 0:
        return out
    r0, c0 = np.divmod(idx, ns)
    sp = speed.ravel()[idx]
    ul, us = v[0].ravel()[idx] / sp, v[1].ravel()[idx] / sp
    base, top = h0.ravel()[idx], reach.ravel()[idx]
    hz_nan = np.where(np.isfinite(hz), hz, np.nan)  # map_coordinates: a NaN corner makes the sample NaN
    for k in range(1, steps + 1):
        ray = base + k / sp
        keep = ray < top  # above everything within reach: it can no longer be hidden
        if not keep.any():
            break
        if not keep.all():
            r0, c0, sp, ul, us, base, top, idx, ray = (a[keep] for a in (r0, c0, sp, ul, us, base, top, idx, ray))
        terrain = ndimage.map_coordinates(
            hz_nan, [r0 + margin + k * ul, c0 + margin + k * us], order=1, mode="constant", cval=np.nan, prefilter=False
        )
        hidden = terrain > ray  # NaN: unknown, not hidden
        if hidden.any():
            out.ravel()[idx[hidden]] = True
            live = ~hidden
            r0, c0, sp, ul, us, base, top, idx = (a[live] for a in (r0, c0, sp, ul, us, base, top, idx))
            if idx.size == 0:
                break
    return out


def terrain_obscured(
    pp: ProjectionParameters, camera: str, dem: SomDem, block: int, margin: int = OBSCURATION_MARGIN_PX
) -> NDArray[np.bool_]:
    """``(nline, nsample)`` bool: the points of ``block``'s 275 m grid that terrain hides from
    ``camera`` in the pass of ``pp``, by the heights of ``dem`` (module docstring)."""
    if dem.resolution_m != 275:
        raise InputError("dem.resolution_m", dem.resolution_m, 275)
    if int(dem.path) != int(pp.path):
        raise InputError("dem.path", int(dem.path), f"the PP's path {int(pp.path)}")
    h_ext = dem.extended_block(int(block), margin)
    heights = h_ext[margin : -margin or None, margin : -margin or None]
    v = view_directions(pp, camera, int(block), heights)
    out = march_obscured(h_ext, margin, v)
    log.debug("block %d %s: %.4f of the grid obscured", block, camera, float(out.mean()))
    return out
