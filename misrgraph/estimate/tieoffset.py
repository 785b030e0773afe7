"""The offset a matched tie point's conjugates share, carried into its covariance.

All conjugates of a tie feature (its observations in the cameras other than An) are found by
matching the same An template, and part of their error is common to them: the change of the
pattern between An's view and the others moves every conjugate of the feature the same way. The
matcher measures the 1 sigma of that common (line, sample) offset, ``s_o`` px per coordinate,
from the pass's own redundancy (:mod:`misrgraph.match.precision`, ``PrecisionFit.shared_offset``).
The adjustment weights the conjugates as independent, so the landmark follows the common offset
while its covariance does not know it. Given the other variables, the landmark's estimate moves
under a common shift ``o`` of its conjugates' measured positions by ``R_i o``, with

    R_i = H_ll,i^-1 sum_c J_c^T W_c        (3 x 2, m/px),

``J_c`` ``(2, 3)`` px/m the conjugate's Jacobian with respect to the landmark, ``W_c =
diag(1/sigma_line^2, 1/sigma_sample^2)`` its weight and ``H_ll,i`` the landmark's 3 x 3 block of
the information matrix (all its rays, An's included, and its DEM factor). With ``o ~ N(0, s_o^2
I_2)`` the landmark's covariance gains ``s_o^2 R_i R_i^T`` (:func:`offset_covariance`), which the
adjustment adds to its marginal (``AdjustConfig.tie_offset_sigma_px``) -- less what the
conjugates' own sigmas already hold of it. A conjugate weighted with ``sigma_c`` whose own error
is ``sigma_own,c = rho_c sigma_c`` (``rho_c``: the ratio of the matcher's two fits' scales for its
camera, ``SharedOffset.own_scale_ratio``) already puts ``a_c = sigma_c^2 (1 - rho_c^2)`` (at most
``s_o^2``) of the shared variance into the landmark's covariance, as if independent:
``a_c R_c R_c^T`` with ``R_c = H_ll,i^-1 J_c^T W_c``. The term is then

    s_o^2 R_i R_i^T - sum_c a_c R_c R_c^T,

exactly ``H^-1 J^T W (C - diag(sigma^2)) W J H^-1`` for the conjugates' true covariance
``C = diag(sigma_own^2) + s_o^2 1 1^T`` (per coordinate; :func:`counted_covariance`). It is first order, and
conditional on the other variables, like the tie points' shared height term
(:mod:`misrgraph.estimate.tieheight`). A line offset also moves the time an observation's geometry
is evaluated at, and with it the predicted sample (up to 0.15 px per px of line on a test pass);
``R`` treats the offset as a shift of the measured coordinates only and leaves that out.

Its effect on the tie landmarks' NEES is measured by ``misrgraph bench nees`` on matched passes
(docs, "The landmarks' NEES, split by time").
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import InputError

__all__ = ["offset_response", "offset_covariance", "counted_covariance", "TIE_OFFSET_MODES"]

Array = NDArray[np.float64]

#: ``AdjustConfig.tie_offset_sigma_px``'s named setting (else a number of px >= 0)
TIE_OFFSET_MODES = ("auto",)


def offset_response(
    h_ll: ArrayLike, jacobian: ArrayLike, sigma_px: ArrayLike, landmark: ArrayLike, shared: ArrayLike
) -> Array:
    """``R (L, 3, 2)`` m/px: each landmark's response to a common (line, sample) shift of its
    ``shared`` observations (module docstring). ``h_ll (L, 3, 3)``; per observation ``jacobian (N,
    2, 3)`` px/m, ``sigma_px (N, 2)``, ``landmark (N,)`` index into ``h_ll``, ``shared (N,)`` bool
    (the conjugates; An's and the GCPs' observations are False)."""
    h = np.asarray(h_ll, float)
    j = np.asarray(jacobian, float)
    sig = np.asarray(sigma_px, float)
    lm = np.asarray(landmark)
    sh = np.asarray(shared, bool)
    n = j.shape[0]
    if (
        h.ndim != 3
        or h.shape[1:] != (3, 3)
        or j.shape != (n, 2, 3)
        or sig.shape != (n, 2)
        or lm.shape != (n,)
        or sh.shape != (n,)
    ):
        raise InputError(
            "(h_ll, jacobian, sigma_px, landmark, shared)",
            (h.shape, j.shape, sig.shape, lm.shape, sh.shape),
            "shapes (L, 3, 3), (N, 2, 3), (N, 2), (N,), (N,)",
        )
    if not np.all(sig[sh] > 0):
        raise InputError("sigma_px", float(np.min(sig[sh])), "positive sigmas (px)")
    s = np.zeros((h.shape[0], 3, 2))
    np.add.at(s, lm[sh], np.swapaxes(j[sh] / sig[sh][:, :, None] ** 2, 1, 2))
    return np.linalg.solve(h, s)


def offset_covariance(response: ArrayLike, sigma_px: float) -> Array:
    """``s_o^2 R R^T`` ``(L, 3, 3)`` m^2 for a shared offset of ``sigma_px`` (1 sigma per coordinate)."""
    if not (np.isfinite(sigma_px) and sigma_px >= 0):
        raise InputError("tie_offset_sigma_px", sigma_px, "a finite 1 sigma >= 0 (px)")
    r = np.asarray(response, float)
    return sigma_px**2 * np.einsum("lij,lkj->lik", r, r)


def counted_covariance(
    h_ll: ArrayLike, jacobian: ArrayLike, sigma_px: ArrayLike, landmark: ArrayLike, counted_px2: ArrayLike
) -> Array:
    """``sum_c a_c R_c R_c^T`` ``(L, 3, 3)`` m^2: the shared variance ``a_c`` (px^2, ``(N,)``; 0 for
    observations that are not conjugates) that each observation's own sigma already carries into
    its landmark's covariance, ``R_c = H_ll^-1 J_c^T W_c``. Arguments as :func:`offset_response`."""
    h = np.asarray(h_ll, float)
    j = np.asarray(jacobian, float)
    sig = np.asarray(sigma_px, float)
    lm = np.asarray(landmark)
    a = np.asarray(counted_px2, float)
    if a.shape != (j.shape[0],) or not np.all(a >= 0):
        raise InputError(
            "counted_px2", a.shape if a.shape != (j.shape[0],) else float(a.min()), "(N,) variances >= 0 (px^2)"
        )
    use = a > 0
    out = np.zeros((h.shape[0], 3, 3))
    if use.any():
        rc = np.linalg.solve(h[lm[use]], np.swapaxes(j[use] / sig[use][:, :, None] ** 2, 1, 2))  # (n, 3, 2)
        np.add.at(out, lm[use], a[use, None, None] * (rc @ np.swapaxes(rc, 1, 2)))
    return out
