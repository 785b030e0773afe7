"""Reference Orbit Imagery from four simulated passes (one block, cameras Df/An/Da, 256 samples):
the mosaic's bookkeeping, its misregistration against the simulator's truth, the co-registration
matching measures on it against that truth, and the GeoTIFF's georeferencing against the SOM grid."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.io.products import ProjectionParameters, read_pp
from misrgraph.io.roi import read_roi
from misrgraph.misr.som import SomGrid
from misrgraph.runs.products import RoiOptions, run_products

#: The SOM DEM's error (1 sigma, m) times the D cameras' parallax against An (tan 70.5 deg), in
#: 275 m pixels: what the ROI's co-registration cannot beat, whatever the navigation.
DEM_PARALLAX_PX = 10.0 * np.tan(np.radians(70.5)) / 275.0


@pytest.fixture(scope="module")
def roi_run(roi_path_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("roi_out")
    res = run_products(
        roi_path_dir,
        out,
        roi=True,
        roi_options=RoiOptions(geotiff=True, quicklooks=True),
        file_format="misr" if importlib.util.find_spec("pyhdf") else "h5",
    )
    return res, out


def test_the_roi_as_misr_files(roi_run):
    """``--format misr``: one L1B2-style file per camera whose unpacked radiance is the ROI's counts."""
    pytest.importorskip("pyhdf")
    from misrgraph.io.misrfiles import read_l1b2

    res, _ = roi_run
    roi = read_roi(res["roi"]["file"])
    files = res["misr_files"]["roi"]
    assert set(files) == set(roi.cameras)
    for c, cam in enumerate(roi.cameras):
        band = read_l1b2(files[cam])
        assert band.camera == cam and band.blocks.tolist() == roi.blocks.tolist()
        imaged = roi.source[c] >= 0
        np.testing.assert_array_equal(band.radiance[imaged], roi.pixels[c][imaged].astype(float))
        np.testing.assert_array_equal(band.obscured, roi.obscured[c])
        assert np.all(band.fill == (~imaged & ~roi.obscured[c]))
    assert len(res["misr_files"]["pp"]) == len(res["passes"])


def test_mosaic_bookkeeping(roi_run):
    res, _ = roi_run
    roi = read_roi(res["roi"]["file"])
    assert roi.cameras == ("Df", "An", "Da") and len(roi.pass_ids) == 4 and roi.pixels.shape == (3, 1, 512, 2048)
    # the block's pass is the clearest; every imaged pixel names a pass and holds counts, others are empty
    assert roi.chosen[0] == int(np.argmax(roi.clear_fraction[0]))
    src, px = roi.source, roi.pixels
    assert set(np.unique(src).tolist()) <= {-1, 0, 1, 2, 3}
    assert np.all(px[src < 0] == 0) and np.all(px[src >= 0] > 0)
    # a point terrain hides from every pass is empty (and counted in the summary)
    assert not np.any(roi.obscured & (src >= 0))
    for j, cam in enumerate(roi.cameras):
        assert res["roi"]["obscured_fraction"][int(roi.blocks[0])][cam] == pytest.approx(float(roi.obscured[j].mean()))
    # 256 samples of the swath: a band across the block, about 256/2048 of it per camera
    frac = np.mean(src >= 0, axis=(1, 2, 3))
    assert np.all((frac > 0.08) & (frac < 0.2)), frac
    # clouds (20 % of the sky each pass, different every pass) are filled from other passes:
    # few pixels are left cloudy, and the block's pass supplies the most clear pixels
    clear = (src >= 0) & ~roi.cloudy
    assert np.mean(roi.cloudy[src >= 0]) < 0.05
    assert np.argmax(np.bincount(src[clear], minlength=4)) == roi.chosen[0]
    assert all(p.endswith(".png") for p in res["roi"]["quicklooks"].values())


