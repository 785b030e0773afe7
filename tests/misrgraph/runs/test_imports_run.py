"""``run_import_dem`` / ``run_import_gcps`` end to end: a pass adjusted on a DEM and a GCP list
that went through the import commands (GeoTIFF tiles, a CSV list) gives the adjustment it gives
on the same inputs in misrgraph's own files."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.estimate.adjust import AdjustConfig
from misrgraph.io.dem import save_dem
from misrgraph.model.dem import DemTiles
from misrgraph.runs.adjust import run_adjust
from misrgraph.sim.simulate import load_scenario

rasterio = pytest.importorskip("rasterio")
from rasterio.transform import Affine  # noqa: E402


def test_adjust_on_imported_geotiff_dem_and_csv_gcps(small_pass_dir, tmp_path):
    sc = load_scenario(small_pass_dir)
    dem, gcps = sc.dem, sc.gcps
    # the scenario's 3" tiles (below 50 deg, where DTED's longitude posting is 3" too) of the
    # first quality class: the import writes one class and keeps 3" postings exactly
    keep = np.isclose(dem.lon_posting, dem.posting_deg) & (dem.quality == 1)
    assert keep.sum() > 50
    sub = DemTiles(
        dem.lat0[keep],
        dem.lon0[keep],
        dem.heights[keep],
        dem.flags[keep],
        dem.quality[keep],
        dem.posting_deg,
        dem.lon_posting[keep],
    )
    save_dem(sub, tmp_path / "dem_native.h5")
    # each tile as a GeoTIFF (rows north to south, pixel-is-area around its postings, float64)
    n, p = sub.size, sub.posting_deg
    tifs = []
    for t in range(len(sub.lat0)):
        path = tmp_path / "tiles" / f"tile_{t:04d}.tif"
        path.parent.mkdir(exist_ok=True)
        top = sub.lat0[t] + (n - 1) * p
        with rasterio.open(
            path,
            "w",
            driver="GTiff",
            height=n,
            width=n,
            count=1,
            dtype="float64",
            crs="EPSG:4326",
            transform=Affine(p, 0.0, sub.lon0[t] - p / 2, 0.0, -p, top + p / 2),
        ) as ds:
            ds.write(sub.heights[t][::-1], 1)
        tifs.append(str(path))
    # the GCP database as a CSV list (repr keeps every float exactly)
    with open(tmp_path / "gcps.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "lat", "lon", "height", "sigma_m", "region"])
        for row in zip(gcps.id, gcps.lat, gcps.lon, gcps.height, gcps.sigma_m, gcps.region):
            w.writerow([int(row[0]), *(repr(float(v)) for v in row[1:5]), row[5]])
    runner = CliRunner()
    r = runner.invoke(
        app, ["import", "dem", *tifs, "--tile-postings", str(n), "--out", str(tmp_path / "dem.h5"), "--json"]
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["tiles"] == len(tifs)
    r = runner.invoke(app, ["import", "gcps", str(tmp_path / "gcps.csv"), "--out", str(tmp_path / "gcp.h5"), "--json"])
    assert r.exit_code == 0, r.output
    native = run_adjust(small_pass_dir, dem_file=tmp_path / "dem_native.h5")
    imported = run_adjust(small_pass_dir, dem_file=tmp_path / "dem.h5", gcp_file=tmp_path / "gcp.h5")
    # the DEM mattered: without it the adjustment differs
    no_dem = run_adjust(small_pass_dir, dem_file=tmp_path / "dem_native.h5", cfg=AdjustConfig.from_dict(use_dem=False))
    assert abs(no_dem["final_cost"] - native["final_cost"]) > 1e-3 * native["final_cost"]
    for key in ("iterations", "observations", "landmarks", "knots"):
        assert imported[key] == native[key], key
    assert imported["final_cost"] == pytest.approx(native["final_cost"], rel=1e-7)
    sig = np.asarray(native["ephemeris"]["sigma"])
    diff = np.abs(np.asarray(imported["ephemeris"]["params"]) - np.asarray(native["ephemeris"]["params"]))
    assert np.all(diff <= 1e-4 * sig)
    for cam, v in native["checkpoint_geolocation_m"].items():
        assert imported["checkpoint_geolocation_m"][cam]["after"]["rms"] == pytest.approx(
            v["after"]["rms"], rel=1e-6
        ), cam
