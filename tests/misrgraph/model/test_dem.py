from __future__ import annotations

import numpy as np
import pytest

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.dem import read_dem, save_dem
from misrgraph.model.dem import (
    FLAG_BOUNDARY,
    FLAG_LAND,
    FLAG_WATER,
    POSTING_DEG,
    DemTiles,
    Geoid,
    fit_grid_surface,
    fit_local_surface,
)
from misrgraph.sim.terrain import SyntheticTerrain, simulate_dem_tiles


def _grid(fun, n=20):
    r, c = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    return fun(r, c)


@pytest.mark.parametrize(
    "method, fun, dfun",
    [
        ("bilinear", lambda r, c: 3 + 2 * r - c + 0.5 * r * c, lambda r, c: (2 + 0.5 * c, -1 + 0.5 * r)),
        ("biquadratic", lambda r, c: 1 + r * r - 0.3 * c * c + r * c, lambda r, c: (2 * r + c, -0.6 * c + r)),
        # cubic convolution (Keys, a = -0.5) is exact up to degree 2
        (
            "bicubic",
            lambda r, c: 2 + 0.3 * r * r - 0.2 * c * c + r * c - c,
            lambda r, c: (0.6 * r + c, -0.4 * c + r - 1),
        ),
    ],
)
def test_fits_reproduce_their_polynomial_class(method, fun, dfun, rng):
    z = _grid(fun)
    r = rng.uniform(3, 16, 30)
    c = rng.uniform(3, 16, 30)
    h, dr, dc, rms = fit_grid_surface(z, r, c, method)
    np.testing.assert_allclose(h, fun(r, c), atol=1e-8)
    er, ec = dfun(r, c)
    np.testing.assert_allclose(dr, er, atol=1e-7)
    np.testing.assert_allclose(dc, ec, atol=1e-7)
    if method == "biquadratic":
        assert np.all(rms < 1e-8)


def test_gradient_matches_numerical_derivative(rng):
    z = _grid(lambda r, c: 100 * np.sin(r / 3) * np.cos(c / 4))
    r, c = rng.uniform(4, 15, 10), rng.uniform(4, 15, 10)
    for method in ("bilinear", "biquadratic", "bicubic"):
        h, dr, dc, _ = fit_grid_surface(z, r, c, method)
        eps = 1e-5
        hr = fit_grid_surface(z, r + eps, c, method)[0]
        hc = fit_grid_surface(z, r, c + eps, method)[0]
        # bilinear/biquadratic windows may switch at integer positions; ours are random reals
        np.testing.assert_allclose(dr, (hr - h) / eps, atol=1e-3)
        np.testing.assert_allclose(dc, (hc - h) / eps, atol=1e-3)


def test_bicubic_is_continuous_across_postings():
    z = _grid(lambda r, c: 100 * np.sin(r / 2.3) * np.cos(c / 3.1) + 7 * r)
    for x in (5.0, 8.0, 11.0):
        eps = 1e-9
        a = fit_grid_surface(z, np.array([x - eps, 6.3]), np.array([6.3, x - eps]), "bicubic")
        b = fit_grid_surface(z, np.array([x + eps, 6.3]), np.array([6.3, x + eps]), "bicubic")
        np.testing.assert_allclose(a[0], b[0], atol=1e-6)  # value
        np.testing.assert_allclose(a[1], b[1], atol=1e-6)  # gradient (C1)
        np.testing.assert_allclose(a[2], b[2], atol=1e-6)


