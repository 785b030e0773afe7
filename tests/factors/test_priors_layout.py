from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.geometry import enu_covariance
from factors.layout import BlockLayout
from factors.priors import gcp_prior, gcp_scene_prior, scene_offset_prior, vector_prior
from misrgraph.model.frames import enu_basis


def test_enu_covariance_is_rotated_diagonal():
    lat, lon = 0.6, -1.9
    c = enu_covariance(lat, lon, [30.0, 30.0, 10.0])
    r = enu_basis(np.degrees(lat), np.degrees(lon))
    np.testing.assert_allclose(r.T @ c @ r, np.diag([900.0, 900.0, 100.0]), atol=1e-9)


def test_gcp_prior_whitens_with_full_covariance():
    c = enu_covariance(0.3, 0.2, 30.0)
    f = gcp_prior(7, np.array([1.0, 2.0, 3.0]), c)
    v = gtsam.Values()
    v.insert(7, np.array([1.0, 2.0, 3.0]) + np.array([30.0, 0, 0]))
    assert f.error(v) == pytest.approx(0.5 * 1.0, rel=1e-9)  # 30 m along any axis = 1 sigma
    assert vector_prior(8, np.zeros(2), [1.0, 2.0]).keys() == [8]


def test_gcp_scene_prior_gives_the_catalogues_joint_distribution():
    """Three GCPs of one scene (own sigma 20 m, shared 25 m per ENU axis), the scene offset
    marginalised by GTSAM: each GCP's covariance is own + shared, two GCPs' cross-covariance the
    shared part -- the closed form of the catalogue's joint distribution."""
    lat, lon = np.radians(38.0), np.radians(-105.0)
    c_own, c_s = enu_covariance(lat, lon, [20.0, 20.0, 12.0]), enu_covariance(lat, lon, 25.0)
    pos = [np.array([-1.2e6, -4.7e6, 3.9e6]) + 1e3 * k for k in range(3)]
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    scene = gtsam.symbol("s", 4)
    g.add(scene_offset_prior(scene, c_s))
    v.insert(scene, np.zeros(3))
    for k, p in enumerate(pos):
        g.add(gcp_scene_prior(gtsam.symbol("g", k), scene, p, c_own))
        v.insert(gtsam.symbol("g", k), p + 7.0)
    opt = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
    for k, p in enumerate(pos):
        np.testing.assert_allclose(opt.atVector(gtsam.symbol("g", k)), p, atol=1e-6)
    m = gtsam.Marginals(g, opt)
    keys = gtsam.KeyVector([gtsam.symbol("g", 0), gtsam.symbol("g", 2)])
    joint = m.jointMarginalCovariance(keys).fullMatrix()
    np.testing.assert_allclose(joint[:3, :3], c_own + c_s, rtol=1e-8)
    np.testing.assert_allclose(joint[:3, 3:], c_s, rtol=1e-8, atol=1e-8)
    # its error: 0.5 |P - o - P_GCP|^2 in the own covariance's metric
    v2 = gtsam.Values()
    v2.insert(gtsam.symbol("g", 0), pos[0] + np.array([3.0, -4.0, 5.0]))
    v2.insert(scene, np.array([1.0, 1.0, 1.0]))
    d = np.array([2.0, -5.0, 4.0])
    f = gcp_scene_prior(gtsam.symbol("g", 0), scene, pos[0], c_own)
    assert f.error(v2) == pytest.approx(0.5 * d @ np.linalg.solve(c_own, d), rel=1e-9)


def test_block_layout_matches_naive_assembly(rng):
    n = 12
    group = np.sort(rng.integers(0, 4, n))
    slot_keys = [rng.integers(0, 5, n), rng.integers(5, 8, n)]
    slot_keys[1][3] = -1
    dims = [3, 2]
    lay = BlockLayout(group, slot_keys, dims, rows=2)
    blocks = [rng.normal(size=(n, 2, 3)), rng.normal(size=(n, 2, 2))]
    buf = lay.assemble(blocks)
    for f in range(lay.n_factors):
        a = lay.factor_matrix(buf, f)
        obs = np.flatnonzero(group == np.unique(group)[f])
        cols = {k: c for k, c in zip(lay.factor_keys[f], lay.col_start[f])}
        naive = np.zeros_like(a)
        for li, i in enumerate(obs):
            for s in range(2):
                k = slot_keys[s][i]
                if k >= 0:
                    naive[2 * li : 2 * li + 2, cols[k] : cols[k] + dims[s]] = blocks[s][i]
        np.testing.assert_array_equal(a, naive)


def test_joint_prior_factor_is_the_gaussian_on_any_number_of_keys():
    """Nine camera keys of five parameters each (more than GTSAM's Python JacobianFactor takes),
    units spanning five decades: the factor's error is 0.5 x^T C^-1 x for random x, and the flat
    problem's reading of it (a JacobianFactor) whitens to the same."""
    from factors.priors import joint_prior_factor

    rng = np.random.default_rng(3)
    dims = [5] * 9
    n = sum(dims)
    a = rng.normal(size=(n, n))
    scale = np.tile(np.logspace(-6, -1, 5), 9)
    c = (a @ a.T / n + 0.05 * np.eye(n)) * np.outer(scale, scale)
    keys = [gtsam.symbol("c", i) for i in range(9)]
    f = joint_prior_factor(keys, dims, c)
    assert list(f.keys()) == keys
    for _ in range(3):
        x = rng.multivariate_normal(np.zeros(n), c)
        v = gtsam.Values()
        for i, k in enumerate(keys):
            v.insert(k, x[5 * i : 5 * i + 5])
        expected = 0.5 * x @ np.linalg.solve(c, x)
        assert f.error(v) == pytest.approx(expected, rel=1e-7)
        jac, b = gtsam.JacobianFactor(f.factor()).jacobian()
        assert 0.5 * np.sum((np.asarray(jac) @ x - np.asarray(b)) ** 2) == pytest.approx(expected, rel=1e-7)
    with pytest.raises(ValueError, match="covariance"):
        joint_prior_factor(keys, dims, c[:-1, :-1])
