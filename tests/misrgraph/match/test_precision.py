"""Per-camera matching precision from a pass's redundancy, against synthetic data of known scale."""

from __future__ import annotations

import numpy as np
import pytest

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
            smooth[:, q] += rng.normal(0, 0.3) * x**2
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
    w = 1.0 / s**2
    res, red = _solve(X, rows, feat_of, ids.size, d, e, w, 1000.0)
    # dense stacked system: smooth blocks per (camera, coordinate), then heights; height prior rows
    p = [X[k].shape[1] for k in rows]
    n_s = 2 * sum(p)
    a_rows, y, wt, cam_of = [], [], [], []
    o = 0
    for k, r in rows.items():
        for q in range(2):
            blk = np.zeros((r.size, n_s + ids.size))
            blk[:, o : o + X[k].shape[1]] = X[k]
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
    r_dense = (Y - A @ sol)[: -ids.size]
    hat = np.einsum("ij,jk,ik->i", A, Ninv, A) * W
    cams = np.concatenate(cam_of)
    res_stacked = np.concatenate([res[r, q] for k, r in rows.items() for q in range(2)])
    assert np.allclose(res_stacked, r_dense, atol=1e-8 * np.abs(Y).max())
    for k in rows:
        dense_red = float(np.sum(1.0 - hat[: -ids.size][cams == k]))
        assert abs(red[k] - dense_red) < 1e-6 * dense_red, (k, red[k], dense_red)