def test_misregistration_against_truth(roi_run):
    """The truth's misregistration of the resampled images: between cameras, the DEM's parallax
    and the two cameras' PP errors; between passes, the two passes' PP errors. Each within 3x
    what those predict (the PP's own 1 sigma, in pixels, over the block)."""
    res, _ = roi_run
    tr = res["roi_truth"]
    # the terrain mask against the truth's rays (this block is gentle: nothing is hidden; the
    # mask's agreement with the truth on a ridge is tests/misrgraph/products/test_terrain.py's)
    for cam, c in res["roi_truth_obscured"].items():
        assert c["points"] > 500 and c["missed"] <= c["hidden"] and c["false"] <= c["flagged"], (cam, c)
        assert c["missed"] == 0 and c["false"] == 0, (cam, c)
    pps = [read_pp(r["files"]["pp"]) for r in res["passes"]]

    def pp_sigma(cam: str) -> float:  # radial 1 sigma (px), worst pass, median over the block
        return max(
            float(np.nanmedian(np.hypot(pp.sigma_line[pp.cameras.index(cam)], pp.sigma_sample[pp.cameras.index(cam)])))
            for pp in pps
        )

    block = int(res["blocks"][0])
    summary_pred = res["roi_predicted_px_by_block"][block]
    for cam in ("Df", "Da"):
        predicted = np.sqrt(DEM_PARALLAX_PX**2 + pp_sigma(cam) ** 2 + pp_sigma("An") ** 2)
        assert tr["between_cameras_px"][cam] < 3 * predicted, (cam, tr["between_cameras_px"][cam], predicted)
        # the summary's own prediction (RMS over the block, chosen pass) agrees with this one
        # (median over the block, worst pass) within the spread of the PP's sigma over a block
        assert summary_pred[cam]["vs_An"] == pytest.approx(predicted, rel=0.3), cam
        assert tr["between_cameras_px"][cam] < 3 * summary_pred[cam]["vs_An"], cam
    for cam in ("Df", "An", "Da"):
        predicted = np.sqrt(2) * pp_sigma(cam)
        assert tr["between_passes_px"][cam] < 3 * predicted, (cam, tr["between_passes_px"][cam], predicted)
        assert summary_pred[cam]["between_passes"] == pytest.approx(predicted, rel=0.3), cam
    assert "vs_An" not in summary_pred["An"]
    assert res["roi_predicted_px"]["Da"]["vs_An"] == summary_pred["Da"]["vs_An"]  # one block: its worst is its own


def test_matched_coregistration_against_truth(roi_run):
    """Matching on the ROI measures what the truth says at the points it matched (the block's
    pairs of a kind pooled): between passes (same camera, same blur) to 0.05 px, the matching
    error within 0.7-1.6 of its LSM sigma (measured 0.02-0.03 px, 0.9-1.3 sigma); between
    cameras it reads higher (another blur and BRDF: the matching error is ~0.2 px, about twice
    the LSM sigma, so subtracting that sigma leaves some of it) but by less than 0.1 px. Against
    the truth at random points of the block the matched points are another sample of the same
    field: their truth differs by the field's variation over the block (measured up to 0.035 px
    between passes)."""
    res, _ = roi_run
    tr, co = res["roi_truth"], res["roi_coregistration"]
    for cam in ("Df", "An", "Da"):
        st = co[cam]["between_passes"]
        at = st["truth_at_matches"]
        assert st["matches"] >= 20 and st["failed"] <= 0.1 * st["matches"] and at["matches"] == st["matches"]
        assert abs(st["excess_px"] - at["truth_px"]) < 0.05, (cam, st)
        assert 0.7 < at["error_over_sigma"] < 1.6, (cam, at)
        assert abs(at["truth_px"] - tr["between_passes_pooled_px"][cam]) < 0.1, (
            cam,
            at,
            tr["between_passes_pooled_px"],
        )
    for cam in ("Df", "Da"):
        st = co[cam]["between_cameras"]
        at = st["truth_at_matches"]
        assert st["matches"] >= 20
        assert -0.05 < st["excess_px"] - at["truth_px"] < 0.1, (cam, st)
        assert at["error_over_sigma"] < 3.0, (cam, at)
    for kind in ("between_cameras", "between_passes"):  # the pooled RMS never exceeds the worst pair's
        for cam, v in tr[f"{kind}_pooled_px"].items():
            assert v <= tr[f"{kind}_px"][cam] + 1e-12, (kind, cam)
    assert set(res["roi_coregistration_px"]) == {"Df", "An", "Da"}


def test_coregistration_pools_the_pairs(roi_run):
    """Each kind pools its pairs: the pooled mean square is the matches-weighted mean of the
    pairs', so the pooled excess never exceeds the worst pair's; its interval holds it; the
    camera's figure is the worse kind of its worst block."""
    res, _ = roi_run
    by_block = res["roi_coregistration_by_block"]
    for cam, kinds in res["roi_coregistration"].items():
        for kind, st in kinds.items():
            lo, hi = st["excess_interval_px"]
            assert lo <= st["excess_px"] <= hi, (cam, kind, st)
            assert st["pairs"] == (3 if kind == "between_passes" else 4), (cam, kind, st["pairs"])
            assert st["excess_px"] <= st["worst_pair"]["excess_px"] + 1e-12, (cam, kind)
            at = st["truth_at_matches"]  # what was rejected was wrong (where anything was)
            assert at["rejected"] == st["rejected"] and at["rejected"] <= 0.05 * at["matches"], (cam, kind, at)
            if at["rejected"]:  # worse than the kept ones; twice as bad once there are a few to average
                factor = 2.0 if at["rejected"] >= 3 else 1.0
                assert at["rejected_error_px"] > factor * at["error_px"], (cam, kind, sorted(at.items()))
            assert st["worst_pair"]["matches"] < st["matches"]
            assert by_block[st["block"]][cam][kind] == st["excess_px"]
        assert res["roi_coregistration_px"][cam] == max(st["excess_px"] for st in kinds.values())
    assert res["roi_coregistration_unmeasured"] == {}  # the block has land and texture in every camera


