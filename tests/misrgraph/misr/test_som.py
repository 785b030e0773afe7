"""The SOM grid against the MISR Toolkit's published conversions, PROJ, pyproj.Geod and the
simulator's orbit; round trips through every form."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from pyproj import Geod

from misrgraph.errors import InputError
from misrgraph.misr.som import N_BLOCKS, RELATIVE_OFFSETS_1100, RESOLUTIONS_M, SomGrid

# (path, resolution, block, line, sample, lat, lon, som_x, som_y): the MISR Toolkit's test vectors
# (MtkBlsToLatLon, MtkLatLonToBls, MtkBlsToSomXY, MtkSomXYToBls, MtkLatLonToSomXY, MtkSomXYToLatLon).
MTK_POINTS = [
    (1, 1100, 1, 0.0, 0.0, 66.226320603703, 110.452237414150, 7461299.999957129359, 527999.999819861725),
    (189, 275, 1, 127.5, 1023.5, 65.821183366596, 173.816760521356, 7495949.999777129851, 809049.999353842111),
]
MTK_CORNERS = [(1, 1100), (189, 275)]  # block 1, line -0.5, sample -0.5 -> (7460750, 527450)

# the tolerances: 1 cm in SOM, 1e-6 deg, 1e-3 pixel
TOL_M, TOL_DEG, TOL_PX = 0.01, 1e-6, 1e-3


@pytest.mark.parametrize("path,res,block,line,sample,lat,lon,x,y", MTK_POINTS)
def test_toolkit_vectors(path, res, block, line, sample, lat, lon, x, y) -> None:
    g = SomGrid(path, res)
    gx, gy = g.bls_to_somxy(block, line, sample)
    assert abs(gx - x) < TOL_M and abs(gy - y) < TOL_M
    glat, glon = g.bls_to_latlon(block, line, sample)
    assert abs(glat - lat) < TOL_DEG and abs(glon - lon) < TOL_DEG
    sx, sy = g.latlon_to_somxy(lat, lon)
    assert abs(sx - x) < TOL_M and abs(sy - y) < TOL_M
    slat, slon = g.somxy_to_latlon(x, y)
    assert abs(slat - lat) < TOL_DEG and abs(slon - lon) < TOL_DEG
    b, ln, s = g.latlon_to_bls(lat, lon)
    assert int(b) == block and abs(ln - line) < TOL_PX and abs(s - sample) < TOL_PX
    b, ln, s = g.somxy_to_bls(x, y)
    assert int(b) == block and abs(ln - line) < TOL_PX and abs(s - sample) < TOL_PX


def test_toolkit_point_off_the_blocks() -> None:
    # MtkLatLonToSomXY / MtkSomXYToLatLon: path 189, (32 N, 90 E) lies off the blocks but on the projection
    g = SomGrid(189, 275)
    x, y = g.latlon_to_somxy(32.0, 90.0)
    assert abs(x - 11640816.350309696048) < TOL_M and abs(y - 7067250.059730839916) < TOL_M
    lat, lon = g.somxy_to_latlon(11640816.350309696048, 7067250.059730839916)
    assert abs(lat - 32.0) < TOL_DEG and abs(lon - 90.0) < TOL_DEG
    b, ln, s = g.somxy_to_bls(x, y, strict=False)
    assert int(b) == 0 and np.isnan(ln) and np.isnan(s)
    with pytest.raises(InputError, match="som_x, som_y"):
        g.somxy_to_bls(x, y)


@pytest.mark.parametrize("path,res", MTK_CORNERS)
def test_toolkit_block1_corner(path, res) -> None:
    g = SomGrid(path, res)
    assert g.bls_to_somxy(1, -0.5, -0.5) == (7460750.0, 527450.0)
    b, ln, s = g.somxy_to_bls(7460750.0, 527450.0)
    assert (int(b), float(ln), float(s)) == (1, -0.5, -0.5)
    # MtkSomXYToBls: one metre before the corner is on no block
    b, ln, s = g.somxy_to_bls(7460749.0, 527449.0, strict=False)
    assert int(b) == 0


def test_block_sizes_and_offsets() -> None:
    assert (SomGrid(1, 1100).nline, SomGrid(1, 1100).nsample) == (128, 512)
    assert (SomGrid(1, 275).nline, SomGrid(1, 275).nsample) == (512, 2048)
    # the offsets at every resolution describe the same shift in metres
    metres = {r: SomGrid(7, r).block_offsets * r for r in RESOLUTIONS_M}
    for r in RESOLUTIONS_M:
        np.testing.assert_array_equal(metres[r], metres[1100])
    assert len(RELATIVE_OFFSETS_1100) == N_BLOCKS - 1 and set(RELATIVE_OFFSETS_1100) <= {-32, -16, 0, 16}


@pytest.mark.parametrize("res", [275, 1100])
def test_blocks_are_contiguous_along_track(res) -> None:
    """The last line of block b and the first of block b+1 are one pixel apart in SOM x."""
    g = SomGrid(100, res)
    b = np.arange(1, N_BLOCKS)
    x_last, _ = g.bls_to_somxy(b, g.nline - 1, 0.0)
    x_first, _ = g.bls_to_somxy(b + 1, 0.0, 0.0)
    np.testing.assert_allclose(x_first - x_last, res, atol=1e-6)


def test_pixel_spacing_on_the_ground() -> None:
    """Adjacent pixel centres are one resolution apart on the WGS84 ellipsoid (pyproj.Geod),
    to the SOM's scale error near the track (< 0.5 %: the swath half-width is 281 km, 4.4 % of R)."""
    geod = Geod(ellps="WGS84")
    g = SomGrid(37, 1100)
    for block in (10, 60, 90, 140):
        lat0, lon0 = g.bls_to_latlon(block, 64.0, 255.0)
        lat1, lon1 = g.bls_to_latlon(block, 65.0, 255.0)
        lat2, lon2 = g.bls_to_latlon(block, 64.0, 256.0)
        d_along = geod.inv(lon0, lat0, lon1, lat1)[2]
        d_cross = geod.inv(lon0, lat0, lon2, lat2)[2]
        assert abs(d_along / 1100 - 1) < 5e-3 and abs(d_cross / 1100 - 1) < 5e-3


