"""The simulator's terrain near the coast: the relief tapers to 0 there instead of standing as a
cliff, and is untouched farther inland than the ramp."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.sim.landmask import coast_distance_m
from misrgraph.sim.terrain import SyntheticTerrain, land_mask, simulate_dem_tiles

CELL_M = 6371e3 * np.pi / 180 / 120  # the land mask's cell (rows)


def _transect() -> tuple[np.ndarray, np.ndarray]:
    """A 25 m-step transect across the Gulf of California and both its coasts (28.3 deg N)."""
    lon = np.arange(-113.6, -110.4, 25.0 / (111.2e3 * np.cos(np.radians(28.3))))
    return np.full(lon.size, 28.3), lon


def test_the_coast_is_no_cliff_with_a_ramp():
    """Without a ramp the land stands hundreds of metres above the sea at the coast; with an 8 km
    ramp the step at every coast crossing is at most the taper at half a cell,
    ``max relief x smoothstep(463 m / 8 km)``, 25 m for the 2.5 km relief."""
    lat, lon = _transect()
    land = land_mask(lat, lon)
    edges = np.flatnonzero(land[1:] != land[:-1])
    assert edges.size >= 2
    cliff = SyntheticTerrain(seed=2).height(lat, lon)
    ramp = SyntheticTerrain(seed=2, coast_ramp_m=8000.0)
    h = ramp.height(lat, lon)
    steps_cliff = np.abs(cliff[edges + 1] - cliff[edges])
    steps_ramp = np.abs(h[edges + 1] - h[edges])
    assert steps_cliff.max() > 200.0, steps_cliff  # the world without the ramp
    t = 0.5 * CELL_M / 8000.0
    assert steps_ramp.max() < ramp.max_relief_m * t * t * (3 - 2 * t), steps_ramp
    # over land the ramp's slope is bounded: the relief's own plus 1.5 x max relief / ramp
    both = land[1:] & land[:-1]
    slope = np.abs(np.diff(h))[both] / 25.0
    slope0 = np.abs(np.diff(cliff))[both] / 25.0
    assert slope.max() < slope0.max() + 1.5 * ramp.max_relief_m / 8000.0 + 0.05


def test_inland_the_relief_is_untouched():
    """Beyond the ramp the height is the relief's exactly; within it the ratio is the smoothstep
    of the distance to the coast (the documented taper)."""
    rng = np.random.default_rng(4)
    lat, lon = rng.uniform(27.0, 31.0, 5000), rng.uniform(-114.0, -109.0, 5000)
    plain, ramp = SyntheticTerrain(seed=5), SyntheticTerrain(seed=5, coast_ramp_m=8000.0)
    h0, h = plain.height(lat, lon), ramp.height(lat, lon)
    d = coast_distance_m(lat, lon, 8000.0)
    far = d >= 8000.0
    near = (d > 0) & ~far
    assert far.sum() > 500 and near.sum() > 100
    np.testing.assert_array_equal(h[far], h0[far])
    t = d[near] / 8000.0
    np.testing.assert_allclose(h[near], h0[near] * t * t * (3 - 2 * t), rtol=1e-12)
    assert np.all(h[~land_mask(lat, lon)] == 0.0)


def test_dem_tiles_hold_the_tapered_terrain():
    """The DEM tiles' heights are the tapered terrain plus the DEM's error (its stated sigma at
    most a few times over), not the untapered relief."""
    ramp = SyntheticTerrain(seed=6, coast_ramp_m=8000.0)
    lat, lon = np.array([28.3, 28.3]), np.array([-112.89, -111.4])  # 2 km from the gulf's coasts
    dem = simulate_dem_tiles(lat, lon, ramp, np.random.default_rng(0), size=32)
    n = dem.heights.shape[1]
    g = np.arange(n)
    glat = dem.lat0[:, None, None] + dem.posting_deg * g[None, :, None] + 0 * g[None, None, :]
    glon = (
        dem.lon0[:, None, None] + dem.lon_posting[:, None, None] * g[None, None, :] + 0 * g[None, :, None] + 180
    ) % 360 - 180
    err = dem.heights - ramp.height(glat, glon)
    assert np.sqrt(np.mean(err**2)) < 3 * 30.0
    d = coast_distance_m(glat, glon, 8000.0)
    near = (d > 0) & (d < 4000)
    assert near.sum() > 50
    untapered = dem.heights - SyntheticTerrain(seed=6).height(glat, glon)
    assert np.sqrt(np.mean(untapered[near] ** 2)) > 3 * np.sqrt(np.mean(err[near] ** 2))


def test_the_dem_errors_correlation_length_is_a_knob():
    """With all of the smooth error in the long-correlated share, DEM errors ~11 km apart are
    nearly the same where its lattice is ~111 km (1200 postings) and independent where it is
    ~4.6 km (50 postings); a spacing that does not divide 360 degrees is refused."""
    from misrgraph.errors import InputError
    from misrgraph.sim.simulate import ScenarioConfig, scenario_terrain
    from misrgraph.sim.terrain import simulate_dem_tiles

    terrain = scenario_terrain(ScenarioConfig())
    lat = np.full(60, 40.05) + 0 * np.arange(60)
    lon = -100.0 + 0.1 * np.arange(60)  # ~8.5 km apart at 40 N
    corr = {}
    for spacing in (50, 1200):
        h = {}
        for f in (1.0, 2.0):
            dem = simulate_dem_tiles(
                lat,
                lon,
                terrain,
                np.random.default_rng(4),
                correlated_fraction=1.0,
                true_over_stated=f,
                correlation_postings=spacing,
            )
            h[f] = dem.surface(lat, lon).height
        e = h[2.0] - h[1.0]  # one draw of the error field
        corr[spacing] = np.corrcoef(e[:-1], e[1:])[0, 1]
    assert corr[1200] > 0.8 and abs(corr[50]) < 0.4, corr
    with pytest.raises(InputError, match="dem_correlation_postings"):
        ScenarioConfig(dem_correlation_postings=7)
