"""Projection Parameters: the fast crossing against the general line search, the height
quadratic and 275 m interpolation against direct projection, the propagated 1-sigma against
Monte Carlo draws from the posterior, accuracy against the simulator's truth, the file and the CLI."""

from __future__ import annotations

import dataclasses
import json

import gtsam
import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.adjust import corrected_geometry, estimated_models, supplied_camera_of
from misrgraph.evaluate.products import score_pp
from misrgraph.io.products import read_pp, save_pp
from misrgraph.io.truth import read_pass_truth
from misrgraph.misr.som import SomGrid
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.frames import geodetic_to_ecef
from misrgraph.products.pp import _posterior, compute_pp, crossing

RED = BANDS.index("red")
BLOCK = 57  # the block of the ``pp`` fixture (conftest.py: PP_BLOCK)


@pytest.fixture(scope="module")
def pp_without_jitter(adjusted):
    """The PP of a posterior without the unresolved attitude jitter (which no draw of the
    posterior holds), on a coarse covariance sub-grid."""
    _, op, _, res = adjusted
    res0 = dataclasses.replace(res, unresolved_attitude_rad=0.0)
    return res0, compute_pp(op, res0, op.path, np.array([BLOCK]), sigma_step=32)


def _grid_points(path: int, step: int, height: float = 0.0):
    g = SomGrid(path)
    x, y = g.block_centres(BLOCK, step=step)
    lat, lon = g.somxy_to_latlon(x, y)
    return geodetic_to_ecef(lat.ravel(), lon.ravel(), np.full(lat.size, height))


@pytest.mark.parametrize("cam", ["Df", "An", "Ca"])
def test_crossing_agrees_with_the_general_line_search(adjusted, cam) -> None:
    _, op, _, res = adjusted
    geo = corrected_geometry(op, res.attitude, res.ephemeris, res.camera)
    c = CAMERAS.index(cam)
    g = _grid_points(op.path, 16, 500.0)
    ref = geo.ground_to_pixel(c, RED, g)
    t_ref = geo.t0[c, RED] + ref.crossing_line * geo.camera.line_time
    # start a second away: the secant steps must find the same crossing
    t, line, sample = crossing(geo, c, RED, g, t_ref + 1.0)
    ok = ref.visible
    assert ok.sum() > 100
    np.testing.assert_allclose(line[ok], ref.crossing_line[ok], atol=1e-4)
    # ground_to_pixel's sample is taken at the exposure time, up to half a line time from t*,
    # while the point drifts across the array (Earth rotation not compensated away from 30 deg)
    c_ = np.full(int(ok.sum()), c)
    y1 = geo._along_cross(c_, np.full_like(c_, RED), g[ok], t[ok] + 0.01)[1]
    y0 = geo._along_cross(c_, np.full_like(c_, RED), g[ok], t[ok] - 0.01)[1]
    rate = (
        np.abs(
            geo.camera.sample_from_focal_plane_y(c_, np.full_like(c_, RED), y1)
            - geo.camera.sample_from_focal_plane_y(c_, np.full_like(c_, RED), y0)
        )
        / 0.02
    )  # pixels/s
    assert np.all(np.abs(sample[ok] - ref.sample[ok]) <= rate * geo.camera.line_time / 2 + 1e-3)


def test_the_pp_sees_what_the_cameras_see(pp) -> None:
    for c, name in enumerate(pp.cameras):
        seen = pp.seen()[c, 0].mean()
        # 1504 pixels of ~250 m (more at the D cameras' slant) on a 563 km wide block
        assert 0.6 < seen < 0.9, name
        assert np.all(np.isfinite(pp.sigma_m[c, 0][np.isfinite(pp.line0[c, 0])]))