def test_real_terrain_held_out_postings():
    """Jacksboro fault DEM (matplotlib sample data, real 3-arcsec postings in Tennessee): fit on
    every second posting, predict the postings in between. Errors are small compared with the
    terrain's variation between neighbouring postings, the bicubic beats the bilinear, and the
    reported interpolation sigma (lower-order residual RMS) is conservative but of the same order
    as the true error."""
    import matplotlib.cbook as cbook

    z = np.asarray(np.load(cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False))["elevation"], dtype=float)
    coarse = z[::2, ::2]
    rr, cc = np.meshgrid(np.arange(3, coarse.shape[0] - 4), np.arange(3, coarse.shape[1] - 4), indexing="ij")
    r = rr.ravel() + 0.5
    c = cc.ravel() + 0.5
    truth = z[2 * rr.ravel() + 1, 2 * cc.ravel() + 1]
    neighbour_step = np.sqrt(np.mean(np.diff(coarse, axis=0) ** 2))
    errs = {}
    for method in ("bilinear", "biquadratic", "bicubic"):
        h, _, _, rms = fit_grid_surface(coarse, r, c, method)
        errs[method] = np.sqrt(np.mean((h - truth) ** 2))
        assert errs[method] < 0.5 * neighbour_step
        assert 0.3 < errs[method] / np.sqrt(np.mean(rms**2)) < 1.2
    assert errs["bicubic"] < errs["bilinear"]


def test_tiles_surface_and_sigma(rng):
    terrain = SyntheticTerrain(seed=1)
    lat, lon = np.array([40.0, -20.0]), np.array([-105.0, 25.0])
    dem = simulate_dem_tiles(lat, lon, terrain, rng, size=32)
    assert set(np.unique(dem.flags)) <= {FLAG_LAND, FLAG_WATER, FLAG_BOUNDARY}
    s = fit_local_surface(dem, lat + 1e-4, lon - 2e-4)
    assert s.valid.all()
    assert np.all(s.sigma >= 30.0)
    true = terrain.height(lat + 1e-4, lon - 2e-4)
    # error = tile bias (sigma from quality) + small noise: within 5 sigma
    assert np.all(np.abs(s.height - true) < 5 * s.sigma)
    # the stated sigma alone: the quality class's, within the combined sigma
    assert np.all(s.stated <= s.sigma) and np.all(s.stated >= 30.0)
    out = fit_local_surface(dem, np.array([0.0]), np.array([0.0]))
    assert not out.valid[0] and np.isnan(out.height[0]) and np.isnan(out.stated[0])


def test_dem_error_statistics_match_quality_sigma():
    rng = np.random.default_rng(7)
    terrain = SyntheticTerrain(seed=2)
    n = 400
    lat = rng.uniform(30, 45, n)
    lon = rng.uniform(-110, -90, n)
    dem = simulate_dem_tiles(lat, lon, terrain, rng, size=8)
    # one sample per point (the points are ~100 km apart, far beyond the error's ~5 km correlation):
    # the posting nearest to each point, in the tile that covers it
    t = dem.tile_of(lat, lon)
    assert np.all(t >= 0)
    r = np.rint((lat - dem.lat0[t]) / POSTING_DEG).astype(int)
    c = np.rint((lon - dem.lon0[t]) / POSTING_DEG).astype(int)
    true = terrain.height(dem.lat0[t] + r * POSTING_DEG, dem.lon0[t] + c * POSTING_DEG)
    err = dem.heights[t, r, c] - true
    quality = dem.quality[t]
    for q, sig in ((1, 30.0), (2, 60.0)):
        e = err[quality == q] / (sig * np.sqrt(1.01))
        k = e.size
        # chi-square of the normalised errors within 4 standard deviations of its mean
        assert abs(np.sum(e**2) - k) < 4 * np.sqrt(2 * k)
    # quality is drawn per 1-degree cell: the fraction over the distinct cells the points fall in
    cells = np.unique(np.stack([np.floor(lat), np.floor(lon)], -1), axis=0, return_index=True)[1]
    k = cells.size
    assert abs(np.mean(quality[cells] == 1) - 0.6) < 4 * np.sqrt(0.24 / k)