def test_offset_stats_interval_covers_the_truth():
    """On offsets drawn with a known misregistration ``e`` (radial RMS) and matching noise
    ``s`` per component (reported as the matches' sigma), the 95 % interval of the excess holds
    ``e`` in 95 % of 400 seeded draws of 40 matches (binomial 3-sigma band 0.917-0.983)."""
    from misrgraph.products.roi import _offset_stats

    e, s, n = 0.15, 0.08, 40
    a = np.sqrt(e**2 / 2 + s**2)  # per-component spread of an offset
    rng = np.random.default_rng(7)
    hits = 0
    for _ in range(400):
        d = np.column_stack([rng.normal(0, a, (n, 2)), np.full((n, 2), s)])
        st = _offset_stats(d)
        lo, hi = st["excess_interval_px"]
        hits += lo <= e <= hi
        assert st["noise_px"] == pytest.approx(s * np.sqrt(2))
    assert 0.917 <= hits / 400 <= 0.983, hits


def test_geotiff_georeferencing(roi_run):
    """A pixel of the GeoTIFF, found by its SOM coordinates through rasterio, holds the ROI's value
    at that block/line/sample; the CRS is the path's misrsom."""
    rasterio = pytest.importorskip("rasterio")
    res, _ = roi_run
    roi = read_roi(res["roi"]["file"])
    grid = SomGrid(roi.path, 275)
    c = roi.cameras.index("An")
    lines, samples = np.nonzero(roi.pixels[c, 0])
    pick = np.linspace(0, lines.size - 1, 25).astype(int)
    with rasterio.open(res["roi"]["geotiff"]["An"]) as ds:
        assert "misrsom" in ds.crs.to_proj4() and "+path=37" in ds.crs.to_proj4()
        img = ds.read(1)
        for k in pick:
            x, y = grid.bls_to_somxy(int(roi.blocks[0]), lines[k], samples[k])
            r, q = ds.index(float(x), float(y))
            assert img[r, q] == roi.pixels[c, 0, lines[k], samples[k]]


def test_cli_roi_refusals(roi_path_dir, path_dir, tmp_path):
    runner = CliRunner()
    r = runner.invoke(app, ["products", str(path_dir), "--out", str(tmp_path / "a"), "--roi"])
    assert r.exit_code == 2 and "--roi" in r.output and "0 passes with whole-swath strips" in r.output
    first = sorted((roi_path_dir / "passes").glob("*.h5"))[0]
    r = runner.invoke(app, ["products", str(roi_path_dir), "--out", str(tmp_path / "b"), "--roi", "--pass", str(first)])
    assert r.exit_code == 2 and "--pass" in r.output
    r = runner.invoke(app, ["products", str(roi_path_dir), "--out", str(tmp_path / "c"), "--geotiff"])
    assert r.exit_code == 2 and "--roi" in r.output
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_view_roi_and_pp_sigma(roi_run, tmp_path):
    """rerun: the ROI's blocks as images with their source maps, and a PP file's 1-sigma heat maps;
    the logged images hold the file's pixels (every 2nd) and sigma grid."""
    pytest.importorskip("rerun")
    import rerun.chunk as rc

    from misrgraph.viz.viewer import run_view

    res, _ = roi_run
    out = run_view(res["roi"]["file"], save=tmp_path / "roi.rrd")
    assert out["kind"] == "reference_orbit_imagery" and out["entities"]["ROI block images"] == 3
    out_pp = run_view(res["passes"][0]["files"]["pp"], save=tmp_path / "pp.rrd")
    assert out_pp["kind"] == "projection_parameters" and out_pp["entities"]["PP sigma maps"] == 3
    roi = read_roi(res["roi"]["file"])
    logged = {}
    for ch in rc.RrdReader(str(tmp_path / "roi.rrd")).store().stream():
        if str(ch.entity_path) == "/roi/An/image":
            rb = ch.to_record_batch()
            col = [c for c in rb.schema.names if c.endswith("buffer")][0]
            buf = rb.column(col).to_pylist()[0]
            buf = buf[0] if buf and isinstance(buf[0], list) else buf  # one image per row
            logged["An"] = np.asarray(buf, dtype=np.uint8).view(np.float32)
    assert np.array_equal(logged["An"], roi.pixels[roi.cameras.index("An"), 0, ::2, ::2].astype(np.float32).ravel())
    # the pass names apply to the source maps: logged on their common ancestor
    paths = {str(ch.entity_path) for ch in rc.RrdReader(str(tmp_path / "roi.rrd")).store().stream()}
    assert "/roi" in paths and "/roi/An/source" in paths