def _shared_attitude(
    seed: int,
    scales: np.ndarray,
    seen: np.ndarray,
    n_features: int = 150,
    duration_s: float = 600.0,
    gcps: dict | None = None,
):
    """Differences from the shared-attitude model: one attitude correction a(t) (roll, pitch,
    yaw; sinusoids of 200-2000 s, 20" each) seen by camera c at its time and through An's ray at
    An's time, plus per-camera offsets, tilts and drifts, heights along the epipolar direction and
    noise of ``scales[c]`` times the stated sigma; camera c sees a fraction ``seen[c]`` of the
    features. Returns the inputs of :func:`camera_sigma_scales` and the :class:`Pointing`; with
    ``gcps`` (``scale``, ``n``, ``ground_m``, ``an_static_arcsec``) also the :class:`GcpRows` of
    ``n`` GCPs seen by every camera and by An (camera ``len(scales)``): the same attitude and
    camera terms, An's static pointing error (the ties see it through An's ray), a ground offset of
    ``ground_m`` per axis per GCP and noise of ``scale`` times their stated sigma."""
    from misrgraph.match.precision import GcpRows, Pointing

    rng = np.random.default_rng(seed)
    arcsec = np.pi / 180 / 3600
    waves = [(rng.uniform(200, 2000), rng.uniform(0, 2 * np.pi), 20 * arcsec) for _ in range(9)]

    def att(t):
        return np.stack(
            [sum(a * np.sin(2 * np.pi * t / p + f) for p, f, a in waves[3 * k : 3 * k + 3]) for k in range(3)], axis=-1
        )

    t_an = rng.uniform(420.0, 420.0 + duration_s, n_features)
    h = rng.normal(0.0, 30.0, n_features)
    d_an = rng.normal(0.0, (gcps or {}).get("an_static_arcsec", 0.0) * arcsec, 3)  # An's static pointing error
    rows, gcp_rows = [], []
    n_gcp = (gcps or {}).get("n", 0)
    t_gcp = rng.uniform(420.0, 420.0 + duration_s, n_gcp)
    x_gcp = rng.uniform(-0.8, 0.8, n_gcp)
    ground = rng.normal(0.0, (gcps or {}).get("ground_m", 0.0), (n_gcp, 3))
    an = scales.size
    for c in range(scales.size + (1 if n_gcp else 0)):
        own = c == an  # An: GCP rows only
        f = np.flatnonzero(rng.random(n_features) < (0.0 if own else seen[c]))
        offset_s = 0.0 if own else 105.0 * (c - 3.5)
        t = t_an[f] + offset_s
        x = rng.uniform(-0.8, 0.8, f.size)
        # pointing sensitivities of the right size (px/rad; An's IFOV is ~3.9e-4 rad a pixel), varying with x
        base = rng.normal(0.0, 2500.0, (2, 3)) + np.diag([2500.0, 2500.0, 0.0])[:2]
        jc = base[None] * (1.0 + 0.2 * x)[:, None, None]
        ka = -np.eye(2, 3)[None] * 2500.0 * (1.0 + 0.1 * rng.normal(size=(1, 2, 3)))
        ka = np.repeat(ka, f.size, axis=0)
        static = (rng.normal(0, 0.5, 2), rng.normal(0, 0.3, 2), rng.normal(0, 0.2, 2))  # offset, tilt in x, drift

        def static_of(x, t):
            return static[0] + np.outer(x, static[1]) + np.outer((t - 720) / 600, static[2])

        smooth = np.einsum("nqa,na->nq", jc, att(t)) + np.einsum("nqa,na->nq", ka, att(t_an[f]) + d_an)
        smooth += static_of(x, t)
        epi = np.column_stack([np.full(f.size, 0.0035 * (c - 3.5)), np.full(f.size, 0.0004)])
        sigma = rng.uniform(0.05, 0.2, f.size)
        d = smooth + h[f][:, None] * epi + rng.standard_normal((f.size, 2)) * (scales[min(c, an - 1)] * sigma)[:, None]
        if not own:
            rows.append((f, np.full(f.size, c), t, x, d, epi, sigma, t_an[f], jc, ka))
        if n_gcp:  # every camera sees every GCP, at its own time: a fixed ground point, no An ray
            tg = t_gcp + offset_s
            jg = base[None] * (1.0 + 0.2 * x_gcp)[:, None, None]
            # px per metre east, north, up: ~1/275 across and along, the view angle's parallax
            gg = np.repeat(
                (
                    np.array([[0.0, -1 / 275, 0.0035 * (c - 3.5)], [1 / 275, 0.0, 0.0004]])
                    + rng.normal(0.0, 2e-4, (2, 3))
                )[None],
                n_gcp,
                axis=0,
            )
            dg = np.einsum("nqa,na->nq", jg, att(tg) + (d_an if own else 0.0)) + np.einsum("nqk,nk->nq", gg, ground)
            if not own:
                dg += static_of(x_gcp, tg)
            sg = rng.uniform(0.02, 0.06, n_gcp)
            dg += rng.standard_normal((n_gcp, 2)) * (gcps["scale"] * sg)[:, None]
            gcp_rows.append((np.arange(n_gcp), np.full(n_gcp, c), tg, x_gcp, dg, sg, jg, gg))
    f, c, t, x, d, e, s, ta, jc, ka = (np.concatenate(v) for v in zip(*rows))
    if not n_gcp:
        return (f, c, t, x, d, e, s), Pointing(ta, jc, ka)
    return (
        (f, c, t, x, d, e, s),
        Pointing(ta, jc, ka),
        GcpRows(*(np.concatenate(v) for v in zip(*gcp_rows)), defining_camera=an),
    )


def test_shared_attitude_estimates_a_camera_with_few_matches():
    """A short pass (10 min, 150 features) whose camera 7 matched 30 % of them (like Da) and
    camera 0 12 % (like Df). The shared-attitude form pays 12 parameters a camera, not a spline
    of its own: camera 7's redundancy is well above 30 and every estimated scale lies within 4
    standard errors of the truth; camera 0, still below 30, takes its twin's scale. The per-camera
    form leaves camera 0 (and here camera 7 too) with less redundancy and camera 0 at scale 1."""
    scales = np.array([2.2, 1.3, 1.0, 0.9, 1.0, 1.1, 1.4, 2.0])
    seen = np.array([0.12, 0.8, 0.9, 0.95, 0.95, 0.9, 0.8, 0.3])
    args, pointing = _shared_attitude(6, scales, seen)
    twin = {c: 7 - c for c in range(8)}
    shared = camera_sigma_scales(*args, pointing=pointing, twin=twin)
    assert shared.model == "shared attitude"
    for cam, k in enumerate(scales[1:], start=1):
        assert shared.estimated[cam], (cam, shared.redundancy[cam])
        tol = 4.0 * k / np.sqrt(2.0 * shared.redundancy[cam])
        assert abs(shared.scale[cam] - k) <= tol, (cam, shared.scale[cam], k, tol)
    assert not shared.estimated[0] and shared.borrowed == {0: 7} and shared.scale[0] == shared.scale[7]
    assert shared.as_dict([f"c{i}" for i in range(8)])["c0"]["scale_from"] == "c7"
    per_camera = camera_sigma_scales(*args, twin=twin)
    assert per_camera.model == "per camera"
    assert per_camera.redundancy[7] < shared.redundancy[7] - 20 and per_camera.redundancy[0] < shared.redundancy[0]
    # without a twin the stated sigma is kept
    alone = camera_sigma_scales(*args, pointing=pointing)
    assert alone.scale[0] == 1.0 and not alone.borrowed


