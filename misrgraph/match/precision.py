"""Each camera's tie-matching precision from the pass's own redundancy.

The least-squares matcher's covariance (:mod:`misrgraph.match.lsm`) sees only what its residuals
show. The largest error between two views of a patch does not show there: the scene looks
different from another angle (BRDF), so the pattern changes at the texture's own scales.
The fit absorbs most of that change, which then moves the matched position. For the D cameras
(70.5 deg against An's nadir) the LSM sigma is about 2x optimistic on the simulator's scenes.

The data carry the missing information. A tie point is matched from An into up to eight cameras,
each at the position the supplied navigation and the DEM predict. The difference
``d = matched - predicted (line, sample)`` of camera ``c`` is

    d_ic = s_c(t_i, x_i) + h_i e_ic + m_ic

* ``s_c`` is the navigation and camera-model error. It is smooth: a cubic B-spline in the
  observation time ``t`` with the adjustment's knot spacing, times ``(1, x)``, plus ``x^2, x^3``
  terms constant in time (``x`` is the sample's offset from the array centre, normalised).
* ``h_i e_ic`` is the feature's height error along An's ray. An's observation defines the tie
  point, so the point keeps one degree of freedom: its height. ``e_ic`` is the image displacement
  in camera ``c`` per metre of height (the epipolar direction).
* ``m_ic`` is the matching error, with sigma ``k_c sigma_ic``.

These are the unknowns the adjustment itself has (a smooth attitude on its knots, a landmark
position). So ``k_c`` is the scale that makes the sigma honest *for the adjustment*: the scatter
the adjustment cannot absorb. Errors faster than the knots, such as jitter, are counted in the
scale. For the adjustment they are observation noise.

Method:

* One weighted least-squares fit of all cameras' smooth models and all heights together. The
  heights are eliminated by a Schur complement, so the cost grows linearly with the features.
* Each camera's redundancy is ``r_c = n_c - tr(N^-1 N_c)``, exact for the linear model.
* ``k_c^2 = sum_c z^2 / r_c`` (Foerstner's variance components), iterated with the weights
  ``1 / (k_c sigma)^2`` until the scales settle.
* Robust: an observation whose radial ``z^2`` exceeds the chi-square (2 dof) quantile of
  ``+-clip`` sigma is left out of the next fit.
* A camera with a redundancy below ``min_redundancy`` keeps ``k_c = 1``. This is reported,
  not hidden.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.interpolate import BSpline

__all__ = ["PrecisionFit", "camera_sigma_scales"]

Array = NDArray[np.float64]


@dataclass
class PrecisionFit:
    """Per-camera sigma scales ``scale[c]`` (1 where not estimated), the redundancy and the kept and
    clipped observation counts behind each (camera index -> value), and the variance-component
    ``iterations``."""

    scale: dict[int, float] = field(default_factory=dict)
    redundancy: dict[int, float] = field(default_factory=dict)
    kept: dict[int, int] = field(default_factory=dict)
    clipped: dict[int, int] = field(default_factory=dict)
    estimated: dict[int, bool] = field(default_factory=dict)
    iterations: int = 0
    #: per input row: True where the observation was clipped (inconsistent with the pass)
    outlier: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))

    def as_dict(self, names: list[str] | tuple[str, ...]) -> dict[str, dict[str, float | int | bool]]:
        return {names[c]: {"scale": self.scale[c], "redundancy": self.redundancy[c], "kept": self.kept[c],
                           "clipped": self.clipped[c], "estimated": self.estimated[c]} for c in sorted(self.scale)}


def _design(t: Array, x: Array, knot_s: float) -> Array:
    """Smooth-model design ``(n, p)``: cubic B-splines in ``t`` (s) times ``(1, x)``, plus ``x^2, x^3``."""
    lo, hi = float(np.min(t)), float(np.max(t))
    n_int = max(int(np.ceil((hi - lo) / knot_s)), 1)
    inner = np.linspace(lo, hi + 1e-9, n_int + 1)
    knots = np.r_[[inner[0]] * 3, inner, [inner[-1]] * 3]
    b = BSpline.design_matrix(np.clip(t, inner[0], inner[-1]), knots, 3).toarray()
    return np.hstack([b, b * x[:, None], (x ** 2)[:, None], (x ** 3)[:, None]])


def _solve(X: dict[int, Array], rows: dict[int, NDArray[np.int64]], feat_of: NDArray[np.int64], n_feat: int, d: Array,
           e: Array, w: Array, h_prior_m: float) -> tuple[Array, dict[int, float]]:
    """Joint weighted least squares of the smooth models and the heights (Schur complement on the
    heights); the residuals ``(n, 2)`` and each camera's redundancy ``n_c - tr(N^-1 N_c)``. Rows
    with ``w = 0`` are out of the fit."""
    # parameter blocks: (camera, coordinate) -> offset into the smooth parameters
    off, o = {}, 0
    for c in rows:
        for q in range(2):
            off[c, q] = o
            o += X[c].shape[1]
    n_s = o
    a_ss = np.zeros((n_s, n_s))
    b = np.zeros((n_s, n_feat))
    rhs_s = np.zeros(n_s)
    dd = np.full(n_feat, 1.0 / h_prior_m ** 2)
    rhs_h = np.zeros(n_feat)
    for c, r in rows.items():
        xc, wc, fc = X[c], w[r], feat_of[r]
        for q in range(2):
            sl = slice(off[c, q], off[c, q] + xc.shape[1])
            a_ss[sl, sl] = xc.T @ (xc * wc[:, None])
            rhs_s[sl] = xc.T @ (wc * d[r, q])
            we = wc * e[r, q]
            np.add.at(b[sl].T, fc, xc * we[:, None])
            np.add.at(dd, fc, we * e[r, q])
            np.add.at(rhs_h, fc, we * d[r, q])
    bd = b / dd  # B D^-1
    s_mat = a_ss - bd @ b.T
    s_mat += np.eye(n_s) * (1e-10 * max(float(np.max(np.diag(s_mat))), 1e-300))  # cameras without data
    q_mat = np.linalg.pinv(s_mat, hermitian=True)
    x_s = q_mat @ (rhs_s - bd @ rhs_h)
    h = (rhs_h - b.T @ x_s) / dd
    res = d.copy()
    for c, r in rows.items():
        for q in range(2):
            res[r, q] -= X[c] @ x_s[off[c, q]:off[c, q] + X[c].shape[1]]
    res -= h[feat_of][:, None] * e
    # redundancy per camera: n_c - tr(N^-1 N_c), N^-1 = [[Q, R], [R^T, H]], R = -Q B D^-1
    qbd = q_mat @ bd
    h_diag = 1.0 / dd + np.sum(bd * qbd, axis=0)
    red = {}
    for c, r in rows.items():
        xc, wc, fc = X[c], w[r], feat_of[r]
        tr = 0.0
        for q in range(2):
            sl = slice(off[c, q], off[c, q] + xc.shape[1])
            tr += float(np.sum(q_mat[sl, sl] * a_ss[sl, sl]))
            we = wc * e[r, q]
            # 2 tr(R B_c^T): B_c's column f is sum over camera c's rows of feature f of x w e
            tr -= 2.0 * float(np.sum(np.sum(qbd[sl][:, fc] * (xc * we[:, None]).T, axis=0)))
            tr += float(np.sum(h_diag[fc] * we * e[r, q]))
        red[c] = 2.0 * float(np.count_nonzero(wc)) - tr
    return res, red


def camera_sigma_scales(feature: NDArray[np.int64], camera: NDArray[np.int64], time_s: Array, x: Array, d: Array,
                        epipolar: Array, sigma: Array, knot_s: float = 60.0, clip: float = 4.0,
                        min_redundancy: float = 30.0, max_iter: int = 10, tol: float = 0.01,
                        height_prior_m: float = 1000.0) -> PrecisionFit:
    """Per-camera scales of the matching sigmas (see the module docstring).

    Arguments, one row per matched (non-defining) observation, ``n`` rows:
    ``feature (n,)`` the tie feature, ``camera (n,)``, ``time_s (n,)`` the observation time (s),
    ``x (n,)`` the normalised sample offset from the array centre, ``d (n, 2)`` matched minus
    predicted (line, sample) px, ``epipolar (n, 2)`` px per metre of height along the defining ray,
    ``sigma (n,)`` px the matcher's sigmas; ``knot_s`` the smooth model's knot spacing (s).
    ``height_prior_m`` is a weak prior on each height (it only removes the exact degeneracy
    between a common height change and the smooth models). The scales are iterated as variance
    components (Foerstner) until they change by less than ``tol`` (relative)."""
    feature = np.asarray(feature, np.int64)
    camera = np.asarray(camera, np.int64)
    d = np.asarray(d, float).reshape(-1, 2)
    e = np.asarray(epipolar, float).reshape(-1, 2)
    sigma = np.asarray(sigma, float)
    n = feature.size
    out = PrecisionFit()
    if n == 0:
        return out
    chi2_clip = float(stats.chi2.isf(2.0 * stats.norm.sf(clip), 2))
    rows = {int(c): np.flatnonzero(camera == c) for c in np.unique(camera)}
    X = {c: _design(np.asarray(time_s, float)[r], np.asarray(x, float)[r], knot_s) for c, r in rows.items()}
    feat_ids, feat_of = np.unique(feature, return_inverse=True)
    scale = {c: 1.0 for c in rows}
    keep = np.ones(n, bool)
    red: dict[int, float] = {}
    it = 0
    cams = sorted(rows)
    cam_pos = np.searchsorted(cams, camera)  # each row's camera, as a position in cams

    def per_row(d: dict[int, float]) -> Array:
        return np.array([d[c] for c in cams])[cam_pos]

    for it in range(1, max_iter + 1):
        w = np.where(keep, 1.0 / (sigma * per_row(scale)) ** 2, 0.0)
        res, red = _solve(X, rows, feat_of, feat_ids.size, d, e, w, height_prior_m)
        z2 = np.sum(res ** 2, axis=1) / sigma ** 2  # against the stated sigma, both coordinates
        change = 0.0
        for c, r in rows.items():
            k = keep[r]
            if red[c] >= min_redundancy:
                new = float(np.sqrt(np.sum(z2[r][k]) / red[c]))
                change = max(change, abs(new / scale[c] - 1.0))
                scale[c] = new
        new_keep = z2 <= per_row(scale) ** 2 * chi2_clip
        if change < tol and np.array_equal(new_keep, keep):
            break
        keep = new_keep
    for c, r in rows.items():
        est = red[c] >= min_redundancy
        out.scale[c] = scale[c] if est else 1.0
        out.redundancy[c] = float(max(red[c], 0.0))
        out.estimated[c] = bool(est)
        out.kept[c] = int(keep[r].sum())
        out.clipped[c] = int((~keep[r]).sum())
    out.iterations = it
    out.outlier = ~keep
    return out
