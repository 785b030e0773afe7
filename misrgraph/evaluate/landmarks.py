"""The landmarks' NEES split into what landmarks near in time share and what each has alone.

A pass's landmark errors are not independent: every landmark seen at about the same time moves with
the same attitude, ephemeris and camera errors. The per-landmark NEES (``nees["landmarks"]`` of
:func:`misrgraph.evaluate.score.score_pass`) averages both parts, so a covariance too small in one
and too large in the other can average to 1. This module splits it with the landmarks' full joint
covariance, which the Schur form gives exactly: two landmarks ``i != j`` co-vary through the other
variables only,

    Cov(e_i, e_j) = G_i S G_j^T,    Cov(e_i) = P_i (the reported marginal),

with ``G_i = H_ll,i^-1 H_lc,i`` the landmark's response (:attr:`misrgraph.estimate.problem.Marginals.landmark_response`)
and ``S`` the other variables' joint covariance. ``C_i = P_i - G_i S G_i^T`` is the landmark's own
part (its rays' noise, its height, and anything the adjustment added to its marginal alone).

The landmarks are grouped by the mean time of their observations, in windows of ``window_s``
(:data:`LANDMARK_GROUP_S`: 300 s, about 2000 km of ground track, over which the knots' errors are
correlated). Per group ``g`` of ``m`` landmarks:

* **common**: the group's mean error ``e_g = mean_i e_i`` against
  ``Cov(e_g) = A S A^T + sum_i C_i / m^2`` (``A = mean_i G_i``): ``e_g^T Cov(e_g)^-1 e_g`` per group,
  NEES/dim over the groups;
* **within**: each landmark's deviation ``d_i = e_i - e_g`` against
  ``Cov(d_i) = P_i - B_i - B_i^T + Cov(e_g)`` (``B_i = Cov(e_i, e_g) = G_i S A^T + C_i / m``):
  ``d_i^T Cov(d_i)^-1 d_i`` per landmark of a group of two or more, NEES/dim over them.

Both are 1 in expectation when the covariance is right. Their terms are correlated (the deviations
of a group sum to zero; the groups share the camera and ephemeris errors), so a chi-square band
that assumes independent terms is too narrow: judge them by the scatter over passes
(``misrgraph bench nees``). Errors and covariances are taken in each landmark's local east,
north, up frame; the per-axis means (``*_enu``) show which direction is off.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import InputError

__all__ = ["LANDMARK_GROUP_S", "landmark_nees_split", "time_groups"]

Array = NDArray[np.float64]

#: the default window (s) of :func:`time_groups`
LANDMARK_GROUP_S = 300.0


def time_groups(time_s: ArrayLike, window_s: float = LANDMARK_GROUP_S) -> NDArray[np.int64]:
    """Group index ``(L,)`` of each landmark by its mean observation time ``time_s (L,)`` (s):
    consecutive windows of ``window_s`` from the earliest."""
    t = np.asarray(time_s, dtype=float)
    if not (np.isfinite(window_s) and window_s > 0):
        raise InputError("window_s", window_s, "a positive number of seconds")
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise InputError(
            "time_s", t.shape if t.ndim != 1 else float(t[~np.isfinite(t)][0]), "finite times (s), one per landmark"
        )
    if t.size == 0:
        return np.zeros(0, np.int64)
    return np.floor((t - t.min()) / window_s).astype(np.int64)


def landmark_nees_split(
    error: ArrayLike, cov: ArrayLike, response: ArrayLike, joint: ArrayLike, group: ArrayLike
) -> dict[str, Any]:
    """The common and within-group landmark NEES (module docstring).

    ``error (L, 3)`` m: estimate minus truth; ``cov (L, 3, 3)`` m^2: each landmark's marginal
    covariance; ``response (L, 3, n_c)``: ``G_i`` (m per unit of the other variables); ``joint
    (n_c, n_c)``: the other variables' joint covariance ``S``; all in the same frame per landmark
    (its local east, north, up for the ``*_enu`` figures to mean that); ``group (L,)`` int.

    Returns ``common``/``common_dim``, ``within``/``within_dim`` (NEES/dim and the dimension they
    were averaged over; ``within`` is NaN when no group has two landmarks), ``common_enu`` and
    ``within_enu`` (mean ``z^2`` per axis) and ``groups``."""
    e = np.asarray(error, float)
    p = np.asarray(cov, float)
    g = np.asarray(response, float)
    s = np.asarray(joint, float)
    grp = np.asarray(group)
    n = e.shape[0]
    if e.shape != (n, 3) or p.shape != (n, 3, 3) or g.ndim != 3 or g.shape[:2] != (n, 3) or grp.shape != (n,):
        raise InputError(
            "(error, cov, response, group)",
            (e.shape, p.shape, g.shape, grp.shape),
            "shapes (L, 3), (L, 3, 3), (L, 3, n_c), (L,)",
        )
    if s.shape != (g.shape[2], g.shape[2]):
        raise InputError("joint", s.shape, f"shape ({g.shape[2]}, {g.shape[2]}) (the response's columns)")
    if n == 0:
        raise InputError("error", 0, "at least one landmark")
    gs = g @ s  # (L, 3, n_c)
    own = p - np.einsum("lic,ljc->lij", gs, g)  # C_i
    common, common_axes, within, within_axes = [], [], [], []
    for label in np.unique(grp):
        idx = np.flatnonzero(grp == label)
        m = idx.size
        a = g[idx].mean(axis=0)  # (3, n_c)
        cov_mean = a @ s @ a.T + own[idx].sum(axis=0) / m**2
        mean = e[idx].mean(axis=0)
        common.append(float(mean @ np.linalg.solve(cov_mean, mean)))
        common_axes.append(mean**2 / np.diag(cov_mean))
        if m < 2:
            continue
        b = gs[idx] @ a.T + own[idx] / m  # Cov(e_i, e_g), (m, 3, 3)
        cov_dev = p[idx] - b - np.swapaxes(b, 1, 2) + cov_mean
        d = e[idx] - mean
        within.extend(np.einsum("li,li->l", d, np.linalg.solve(cov_dev, d[:, :, None])[:, :, 0]).tolist())
        within_axes.append(d**2 / np.einsum("lii->li", cov_dev))
    out: dict[str, Any] = {
        "groups": len(common),
        "common": float(np.sum(common) / (3 * len(common))),
        "common_dim": 3 * len(common),
        "common_enu": np.mean(common_axes, axis=0).tolist(),
    }
    if within:
        out.update(
            within=float(np.mean(within) / 3),
            within_dim=3 * len(within),
            within_enu=np.concatenate(within_axes).mean(axis=0).tolist(),
        )
    else:
        out.update(within=float("nan"), within_dim=0, within_enu=[float("nan")] * 3)
    return out
