"""The rerun recordings hold the documented entities, and the ellipsoids match their covariances."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.model.constants import ANGLES, CAMERAS
from misrgraph.runs.adjust import run_adjust
from misrgraph.viz.viewer import run_view


def _read(path):
    import rerun.chunk as rc

    rows: dict[str, int] = {}
    batches: dict[str, list] = {}
    for ch in rc.RrdReader(str(path)).store().stream():
        p = str(ch.entity_path)
        rows[p] = rows.get(p, 0) + ch.num_rows
        batches.setdefault(p, []).append(ch.to_record_batch())
    return rows, batches


@pytest.fixture(scope="module")
def recording(small_pass_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("view")
    run_adjust(small_pass_dir, out=d / "r.h5")
    out = run_view(d / "r.h5", save=d / "r.rrd", exaggeration=150.0)
    return d / "r.h5", d / "r.rrd", out


def test_documented_entities_and_row_counts(recording):
    _, rrd, out = recording
    rows, _ = _read(rrd)
    for name, n in out["entities"].items():
        assert rows.get("/" + name) == n, name
    for a in ANGLES:
        for s in ("estimate", "upper", "lower", "truth", "knots"):
            assert f"/attitude/{a}/{s}" in rows
    for cam in CAMERAS:
        assert f"/world/footprints/{cam}" in rows and f"/residuals/{cam}/histogram" in rows
    assert "/world/orbit" in rows and "/world/globe" in rows
    _, batches = _read(rrd)
    for name, n in out["instances"].items():
        rb = batches["/" + name][0]
        col = [c for c in rb.schema.names if "positions" in c][0]
        assert len(rb.column(col).to_pylist()[0]) == n, name
    with h5py.File(recording[0], "r") as f:
        assert out["instances"]["world/landmarks/tie"] == int(np.sum(f["landmarks/kind"][()] == 0))


def test_ellipsoid_sizes_match_covariances(recording):
    h5, rrd, out = recording
    _, batches = _read(rrd)
    rb = batches["/world/landmarks/tie/ellipsoids"][0]
    col = [c for c in rb.schema.names if "half_sizes" in c][0]
    half = np.asarray(rb.column(col).to_pylist()[0], dtype=float)
    with h5py.File(h5, "r") as f:
        kind = f["landmarks/kind"][()]
        cov = f["landmarks/covariance"][()][kind == 0]
    expect = 3.0 * np.sqrt(np.linalg.eigvalsh(cov)) * 150.0
    np.testing.assert_allclose(np.sort(half, axis=1), np.sort(expect, axis=1), rtol=1e-5)


def test_calibration_recording(small_month_dir, tmp_path):
    from misrgraph.runs.calibrate import run_calibrate

    run_calibrate(small_month_dir, out=tmp_path / "cgm.h5", max_passes=15)
    out = run_view(tmp_path / "cgm.h5", save=tmp_path / "c.rrd")
    rows, batches = _read(tmp_path / "c.rrd")
    assert rows["/calibration/correlation"] == 1
    assert all(f"/calibration/{c}/corrections" in rows for c in CAMERAS)
    assert out["kind"] == "camera_model"


def test_view_needs_a_destination(recording):
    with pytest.raises(InputError, match="--save/--spawn"):
        run_view(recording[0])


def test_view_pass_imagery_logs_windows_with_matched_and_true_positions(imagery_pass_dir, tmp_path):
    """A pass with imagery (matched by the fixture): one image per GCP window, written to an .rrd."""
    f = sorted((imagery_pass_dir / "passes").glob("*.h5"))[0]
    out = run_view(f, save=tmp_path / "img.rrd")
    assert out["kind"] == "orbit_pass" and out["entities"]["image windows"] >= 9
    assert (tmp_path / "img.rrd").stat().st_size > 10_000