def test_dem_save_load(tmp_path, rng):
    dem = simulate_dem_tiles([10.0], [20.0], SyntheticTerrain(), rng, size=8)
    save_dem(dem, tmp_path / "d.h5")
    back = read_dem(tmp_path / "d.h5")
    np.testing.assert_allclose(back.heights, dem.heights, atol=1e-3)  # stored as float32
    np.testing.assert_array_equal(back.flags, dem.flags)
    with pytest.raises(FileFormatError):
        read_dem(tmp_path / "missing.h5")


def test_geoid_options():
    assert Geoid("zero").undulation(10.0, 20.0) == 0.0
    assert Geoid("constant", value=-30.0).undulation(np.zeros(3), np.zeros(3)).tolist() == [-30.0] * 3
    with pytest.raises(InputError, match="geoid"):
        Geoid("egm2008")
    with pytest.raises(InputError, match="geoid.function"):
        Geoid("function")


def test_synthetic_terrain_is_realistic():
    t = SyntheticTerrain(seed=3)
    lat, lon = np.meshgrid(np.linspace(38, 39, 200), np.linspace(-106, -105, 200), indexing="ij")
    h = t.relief(lat, lon)
    assert 300 < np.ptp(h) < 5000
    slope = np.degrees(np.arctan(np.hypot(*np.gradient(h, 556.0))))
    assert 1.0 < np.percentile(slope, 95) < 35.0


def test_tiles_are_one_continuous_dem(rng):
    """Repeat features share a tile; overlapping tiles agree; the surface has no jump where the
    chosen tile changes (a DEM that depended on the tile picked would be discontinuous)."""
    terrain = SyntheticTerrain(seed=3)
    p = POSTING_DEG
    # the tile grid steps every 32 - 2 * 3 - 1 = 25 postings: features 0 and 2 lie in adjacent
    # tiles of one column, 10 postings apart; feature 1 repeats feature 0 (a repeat pass)
    lat = np.array([48024.3, 48024.3, 48034.6, 48110.0]) * p
    lon = np.array([-125989.6, -125989.6, -125989.6, -125950.0]) * p
    dem = simulate_dem_tiles(lat, lon, terrain, rng, size=32)
    origins = np.stack([dem.lat0, dem.lon0], -1)
    assert len(np.unique(origins, axis=0)) == len(origins)  # the repeated feature has one tile
    # overlapping tiles hold the same heights at their shared postings
    shared = 0
    for a in range(len(origins)):
        for b in range(a + 1, len(origins)):
            di = int(round((dem.lat0[b] - dem.lat0[a]) / p))
            dj = int(round((dem.lon0[b] - dem.lon0[a]) / p))
            ra, ca = slice(max(di, 0), 32 + min(di, 0)), slice(max(dj, 0), 32 + min(dj, 0))
            rb, cb = slice(max(-di, 0), 32 + min(-di, 0)), slice(max(-dj, 0), 32 + min(-dj, 0))
            if dem.heights[a][ra, ca].size:
                shared += dem.heights[a][ra, ca].size
                np.testing.assert_array_equal(dem.heights[a][ra, ca], dem.heights[b][rb, cb])
    assert shared > 0
    # walk across the tiles in 1 cm steps: no jump beyond slope x step
    t = np.linspace(0.0, 1.0, 20001)
    la = lat[0] + t * (lat[2] - lat[0])
    lo = lon[0] + t * (lon[2] - lon[0])
    s = fit_local_surface(dem, la, lo)
    tiles = dem.tile_of(la, lo)
    assert s.valid.all()
    pair = np.ones(t.size - 1, bool)
    assert np.sum(tiles[:-1] != tiles[1:]) >= 1  # the walk does change tiles
    step_m = np.hypot(np.diff(la) * 111e3, np.diff(lo) * 111e3 * np.cos(np.radians(40.0)))
    slope = np.hypot(s.dh_dlat / 111e3, s.dh_dlon / (111e3 * np.cos(np.radians(40.0))))
    jump = np.abs(np.diff(s.height))[pair]
    assert np.all(jump <= 2 * slope[:-1][pair] * step_m[pair] + 1e-6)