def test_shared_attitude_without_the_an_term_inflates_the_scales():
    """K_c matters: dropping the attitude seen through An's ray (K = 0) leaves the part of it the
    cameras' own terms cannot mimic in the scatter. The pooled scale (all cameras, weighted by
    redundancy; standard error ``1 / sqrt(2 sum r)``) grows by more than 5 standard errors."""
    from misrgraph.match.precision import Pointing

    scales = np.ones(8)
    args, pointing = _shared_attitude(7, scales, np.full(8, 0.8))
    fit = camera_sigma_scales(*args, pointing=pointing)
    blind = camera_sigma_scales(
        *args, pointing=Pointing(pointing.an_time_s, pointing.camera_px_per_rad, np.zeros_like(pointing.an_px_per_rad))
    )

    def pooled(f):
        r = np.array([f.redundancy[c] for c in f.scale])
        k = np.array([f.scale[c] for c in f.scale])
        return float(np.sqrt(np.sum(k**2 * r) / np.sum(r))), float(1.0 / np.sqrt(2.0 * np.sum(r)))

    k_fit, se = pooled(fit)
    k_blind, _ = pooled(blind)
    assert abs(k_fit - 1.0) < 4.0 * se, (k_fit, se)
    assert k_blind > k_fit + 5.0 * se, (k_blind, k_fit, se)


def _dense_feature_system(a, y, e, ff, n_f, w, prior):
    """The dense stacked solution of ``y = a s + sum_j e[:, j] u[ff, j]`` with zero-mean priors of
    precision ``prior (q,)`` on each feature's ``q`` unknowns (columns of ``a`` equilibrated as the
    solvers do; pseudo-inverse for the gauge): residuals, hat diagonal, the unknowns ``(n_f, q)`` and
    their covariance blocks ``(n_f, q, q)``."""
    q, p, m = e.shape[1], a.shape[1], y.size
    col = np.sqrt(np.einsum("mp,m->p", a * a, w))
    col[col == 0] = 1.0  # a spline coefficient no row sees
    A = np.zeros((m, p + q * n_f))
    A[:, :p] = a / col
    for j in range(q):
        A[np.arange(m), p + q * ff + j] = e[:, j]
    N = A.T @ (A * w[:, None]) + np.diag(np.r_[np.zeros(p), np.tile(prior, n_f)])
    Ninv = np.linalg.pinv(N, hermitian=True, rcond=1e-12)
    x_all = Ninv @ (A.T @ (w * y))
    blocks = np.array([Ninv[p + q * k : p + q * (k + 1), p + q * k : p + q * (k + 1)] for k in range(n_f)])
    return y - A @ x_all, np.einsum("ij,jk,ik->i", A, Ninv, A) * w, x_all[p:].reshape(n_f, q), blocks


def test_shared_attitude_solution_and_hat_diagonal_match_the_dense_system():
    """``_solve_rows``'s Schur-complement residuals and hat diagonal equal the dense stacked
    computation (heights and their prior included; pseudo-inverse for the gauge)."""
    from misrgraph.match.precision import _shared_design, _solve_rows

    (f, c, t, x, d, e, s), pointing = _shared_attitude(
        8, np.array([1.0, 2.0, 1.5]), np.array([0.6, 0.8, 0.7]), n_features=40
    )
    ids, feat_of = np.unique(f, return_inverse=True)
    a = _shared_design(c, [0, 1, 2], t, x, pointing, 120.0)
    y, ee, ff, w = d.reshape(-1), e.reshape(-1), np.repeat(feat_of, 2), np.repeat(1.0 / s**2, 2)
    res, hat = _solve_rows(a, y, ee, ff, ids.size, w, 1000.0)
    r_dense, hat_dense, _, _ = _dense_feature_system(a, y, ee[:, None], ff, ids.size, w, np.array([1e-6]))
    assert np.allclose(res, r_dense, atol=1e-6 * np.abs(y).max())
    assert np.allclose(hat, hat_dense, atol=1e-6)