def _flat_pp(blocks: list[int], sigmas: dict[str, tuple[float, float]]) -> ProjectionParameters:
    """A PP whose 1-sigma is constant per camera (line, sample) over its blocks (other grids zero)."""
    from misrgraph.io.products import ProjectionParameters

    cams = tuple(sigmas)
    shape = (len(cams), len(blocks), 128, 512)
    z = np.zeros(shape)
    sl = np.stack([np.full(shape[1:], sigmas[c][0]) for c in cams])
    ss = np.stack([np.full(shape[1:], sigmas[c][1]) for c in cams])
    sl[..., :8] = np.nan  # points outside the view hold no sigma
    return ProjectionParameters(37, np.array(blocks), cams, "red", "P", z, z, z, z, z, z, sl, ss, z, z)


def test_predicted_coregistration_closed_form():
    """roi_predicted_coregistration on PP of constant 1-sigma: the chosen pass's camera and An with
    the DEM's parallax against An, the two least precise passes between passes; a pass without the
    block is left out."""
    from misrgraph.products.roi import roi_predicted_coregistration

    pps = [
        _flat_pp([70, 71], {"An": (0.06, 0.08), "Da": (0.3, 0.4)}),
        _flat_pp([70, 71], {"An": (0.12, 0.16), "Da": (0.6, 0.8)}),
        _flat_pp([70, 71], {"An": (0.09, 0.12), "Da": (0.36, 0.48)}),
        _flat_pp([62], {"An": (3.0, 4.0), "Da": (3.0, 4.0)}),
    ]  # another block: not in 71's figures
    out = roi_predicted_coregistration(pps, 71, 0, ("An", "Da"), dem_sigma_m=10.0, resolution_m=275.0)
    parallax = 10.0 * np.tan(np.radians(70.5)) / 275.0
    assert out["Da"]["vs_An"] == pytest.approx(np.sqrt(parallax**2 + 0.5**2 + 0.1**2))
    assert out["Da"]["between_passes"] == pytest.approx(np.hypot(1.0, 0.6))
    assert out["An"] == {"between_passes": pytest.approx(np.hypot(0.2, 0.15))}
    # with the second pass chosen, against An uses its sigmas
    assert roi_predicted_coregistration(pps, 71, 1, ("An", "Da"), 0.0, 275.0)["Da"]["vs_An"] == pytest.approx(
        np.hypot(1.0, 0.2)
    )


def test_consistent_matches_rejects_wrong_matches_only():
    """An affine misregistration (0.1-0.3 px over the block) measured with LSM noise sigma 0.05
    px, plus 4 wrong matches 0.4-0.9 px off: over 50 seeded pairs of 60 matches every wrong one
    is rejected, and of the 2800 good ones at most 3 (a 4-sigma test rejects ~1.3e-4 of them per
    match, ~0.4 expected; the robust sigma's own scatter adds a little)."""
    from misrgraph.products.roi import consistent_matches

    rng = np.random.default_rng(3)
    false_rejects = 0
    for _ in range(50):
        pts = np.column_stack([rng.integers(30, 480, 60), rng.integers(30, 2000, 60)])
        field = 0.1 + 0.2 * pts[:, :1] / 512 * np.array([[1.0, -0.5]]) + 0.1 * pts[:, 1:] / 2048
        d = np.column_stack([field + rng.normal(0, 0.05, (60, 2)), np.full((60, 2), 0.05)])
        wrong = rng.choice(60, 4, replace=False)
        d[wrong, :2] += rng.uniform(0.4, 0.9, (4, 1)) * np.array(
            [[np.cos(a), np.sin(a)] for a in rng.uniform(0, 2 * np.pi, 4)]
        )
        keep = consistent_matches(pts, d)
        assert not keep[wrong].any()
        false_rejects += int((~keep).sum()) - 4
    assert false_rejects <= 3, false_rejects
