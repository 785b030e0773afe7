"""MISR's own files: the SOM parameters against the MISR Toolkit's published table, block/line/
sample from a written file's own grid metadata (through PROJ's general ``som``) against
``som convert``, PP and ROI files read back with raw HDF4 calls and GDAL, the RDQI packing, and an
AGP written field by field with raw HDF4 calls (not our writer) imported as a DEM an adjustment
runs on."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyhdf")

from pyhdf.SD import SD, SDC  # noqa: E402

from misrgraph.errors import FileFormatError, InputError  # noqa: E402
from misrgraph.io.hdfeos import parse_odl, read_eos_file  # noqa: E402
from misrgraph.io.misrfiles import (  # noqa: E402
    PP_FILL,
    RDQI_FILL,
    RDQI_OBSCURED,
    agp_to_dem,
    deg_to_packed_dms,
    misr_file_name,
    packed_dms_to_deg,
    read_agp,
    read_l1b2,
    som_proj_params,
    write_pp_misr,
    write_roi_misr,
)
from misrgraph.io.products import PP_COEFFICIENTS, PP_SIGMAS, ProjectionParameters  # noqa: E402
from misrgraph.io.roi import RoiFile  # noqa: E402
from misrgraph.misr.som import N_BLOCKS, RELATIVE_OFFSETS_1100, SomGrid  # noqa: E402

GDAL = shutil.which("gdalinfo") is not None and shutil.which("gdal_translate") is not None
needs_gdal = pytest.mark.skipif(not GDAL, reason="GDAL's command-line tools (gdal-bin) are not installed")

#: Longitude of the ascending node (packed DMS) per path, from the MISR Toolkit's own test of
#: MtkPathToProjParam (CoordQuery/src/MtkPathToProjParam_test.c).
MTK_ASCENDING_NODE = {
    1: 127045037.928240340,
    2: 126012055.696480690,
    37: 72008017.584892705,
    100: -25012003.015965667,
    233: -230041039.840000000,
}


def _pp(path: int = 37, blocks=(57, 58), cameras=("Df", "An")) -> ProjectionParameters:
    rng = np.random.default_rng(5)
    shape = (len(cameras), len(blocks), 128, 512)
    arrays = {name: rng.normal(0, 50, shape) for name in PP_COEFFICIENTS + PP_SIGMAS}
    arrays["line0"][0, 0, :4, :4] = np.nan  # beyond the margin
    return ProjectionParameters(
        path=path,
        blocks=np.asarray(blocks),
        cameras=tuple(cameras),
        band="red",
        pass_id="P037_O012345",
        **arrays,
    )


def _roi(path: int = 37, blocks=(57,)) -> RoiFile:
    rng = np.random.default_rng(9)
    shape = (2, len(blocks), 512, 2048)
    pixels = rng.integers(1, 16000, shape).astype(np.uint16)
    source = rng.integers(0, 2, shape).astype(np.int8)
    source[:, :, :10] = -1
    obscured = np.zeros(shape, bool)
    obscured[:, :, 10:12] = True
    source[obscured] = -1
    pixels[source < 0] = 0
    cloudy = rng.random(shape) < 0.1
    return RoiFile(
        path=path,
        band="red",
        cameras=("Df", "An"),
        pass_ids=("P037_O000001", "P037_O000002"),
        blocks=np.asarray(blocks),
        pixels=pixels,
        source=source,
        cloudy=cloudy,
        obscured=obscured,
        clear_fraction=np.ones((len(blocks), 2)),
        chosen=np.zeros(len(blocks), np.int64),
        full_scale_dn=16383,
    )


@pytest.fixture(scope="module")
def pp_files(tmp_path_factory) -> tuple[ProjectionParameters, dict[str, Path]]:
    pp = _pp()
    return pp, write_pp_misr(pp, tmp_path_factory.mktemp("pp"))


@pytest.fixture(scope="module")
def roi_files(tmp_path_factory) -> tuple[RoiFile, dict[str, Path]]:
    roi = _roi()
    return roi, write_roi_misr(roi, tmp_path_factory.mktemp("roi"))


def test_som_parameters_are_the_misr_toolkits() -> None:
    for path, asc in MTK_ASCENDING_NODE.items():
        pp = som_proj_params(path)
        assert pp[4] == pytest.approx(asc, abs=1e-6), path
        assert pp[:4] == (6378137.0, -0.006694348, 0.0, 98018013.752)
        assert pp[8] == 98.88 and pp[11] == 180.0
    for deg in (-230.684, -0.5, 0.0, 98.30382, 127.7605356):
        assert packed_dms_to_deg(deg_to_packed_dms(deg)) == pytest.approx(deg, abs=1e-9)


def test_file_names_follow_misrs_pattern() -> None:
    assert misr_file_name("PP", 37, 12345, "Df") == "MISR_AM1_PP_P037_O012345_DF_F01_0001.hdf"
    assert misr_file_name("AGP", 7, format_version=1, version=24) == "MISR_AM1_AGP_P007_F01_0024.hdf"


@pytest.mark.parametrize("path", [1, 37, 233])
def test_block_line_sample_from_the_files_own_metadata_equals_som_convert(tmp_path: Path, path: int) -> None:
    """The grid corners, pixel size, block offsets and SOM parameters read from a written file,
    put through PROJ's general Space Oblique Mercator (not misrsom), give the latitude and
    longitude that ``som convert`` gives for the same block, line and sample."""
    from pyproj import Transformer

    from misrgraph.runs.som import run_som_convert

    files = write_pp_misr(_pp(path, blocks=(60,), cameras=("Df",)), tmp_path)
    e = read_eos_file(files["Df"])
    g = e.grids["Projection_Parameters"]
    ulc, lrc = g["UpperLeftPointMtrs"], g["LowerRightMtrs"]
    nl, ns = int(g["XDim"]), int(g["YDim"])
    rx, ry = (lrc[0] - ulc[0]) / nl, (ulc[1] - lrc[1]) / ns
    rel = np.asarray(e.grid_attributes["Projection_Parameters"]["_BLKSOM:Projection_Parameters"], dtype=float)
    absolute = np.concatenate([[0.0], np.cumsum(rel)])
    params = g["ProjParams"]
    som = (
        f"+proj=som +inc_angle={packed_dms_to_deg(params[3])!r} +ps_rev={params[8] / 1440.0!r} "
        f"+asc_lon={packed_dms_to_deg(params[4])!r} +a={params[0]!r} +rf=298.257223563 +units=m +type=crs"
    )
    to_geo = Transformer.from_crs(som, "EPSG:4326", always_xy=True)
    rng = np.random.default_rng(path)
    block = rng.integers(1, N_BLOCKS + 1, 40)
    line = rng.uniform(-0.5, nl - 0.5, 40)
    sample = rng.uniform(-0.5, ns - 0.5, 40)
    x = ulc[0] + rx / 2 + ((block - 1) * nl + line) * rx
    y = lrc[1] + ry / 2 + (sample + absolute[block - 1]) * ry
    lon, lat = to_geo.transform(x, y)
    for k in range(0, 40, 7):
        got = run_som_convert(path, block=int(block[k]), line=float(line[k]), sample=float(sample[k]))
        assert got["lat"] == pytest.approx(lat[k], abs=1e-9)
        assert got["lon"] == pytest.approx(lon[k], abs=1e-9)
    grid_lat, grid_lon = SomGrid(path).bls_to_latlon(block, line, sample)
    np.testing.assert_allclose(grid_lat, lat, atol=1e-9)
    np.testing.assert_allclose(grid_lon, lon, atol=1e-9)
    assert np.allclose(rel, RELATIVE_OFFSETS_1100)


def test_pp_files_hold_every_field_per_camera(pp_files) -> None:
    pp, files = pp_files
    assert {c: p.name for c, p in files.items()} == {
        "Df": "MISR_AM1_PP_P037_O012345_DF_F01_0001.hdf",
        "An": "MISR_AM1_PP_P037_O012345_AN_F01_0001.hdf",
    }
    sd = SD(str(files["An"]), SDC.READ)
    attrs = sd.attributes()
    assert (attrs["Path_number"], attrs["Start_block"], attrs["End block"], attrs["AM1_orbitnumber"]) == (
        37,
        57,
        58,
        12345,
    )
    core = parse_odl(attrs["coremetadata"])["INVENTORYMETADATA"]
    assert core["ECSDATAGRANULE"]["LOCALGRANULEID"]["VALUE"] == files["An"].name
    for name in PP_COEFFICIENTS + PP_SIGMAS:
        sds = sd.select(name)
        assert sds.info()[2] == [N_BLOCKS, 128, 512]
        data = sds[56:58]
        want = np.asarray(getattr(pp, name)[1], dtype=np.float32)
        np.testing.assert_array_equal(data, want)
        assert np.all(sds[10] == np.float32(PP_FILL))
        sds.endaccess()
    sd.end()
    sd = SD(str(files["Df"]), SDC.READ)
    assert np.all(sd.select("line0")[56, :4, :4] == np.float32(PP_FILL))  # NaN beyond the margin
    sd.end()


@needs_gdal
def test_gdal_opens_pp_and_roi_files(tmp_path: Path, pp_files, roi_files) -> None:
    pp_file = pp_files[1]["An"]
    roi, files = roi_files
    roi_file = files["Df"]
    for f, grid, field, size, res in (
        (pp_file, "Projection_Parameters", "sigma_m", [128, 512], 1100.0),
        (roi_file, "RedBand", "Red Radiance/RDQI", [512, 2048], 275.0),
    ):
        target = f'HDF4_EOS:EOS_GRID:"{f}":{grid}:{field}'
        info = json.loads(
            subprocess.run(["gdalinfo", "-json", target], capture_output=True, text=True, check=True).stdout
        )
        assert info["size"] == size and len(info["bands"]) == N_BLOCKS
        assert info["geoTransform"] == [7460750.0, res, 0.0, 1090650.0, 0.0, -res]
        assert "GCTP projection number 22" in info["coordinateSystem"]["wkt"]
        md = info["metadata"][""]
        assert md["Path_number"] == "37" and md["Start_block"] == "57"
        assert int(float(md["Block_size.resolution_x"])) == int(res)
    raw = tmp_path / "b57.bin"
    target = f'HDF4_EOS:EOS_GRID:"{roi_file}":RedBand:Red Radiance/RDQI'
    # GDAL reads an XDim-first field in its storage order, a raster block of HDF4_BLOCK_PIXELS at a
    # time: with a block that holds the whole MISR block the values come out as stored
    subprocess.run(
        [
            "gdal_translate",
            "-q",
            "--config",
            "HDF4_BLOCK_PIXELS",
            str(512 * 2048),
            "-of",
            "ENVI",
            "-b",
            "57",
            target,
            str(raw),
        ],
        check=True,
    )
    got = np.fromfile(raw, dtype="<u2").reshape(512, 2048)
    expected = np.where(
        roi.obscured[0, 0],
        RDQI_OBSCURED,
        np.where(roi.source[0, 0] < 0, RDQI_FILL, (roi.pixels[0, 0].astype(np.int64) << 2) | roi.cloudy[0, 0]),
    )
    np.testing.assert_array_equal(got, expected)


def test_roi_radiance_rdqi_packs_and_unpacks(roi_files) -> None:
    roi, files = roi_files
    assert files["An"].name == "MISR_AM1_ROI_P037_AN_F01_0001.hdf"
    band = read_l1b2(files["An"])
    assert band.path == 37 and band.resolution_m == 275 and band.camera == "An"
    np.testing.assert_array_equal(band.blocks, [57])
    c = 1
    empty = roi.source[c, 0] < 0
    np.testing.assert_array_equal(band.obscured[0], roi.obscured[c, 0])
    np.testing.assert_array_equal(band.fill[0], empty & ~roi.obscured[c, 0])
    ok = ~empty
    np.testing.assert_array_equal(band.radiance[0][ok], roi.pixels[c, 0][ok].astype(float))
    assert np.all(np.isnan(band.radiance[0][empty]))
    np.testing.assert_array_equal(band.rdqi[0][ok], roi.cloudy[c, 0][ok].astype(np.uint8))
    sd = SD(str(files["An"]), SDC.READ)
    src = sd.select("ROI Source Pass")
    np.testing.assert_array_equal(src[56], roi.source[c, 0])
    assert sd.attributes()["ROI_pass_ids"] == "P037_O000001,P037_O000002"
    sd.end()


# ------------------------------------------------------------------------------------- AGP in


def write_agp_by_hand(
    path: Path, sky_path: int, heights: np.ndarray, sigma: np.ndarray, blocks: tuple[int, int]
) -> None:
    """An AGP written with raw HDF4 calls from MISR's published layout (grid Standard, 1.1 km,
    AveSceneElev int16 with fill -9999, StdDevSceneElev float32), not through misrgraph's writer."""
    from pyhdf.V import V  # noqa: F401
    from pyhdf.VS import VS  # noqa: F401

    params = som_proj_params(sky_path)
    struct = (
        "GROUP=SwathStructure\nEND_GROUP=SwathStructure\nGROUP=GridStructure\n\tGROUP=GRID_1\n"
        '\t\tGridName="Standard"\n\t\tXDim=128\n\t\tYDim=512\n'
        "\t\tUpperLeftPointMtrs=(7460750.000000,1090650.000000)\n\t\tLowerRightMtrs=(7601550.000000,527450.000000)\n"
        "\t\tProjection=GCTP_SOM\n\t\tProjParams=(" + ",".join(repr(float(p)) for p in params) + ")\n"
        "\t\tSphereCode=12\n\t\tGridOrigin=HDFE_GD_UL\n"
        '\t\tGROUP=Dimension\n\t\t\tOBJECT=Dimension_1\n\t\t\t\tDimensionName="SOMBlockDim"\n\t\t\t\tSize=180\n'
        "\t\t\tEND_OBJECT=Dimension_1\n\t\tEND_GROUP=Dimension\n\t\tGROUP=DataField\n"
        '\t\t\tOBJECT=DataField_1\n\t\t\t\tDataFieldName="AveSceneElev"\n\t\t\t\tDataType=DFNT_INT16\n'
        '\t\t\t\tDimList=("SOMBlockDim","XDim","YDim")\n\t\t\tEND_OBJECT=DataField_1\n'
        '\t\t\tOBJECT=DataField_2\n\t\t\t\tDataFieldName="StdDevSceneElev"\n\t\t\t\tDataType=DFNT_FLOAT32\n'
        '\t\t\t\tDimList=("SOMBlockDim","XDim","YDim")\n\t\t\tEND_OBJECT=DataField_2\n'
        "\t\tEND_GROUP=DataField\n\tEND_GROUP=GRID_1\nEND_GROUP=GridStructure\nEND\n"
    )
    sd = SD(str(path), SDC.WRITE | SDC.CREATE | SDC.TRUNC)
    sd.attr("HDFEOSVersion").set(SDC.CHAR8, "HDFEOS_V2.17")
    sd.attr("StructMetadata.0").set(SDC.CHAR8, struct)
    sd.attr("Path_number").set(SDC.INT32, sky_path)
    sd.attr("Start_block").set(SDC.INT32, blocks[0])
    sd.attr("End block").set(SDC.INT32, blocks[1])
    refs = []
    for name, typ, data, fill in (
        ("AveSceneElev", SDC.INT16, heights.astype(np.int16), -9999),
        ("StdDevSceneElev", SDC.FLOAT32, sigma.astype(np.float32), -9999.0),
    ):
        s = sd.create(name, typ, [180, 128, 512])
        for i, d in enumerate(("SOMBlockDim", "XDim", "YDim")):
            s.dim(i).setname(f"{d}:Standard")
        s.setfillvalue(fill)
        s[:] = data
        refs.append(s.ref())
        s.endaccess()
    sd.end()
    _grid_vgroups_by_hand(
        path,
        "Standard",
        refs,
        (
            ("Block_size.resolution_x", "INT32", 1100),
            ("_FV_AveSceneElev", "INT16", -9999),
            ("_FV_StdDevSceneElev", "FLOAT32", -9999.0),
        ),
    )


