"""Real inputs: GCP lists (CSV, GeoJSON), DEM rasters and geoid grids written in those formats
and read back through misrgraph.io.external (and the ``import`` commands)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import InputError
from misrgraph.io.dem import read_dem
from misrgraph.io.external import read_gcp_table, read_geoid_grid, read_raster_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.model.dem import Geoid, fit_local_surface

rasterio = pytest.importorskip("rasterio")
from rasterio.transform import Affine  # noqa: E402


def from_origin(west: float, north: float, xsize: float, ysize: float) -> Affine:
    return Affine(xsize, 0.0, west, 0.0, -ysize, north)


runner = CliRunner()


# ----------------------------------------------------------------------------------- GCP lists
def _write_csv(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def test_csv_gcps_with_horizontal_and_vertical_sigma(tmp_path):
    p = _write_csv(
        tmp_path / "gcps.csv",
        "ID,Latitude,Longitude,height,sigma_h_m,sigma_v_m,region",
        ["7,36.5,-84.2,300.5,12,25,Tennessee", "9,-33.9,151.2,40,5,8,Sydney"],
    )
    db = read_gcp_table(p)
    assert db.id.tolist() == [7, 9]
    np.testing.assert_allclose(db.lat, [36.5, -33.9])
    np.testing.assert_allclose(db.height, [300.5, 40.0])
    assert db.region.tolist() == ["Tennessee", "Sydney"]
    # the ECEF covariance is diag(12^2, 12^2, 25^2) in the local east/north/up basis
    cov = db.covariance_ecef()[0]
    la, lo = np.radians(36.5), np.radians(-84.2)
    e = np.array([-np.sin(lo), np.cos(lo), 0.0])
    n = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
    u = np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    r = np.stack([e, n, u], axis=1)
    np.testing.assert_allclose(r.T @ cov @ r, np.diag([144.0, 144.0, 625.0]), atol=1e-9)


def test_csv_gcps_one_sigma_round_trip_through_the_cli(tmp_path):
    p = _write_csv(tmp_path / "g.csv", "lat,lon,height", ["10,20,5", "11,21,6", "12,22,7"])
    out = tmp_path / "gcp.h5"
    res = runner.invoke(app, ["import", "gcps", str(p), "--out", str(out), "--sigma-m", "15", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["gcps"] == 3
    db = read_gcp_database(out)
    assert db.id.tolist() == [0, 1, 2]
    np.testing.assert_allclose(db.sigma_m, 15.0)
    np.testing.assert_allclose(db.lon, [20, 21, 22])


def test_csv_gcps_with_source_scenes_through_the_cli(tmp_path):
    """A list that records each GCP's source scene: the shared sigma travels into the database
    (and the own covariance is what is left of the stated sigma); an empty scene is none."""
    p = _write_csv(
        tmp_path / "s.csv",
        "lat,lon,height,sigma_m,scene,scene_sigma_m",
        ["10,20,5,30,3,18", "10.2,20.1,6,30,3,18", "40,-100,900,20,,"],
    )
    out = tmp_path / "gcp.h5"
    res = runner.invoke(app, ["import", "gcps", str(p), "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    db = read_gcp_database(out)
    assert db.scene.tolist() == [3, 3, -1]
    np.testing.assert_allclose(db.scene_sigma_m, [18.0, 18.0, 0.0])
    assert list(db.scenes()) == [3] and db.scenes()[3].tolist() == [0, 1]
    np.testing.assert_allclose(np.linalg.eigvalsh(db.own_covariance_ecef()[0]), 30.0**2 - 18.0**2, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.eigvalsh(db.own_covariance_ecef()[2]), 400.0, rtol=1e-9)


def test_geojson_gcps_height_from_the_third_coordinate(tmp_path):
    doc = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [-84.3, 36.6, 412.0]},
                "properties": {"id": 3, "sigma_e_m": 4, "sigma_n_m": 5, "sigma_u_m": 9},
            },
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [190.0, 1.0, 2.0]},
                "properties": {"id": 4, "sigma_e_m": 1, "sigma_n_m": 2, "sigma_u_m": 3, "height": 50.0},
            },
        ],
    }
    p = tmp_path / "g.geojson"
    p.write_text(json.dumps(doc))
    db = read_gcp_table(p)
    np.testing.assert_allclose(db.height, [412.0, 50.0])  # a height property wins over the coordinate
    np.testing.assert_allclose(db.lon, [-84.3, -170.0])
    np.testing.assert_allclose(db.sigma_m, [[4, 5, 9], [1, 2, 3]])


def test_heights_above_the_geoid_need_a_geoid(tmp_path):
    p = _write_csv(tmp_path / "g.csv", "lat,lon,height_msl,sigma_m", ["10,20,100,5"])
    with pytest.raises(InputError, match="height_msl"):
        read_gcp_table(p)
    db = read_gcp_table(p, geoid=Geoid("constant", value=-30.0))
    np.testing.assert_allclose(db.height, [70.0])


@pytest.mark.parametrize(
    ("header", "row", "field"),
    [
        ("lat,lon,height,sigma_m", "10,abc,5,3", "row 0 (column lon)"),
        ("lat,lon,height,sigma_m", "95,10,5,3", "row 0 (column lat)"),
        ("lat,lon,height,sigma_m", "10,10,5,-3", "row 0 (sigma)"),
        ("lat,lon,sigma_m", "10,10,3", "column height"),
        ("lat,lon,height", "10,10,3", "column sigma_m"),
        ("id,lat,lon,height,sigma_m", "1.5,10,10,3,3", "column id"),
        ("lat,lon,height,sigma_m,scene", "10,10,3,3,1", "column scene_sigma_m"),
        ("lat,lon,height,sigma_m,scene,scene_sigma_m", "10,10,3,30,1,40", "scene_sigma_m[0]"),
        ("lat,lon,height,sigma_m,scene,scene_sigma_m", "10,10,3,30,1.5,10", "column scene"),
    ],
)
def test_bad_gcp_list_names_row_and_column(tmp_path, header, row, field):
    p = _write_csv(tmp_path / "g.csv", header, [row])
    with pytest.raises(InputError) as exc:
        read_gcp_table(p)
    assert field in str(exc.value)
    res = runner.invoke(app, ["import", "gcps", str(p), "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and field in res.stderr and "Traceback" not in res.output
    assert not (tmp_path / "x.h5").exists()


# ------------------------------------------------------------------------------------ rasters
def _jacksboro() -> tuple[np.ndarray, float, float, float]:
    """matplotlib's real 3" DEM of the Jacksboro fault (Tennessee): heights (rows north to
    south), west and north edges (deg) and the posting (deg)."""
    cbook = pytest.importorskip("matplotlib.cbook")
    d = cbook.get_sample_data("jacksboro_fault_dem.npz")
    # the file's 'ymin' is the northern edge: the rows run north to south
    north = max(float(d["ymin"]), float(d["ymax"]))
    return d["elevation"].astype(np.int16), float(d["xmin"]), north, float(d["dx"])


def _geotiff(path: Path, z: np.ndarray, transform, crs: str, nodata=None) -> Path:
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        height=z.shape[0],
        width=z.shape[1],
        count=1,
        dtype=z.dtype,
        crs=crs,
        transform=transform,
        nodata=nodata,
    ) as ds:
        ds.write(z, 1)
    return path


def test_jacksboro_geotiff_keeps_its_postings(tmp_path):
    z, west, north, dx = _jacksboro()
    tif = _geotiff(tmp_path / "jacksboro.tif", z, from_origin(west, north, dx, dx), "EPSG:4326", -32768)
    out = tmp_path / "dem.h5"
    res = runner.invoke(app, ["import", "dem", str(tif), "--out", str(out), "--tile-postings", "128", "--json"])
    assert res.exit_code == 0, res.output
    dem = read_dem(out)
    assert dem.size == 128 and dem.heights.shape[0] == json.loads(res.stdout)["tiles"]
    # every posting's height is the raster's, wherever a tile holds it (float32 storage)
    lat_c = north - (np.arange(z.shape[0]) + 0.5) * dx
    lon_c = west + (np.arange(z.shape[1]) + 0.5) * dx
    rng = np.random.default_rng(3)
    i, j = rng.integers(4, z.shape[0] - 4, 300), rng.integers(4, z.shape[1] - 4, 300)
    s = fit_local_surface(dem, lat_c[i], lon_c[j], "bicubic")
    assert s.valid.all()
    np.testing.assert_allclose(s.height, z[i, j], atol=1e-3)
    # between postings, the bilinear surface is the raster's bilinear interpolation
    from scipy.interpolate import RegularGridInterpolator

    interp = RegularGridInterpolator((lat_c[::-1], lon_c), z[::-1].astype(float))
    la = rng.uniform(lat_c[-5], lat_c[4], 300)
    lo = rng.uniform(lon_c[4], lon_c[-5], 300)
    s = fit_local_surface(dem, la, lo, "bilinear")
    np.testing.assert_allclose(s.height, interp(np.c_[la, lo]), atol=1e-3)


def test_jacksboro_in_a_dted_cell_keeps_its_postings(tmp_path):
    """A DTED level-1 cell (1201 x 1201 postings, 3", pixel-is-point, int16, -32767 null) written by
    GDAL's DTED driver, holding the Jacksboro heights at their own postings (its pixel centres lie
    on the cell's 3" grid) and nulls elsewhere: the import keeps the heights at every posting and
    drops the tiles that reach into the nulls."""
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    z, west, north, dx = _jacksboro()
    n = 1201
    lat_top, lon_left = 37.0, -85.0  # the cell N36 W085
    i0 = int(round((lat_top - (north - dx / 2)) / dx))
    j0 = int(round(((west + dx / 2) - lon_left) / dx))
    assert abs(lat_top - i0 * dx - (north - dx / 2)) < 1e-9 and abs(lon_left + j0 * dx - (west + dx / 2)) < 1e-9
    cell = np.full((n, n), -32767, np.int16)
    cell[i0 : i0 + z.shape[0], j0 : j0 + z.shape[1]] = z
    transform = from_origin(lon_left - dx / 2, lat_top + dx / 2, dx, dx)
    dt1 = tmp_path / "n36_w085.dt1"
    with MemoryFile() as mem:
        with mem.open(
            driver="GTiff",
            height=n,
            width=n,
            count=1,
            dtype="int16",
            crs="EPSG:4326",
            transform=transform,
            nodata=-32767,
        ) as ds:
            ds.write(cell, 1)
        with mem.open() as ds:
            rio_copy(ds, dt1, driver="DTED")
    with rasterio.open(dt1) as ds:  # GDAL reads it back as a DTED cell
        assert ds.driver == "DTED" and ds.shape == (n, n) and ds.nodata == -32767
    out = tmp_path / "dem.h5"
    res = runner.invoke(app, ["import", "dem", str(dt1), "--out", str(out), "--tile-postings", "128", "--json"])
    assert res.exit_code == 0, res.output
    dem = read_dem(out)
    tiles = json.loads(res.stdout)["tiles"]
    assert 0 < tiles == dem.heights.shape[0] <= (z.shape[0] // 128) * (z.shape[1] // 128) + 4
    # no tile holds a null: every height is Jacksboro's range
    assert dem.heights.min() >= z.min() - 1e-3 and dem.heights.max() <= z.max() + 1e-3
    lat_c = north - (np.arange(z.shape[0]) + 0.5) * dx
    lon_c = west + (np.arange(z.shape[1]) + 0.5) * dx
    rng = np.random.default_rng(4)
    i, j = rng.integers(0, z.shape[0], 4000), rng.integers(0, z.shape[1], 4000)
    s = fit_local_surface(dem, lat_c[i], lon_c[j], "bicubic")
    assert s.valid.sum() > 300  # the postings inside the kept tiles
    np.testing.assert_allclose(s.height[s.valid], z[i, j][s.valid], atol=1e-3)


def test_projected_raster_is_resampled_to_geographic_postings(tmp_path):
    # a smooth analytic surface in UTM zone 16N: the geographic postings must carry its value
    from pyproj import Transformer

    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32616", always_xy=True)
    x0, y0 = to_utm.transform(-84.3, 36.6)
    res_m = 30.0
    n = 700
    xs = x0 - 10_000 + (np.arange(n) + 0.5) * res_m
    ys = y0 + 10_000 - (np.arange(n) + 0.5) * res_m

    def height(x, y):
        return 500.0 + 80.0 * np.sin((x - x0) / 4000.0) + 60.0 * np.cos((y - y0) / 5000.0)

    z = height(xs[None, :], ys[:, None]).astype(np.float32)
    tif = _geotiff(tmp_path / "utm.tif", z, from_origin(x0 - 10_000, y0 + 10_000, res_m, res_m), "EPSG:32616")
    dem = read_raster_dem([tif], posting_arcsec=1.0, tile_postings=200)
    lat0 = dem.lat0[:, None, None] + np.arange(dem.size)[None, :, None] * dem.posting_deg
    lon0 = dem.lon0[:, None, None] + np.arange(dem.size)[None, None, :] * dem.posting_deg
    lat, lon = np.broadcast_arrays(lat0, lon0)
    x, y = to_utm.transform(lon.ravel(), lat.ravel())
    # bilinear resampling of a 30 m grid: error ~ (30 m)^2 / 8 * curvature (80/4000^2 per m^2)
    bound = 30.0**2 / 8 * (80 / 4000**2 + 60 / 5000**2) * 2
    np.testing.assert_allclose(dem.heights.ravel(), height(np.asarray(x), np.asarray(y)), atol=bound)


def test_geoid_grid_makes_heights_ellipsoidal(tmp_path):
    # a global 1-degree grid of N = 20 sin(lat) + 10 cos(lon) (pixel-is-area, centres at half degrees)
    lat = 89.5 - np.arange(180)
    lon = -179.5 + np.arange(360)
    n_grid = (20 * np.sin(np.radians(lat))[:, None] + 10 * np.cos(np.radians(lon))[None, :]).astype(np.float32)
    g = _geotiff(tmp_path / "geoid.tif", n_grid, from_origin(-180, 90, 1, 1), "EPSG:4326")
    geoid = read_geoid_grid(g)
    # at grid centres exact; between them, within bilinear error of the smooth field
    np.testing.assert_allclose(geoid.undulation(lat[10], lon[200]), n_grid[10, 200], atol=1e-5)
    rng = np.random.default_rng(1)
    la, lo = rng.uniform(-89, 89, 500), rng.uniform(-180, 180, 500)
    want = 20 * np.sin(np.radians(la)) + 10 * np.cos(np.radians(lo))
    np.testing.assert_allclose(geoid.undulation(la, lo), want, atol=30 * np.radians(1) ** 2 / 8 * 2)
    z, west, north, dx = _jacksboro()
    tif = _geotiff(tmp_path / "j.tif", z, from_origin(west, north, dx, dx), "EPSG:4326")
    plain = read_raster_dem([tif], tile_postings=128)
    ell = read_raster_dem([tif], tile_postings=128, geoid=geoid)
    la = plain.lat0[:, None, None] + np.arange(128)[None, :, None] * plain.posting_deg
    lo = plain.lon0[:, None, None] + np.arange(128)[None, None, :] * plain.posting_deg
    np.testing.assert_allclose(ell.heights - plain.heights, geoid.undulation(*np.broadcast_arrays(la, lo)), atol=1e-6)


def test_raster_with_no_data_drops_tiles_and_a_too_small_raster_is_refused(tmp_path):
    z, west, north, dx = _jacksboro()
    z = z.copy()
    z[:60, :60] = -32768  # a hole in the north-west corner
    tif = _geotiff(tmp_path / "hole.tif", z, from_origin(west, north, dx, dx), "EPSG:4326", -32768)
    dem = read_raster_dem([tif], tile_postings=128)
    full = read_raster_dem(
        [_geotiff(tmp_path / "full.tif", _jacksboro()[0], from_origin(west, north, dx, dx), "EPSG:4326", -32768)],
        tile_postings=128,
    )
    assert 0 < dem.lat0.size < full.lat0.size
    assert np.all(dem.heights > 0)
    s = fit_local_surface(dem, np.array([north - 10 * dx]), np.array([west + 10 * dx]))
    assert not s.valid[0]
    with pytest.raises(InputError, match="tile_postings"):
        read_raster_dem([tif], tile_postings=1201)