def test_tile_hint_reads_the_same_dem(rng):
    terrain = SyntheticTerrain(seed=4)
    lat = rng.uniform(40.0, 40.5, 60)
    lon = rng.uniform(-105.5, -105.0, 60)
    dem = simulate_dem_tiles(lat, lon, terrain, rng, size=32)
    first = fit_local_surface(dem, lat, lon)
    # the points move by up to ~10 postings: some hinted tiles still hold them, some not
    la2 = lat + rng.normal(0, 5 * POSTING_DEG, 60)
    lo2 = lon + rng.normal(0, 5 * POSTING_DEG, 60)
    hinted = fit_local_surface(dem, la2, lo2, hint=first.tile)
    fresh = fit_local_surface(dem, la2, lo2)
    np.testing.assert_array_equal(hinted.valid, fresh.valid)
    v = fresh.valid
    assert v.sum() > 40
    np.testing.assert_allclose(hinted.height[v], fresh.height[v], rtol=0, atol=1e-9)
    np.testing.assert_allclose(hinted.dh_dlat[v], fresh.dh_dlat[v], rtol=1e-12, atol=1e-9)


def test_dted_longitude_spacing_by_zone():
    from misrgraph.model.dem import dted_lon_posting_deg

    lat = np.array([0.0, 49.9, 50.0, 69.9, 70.0, 74.9, 75.0, 79.9, 80.0, 89.0, -55.0])
    np.testing.assert_allclose(dted_lon_posting_deg(lat) * 3600, [3, 3, 6, 6, 9, 9, 12, 12, 18, 18, 6])


@pytest.mark.parametrize("lat0", [10.0, 55.0, 72.0, 81.5])
def test_tiles_across_the_antimeridian_and_at_high_latitude(rng, lat0):
    """A walk across 180 deg longitude reads one continuous surface (no jump beyond slope x step);
    tiles carry DTED's longitude spacing for their latitude; heights match the terrain at the
    postings' own positions to within the DEM's error."""
    from misrgraph.model.dem import dted_lon_posting_deg

    terrain = SyntheticTerrain(seed=5)
    n = 4001
    lo = np.linspace(179.99, 180.01, n)  # 0.02 deg: ~2.2 km at the equator
    lo = (lo + 180.0) % 360.0 - 180.0
    la = np.full(n, lat0)
    dem = simulate_dem_tiles(la, lo, terrain, rng, size=32)
    np.testing.assert_allclose(dem.lon_posting, dted_lon_posting_deg(lat0))
    assert np.all((dem.lon0 >= -180.0) & (dem.lon0 < 180.0))
    s = fit_local_surface(dem, la, lo)
    assert s.valid.all()
    tiles = dem.tile_of(la, lo)
    # the walk changes tiles at or near 180 deg, or one tile spans it (18" postings at 81.5 deg)
    assert np.unique(tiles).size > 1 or dem.lon0[tiles[0]] + 31 * dem.lon_posting[tiles[0]] > 180.0
    coslat = np.cos(np.radians(lat0))
    step_m = 0.02 / (n - 1) * 111e3 * coslat
    slope = np.hypot(s.dh_dlat / 111e3, s.dh_dlon / (111e3 * coslat))
    assert np.all(np.abs(np.diff(s.height)) <= 2 * slope[:-1] * step_m + 1e-6)
    # the postings sit where the tile says: heights = terrain there + error within 5 sigma
    t = np.unique(tiles)
    rr, cc = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    plat, plon = dem.posting_position(t[:, None, None], rr[None], cc[None])
    land = dem.flags[t] != FLAG_WATER
    err = (dem.heights[t] - terrain.height(plat, plon))[land]
    assert err.size == 0 or np.all(np.abs(err) < 5 * 60.0)


