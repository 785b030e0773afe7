"""The height error a matched tie point's rays share, estimated from the pass's DEM residuals.

A tie point measured by template matching is defined by An's interest point (the centre pixel of
An's template); its conjugates in the other cameras are found by matching that template, so each
measures the texture-weighted parallax under the whole template, not the centre's. Relief the
matcher's affine model cannot follow (the terrain's departure from a plane over the template) and
the view-dependent change of the pattern move all the conjugates of one point along their
epipolar directions together. To the adjustment that is an error ``dh`` of the point's height
along An's ray, and the point's own (free) height absorbs it: the rays cannot see it, and the
covariance from them states the height too well (docs/explanation/conventions.md, "Matched tie points'
heights").

Only the DEM factor sees it, because it compares the rays' point with the DEM under An's centre.
With the landmark taken as the rays' point, ``dh`` is an error of that factor's row alone, and
its residual ``r_i`` (m) has, to first order,

    E[r_i^2] = q_i sigma_i^2 + q_i^2 s^2,      Var[r_i^2] = 2 (q_i sigma_i^2 + q_i^2 s^2)^2,

with ``sigma_i`` the factor's stated 1 sigma (m), ``q_i`` its redundancy number (0..1, from the
whitened system) and ``s^2`` the shared height variance (m^2). :func:`shared_height_variance`
estimates ``s^2`` by generalised least squares on the ``r_i^2`` (weights ``1 / Var[r_i^2]``,
iterated), with its standard error, clipped at 0. :func:`inflate_along` then adds ``s^2 u u^T``
to each tie landmark's covariance, ``u`` the unit vector along An's ray: the landmark's estimate is
the rays' point, and the point An's centre sees lies ``dh`` from it along ``u``. Both are first
order in ``s^2 / sigma_i^2`` (the DEM holds a landmark's height weakly: ``sigma_i`` 30-60 m
against the rays' 5-15 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import InputError

__all__ = ["SharedHeight", "shared_height_variance", "pool_shared_height", "inflate_along", "TIE_HEIGHT_MODES"]

Array = NDArray[np.float64]

#: ``AdjustConfig.tie_height_sigma_m`` as a word: "auto" estimates it for matched tie points and
#: leaves point measurements (the simulator's own observations) without it; "estimate" always
#: estimates it; a number (m, >= 0) fixes it
TIE_HEIGHT_MODES = ("auto", "estimate")


@dataclass(frozen=True)
class SharedHeight:
    """The estimate: ``variance_m2`` (``s^2``, clipped at 0), ``unclipped_m2`` (the estimator's
    own value, may be negative), ``standard_error_m2`` and the number of DEM rows ``n`` used."""

    variance_m2: float
    unclipped_m2: float
    standard_error_m2: float
    n: int

    @property
    def sigma_m(self) -> float:
        return float(np.sqrt(self.variance_m2))


def shared_height_variance(
    residual_m: ArrayLike, sigma_m: ArrayLike, redundancy: ArrayLike, iterations: int = 10
) -> SharedHeight:
    """``s^2`` (m^2) from DEM-factor residuals (see the module docstring).

    ``residual_m (n,)``: each DEM factor's residual at the optimum (m, landmark height minus DEM);
    ``sigma_m (n,)``: its stated 1 sigma (m, > 0); ``redundancy (n,)``: its redundancy number
    (0..1]. GLS for ``r_i^2 - q_i sigma_i^2 = q_i^2 s^2 + noise``:
    ``s^2 = sum w_i q_i^2 (r_i^2 - q_i sigma_i^2) / sum w_i q_i^4`` with
    ``w_i = 1 / (2 (q_i sigma_i^2 + q_i^2 s^2)^2)`` at the previous ``s^2`` (clipped at 0), and
    standard error ``1 / sqrt(sum w_i q_i^4)``."""
    r = np.asarray(residual_m, float).ravel()
    sig = np.asarray(sigma_m, float).ravel()
    q = np.asarray(redundancy, float).ravel()
    for name, a in (("sigma_m", sig), ("redundancy", q)):
        if a.size != r.size:
            raise InputError(name, a.size, f"{r.size} values (one per DEM residual)")
    if not np.all(np.isfinite(r)):
        raise InputError("residual_m", r[~np.isfinite(r)][0], "finite residuals (m)")
    if r.size and not (np.all(np.isfinite(sig)) and sig.min() > 0):
        raise InputError("sigma_m", float(sig.min()), "positive sigmas (m)")
    if r.size and not (np.all(np.isfinite(q)) and q.min() > 0 and q.max() <= 1 + 1e-9):
        raise InputError("redundancy", [float(q.min()), float(q.max())], "redundancy numbers in (0, 1]")
    if r.size < 2:
        return SharedHeight(0.0, float("nan"), float("inf"), int(r.size))
    y = r**2 - q * sig**2
    a = q**2
    s2 = 0.0
    est = 0.0
    for _ in range(iterations):
        w = 0.5 / (q * sig**2 + a * s2) ** 2
        info = float(np.sum(w * a * a))
        est = float(np.sum(w * a * y)) / info
        new = max(est, 0.0)
        if abs(new - s2) <= 1e-6 * max(new, 1.0):
            s2 = new
            break
        s2 = new
    w = 0.5 / (q * sig**2 + a * s2) ** 2
    return SharedHeight(s2, est, float(1.0 / np.sqrt(np.sum(w * a * a))), int(r.size))


def pool_shared_height(unclipped_m2: ArrayLike, n: ArrayLike) -> SharedHeight:
    """``s^2`` (m^2) pooled over passes from each pass's own estimate.

    ``unclipped_m2 (P,)``: each pass's unclipped estimate (:attr:`SharedHeight.unclipped_m2`; the
    clipped values are biased up, these are not); ``n (P,)``: its number of DEM rows. On a short
    pass (tens of tie points) one estimate's standard error is as large as the variance itself; a
    campaign's passes see the same matcher and terrain class, so their mean is the steadier figure.
    The mean is weighted by ``n`` (weights that do not depend on the estimates' noise, so the mean
    stays unbiased); its standard error comes from the passes' scatter about it,
    ``sqrt(P / (P - 1) * sum w_p^2 (u_p - mean)^2)`` with ``w_p = n_p / sum n`` (needs ``P >= 2``).
    Returns a :class:`SharedHeight` whose ``n`` is the total number of DEM rows."""
    u = np.asarray(unclipped_m2, float).ravel()
    m = np.asarray(n, float).ravel()
    if u.size != m.size:
        raise InputError("n", m.size, f"{u.size} counts (one per pass estimate)")
    if u.size < 2:
        raise InputError("unclipped_m2", u.size, "estimates from at least 2 passes")
    if not np.all(np.isfinite(u)):
        raise InputError("unclipped_m2", u[~np.isfinite(u)][0], "finite estimates (m^2)")
    if not (np.all(np.isfinite(m)) and m.min() > 0):
        raise InputError("n", float(m.min()), "positive numbers of DEM rows")
    w = m / m.sum()
    mean = float(np.sum(w * u))
    se = float(np.sqrt(u.size / (u.size - 1.0) * np.sum(w**2 * (u - mean) ** 2)))
    return SharedHeight(max(mean, 0.0), mean, se, int(m.sum()))


def inflate_along(cov: ArrayLike, direction: ArrayLike, variance_m2: float) -> Array:
    """``cov + s^2 u u^T`` per point: ``cov (N, 3, 3)`` (m^2), ``direction (N, 3)`` (any length,
    normalised here), ``variance_m2`` ``s^2`` (m^2, >= 0)."""
    c = np.asarray(cov, float)
    u = np.asarray(direction, float)
    if c.ndim != 3 or c.shape[1:] != (3, 3):
        raise InputError("cov", c.shape, "shape (N, 3, 3)")
    if u.shape != (c.shape[0], 3):
        raise InputError("direction", u.shape, f"shape ({c.shape[0]}, 3)")
    if not (np.isfinite(variance_m2) and variance_m2 >= 0):
        raise InputError("variance_m2", variance_m2, "a variance >= 0 (m^2)")
    n = np.linalg.norm(u, axis=1, keepdims=True)
    if np.any(~np.isfinite(n) | (n <= 0)):
        raise InputError(
            "direction",
            u[np.flatnonzero(~np.isfinite(n[:, 0]) | (n[:, 0] <= 0))[0]].tolist(),
            "non-zero finite vectors",
        )
    u = u / n
    return c + variance_m2 * np.einsum("ni,nj->nij", u, u)