def _grid_vgroups_by_hand(path: Path, grid_name: str, refs: list[int], attributes: tuple) -> None:
    """The HDF-EOS2 grid Vgroups, with raw HDF4 calls: ``grid_name`` (class GRID) holding ``Data
    Fields`` (the SDSs ``refs``) and ``Grid Attributes`` (one ``Attr0.0`` Vdata per ``(name, HC
    type name, value)``)."""
    from pyhdf.HDF import HC, HDF
    from pyhdf.V import V  # noqa: F401
    from pyhdf.VS import VS  # noqa: F401

    hdf = HDF(str(path), HC.WRITE)
    v, vs = hdf.vgstart(), hdf.vstart()
    grid = v.create(grid_name)
    grid._class = "GRID"
    fields = v.create("Data Fields")
    fields._class = "GRID Vgroup"
    attrs = v.create("Grid Attributes")
    attrs._class = "GRID Vgroup"
    grid.insert(fields)
    grid.insert(attrs)
    for r in refs:
        fields.add(HC.DFTAG_NDG, r)
    for name, typ, value in attributes:
        vd = vs.create(name, (("AttrValues", getattr(HC, typ), 1),))
        vd._class = "Attr0.0"
        vd.write([[value]])
        attrs.insert(vd)
        vd.detach()
    for vg in (attrs, fields, grid):
        vg.detach()
    vs.end()
    v.end()
    hdf.close()