def test_tiles_stop_at_the_pole(rng):
    terrain = SyntheticTerrain(seed=6)
    lat, lon = np.array([89.9985, 89.9]), np.array([10.0, -170.0])  # 1.8 postings from the pole; 120
    dem = simulate_dem_tiles(lat, lon, terrain, rng, size=32)
    assert np.all(dem.lat0 + 31 * POSTING_DEG <= 90.0 + 1e-9)
    s = fit_local_surface(dem, lat, lon)
    assert not s.valid[0] and s.valid[1]  # within 3 postings of the pole: no tile holds it
    with pytest.raises(InputError, match="dem.lat0"):
        DemTiles(np.array([89.99]), np.array([0.0]), np.zeros((1, 32, 32)), np.ones((1, 32, 32)), np.array([1]))


def test_dem_file_keeps_the_longitude_spacing(rng, tmp_path):
    terrain = SyntheticTerrain(seed=7)
    dem = simulate_dem_tiles(np.array([20.0, 60.0]), np.array([5.0, 5.0]), terrain, rng, size=16)
    save_dem(dem, tmp_path / "d.h5")
    back = read_dem(tmp_path / "d.h5")
    np.testing.assert_array_equal(back.lon_posting, dem.lon_posting)
    assert sorted(set(np.round(dem.lon_posting * 3600, 6))) == [3.0, 6.0]


def test_smoothed_dem_keeps_planes_damps_noise_and_stays_continuous(rng):
    """``DemTiles.smoothed``: a plane is unchanged wherever the surface can read (the kernel is
    symmetric and cut at 2 postings, inside the tiles' margin); white noise at the postings keeps
    the variance the kernel's weights give it (sum of squared weights, closed form); the smoothed
    tiles are still one continuous DEM (no jump where the tile changes); 0 returns the DEM itself."""
    from scipy.stats import norm

    n, s = 32, 1.0
    r, c = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    plane = 100.0 + 3.0 * r - 2.0 * c
    noise = rng.standard_normal((200, n, n))
    dem = DemTiles(
        np.zeros(201),
        np.zeros(201),
        np.concatenate([plane[None], noise]),
        np.ones((201, n, n), np.uint8),
        np.ones(201, np.int64),
    )
    sm = dem.smoothed(s)
    assert dem.smoothed(0.0) is dem and dem.smoothed(s) is sm
    np.testing.assert_allclose(sm.heights[0, 2:-2, 2:-2], plane[2:-2, 2:-2], atol=1e-9)
    w = norm.pdf(np.arange(-2, 3) / s)
    w /= w.sum()
    expected = float(np.sum(w**2) ** 2)  # separable: rows, then columns
    got = float(np.var(sm.heights[1:, 2:-2, 2:-2]))
    assert got == pytest.approx(expected, rel=0.05)
    with pytest.raises(InputError, match="smoothing"):
        dem.smoothed(-1.0)
    # continuity across tiles, as test_tiles_are_one_continuous_dem does for the raw DEM
    p = POSTING_DEG
    lat = np.array([48024.3, 48034.6]) * p
    lon = np.array([-125989.6, -125989.6]) * p
    tiles = simulate_dem_tiles(lat, lon, SyntheticTerrain(seed=3), rng, size=32).smoothed(s)
    t = np.linspace(0.0, 1.0, 20001)
    la, lo = lat[0] + t * (lat[1] - lat[0]), lon[0] + t * (lon[1] - lon[0])
    f = fit_local_surface(tiles, la, lo)
    which = tiles.tile_of(la, lo)
    assert f.valid.all() and np.sum(which[:-1] != which[1:]) >= 1
    step_m = np.hypot(np.diff(la) * 111e3, np.diff(lo) * 111e3 * np.cos(np.radians(40.0)))
    slope = np.hypot(f.dh_dlat / 111e3, f.dh_dlon / (111e3 * np.cos(np.radians(40.0))))
    assert np.all(np.abs(np.diff(f.height)) <= 2 * slope[:-1] * step_m + 1e-6)
