"""Per-camera matching precision from a pass's redundancy, against synthetic data of known scale."""

from __future__ import annotations

import numpy as np

from misrgraph.match.precision import camera_sigma_scales


def _synthetic(seed: int, scales: np.ndarray, n_features: int = 1000, outlier_rate: float = 0.0):
    """Differences d = smooth navigation + height along the epipolar direction + noise of scale
    ``scales[c]`` times the stated sigma, for cameras 0..len(scales)-1."""
    rng = np.random.default_rng(seed)
    t_feat = rng.uniform(0.0, 2700.0, n_features)
    h = rng.normal(0.0, 30.0, n_features)
    rows = []
    for c in range(scales.size):
        seen = rng.random(n_features) < 0.8
        f = np.flatnonzero(seen)
        t = t_feat[f] + 40.0 * (c - 3.5)
        x = rng.uniform(-0.7, 0.7, f.size)
        # smooth navigation/camera error: periods of 600-3000 s, a cross-track tilt and a curvature
        smooth = np.zeros((f.size, 2))
        for q in range(2):
            for _ in range(4):
                per, ph, amp = rng.uniform(600, 3000), rng.uniform(0, 2 * np.pi), rng.normal(0, 1.5)
                smooth[:, q] += amp * np.sin(2 * np.pi * t / per + ph) * (1 + 0.3 * x)
            smooth[:, q] += rng.normal(0, 0.3) * x ** 2
        epi = np.column_stack([np.full(f.size, 0.0035 * (c - 3.5)), np.full(f.size, 0.0004)])
        sigma = rng.uniform(0.03, 0.2, f.size)
        noise = rng.standard_normal((f.size, 2)) * (scales[c] * sigma)[:, None]
        d = smooth + h[f][:, None] * epi + noise
        bad = rng.random(f.size) < outlier_rate
        d[bad] += rng.choice([-1, 1], (bad.sum(), 2)) * rng.uniform(1.0, 3.0, (bad.sum(), 2))
        rows.append((f, np.full(f.size, c), t, x, d, epi, sigma, bad))
    return [np.concatenate(v) for v in zip(*rows)]


def test_recovers_each_cameras_scale():
    """Scales 0.7-2.5: each recovered within 4 standard errors (chi-square: k / sqrt(2 redundancy))."""
    scales = np.array([2.5, 1.4, 1.0, 0.7, 0.8, 1.1, 1.5, 2.2])
    f, c, t, x, d, e, s, _ = _synthetic(1, scales)
    fit = camera_sigma_scales(f, c, t, x, d, e, s)
    for cam, k in enumerate(scales):
        assert fit.estimated[cam]
        tol = 4.0 * k / np.sqrt(2.0 * fit.redundancy[cam])
        assert abs(fit.scale[cam] - k) <= tol, (cam, fit.scale[cam], k, tol)


def test_mismatches_are_clipped_not_counted():
    """1 % of the measurements off by 1-3 px per coordinate: clipped, and the scales still recovered."""
    scales = np.array([2.0, 1.0, 1.0, 2.0])
    f, c, t, x, d, e, s, bad = _synthetic(2, scales, outlier_rate=0.01)
    fit = camera_sigma_scales(f, c, t, x, d, e, s)
    assert sum(fit.clipped.values()) >= 0.8 * bad.sum()
    for cam, k in enumerate(scales):
        assert abs(fit.scale[cam] - k) <= 4.0 * k / np.sqrt(2.0 * fit.redundancy[cam]), (cam, fit.scale[cam])


def test_without_the_height_term_the_scale_would_be_inflated():
    """The epipolar (height) term matters: with it zeroed, heights of 30 m leak into the scatter."""
    scales = np.ones(4)
    f, c, t, x, d, e, s, _ = _synthetic(3, scales)
    with_h = camera_sigma_scales(f, c, t, x, d, e, s)
    without = camera_sigma_scales(f, c, t, x, d, np.zeros_like(e), s)
    assert max(abs(v - 1.0) for v in with_h.scale.values()) < 0.15
    assert without.scale[0] > 2.0 * with_h.scale[0]


def test_too_little_redundancy_keeps_the_stated_sigma():
    scales = np.array([3.0, 3.0])
    f, c, t, x, d, e, s, _ = _synthetic(4, scales, n_features=40)
    fit = camera_sigma_scales(f, c, t, x, d, e, s)
    assert not any(fit.estimated.values()) and all(v == 1.0 for v in fit.scale.values())


def test_schur_solution_and_redundancy_match_the_dense_hat_matrix():
    """The Schur-complement residuals and per-camera redundancies equal the dense computation
    (residual of the stacked weighted least squares; n_c - sum of its hat-matrix diagonal)."""
    from misrgraph.match.precision import _design, _solve

    f, c, t, x, d, e, s, _ = _synthetic(5, np.array([1.0, 2.0, 1.5]), n_features=80)
    rows = {int(k): np.flatnonzero(c == k) for k in np.unique(c)}
    X = {k: _design(t[r], x[r], 600.0) for k, r in rows.items()}
    ids, feat_of = np.unique(f, return_inverse=True)
    w = 1.0 / s ** 2
    res, red = _solve(X, rows, feat_of, ids.size, d, e, w, 1000.0)
    # dense stacked system: smooth blocks per (camera, coordinate), then heights; height prior rows
    p = [X[k].shape[1] for k in rows]
    n_s = 2 * sum(p)
    a_rows, y, wt, cam_of = [], [], [], []
    o = 0
    for k, r in rows.items():
        for q in range(2):
            blk = np.zeros((r.size, n_s + ids.size))
            blk[:, o:o + X[k].shape[1]] = X[k]
            blk[np.arange(r.size), n_s + feat_of[r]] = e[r, q]
            a_rows.append(blk), y.append(d[r, q]), wt.append(w[r]), cam_of.append(np.full(r.size, k))
            o += X[k].shape[1]
    prior = np.hstack([np.zeros((ids.size, n_s)), np.eye(ids.size)])
    A = np.vstack(a_rows + [prior])
    W = np.concatenate(wt + [np.full(ids.size, 1e-6)])
    Y = np.concatenate(y + [np.zeros(ids.size)])
    N = A.T @ (A * W[:, None])
    Ninv = np.linalg.pinv(N, hermitian=True)
    sol = Ninv @ (A.T @ (W * Y))
    r_dense = (Y - A @ sol)[:-ids.size]
    hat = np.einsum("ij,jk,ik->i", A, Ninv, A) * W
    cams = np.concatenate(cam_of)
    res_stacked = np.concatenate([res[r, q] for k, r in rows.items() for q in range(2)])
    assert np.allclose(res_stacked, r_dense, atol=1e-8 * np.abs(Y).max())
    for k in rows:
        dense_red = float(np.sum(1.0 - hat[:-ids.size][cams == k]))
        assert abs(red[k] - dense_red) < 1e-6 * dense_red, (k, red[k], dense_red)
