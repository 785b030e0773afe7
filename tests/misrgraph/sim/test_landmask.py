"""The packed, memory-mapped land mask answers exactly as ``global_land_mask`` does."""

from __future__ import annotations

import numpy as np

from misrgraph.sim import landmask


def test_same_answers_as_global_land_mask(tmp_path, monkeypatch):
    monkeypatch.setenv("MISRGRAPH_CACHE", str(tmp_path))
    landmask._mask.cache_clear()
    try:
        rng = np.random.default_rng(0)
        lat = np.concatenate([np.degrees(np.arcsin(rng.uniform(-1, 1, 20000))), [90.0, -90.0, 0.0, 89.999]])
        lon = np.concatenate([rng.uniform(-180, 180, 20000), [0.0, 0.0, -180.0, 179.999]])
        mine = landmask.is_land(lat, lon)
        assert landmask.mask_cache_path().exists()
        from global_land_mask import globe  # the library's own answer (0.9 GB in this process)

        np.testing.assert_array_equal(mine, globe.is_land(lat.copy(), lon.copy()))
        assert 0.2 < mine[:20000].mean() < 0.4  # about 29 % of the Earth's surface is land
        assert mine.reshape(-1)[:10].shape == (10,) and landmask.is_land(
            lat[:6].reshape(2, 3), lon[:6].reshape(2, 3)
        ).shape == (2, 3)
    finally:
        landmask._mask.cache_clear()


def test_an_unwritable_cache_falls_back_to_the_temporary_directory(tmp_path, monkeypatch):
    import os
    import tempfile

    monkeypatch.setenv("MISRGRAPH_CACHE", "/proc/misrgraph-cannot-write-here")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    landmask._mask.cache_clear()
    try:
        assert landmask.is_land([48.86, 0.0], [2.35, -30.0]).tolist() == [True, False]  # Paris, mid-Atlantic
        assert list((tmp_path / f"misrgraph-{os.getuid()}").glob("landmask-*.npy"))
    finally:
        landmask._mask.cache_clear()


def _brute_force_coast_distance(lat: float, lon: float, reach_m: float, step_m: float = 40.0) -> float:
    """Distance (m) from (lat, lon) to the nearest water on a ``step_m`` local east/north lattice."""
    g = np.arange(-reach_m, reach_m + step_m / 2, step_m)
    e, n = np.meshgrid(g, g)
    r = 6371e3
    water = ~landmask.is_land(
        lat + np.degrees(n / r), (lon + np.degrees(e / (r * np.cos(np.radians(lat)))) + 180) % 360 - 180
    )
    return float(np.hypot(e[water], n[water]).min()) if water.any() else np.inf


def test_coast_distance_against_brute_force():
    """Land points within 4 km of the coast (Gulf of California at 28 deg N, Norway at 68 deg N
    where a cell's columns are 0.37 of its rows, Fiji across the antimeridian): the distance is
    within half a cell's diagonal (0.71 x 926 m) of the distance to the nearest water sample, the
    bound of centre-to-centre distances less half a cell, and unbiased to a sixth of a cell."""
    cell = 6371e3 * np.pi / 180 / 120
    rng = np.random.default_rng(3)
    errors = []
    for lat0, lon0 in ((28.0, -112.0), (68.0, 14.0), (-17.0, 179.6)):
        lat, lon = lat0 + rng.uniform(-1, 1, 4000), (lon0 + rng.uniform(-1, 1, 4000) + 180) % 360 - 180
        d = landmask.coast_distance_m(lat, lon, 5000.0)
        assert np.all(d[~landmask.is_land(lat, lon)] == 0.0) and d.max() == 5000.0
        near = np.flatnonzero((d > 0) & (d < 4000))[:40]
        assert near.size >= 20, (lat0, lon0)
        errors += [d[k] - _brute_force_coast_distance(lat[k], lon[k], 5000.0) for k in near]
    errors = np.array(errors)
    assert np.abs(errors).max() < 0.71 * cell, np.abs(errors).max()
    assert abs(errors.mean()) < cell / 6, errors.mean()


def test_coast_distance_is_continuous_and_capped():
    """Along a 50 m-step transect across the Gulf of California, on a cell edge (28.5 deg N, where
    the bilinear blend mixes two rows whose coasts differ): over land the distance never jumps by
    more than the step plus a fifth of a cell; on the land side of each coast crossing it is under
    half a cell (the mask's coast is a cell edge the blend of two rows can miss by that much); it
    stops at the cap and is 0 over water."""
    cell = 6371e3 * np.pi / 180 / 120
    lon = np.arange(-113.6, -110.4, 50.0 / (111.2e3 * np.cos(np.radians(28.5))))
    lat = np.full(lon.size, 28.5)
    d = landmask.coast_distance_m(lat, lon, 3000.0)
    land = landmask.is_land(lat, lon)
    both = land[1:] & land[:-1]
    assert np.abs(np.diff(d))[both].max() < 50.0 + cell / 5
    edges = np.flatnonzero(land[1:] != land[:-1])
    assert edges.size >= 2
    for k in edges:  # the land side of each coast crossing
        assert d[k if land[k] else k + 1] < cell / 2
    assert d.max() == 3000.0 and np.all(d[~land] == 0.0)
    assert landmask.coast_distance_m(lat, lon, 0.0).max() == 0.0
