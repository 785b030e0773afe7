from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.layout import BlockLayout
from factors.priors import gcp_prior, vector_prior
from factors.geometry import enu_covariance
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
                    naive[2 * li:2 * li + 2, cols[k]:cols[k] + dims[s]] = blocks[s][i]
        np.testing.assert_array_equal(a, naive)