@pytest.mark.parametrize("path", [1, 37, 120, 189, 233])
def test_the_simulated_orbit_flies_down_the_middle_of_the_blocks(path) -> None:
    """The simulator's Terra-like orbit of a WRS-2 path and MISR's SOM grid of the same path are
    built independently; nadir must fall near the blocks' middle sample (255.5). The block is
    563 km wide and must hold the swath (+-190 km at An, wider for the D cameras), so nadir may
    stray at most ~80 km (74 px); a path off by one would put it ~150 px away."""
    from misrgraph.model.frames import EarthOrientation, ecef_to_geodetic
    from misrgraph.model.orbit import terra_like_orbit

    eph = terra_like_orbit(path=path, start_lat_deg=70.0, duration_s=2400.0, step_s=30.0)
    r = np.einsum("nij,nj->ni", EarthOrientation(eph.epoch_utc).eci_to_ecef(eph.t), eph.position)
    lat, lon, _ = ecef_to_geodetic(r)
    b, _, s = SomGrid(path, 1100).latlon_to_bls(lat, lon)
    assert np.all(b >= 1)
    assert np.max(np.abs(s - 255.5)) < 74.0


resolutions = st.sampled_from([275, 1100])


@given(
    path=st.integers(1, 233),
    res=resolutions,
    block=st.integers(1, N_BLOCKS),
    u=st.floats(0.0, 1.0),
    v=st.floats(0.0, 1.0),
)
@example(path=1, res=275, block=28, u=0.0, v=0.0)  # a block's first corner, which round-trips to a hair before it
def test_round_trip_through_every_form(path, res, block, u, v) -> None:
    g = SomGrid(path, res)
    line, sample = -0.5 + u * g.nline, -0.5 + v * g.nsample
    x, y = g.bls_to_somxy(block, line, sample)
    lat, lon = g.somxy_to_latlon(x, y)
    x2, y2 = g.latlon_to_somxy(lat, lon)
    assert abs(x2 - x) < TOL_M and abs(y2 - y) < TOL_M
    b, ln, s = g.latlon_to_bls(lat, lon, strict=False)
    # a point on the last line's far edge may belong to the next block: compare positions
    xb, yb = g.bls_to_somxy(b, ln, s) if b else (np.nan, np.nan)
    assert abs(xb - x) < TOL_PX * res and abs(yb - y) < TOL_PX * res


def test_vectorised_shapes() -> None:
    g = SomGrid(37, 1100)
    x, y = g.block_centres(50, step=4)
    assert x.shape == (32, 128)
    b, ln, s = g.somxy_to_bls(x, y)
    assert np.all(b == 50)
    np.testing.assert_allclose(ln[:, 0], np.arange(0, 128, 4), atol=1e-9)
    np.testing.assert_allclose(s[0], np.arange(0, 512, 4), atol=1e-9)


@pytest.mark.parametrize(
    "call,field",
    [
        (lambda: SomGrid(0), "path"),
        (lambda: SomGrid(234), "path"),
        (lambda: SomGrid(5, 500), "resolution_m"),
        (lambda: SomGrid(5).bls_to_somxy(181, 0, 0), "block"),
        (lambda: SomGrid(5).bls_to_somxy(1.5, 0, 0), "block"),
        (lambda: SomGrid(5).bls_to_somxy([1, 2], [0, 128.0], 0), r"line\[1\]"),
        (lambda: SomGrid(5).bls_to_somxy(1, 0, np.nan), "sample"),
        (lambda: SomGrid(5).latlon_to_somxy(91.0, 0.0), "lat"),
        (lambda: SomGrid(5).somxy_to_latlon(np.inf, 0.0), "som_x"),
        (lambda: SomGrid(5).block_centres(3, step=3), "step"),
    ],
)
def test_bad_input_names_the_field(call, field) -> None:
    with pytest.raises(InputError, match=field):
        call()