def test_pointing_of_the_wrong_shape_is_refused_by_name():
    from misrgraph.errors import InputError
    from misrgraph.match.precision import Pointing

    args, pointing = _shared_attitude(9, np.ones(2), np.ones(2), n_features=20)
    bad = Pointing(pointing.an_time_s[:-1], pointing.camera_px_per_rad, pointing.an_px_per_rad)
    with pytest.raises(InputError, match="pointing.an_time_s"):
        camera_sigma_scales(*args, pointing=bad)


def test_gcp_scale_recovered_and_blind_to_what_a_gcps_views_share():
    """GCP observations joined to the shared-attitude fit (a 10-minute pass, 25 GCPs in nine
    cameras, their sigma 1.8x optimistic): the GCP scale lies within 4 standard errors of 1.8
    (``k / sqrt(2 r)``) and the tie cameras' within theirs. The ground offsets (catalogue error,
    chip registration) and An's static pointing error are the fit's own unknowns: drawn 0 or 100 m
    and 0 or 20", the residuals -- and so every scale -- are the same to rounding."""
    scales = np.array([2.0, 1.3, 1.0, 0.9, 1.0, 1.1, 1.4, 2.0])
    seen = np.full(8, 0.8)
    fits = []
    for ground_m, an_arcsec in ((30.0, 10.0), (0.0, 0.0), (100.0, 20.0)):
        args, pointing, gcp = _shared_attitude(
            11, scales, seen, gcps={"scale": 1.8, "n": 25, "ground_m": ground_m, "an_static_arcsec": an_arcsec}
        )
        fits.append(camera_sigma_scales(*args, pointing=pointing, gcp=gcp))
    fit = fits[0]
    g = fit.gcp
    assert g is not None and g.estimated and g.kept == 225 and g.redundancy > 100, g
    assert abs(g.scale - 1.8) <= 4.0 * 1.8 / np.sqrt(2.0 * g.redundancy), g
    for cam, k in enumerate(scales):
        assert abs(fit.scale[cam] - k) <= 4.0 * k / np.sqrt(2.0 * fit.redundancy[cam]), (cam, fit.scale[cam], k)
    for other in fits[1:]:
        assert other.gcp.scale == pytest.approx(g.scale, rel=1e-6)
        assert all(other.scale[c] == pytest.approx(fit.scale[c], rel=1e-6) for c in fit.scale)
    # too few GCP rows for the redundancy asked: not estimated, the stated sigma kept
    few = camera_sigma_scales(*args, pointing=pointing, gcp=gcp, gcp_min_redundancy=10 * g.redundancy)
    assert not few.gcp.estimated and few.gcp.scale == 1.0


def test_gcp_rows_need_the_shared_attitude_and_the_right_shapes():
    from misrgraph.errors import InputError

    args, pointing, gcp = _shared_attitude(
        12, np.ones(2), np.ones(2), n_features=30, gcps={"scale": 1.0, "n": 4, "ground_m": 10.0}
    )
    with pytest.raises(InputError, match="gcp"):
        camera_sigma_scales(*args, gcp=gcp)  # the per-camera form has no attitude to share
    with pytest.raises(InputError, match="gcp.d"):
        camera_sigma_scales(*args, pointing=pointing, gcp=gcp._replace(d=gcp.d[:-1]))
    with pytest.raises(InputError, match="gcp.sigma"):
        camera_sigma_scales(*args, pointing=pointing, gcp=gcp._replace(sigma=-gcp.sigma))


