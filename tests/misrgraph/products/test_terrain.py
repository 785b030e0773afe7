"""Terrain obscuration: the march against closed-form walls, the neighbouring blocks' placement
against the SOM grid, the view direction against the PP's own mapping, and the mask against rays
cast through the true geometry onto a ridge."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.evaluate.products import truth_hidden
from misrgraph.io.dem import SomDem
from misrgraph.misr.som import BLOCK1_CORNER_SOM, SomGrid
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.frames import geodetic_to_ecef
from misrgraph.products.terrain import march_obscured, terrain_obscured, view_directions

BLOCK = 57  # the pp fixture's block (conftest.py)
RISE_M = 97.0  # metres the ray climbs per grid pixel (a D camera: 275 m / tan 70.5 deg)


def _wall_scene(direction: tuple[float, float], nl: int = 40, ns: int = 30, margin: int = 12):
    """Flat ground at 0 with a 3-pixel wall of 500 m across lines 20-22, rays climbing RISE_M per
    pixel along ``direction`` (unit, grid lines/samples)."""
    h = np.zeros((nl + 2 * margin, ns + 2 * margin), np.float32)
    h[margin + 20 : margin + 23, :] = 500.0
    v = np.empty((2, nl, ns))
    v[0], v[1] = direction[0] / RISE_M, direction[1] / RISE_M
    return h, v, margin


def test_march_against_a_wall() -> None:
    """Rays towards +line from line l reach the wall's face (line 20) at k = 20 - l pixels, 97 m
    per pixel up: the 500 m wall hides lines 15..19 (485 m at k = 5 < 500 m) and nothing else --
    not the wall, not the ground behind it (those rays climb away from it)."""
    h, v, m = _wall_scene((1.0, 0.0))
    hidden = march_obscured(h, m, v)
    lines = np.flatnonzero(hidden.any(axis=1))
    assert lines.tolist() == [15, 16, 17, 18, 19]
    assert hidden[15:20].all()
    # rays the other way (towards -line) are hidden behind it: lines 23..27
    hidden = march_obscured(h, m, -v)
    assert np.flatnonzero(hidden.any(axis=1)).tolist() == [23, 24, 25, 26, 27]
    # rays along the wall (towards +sample) never meet it; a ray twice as steep (194 m per
    # pixel) is hidden over the last two pixels only (388 m at k = 2, 582 m at k = 3)
    assert not march_obscured(h, m, v[::-1]).any()
    assert np.flatnonzero(march_obscured(h, m, 0.5 * v).any(axis=1)).tolist() == [18, 19]


def test_march_unknowns_hide_nothing() -> None:
    h, v, m = _wall_scene((1.0, 0.0))
    v[:, 17] = np.nan  # not imaged
    h2 = h.copy()
    h2[m + 20 : m + 23, m : m + 10] = np.nan  # no DEM there (block samples 0..9)
    hidden = march_obscured(h2, m, v)
    assert not hidden[17].any() and not hidden[:, :10].any()
    assert hidden[[15, 16, 18, 19], 10:].all()
    with pytest.raises(InputError, match="v, h_ext"):
        march_obscured(h[1:], m, v)


def test_extended_block_places_the_neighbours_by_the_som_grid() -> None:
    """Heights that are a function of SOM (x, y): every value of the extended block equals the
    function at the SOM position of its row/column counted from the block's corner, across the
    block edges where the neighbours' offsets differ (blocks 56/57/58 of path 37: 64 pixels)."""
    grid = SomGrid(37, 275)
    blocks = np.array([56, 57, 58])
    r = 275.0

    def field(x, y):
        return ((x - BLOCK1_CORNER_SOM[0]) * 1e-3 + (y - BLOCK1_CORNER_SOM[1]) * 1e-5).astype(np.float32)

    heights = np.stack([field(*grid.block_centres(int(b))) for b in blocks])
    dem = SomDem(37, 275, blocks, heights, 10.0)
    m = 40
    ext = dem.extended_block(57, m)
    rows, cols = np.meshgrid(np.arange(ext.shape[0]), np.arange(ext.shape[1]), indexing="ij")
    x = BLOCK1_CORNER_SOM[0] + r / 2 + ((57 - 1) * grid.nline + rows - m) * r
    y = BLOCK1_CORNER_SOM[1] + r / 2 + (cols - m + grid.block_offsets[56]) * r
    ok = np.isfinite(ext)
    np.testing.assert_allclose(ext[ok], field(x, y)[ok], rtol=1e-6)
    # block 56 lies 64 samples to the right: its rows hold data from column m + 64 on
    assert np.isnan(ext[0, : m + 64]).all() and np.isfinite(ext[0, m + 64 :]).all()
    assert ok[m:-m, m:-m].all() and not ok[m:-m, :m].any()
    # without the neighbours the margin is unknown
    alone = SomDem(37, 275, blocks[1:2], heights[1:2], 10.0).extended_block(57, m)
    assert np.isnan(alone[:m]).all() and np.isnan(alone[-m:]).all()
    with pytest.raises(InputError, match="margin"):
        dem.extended_block(57, grid.nline + 1)


