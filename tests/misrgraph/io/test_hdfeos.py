"""HDF-EOS2 grid files: the layout checked with raw HDF4 calls and with GDAL's HDF4_EOS driver
(an independent reader; those tests skip where gdal-bin is not installed), the ODL parser on a
structural metadata text typed from MISR's published layout, and the refusals."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyhdf")

from pyhdf.SD import SD, SDC  # noqa: E402

from misrgraph.errors import FileFormatError, InputError, OutputError  # noqa: E402
from misrgraph.io.hdfeos import EosField, EosGrid, parse_odl, read_eos_field, read_eos_file, write_eos_file  # noqa: E402

GDAL = shutil.which("gdalinfo") is not None and shutil.which("gdal_translate") is not None
needs_gdal = pytest.mark.skipif(not GDAL, reason="GDAL's command-line tools (gdal-bin) are not installed")

#: The head of an AGP's StructMetadata.0 as MISR writes it (grid Standard, 1.1 km, path 37).
AGP_STRUCT = """GROUP=SwathStructure
END_GROUP=SwathStructure
GROUP=GridStructure
\tGROUP=GRID_1
\t\tGridName="Standard"
\t\tXDim=128
\t\tYDim=512
\t\tUpperLeftPointMtrs=(7460750.000000,1090650.000000)
\t\tLowerRightMtrs=(7601550.000000,527450.000000)
\t\tProjection=GCTP_SOM
\t\tProjParams=(6378137,-0.006694348,0,98018013.752,72008017.5848927,0,0,0,98.88,0,0,180,0)
\t\tSphereCode=12
\t\tGridOrigin=HDFE_GD_UL
\t\tGROUP=Dimension
\t\t\tOBJECT=Dimension_1
\t\t\t\tDimensionName="SOMBlockDim"
\t\t\t\tSize=180
\t\t\tEND_OBJECT=Dimension_1
\t\tEND_GROUP=Dimension
\t\tGROUP=DataField
\t\t\tOBJECT=DataField_1
\t\t\t\tDataFieldName="AveSceneElev"
\t\t\t\tDataType=DFNT_INT16
\t\t\t\tDimList=("SOMBlockDim","XDim","YDim")
\t\t\tEND_OBJECT=DataField_1
\t\tEND_GROUP=DataField
\tEND_GROUP=GRID_1
END_GROUP=GridStructure
END
"""


def _grid(n_blocks: int = 6) -> EosGrid:
    rng = np.random.default_rng(3)
    a = rng.normal(0, 100, (n_blocks, 8, 16)).astype(np.float32)
    a[0, 0, :3] = -9999.0
    b = rng.integers(0, 60000, (n_blocks, 8, 16)).astype(np.uint16)
    return EosGrid(
        name="Test_Grid",
        xdim=8,
        ydim=16,
        upper_left_m=(1000.0, 2600.0),
        lower_right_m=(1800.0, 1000.0),
        projection="GCTP_SOM",
        proj_params=(6378137.0, -0.006694348, 0, 98018013.752, 72008017.5848927, 0, 0, 0, 98.88, 0, 0, 180, 0),
        sphere_code=12,
        dimensions={"SOMBlockDim": n_blocks},
        fields=[
            EosField("heights", a, ("SOMBlockDim", "XDim", "YDim"), -9999.0, {"units": "m"}),
            EosField("Red Radiance/RDQI", b, ("SOMBlockDim", "XDim", "YDim"), 65515),
        ],
        attributes={"Scale factor": 0.047, "Block_size.size_x": np.int32(8)},
    )


def test_odl_parser_reads_misr_structural_metadata() -> None:
    odl = parse_odl(AGP_STRUCT)
    g = odl["GridStructure"]["GRID_1"]
    assert g["GridName"] == "Standard" and g["XDim"] == 128 and g["YDim"] == 512
    assert g["UpperLeftPointMtrs"] == (7460750.0, 1090650.0)
    assert g["ProjParams"][4] == pytest.approx(72008017.5848927) and g["ProjParams"][11] == 180
    assert g["DataField"]["DataField_1"]["DimList"] == ("SOMBlockDim", "XDim", "YDim")
    assert g["Dimension"]["Dimension_1"] == {"DimensionName": "SOMBlockDim", "Size": 180}


def test_the_layout_is_hdf_eos2s(tmp_path: Path) -> None:
    """What the HDF-EOS2 library looks up, read with plain HDF4 calls."""
    from pyhdf.HDF import HC, HDF
    from pyhdf.V import V  # noqa: F401
    from pyhdf.VS import VS  # noqa: F401

    g = _grid()
    f = write_eos_file(tmp_path / "t.hdf", [g], {"Path_number": np.int32(37)})
    sd = SD(str(f), SDC.READ)
    attrs = sd.attributes()
    assert attrs["HDFEOSVersion"].startswith("HDFEOS_V2")
    assert 'GridName="Test_Grid"' in attrs["StructMetadata.0"]
    assert attrs["Path_number"] == 37
    sds = sd.select("heights")
    assert [sds.dim(i).info()[0] for i in range(3)] == ["SOMBlockDim:Test_Grid", "XDim:Test_Grid", "YDim:Test_Grid"]
    assert sds.getfillvalue() == -9999.0
    np.testing.assert_array_equal(sds[:], g.fields[0].data)
    heights_ref = sds.ref()
    sds.endaccess()
    sd.end()
    hdf = HDF(str(f), HC.READ)
    v, vs = hdf.vgstart(), hdf.vstart()
    found = {}
    ref = v.getid(-1)
    while True:
        vg = v.attach(ref)
        found[(vg._name, vg._class)] = vg.tagrefs()
        vg.detach()
        try:
            ref = v.getid(ref)
        except Exception:
            break
    grid_members = found[("Test_Grid", "GRID")]
    names = {v.attach(r)._name for t, r in grid_members if t == HC.DFTAG_VG}
    assert names == {"Data Fields", "Grid Attributes"}
    assert (HC.DFTAG_NDG, heights_ref) in found[("Data Fields", "GRID Vgroup")]
    attr_refs = [r for t, r in found[("Grid Attributes", "GRID Vgroup")] if t == HC.DFTAG_VH]
    values = {}
    for r in attr_refs:
        vd = vs.attach(r)
        assert vd._class == "Attr0.0" and vd._fields == ["AttrValues"]
        values[vd._name] = vd.read(1)[0][0]
        vd.detach()
    vs.end()
    v.end()
    hdf.close()
    assert values["Scale factor"] == pytest.approx(0.047)
    assert values["_FV_heights"] == pytest.approx(-9999.0)
    assert values["_FV_Red Radiance/RDQI"] == 65515


def test_written_file_reads_back(tmp_path: Path) -> None:
    g = _grid()
    f = write_eos_file(
        tmp_path / "t.hdf",
        [g],
        {"Start_block": np.int32(3)},
        {"Meta": ("Blockmetadata", {"Block_number": np.arange(1, 7, dtype=np.int32)})},
    )
    e = read_eos_file(f)
    assert e.grids["Test_Grid"]["dimensions"] == {"SOMBlockDim": 6}
    assert set(e.grids["Test_Grid"]["fields"]) == {"heights", "Red Radiance/RDQI"}
    assert e.grid_attributes["Test_Grid"]["Scale factor"] == pytest.approx(0.047)
    np.testing.assert_array_equal(e.vdatas["Meta"]["Block_number"], np.arange(1, 7))
    np.testing.assert_array_equal(read_eos_field(f, "Red Radiance/RDQI", [2, 4]), g.fields[1].data[[2, 4]])


def _gdal_json(target: str) -> dict:
    out = subprocess.run(["gdalinfo", "-json", target], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def _gdal_band(target: str, band: int, dtype: str, tmp: Path) -> np.ndarray:
    raw = tmp / f"band{band}.bin"
    # HDF4_BLOCK_PIXELS: read the whole raster as one block (GDAL reads an XDim-first field in its
    # storage order one raster block at a time)
    subprocess.run(
        [
            "gdal_translate",
            "-q",
            "--config",
            "HDF4_BLOCK_PIXELS",
            "4194304",
            "-of",
            "ENVI",
            "-b",
            str(band),
            target,
            str(raw),
        ],
        check=True,
    )
    return np.fromfile(raw, dtype=dtype)


@needs_gdal
def test_gdal_reads_grid_fields_fill_values_and_data(tmp_path: Path) -> None:
    g = _grid()
    f = write_eos_file(tmp_path / "t.hdf", [g], {"Path_number": np.int32(37)})
    listing = _gdal_json(str(f))
    subs = listing["metadata"]["SUBDATASETS"]
    names = {v for k, v in subs.items() if k.endswith("_NAME")}
    assert f'HDF4_EOS:EOS_GRID:"{f}":Test_Grid:heights' in names
    target = f'HDF4_EOS:EOS_GRID:"{f}":Test_Grid:heights'
    info = _gdal_json(target)
    assert info["size"] == [8, 16]  # XDim columns, YDim rows
    assert len(info["bands"]) == 6  # one band per block of SOMBlockDim
    assert info["bands"][0]["noDataValue"] == -9999.0
    assert info["geoTransform"] == [1000.0, 100.0, 0.0, 2600.0, 0.0, -100.0]
    assert "GCTP projection number 22" in info["coordinateSystem"]["wkt"]
    md = info["metadata"][""]
    assert float(md["Scale factor"]) == pytest.approx(0.047)
    assert md["Path_number"] == "37"
    for band in (1, 4):
        got = _gdal_band(target, band, "<f4", tmp_path)
        # GDAL returns the block's values in the file's storage order (XDim outer, YDim inner)
        np.testing.assert_array_equal(got, g.fields[0].data[band - 1].ravel())


def test_refuses_files_that_are_not_hdf_eos2(tmp_path: Path) -> None:
    text = tmp_path / "x.hdf"
    text.write_text("not hdf")
    with pytest.raises(FileFormatError, match="not a readable HDF4 file"):
        read_eos_file(text)
    plain = tmp_path / "plain.hdf"
    sd = SD(str(plain), SDC.WRITE | SDC.CREATE)
    s = sd.create("a", SDC.INT16, [2, 2])
    s[:] = np.zeros((2, 2), np.int16)
    s.endaccess()
    sd.end()
    with pytest.raises(FileFormatError, match="no StructMetadata.0"):
        read_eos_file(plain)
    lying = tmp_path / "lying.hdf"
    sd = SD(str(lying), SDC.WRITE | SDC.CREATE)
    sd.attr("StructMetadata.0").set(SDC.CHAR8, AGP_STRUCT)
    sd.end()
    with pytest.raises(FileFormatError, match="field AveSceneElev is in the metadata but not in the file"):
        read_eos_file(lying)
    with pytest.raises(FileFormatError, match="no such file"):
        read_eos_file(tmp_path / "missing.hdf")


def test_a_failed_write_leaves_no_file(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match=str(blocker)):
        write_eos_file(blocker / "t.hdf", [_grid()])
    g = _grid()
    bad = EosGrid(**{**g.__dict__, "attributes": {"complex": np.array([1 + 2j])}})
    with pytest.raises(InputError, match="dtype"):
        write_eos_file(tmp_path / "half.hdf", [bad])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.parametrize("chunked", [True, False])
def test_a_field_given_for_some_blocks_reads_as_fill_elsewhere(tmp_path: Path, monkeypatch, chunked: bool) -> None:
    """With HDF4's chunking (only the given blocks stored) and without it (the whole field)."""
    from misrgraph.io import hdfeos

    if not chunked:
        monkeypatch.setattr(hdfeos, "_chunk_deflate", lambda *a: False)
    some = np.arange(2 * 8 * 16, dtype=np.int16).reshape(2, 8, 16)
    g = EosGrid(
        **{
            **_grid().__dict__,
            "dimensions": {"SOMBlockDim": 180},
            "fields": [EosField("h", some, ("SOMBlockDim", "XDim", "YDim"), -9999, index=[3, 170])],
        }
    )
    f = write_eos_file(tmp_path / "t.hdf", [g])
    data = read_eos_field(f, "h")
    assert data.shape == (180, 8, 16)
    np.testing.assert_array_equal(data[[3, 170]], some)
    assert np.all(np.delete(data, [3, 170], axis=0) == -9999)
    sd = SD(str(f), SDC.READ)
    assert sd.select("h").getcompress()[0] == SDC.COMP_DEFLATE
    sd.end()