def _agp_from_terrain(sc, sky_path: int, blocks: tuple[int, int]):
    """AveSceneElev from the scenario's true terrain at the 1.1 km sample centres (m), and a
    StdDevSceneElev of 5, 6 or 7 m by block."""
    from misrgraph.sim.simulate import scenario_terrain

    terrain = scenario_terrain(sc.config)
    grid = SomGrid(sky_path)
    h = np.full((180, 128, 512), -9999, np.int16)
    sd = np.full((180, 128, 512), -9999.0, np.float32)
    for b in range(blocks[0], blocks[1] + 1):
        x, y = grid.block_centres(b)
        lat, lon = grid.somxy_to_latlon(x, y)
        h[b - 1] = np.round(terrain.height(lat, lon)).astype(np.int16)
        sd[b - 1] = 5.0 + b % 3
    return h, sd


def test_an_agp_written_by_hand_imports_with_its_heights_and_sigmas(tmp_path: Path, small_pass) -> None:
    sc, op = small_pass
    blocks = (55, 60)
    h, sd = _agp_from_terrain(sc, op.path, blocks)
    f = tmp_path / misr_file_name("AGP", op.path, version=24)
    write_agp_by_hand(f, op.path, h, sd, blocks)
    agp = read_agp(f)
    assert agp.path == op.path
    np.testing.assert_array_equal(agp.blocks, np.arange(55, 61))
    sel = h[54:60] != -9999
    np.testing.assert_array_equal(agp.ave_scene_elev[sel], h[54:60][sel].astype(float))
    assert np.all(np.isnan(agp.ave_scene_elev[~sel]))
    dem = agp_to_dem(agp, posting_arcsec=30.0, tile_postings=48)
    assert dem.heights.shape[0] > 0 and dem.sigma_m is not None
    # postings against the AGP's own values at their block/line/sample (nearest 1.1 km sample)
    grid = SomGrid(op.path)
    t = np.arange(dem.heights.shape[0])
    lat = dem.lat0[t][:, None, None] + np.arange(dem.size)[None, :, None] * dem.posting_deg
    lon = dem.lon0[t][:, None, None] + np.arange(dem.size)[None, None, :] * dem.lon_posting[t][:, None, None]
    lat, lon = np.broadcast_arrays(lat, lon)
    b, ln, s = grid.latlon_to_bls(lat.ravel(), lon.ravel(), strict=False)
    inside = (b >= 56) & (b <= 59) & (ln > 1) & (ln < 126) & (s > 1) & (s < 510)
    k = b[inside] - 1
    near = h[k, np.round(ln[inside]).astype(int), np.round(s[inside]).astype(int)].astype(float)
    got = dem.heights.ravel()[inside]
    # bilinear between neighbouring 1.1 km samples: within the local relief of the samples
    assert np.median(np.abs(got - near)) < 20.0
    np.testing.assert_allclose(dem.sigma_m.ravel()[inside], 5.0 + (k + 1) % 3, atol=1e-5)
    surf = dem.surface(lat.ravel()[inside][:50], lon.ravel()[inside][:50])
    assert np.all(surf.sigma >= (5.0 + (k[:50] + 1) % 3) - 1e-6)