@pytest.mark.parametrize("cam", ["Df", "Af", "An", "Da"])
def test_height_quadratic_and_275m_interpolation(adjusted, pp, cam) -> None:
    """Random 275 m grid points at random heights (0..6 km): the PP's bilinear interpolation plus
    height quadratic against a direct projection through the same adjusted geometry."""
    _, op, _, res = adjusted
    geo = corrected_geometry(op, res.attitude, res.ephemeris, res.camera)
    c = CAMERAS.index(cam)
    rng = np.random.default_rng(3)
    g275 = SomGrid(op.path, 275)
    ln = rng.uniform(4, 507, 300)
    sm = rng.uniform(4, 2043, 300)
    h = rng.uniform(0, 6000, 300)
    lat, lon = g275.bls_to_latlon(BLOCK, ln, sm)
    ground = geodetic_to_ecef(lat, lon, h)
    l_pp, s_pp = pp.image_coords(cam, BLOCK, ln, sm, h, resolution_m=275)
    t_guess = geo.t0[c, RED] + l_pp * geo.camera.line_time
    _, l_true, s_true = crossing(geo, c, RED, ground, t_guess)
    ok = np.isfinite(l_pp) & np.isfinite(l_true)
    assert ok.sum() > 150
    err = np.hypot(l_pp[ok] - l_true[ok], s_pp[ok] - s_true[ok])
    assert np.max(err) < 0.01, f"{cam}: {np.max(err):.4f} px"


@pytest.mark.parametrize("cam", ["Df", "An", "Da"])
def test_sigma_against_monte_carlo(adjusted, pp_without_jitter, cam) -> None:
    """Draws of the posterior (knots, ephemeris and camera corrections jointly), each geometry
    projected exactly: the spread must match the linear propagation (no jitter on either side)."""
    _, op, _, res = adjusted
    res0, pp0 = pp_without_jitter
    c = CAMERAS.index(cam)
    post = _posterior(res0)
    mean = np.concatenate([res.values.atVector(k) for k in post.keys])
    chol = np.linalg.cholesky(post.cov + 1e-30 * np.eye(mean.size))
    sizes = np.cumsum([res.values.atVector(k).size for k in post.keys])[:-1]
    g = _grid_points(op.path, 32)
    l0 = pp0.line0[c, 0][::32, ::32].ravel()
    ok = pp0.seen()[c, 0][::32, ::32].ravel()
    geo0 = corrected_geometry(op, res.attitude, res.ephemeris, res.camera)
    t_guess = geo0.t0[c, RED] + l0[ok] * geo0.camera.line_time
    rng = np.random.default_rng(7)
    draws = []
    for _ in range(80):
        v = gtsam.Values()
        for k, seg in zip(post.keys, np.split(mean + chol @ rng.standard_normal(mean.size), sizes)):
            v.insert(k, seg)
        att, eph, cm = estimated_models(res.pass_graph, v, supplied_camera_of(res))
        _, ln, sm = crossing(corrected_geometry(op, att, eph, cm), c, RED, g[ok], t_guess, margin_px=50.0)
        draws.append(np.stack([ln, sm], -1))
    mc = np.std(np.array(draws), axis=0, ddof=1)
    pred = np.stack([pp0.sigma_line[c, 0][::32, ::32].ravel()[ok], pp0.sigma_sample[c, 0][::32, ::32].ravel()[ok]], -1)
    # 80 draws: each sigma to ~8 % (1 sigma); the points share the draws, so compare the means
    ratio = mc.mean(axis=0) / pred.mean(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.25), f"{cam}: Monte Carlo / predicted = {ratio}"


def test_accuracy_against_truth(adjusted, pp) -> None:
    sc, op, cam, _ = adjusted
    truth = read_pass_truth(sc.pass_files[0])
    out = score_pp(pp, op, truth, supplied_camera=cam)["pp_error_m"]
    assert set(out) == set(CAMERAS)
    for name, v in out.items():
        assert v["n"] > 500
        # the adjustment improves the geolocation of every camera (at least two-fold; several-fold
        # over all cameras, below: a camera whose supplied error happens to be small gains less)
        assert v["supplied_rms"] > 2 * v["rms"], name
        # one pass's points share one navigation error: allow its scatter (chi-square of a few dof)
        assert 0.2 < v["rms_over_predicted"] < 2.5, name
    rms = np.array([v["rms"] for v in out.values()])
    pred = np.array([v["predicted_rms"] for v in out.values()])
    supplied = np.array([v["supplied_rms"] for v in out.values()])
    assert np.sqrt(np.mean(supplied**2) / np.mean(rms**2)) > 4
    assert 0.4 < np.sqrt(np.mean(rms**2) / np.mean(pred**2)) < 1.6