@pytest.mark.parametrize("cam", ["Df", "Ca", "An"])
def test_view_direction_follows_the_ray_in_the_pp(pp, cam) -> None:
    """Raising a point by dh and moving it by v dh keeps its image position (the PP's own
    height quadratic and 275 m interpolation, not the gradients v is made of), to what the
    neighbouring grid's curvature allows over the 2-3 pixel move (0.02 pixel)."""
    grid = SomGrid(37, 275)
    h = np.full((grid.nline, grid.nsample), 300.0, np.float32)
    v = view_directions(pp, cam, BLOCK, h)
    rng = np.random.default_rng(3)
    ln, sm = rng.uniform(40, 470, 400), rng.uniform(40, 2000, 400)
    vi = v[:, ln.round().astype(int), sm.round().astype(int)]
    l0, s0 = pp.image_coords(cam, BLOCK, ln, sm, np.full(400, 300.0), resolution_m=275)
    dh = 250.0
    l1, s1 = pp.image_coords(cam, BLOCK, ln + vi[0] * dh, sm + vi[1] * dh, np.full(400, 300.0 + dh), resolution_m=275)
    ok = np.isfinite(l0) & np.isfinite(l1) & np.isfinite(vi).all(0)
    assert ok.sum() > 200
    d = np.hypot(l1 - l0, s1 - s0)[ok]
    assert np.max(d) < 0.02, np.max(d)
    # the climb per pixel is 275 m / tan(view zenith): ~97 m in Df, beyond 1 km near nadir
    rise = 1.0 / np.hypot(*vi[:, ok])
    if cam == "Df":
        assert 80 < np.median(rise) < 110
    if cam == "An":
        assert np.median(rise) > 1000


def test_mask_against_rays_cast_through_the_true_geometry(adjusted, pp) -> None:
    """A 2 km ridge (Gaussian across the track, 1.5 km wide: back slopes up to 39 deg) on block
    57, the SOM DEM sampled from it exactly. The mask (PP directions, 275 m DEM, bilinear) and
    rays cast through the *true* geometry onto the continuous ridge (:func:`truth_hidden`) agree
    on which columns of points are hidden to within one pixel at each end of the hidden run. The
    D and C cameras see past 19.5 and 30 deg of elevation, so the ridge hides ground from them;
    the B, A and An cameras look more steeply than its slopes and see everything."""
    from misrgraph.io.truth import read_pass_truth

    sc, op, _, _ = adjusted
    geo = read_pass_truth(sc.pass_files[0]).geometry(op)
    grid = SomGrid(37, 275)
    x0 = grid.bls_to_somxy(BLOCK, 256, 1024)[0]

    def ridge_xy(x, y):
        return 2000.0 * np.exp(-0.5 * ((np.asarray(x) - x0) / 1500.0) ** 2)

    def surface(lat, lon):
        x, _ = grid.latlon_to_somxy(lat, lon)
        return ridge_xy(x, None)

    dem = SomDem(37, 275, np.array([BLOCK]), ridge_xy(*grid.block_centres(BLOCK)).astype(np.float32)[None], 0.0)
    columns = np.array([700, 1000, 1300])
    lines = np.arange(200, 313)
    li, si = np.meshgrid(lines, columns, indexing="ij")
    lat, lon = grid.bls_to_latlon(np.full(li.size, BLOCK), li.ravel(), si.ravel())
    ground = geodetic_to_ecef(lat, lon, surface(lat, lon))
    red = BANDS.index("red")
    for cam in ("Df", "Ca", "Bf", "Aa", "An"):
        mask = terrain_obscured(pp, cam, dem, BLOCK)[li, si]
        truth = truth_hidden(geo, CAMERAS.index(cam), red, ground, surface).reshape(li.shape)
        if cam in ("Df", "Ca"):
            assert truth.sum() >= 3 * columns.size, (cam, int(truth.sum()))
        else:
            assert not truth.any() and not mask.any(), cam
        for j in range(columns.size):
            t, mk = np.flatnonzero(truth[:, j]), np.flatnonzero(mask[:, j])
            assert (t.size == 0) == (mk.size == 0), (cam, columns[j])
            if t.size:  # one run of hidden lines, the same to a pixel at each end
                assert mk.size == mk[-1] - mk[0] + 1 and t.size == t[-1] - t[0] + 1, (cam, t, mk)
                assert abs(int(mk[0]) - int(t[0])) <= 1 and abs(int(mk[-1]) - int(t[-1])) <= 1, (cam, columns[j], t, mk)


def test_terrain_obscured_refuses_a_foreign_dem(pp) -> None:
    grid = SomGrid(38, 275)
    dem = SomDem(38, 275, np.array([BLOCK]), np.zeros((1, grid.nline, grid.nsample), np.float32), 10.0)
    with pytest.raises(InputError, match="dem.path"):
        terrain_obscured(pp, "Df", dem, BLOCK)