def test_feature_blocks_solution_and_covariance_match_the_dense_system():
    """``_solve_blocks`` with three unknowns per feature (height, line and sample offsets, each with
    its prior): residuals, hat diagonal, the features' unknowns and their covariance blocks equal
    the dense stacked computation."""
    from misrgraph.match.precision import _shared_design, _solve_blocks

    (f, c, t, x, d, e, s), pointing = _shared_attitude(
        8, np.array([1.0, 2.0, 1.5]), np.array([0.6, 0.8, 0.7]), n_features=40
    )
    ids, of = np.unique(f, return_inverse=True)
    n_f = ids.size
    a = _shared_design(c, [0, 1, 2], t, x, pointing, 120.0)
    m = 2 * f.size
    y, w, ff = d.reshape(-1), np.repeat(1.0 / s**2, 2), np.repeat(of, 2)
    e3 = np.zeros((m, 3))
    e3[:, 0], e3[0::2, 1], e3[1::2, 2] = e.reshape(-1), 1.0, 1.0
    prior = np.array([1e-6, 1 / 0.003, 1 / 0.003])
    res, hat, u, cov_u = _solve_blocks(a, y, e3, ff, n_f, w, prior)
    r_dense, hat_dense, u_dense, blocks = _dense_feature_system(a, y, e3, ff, n_f, w, prior)
    assert np.allclose(res, r_dense, atol=1e-6 * np.abs(y).max())
    assert np.allclose(hat, hat_dense, atol=1e-6)
    # the heights (m) sit on a weak prior, so their last digits depend on the pseudo-inverse; 0.1 mm
    assert np.allclose(u[:, 0], u_dense[:, 0], atol=1e-4)
    assert np.allclose(u[:, 1:], u_dense[:, 1:], rtol=1e-6, atol=1e-9)
    assert np.allclose(cov_u[:, 1:, 1:], blocks[:, 1:, 1:], rtol=1e-6)


def test_shared_offset_recovered_and_kept_out_of_the_camera_scales():
    """An offset every conjugate of a feature shares (the template's own position error), drawn with
    1 sigma 0 or 0.06 px per coordinate on top of the model's noise: the fit with
    ``shared_offset`` recovers 0.06 within 4 standard errors (``s / sqrt(2 r)``) and puts the zero
    case below a quarter of the conjugates' median sigma (a variance component near zero settles a
    little above it), and keeps each camera's scale
    within its 4 standard errors of the truth. Without it the shared part inflates the cameras'
    scales (the A/B-like cameras by more than 4 standard errors)."""
    scales = np.array([2.0, 1.3, 1.0, 0.9, 1.0, 1.1, 1.4, 2.0])
    (f, c, t, x, d, e, s), pointing = _shared_attitude(11, scales, np.full(8, 0.8))
    rng = np.random.default_rng(5)
    ids, of = np.unique(f, return_inverse=True)
    for sd in (0.0, 0.06):
        dd = d + rng.normal(0.0, sd, (ids.size, 2))[of] if sd else d
        fit = camera_sigma_scales(f, c, t, x, dd, e, s, pointing=pointing, shared_offset=True)
        so = fit.shared_offset
        assert so is not None and so.estimated, so
        if sd:
            assert abs(so.sigma_px - sd) <= 4.0 * sd / np.sqrt(2.0 * so.redundancy), so
        else:  # a variance component near zero: the iteration settles a little above it
            assert so.sigma_px < 0.25 * np.median(s), so
        for cam, k in enumerate(scales):
            assert abs(fit.scale[cam] - k) <= 4.0 * k / np.sqrt(2.0 * fit.redundancy[cam]), (sd, cam, fit.scale[cam])
        if sd:
            plain = camera_sigma_scales(f, c, t, x, dd, e, s, pointing=pointing)
            assert plain.shared_offset is None
            inflated = [
                cam
                for cam in (2, 3, 4, 5)
                if plain.scale[cam] - scales[cam] > 4.0 * scales[cam] / np.sqrt(2.0 * plain.redundancy[cam])
            ]
            assert len(inflated) >= 2, {cam: plain.scale[cam] for cam in range(8)}
    from misrgraph.errors import InputError

    with pytest.raises(InputError, match="shared_offset"):
        camera_sigma_scales(f, c, t, x, d, e, s, shared_offset=True)  # the per-camera form has no such term
