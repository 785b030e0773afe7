"""The offset a matched tie point's conjugates share: the landmark's response to it against a
numerical re-triangulation, and its covariance in a matched pass's result."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.estimate.tieoffset import counted_covariance, offset_covariance, offset_response


def test_the_response_is_the_landmarks_move_under_a_common_shift_of_their_conjugates(small_pass):
    """Every tie point's non-An observations shifted by the same amount: triangulating again with
    the other variables held (landmark-only Gauss-Newton on the rebuilt graph) moves each landmark
    by ``R o`` to first order (no DEM factors: the graph rebuilt from shifted observations would
    fit its local DEM surfaces around slightly different points). A sample shift moves only the
    measured coordinate: equal to 1e-3 of the move (0.01 px; ``R`` is Gauss-Newton's response,
    and the pass's unrejected 3-10 px blunders add a residual-curvature term of ~4e-4 at the
    landmarks they touch). A line shift also moves the time the geometry is evaluated at, and with
    it the predicted sample, by up to 0.15 px per px of line on this pass (the residual's own
    derivative, measured in the test); ``R`` leaves that out, so the line column agrees to 0.15 of
    the sample column's move plus the same 1e-3."""
    from misrgraph.estimate.graph import GraphConfig, build_pass_graph
    from misrgraph.estimate.solver import solve
    from misrgraph.io.passes import KIND_TIE
    from misrgraph.model.constants import CAMERAS

    sc, p = small_pass
    cfg = GraphConfig(use_dem=False)
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, cfg)
    values = solve(pg.problem).values
    flat = pg.problem.flat()
    x = flat.from_values(values)
    jac, sigma, lm = flat.landmark_jacobians(x)
    obs = p.observations
    rows = pg.obs_index[pg.collinearity.order]
    index = {int(k): i for i, k in enumerate(pg.problem.eliminate_first)}
    tie = np.zeros(len(index), bool)
    tie[[index[int(k)] for k, r in zip(pg.landmark_keys, pg.landmark_rows) if p.landmarks.kind[r] == KIND_TIE]] = True
    conj = (obs.camera[rows] != CAMERAS.index("An")) & tie[lm]
    r = offset_response(flat.normal_equations(x)[0], jac, sigma, lm, conj)
    n_l = 3 * len(index)
    mask = np.zeros(len(obs.line), bool)
    mask[rows[conj]] = True

    def shifted(coord: str, by: float) -> tuple[np.ndarray, np.ndarray]:
        """The landmarks re-triangulated (other variables held) and the whitened collinearity
        residuals at the optimum, with the conjugates' ``coord`` shifted ``by`` px."""
        q = dataclasses.replace(p, observations=dataclasses.replace(obs, **{coord: getattr(obs, coord) + by * mask}))
        f = build_pass_graph(q, sc.camera_model, sc.dem, sc.gcps, cfg).problem.flat()
        xx = f.from_values(values)
        res = f.residual(xx)[: 2 * len(rows)].reshape(-1, 2)
        for _ in range(6):
            blk, _, _, g, _ = f.normal_equations(xx)
            xx[:n_l] -= np.linalg.solve(blk, g[:n_l].reshape(-1, 3, 1)).ravel()
        return xx[:n_l].reshape(-1, 3), res

    base, r0 = shifted("line", 0.0)
    by = 0.01
    moved_s = shifted("sample", by)[0] - base
    want_s = r[:, :, 1] * by
    assert np.abs(want_s[tie]).max() > 0.2  # metres: the shift moves the tie points measurably
    np.testing.assert_allclose(moved_s[tie], want_s[tie], atol=1e-3 * np.abs(want_s[tie]).max())
    np.testing.assert_allclose(moved_s[~tie], 0.0, atol=1e-6)  # the GCPs' observations were not shifted
    moved_l, r1 = shifted("line", by)
    cross = np.abs((r1 - r0)[conj[np.arange(len(rows))], 1] * sigma[conj, 1] / by).max()
    assert 0.0 < cross < 0.15, cross  # the predicted sample moves with the line's time
    want_l = r[:, :, 0] * by
    assert np.all(
        np.abs(moved_l - base - want_l)[tie] <= 0.15 * np.abs(want_s[tie]).max() + 1e-3 * np.abs(want_l[tie]).max()
    )
    cov = offset_covariance(r, 0.05)
    np.testing.assert_allclose(cov[tie], 0.05**2 * r[tie] @ np.swapaxes(r[tie], 1, 2))