def test_scores_per_block(adjusted, pp) -> None:
    """The per-block figures of a one-block PP are the camera's figures, and the predicted pixel
    1-sigma is the RMS of the PP's own ``hypot(sigma_line, sigma_sample)`` on the scored sub-grid."""
    sc, op, cam, _ = adjusted
    scores = score_pp(pp, op, read_pass_truth(sc.pass_files[0]), step=8)
    for name, v in scores["pp_error_m"].items():
        b = scores["pp_error_by_block"][name]
        assert list(b) == [BLOCK]
        blk = b[BLOCK]
        assert (
            blk["n"] == v["n"]
            and blk["rms"] == pytest.approx(v["rms"])
            and blk["error_px_rms"] == pytest.approx(v["error_px_rms"])
        )
        c = pp.cameras.index(name)
        sub = (slice(None, None, 8), slice(None, None, 8))
        ok = pp.seen()[c, 0][sub] & np.isfinite(pp.sigma_line[c, 0][sub])
        direct = np.sqrt(np.mean(pp.sigma_line[c, 0][sub][ok] ** 2 + pp.sigma_sample[c, 0][sub][ok] ** 2))
        assert blk["predicted_px_rms"] == pytest.approx(direct, rel=0.02), name


def test_file_round_trip(pp, tmp_path) -> None:
    p = tmp_path / "pp.h5"
    save_pp(pp, p)
    back = read_pp(p)
    assert back.path == pp.path and back.cameras == pp.cameras and back.blocks.tolist() == [BLOCK]
    np.testing.assert_array_equal(back.line0, pp.line0)
    np.testing.assert_allclose(back.sigma_m, pp.sigma_m, rtol=1e-6)
    (tmp_path / "bad.h5").write_bytes(p.read_bytes()[:-5000])
    with pytest.raises(FileFormatError):
        read_pp(tmp_path / "bad.h5")


def test_bad_input(adjusted, pp) -> None:
    _, op, _, res = adjusted
    with pytest.raises(InputError, match="blocks"):
        compute_pp(op, res, op.path, np.array([0]))
    with pytest.raises(InputError, match="band"):
        compute_pp(op, res, op.path, np.array([5]), band="violet")
    with pytest.raises(InputError, match="block"):
        pp.image_coords("An", 3, 0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="camera"):
        pp.image_coords("Zz", BLOCK, 0.0, 0.0, 0.0)


def test_products_command(small_pass_dir, tmp_path) -> None:
    res = CliRunner().invoke(
        app,
        ["products", str(small_pass_dir), "--out", str(tmp_path / "p"), "--blocks", "60", "--format", "misr", "--json"],
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["blocks"] == [60, 60] and set(out["pp_error_m"]) == set(CAMERAS)
    for v in out["pp_error_m"].values():
        assert {"rms", "predicted_rms"} <= set(v)
    pp = read_pp(out["files"]["pp"])
    assert pp.blocks.tolist() == [60]
    assert json.loads((tmp_path / "p" / "products.json").read_text())["misr_files"] == out["misr_files"]
    # the MISR files hold the HDF5 product's values, field by field (read with plain HDF4 calls)
    pytest.importorskip("pyhdf")
    from pyhdf.SD import SD, SDC

    misr = out["misr_files"]["pp"][pp.pass_id]
    assert set(misr) == set(CAMERAS)
    for c in ("Df", "An", "Da"):
        sd = SD(misr[c], SDC.READ)
        assert sd.attributes()["Path_number"] == 37
        for name in ("line0", "sigma_m"):
            want = np.asarray(getattr(pp, name)[CAMERAS.index(c), 0], np.float32)
            got = sd.select(name)[59]
            np.testing.assert_array_equal(got, np.where(np.isfinite(want), want, np.float32(-9999.0)))
        sd.end()
    bad = CliRunner().invoke(app, ["products", str(small_pass_dir), "--out", str(tmp_path / "q"), "--blocks", "90-80"])
    assert bad.exit_code == 2 and "--blocks" in bad.output
    bad = CliRunner().invoke(app, ["products", str(small_pass_dir), "--out", str(tmp_path / "r"), "--format", "hdf"])
    assert bad.exit_code == 2 and "--format" in bad.output and not (tmp_path / "r").exists()