def test_import_agp_cli_and_an_adjustment_on_it(tmp_path: Path, small_pass, small_pass_dir) -> None:
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.estimate.adjust import adjust_pass
    from misrgraph.io.camera import load_camera_model
    from misrgraph.io.dem import read_dem

    sc, op = small_pass
    blocks = (52, 62)
    h, sd = _agp_from_terrain(sc, op.path, blocks)
    f = tmp_path / "agp.hdf"
    write_agp_by_hand(f, op.path, h, sd, blocks)
    out = tmp_path / "dem.h5"
    r = CliRunner().invoke(app, ["import", "agp", str(f), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    assert summary["path"] == op.path and summary["blocks"] == [52, 62]
    dem = read_dem(out)
    assert dem.sigma_m is not None
    cam = load_camera_model(small_pass_dir / "camera_model.h5").at_temperature(op.temperature_c)
    res = adjust_pass(op, cam, dem, sc.gcps)
    assert res.status == "converged" and np.isfinite(res.final_cost)
    bad = tmp_path / "not_agp.hdf"
    bad.write_bytes(b"\x0e\x03\x13\x01" + b"\x00" * 100)
    r = CliRunner().invoke(app, ["import", "agp", str(bad), "--out", str(tmp_path / "x.h5")])
    assert r.exit_code == 2 and "not_agp.hdf" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "x.h5").exists()


def test_read_l1b2_refuses_a_file_without_the_band(pp_files) -> None:
    pp_file = pp_files[1]["Df"]
    with pytest.raises(FileFormatError, match="no grid 'RedBand'"):
        read_l1b2(pp_file)
    with pytest.raises(FileFormatError, match="no grid 'Standard'"):
        read_agp(pp_file)


# ------------------------------------------------------------------------------------ L1B2 in


def write_l1b2_by_hand(path: Path, sky_path: int, camera_values: np.ndarray, blocks: list[int], scale: float) -> None:
    """A terrain-projected L1B2 red band written with raw HDF4 calls from MISR's published layout
    (grid RedBand, 275 m, ``Red Radiance/RDQI`` uint16 with fill 65515, ``Scale factor``), the
    blocks ``blocks`` holding ``camera_values (B, 512, 2048)``; not through misrgraph's writer."""
    from pyhdf.V import V  # noqa: F401
    from pyhdf.VS import VS  # noqa: F401

    params = som_proj_params(sky_path)
    struct = (
        "GROUP=SwathStructure\nEND_GROUP=SwathStructure\nGROUP=GridStructure\n\tGROUP=GRID_1\n"
        '\t\tGridName="RedBand"\n\t\tXDim=512\n\t\tYDim=2048\n'
        "\t\tUpperLeftPointMtrs=(7460750.000000,1090650.000000)\n\t\tLowerRightMtrs=(7601550.000000,527450.000000)\n"
        "\t\tProjection=GCTP_SOM\n\t\tProjParams=(" + ",".join(repr(float(p)) for p in params) + ")\n"
        "\t\tSphereCode=12\n\t\tGridOrigin=HDFE_GD_UL\n"
        '\t\tGROUP=Dimension\n\t\t\tOBJECT=Dimension_1\n\t\t\t\tDimensionName="SOMBlockDim"\n\t\t\t\tSize=180\n'
        "\t\t\tEND_OBJECT=Dimension_1\n\t\tEND_GROUP=Dimension\n\t\tGROUP=DataField\n"
        '\t\t\tOBJECT=DataField_1\n\t\t\t\tDataFieldName="Red Radiance/RDQI"\n\t\t\t\tDataType=DFNT_UINT16\n'
        '\t\t\t\tDimList=("SOMBlockDim","XDim","YDim")\n\t\t\tEND_OBJECT=DataField_1\n'
        "\t\tEND_GROUP=DataField\n\tEND_GROUP=GRID_1\nEND_GROUP=GridStructure\nEND\n"
    )
    data = np.full((180, 512, 2048), 65515, np.uint16)
    for k, b in enumerate(blocks):
        data[b - 1] = camera_values[k]
    sd = SD(str(path), SDC.WRITE | SDC.CREATE | SDC.TRUNC)
    sd.attr("StructMetadata.0").set(SDC.CHAR8, struct)
    sd.attr("Path_number").set(SDC.INT32, sky_path)
    sd.attr("Start_block").set(SDC.INT32, min(blocks))
    sd.attr("End block").set(SDC.INT32, max(blocks))
    s = sd.create("Red Radiance/RDQI", SDC.UINT16, [180, 512, 2048])
    for i, d in enumerate(("SOMBlockDim", "XDim", "YDim")):
        s.dim(i).setname(f"{d}:RedBand")
    s.setfillvalue(65515)
    s.setcompress(SDC.COMP_DEFLATE, 1)
    s[:] = data
    ref = s.ref()
    s.endaccess()
    sd.end()
    _grid_vgroups_by_hand(
        path, "RedBand", [ref], (("Scale factor", "FLOAT64", scale), ("_FV_Red Radiance/RDQI", "UINT16", 65515))
    )


def _l1b2_values(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    dn = rng.integers(1, 16000, (1, 512, 2048))
    rdqi = rng.integers(0, 3, dn.shape)
    values = (dn << 2) | rdqi
    obscured = np.zeros(dn.shape, bool)
    obscured[:, 100:110, 300:400] = True
    fill = np.zeros(dn.shape, bool)
    fill[:, :, :50] = True
    values = np.where(obscured, 65511, np.where(fill, 65515, values)).astype(np.uint16)
    return values, dn, rdqi, obscured | fill


def test_an_l1b2_written_by_hand_unpacks_and_imports_as_an_roi(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.io.roi import read_roi

    files = []
    truth = {}
    for k, cam in enumerate(("DF", "AN")):
        values, dn, rdqi, masked = _l1b2_values(k)
        f = tmp_path / f"MISR_AM1_GRP_TERRAIN_GM_P037_O012345_{cam}_F03_0024.hdf"
        write_l1b2_by_hand(f, 37, values, [60], 0.0471)
        files.append(f)
        truth[cam] = (values, dn, rdqi, masked)
    band = read_l1b2(files[1], blocks=[60])
    values, dn, rdqi, masked = truth["AN"]
    assert band.camera == "An" and band.resolution_m == 275 and band.scale_factor == pytest.approx(0.0471)
    np.testing.assert_array_equal(band.obscured, values == 65511)
    np.testing.assert_array_equal(band.fill, values == 65515)
    np.testing.assert_allclose(band.radiance[~masked], dn[~masked] * 0.0471)
    assert np.all(np.isnan(band.radiance[masked]))
    np.testing.assert_array_equal(band.rdqi[~masked], rdqi[~masked])
    out = tmp_path / "l1b2_roi.h5"
    r = CliRunner().invoke(app, ["import", "l1b2", *map(str, files), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    assert summary["cameras"] == ["Df", "An"] and summary["blocks"] == [60, 60] and summary["path"] == 37
    roi = read_roi(out)
    assert roi.cameras == ("Df", "An") and roi.pass_ids == ("P037_O012345",)
    for c, cam in enumerate(("DF", "AN")):
        values, dn, rdqi, masked = truth[cam]
        usable = ~masked & (rdqi < 2)
        np.testing.assert_array_equal(roi.pixels[c][usable], dn[usable])
        assert np.all(roi.pixels[c][~usable] == 0) and np.all(roi.source[c][~usable] == -1)
        np.testing.assert_array_equal(roi.obscured[c], values == 65511)
    r = CliRunner().invoke(app, ["import", "l1b2", str(files[0]), str(files[0]), "--out", str(tmp_path / "x.h5")])
    assert r.exit_code == 2 and "Df" in r.output and not (tmp_path / "x.h5").exists()


def test_l1b2_imagery_compared_with_an_roi_finds_a_known_shift(tmp_path: Path) -> None:
    """An ROI of a textured block and L1B2 files of the same block shifted by 0.4 px across the
    track: ``import l1b2 --compare`` measures the shift."""
    from scipy import ndimage
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.io.roi import roi_writer
    from misrgraph.runs.imports import _RoiBlock

    rng = np.random.default_rng(4)
    texture = ndimage.gaussian_filter(rng.normal(0, 1, (512, 2048)), 3.0)
    counts = 6000 + 2000 * texture / texture.std()
    shifted = ndimage.shift(counts, (0.0, 0.4), order=3, mode="nearest")
    ref = tmp_path / "roi.h5"
    with roi_writer(ref, 37, "red", ("An",), ["P037_O000001"], np.array([60]), 16383) as w:
        w.write(
            _RoiBlock(
                block=60,
                pixels=np.rint(counts)[None].astype(np.uint16),
                source=np.zeros((1, 512, 2048), np.int8),
                cloudy=np.zeros((1, 512, 2048), bool),
                obscured=np.zeros((1, 512, 2048), bool),
                clear_fraction=np.ones(1),
                chosen=0,
            )
        )
    f = tmp_path / "MISR_AM1_GRP_TERRAIN_GM_P037_O012345_AN_F03_0024.hdf"
    write_l1b2_by_hand(f, 37, (np.rint(shifted).astype(np.int64) << 2)[None].astype(np.uint16), [60], 0.05)
    r = CliRunner().invoke(
        app, ["import", "l1b2", str(f), "--out", str(tmp_path / "l1b2.h5"), "--compare", str(ref), "--json"]
    )
    assert r.exit_code == 0, r.output
    v = json.loads(r.output)["comparison"]["An"]["60"]
    assert v["matches"] >= 20
    assert v["mean_px"] == pytest.approx(0.4, abs=0.05) and v["rms_px"] == pytest.approx(0.4, abs=0.05)


def test_export_refuses_two_passes_that_would_share_a_misr_file_name(tmp_path: Path) -> None:
    from misrgraph.io.products import save_pp
    from misrgraph.runs.products import export_misr

    a, b = _pp(cameras=("An",)), _pp(cameras=("An",))
    b.pass_id = "P037_O12345"  # the same orbit as a's P037_O012345
    save_pp(a, tmp_path / "a.h5")
    save_pp(b, tmp_path / "b.h5")
    rows = [{"files": {"pp": str(tmp_path / "a.h5")}}, {"files": {"pp": str(tmp_path / "b.h5")}}]
    with pytest.raises(InputError, match="different orbits"):
        export_misr({"passes": rows, "roi": None}, tmp_path / "misr")
    assert not (tmp_path / "misr").exists()  # refused before either pass was written
    b.pass_id = "P037_O012346"
    save_pp(b, tmp_path / "b.h5")
    got = export_misr({"passes": rows, "roi": None}, tmp_path / "misr")
    assert sorted(Path(f["An"]).name for f in got["pp"].values()) == [
        "MISR_AM1_PP_P037_O012345_AN_F01_0001.hdf",
        "MISR_AM1_PP_P037_O012346_AN_F01_0001.hdf",
    ]