def test_the_term_is_the_conjugates_true_covariance_propagated():
    """Per landmark, observations weighted by ``sigma`` whose true errors are, per coordinate,
    ``diag(sigma_own^2) + s_o^2 1 1^T`` over the conjugates (``sigma_own = rho sigma``; the first,
    An's, independent at ``sigma``): the term equals the dense propagation of that covariance
    through the least-squares estimate minus the propagation the independent weights assume."""
    rng = np.random.default_rng(3)
    n_l, per, s_o = 4, 6, 0.04
    lm = np.repeat(np.arange(n_l), per)
    jac = rng.normal(0.0, 2e-3, (lm.size, 2, 3))  # px per m
    sigma = rng.uniform(0.05, 0.09, lm.size)
    rho = np.sqrt(1.0 - rng.uniform(0.0, 1.0, lm.size) * s_o**2 / sigma**2)  # sigma^2 (1 - rho^2) <= s_o^2
    shared = np.tile(np.arange(per) > 0, n_l)
    w = 1.0 / sigma**2
    h = np.array(
        [sum(w[n] * jac[n].T @ jac[n] for n in np.flatnonzero(lm == i)) + 1e-6 * np.eye(3) for i in range(n_l)]
    )
    counted = np.where(shared, sigma**2 * (1.0 - rho**2), 0.0)
    term = offset_covariance(offset_response(h, jac, np.c_[sigma, sigma], lm, shared), s_o) - counted_covariance(
        h, jac, np.c_[sigma, sigma], lm, counted
    )
    for i in range(n_l):
        idx = np.flatnonzero(lm == i)
        a = np.concatenate([w[n] * jac[n].T for n in idx], axis=1)  # (3, 2 per): J^T W
        own = np.where(shared[idx], (rho[idx] * sigma[idx]) ** 2, sigma[idx] ** 2)
        true = np.kron(np.diag(own) + s_o**2 * np.outer(shared[idx], shared[idx]), np.eye(2))
        assumed = np.kron(np.diag(sigma[idx] ** 2), np.eye(2))
        hi = np.linalg.inv(h[i])
        want = hi @ a @ (true - assumed) @ a.T @ hi
        np.testing.assert_allclose(term[i], want, rtol=1e-9, atol=1e-12 * np.abs(want).max())


def test_bad_input_is_named():
    h = np.tile(np.eye(3), (2, 1, 1))
    j = np.ones((3, 2, 3))
    with pytest.raises(InputError, match="sigma_px"):
        offset_response(h, j, np.zeros((3, 2)), np.array([0, 1, 1]), np.ones(3, bool))
    with pytest.raises(InputError, match="h_ll, jacobian"):
        offset_response(h, j[:2], np.ones((3, 2)), np.array([0, 1, 1]), np.ones(3, bool))
    with pytest.raises(InputError, match="tie_offset_sigma_px"):
        offset_covariance(np.zeros((2, 3, 2)), -1.0)
    with pytest.raises(InputError, match="counted_px2"):
        counted_covariance(h, j, np.ones((3, 2)), np.array([0, 1, 1]), -np.ones(3))
    from misrgraph.estimate.adjust import AdjustConfig

    with pytest.raises(InputError, match="tie_offset_sigma_px"):
        AdjustConfig(tie_offset_sigma_px="measured")


def test_a_matched_pass_carries_the_matchers_offset_into_its_tie_points(imagery_pass_dir, tmp_path):
    """Adjusted from its matched observations, the pass takes the offset the matcher measured
    (``tie.shared_offset``, with the conjugates' own-scale ratio per camera) and adds its term to
    each tie point's covariance -- which stays positive definite, and grows in some direction --
    and nothing to the GCPs'; switched off (0) the same solve has the plain covariances; the
    simulated observations get no such term; the CLI says what it added."""
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.estimate.adjust import AdjustConfig
    from misrgraph.io.imagery import read_matched
    from misrgraph.io.passes import KIND_GCP, KIND_TIE
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.sim.simulate import load_scenario

    so = read_matched(load_scenario(imagery_pass_dir).pass_files[0]).summary["tie"]["shared_offset"]
    on = run_adjust(imagery_pass_dir, observations="matched", out=tmp_path / "on.h5")
    off = run_adjust(
        imagery_pass_dir, observations="matched", out=tmp_path / "off.h5", cfg=AdjustConfig(tie_offset_sigma_px=0)
    )
    assert on["tie_offset"]["source"] == "matched" and on["tie_offset"]["sigma_px"] == so["sigma_px"] > 0
    assert on["tie_offset"]["own_scale_ratio"] == so["own_scale_ratio"] and set(so["own_scale_ratio"]) == {
        "Df",
        "Cf",
        "Bf",
        "Af",
        "Aa",
        "Ba",
        "Ca",
        "Da",
    }
    assert off["tie_offset"]["source"] == "off"
    with h5py.File(tmp_path / "on.h5") as a, h5py.File(tmp_path / "off.h5") as b:
        kind = a["landmarks/kind"][:]
        assert np.array_equal(a["landmarks/ecef"][:], b["landmarks/ecef"][:])
        total = a["landmarks/covariance"][:]
        d = total - b["landmarks/covariance"][:]
    assert on["tie_offset"]["tie_points"] == int(np.sum(kind == KIND_TIE))
    assert np.all(np.linalg.eigvalsh(total[kind == KIND_TIE])[:, 0] > 0)
    eig = np.linalg.eigvalsh(0.5 * (d + np.swapaxes(d, 1, 2)))
    assert np.all(eig[kind == KIND_TIE][:, -1] > 0.1)  # m^2
    np.testing.assert_allclose(d[kind == KIND_GCP], 0.0, atol=1e-12)
    assert run_adjust(imagery_pass_dir)["tie_offset"]["source"] == "off"
    r = CliRunner().invoke(app, ["adjust", str(imagery_pass_dir), "--observations", "matched"])
    assert r.exit_code == 0, r.output
    assert "offset shared by a tie point's conjugates" in " ".join(r.stdout.split())
    r = CliRunner().invoke(app, ["adjust", str(imagery_pass_dir), "--tie-offset-sigma-px", "some"])
    assert r.exit_code != 0 and "--tie-offset-sigma-px" in r.output
