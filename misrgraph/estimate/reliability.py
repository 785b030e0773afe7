"""Reliability of a least-squares solution: redundancy numbers, Baarda's test, variance components.

For whitened residuals ``e = r(x*)`` and Jacobian ``J`` (``m x n``) at the optimum, the residuals'
covariance is ``R = I - J H^-1 J^T`` with ``H = J^T J``; its diagonal ``r_k`` are the redundancy
numbers (``0 <= r_k <= 1``, summing to ``m - n``): how much of an error in row ``k`` shows in its
own residual. From them:

* **Baarda's data snooping**, per observation (an image point = two rows): ``T_i = e_i^T R_i^-1 e_i``
  is chi-square with 2 dof when observation ``i`` is right; a 1-2 px mismatch at 0.2 px sigma
  gives ``T`` of 25-100. The per-coordinate ``w = e_k / sqrt(r_k)`` is standard normal.
* **Variance components** per class of rows (tie-point observations, GCP observations, DEM
  heights, priors): ``sigma0_c^2 = sum_c e_k^2 / sum_c r_k`` -- 1 when the class's sigmas are right
  (Foerstner's estimate after one iteration).

``J H^-1 J^T`` is formed through the Schur complement on the landmark blocks (each row touches at
most one landmark): with ``D`` the 3x3 landmark blocks of ``H``, ``G = D^-1 H_lc`` and
``S = L L^T`` the reduced system, a row ``a = [a_l, a_c]`` has
``a H^-1 a^T = a_l D^-1 a_l^T + ||L^-1 (G^T a_l^T - a_c^T)||^2``; rows are processed in chunks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy import stats

from misrgraph.estimate.problem import FlatProblem, reduced_cholesky, schur_reduce

__all__ = ["Reliability", "reliability", "critical_T", "class_scale", "W_TEST_ALPHA"]

Array = NDArray[np.float64]

#: significance of the per-observation test (two-dimensional, chi-square 2 dof)
W_TEST_ALPHA = 1e-3


def critical_T(alpha: float = W_TEST_ALPHA) -> float:
    """Critical value of the per-observation statistic ``T`` (chi-square, 2 dof) at ``alpha``."""
    return float(stats.chi2.isf(alpha, 2))


@dataclass
class Reliability:
    """Per row of the flat residual: whitened residual ``e (m,)``, leverage ``h (m,)`` and redundancy
    number ``r = 1 - h``; per observation (collinearity rows in pairs): the 2x2 residual covariance
    ``R_obs (N, 2, 2)`` and the test statistic ``T (N,)``."""

    e: Array
    h: Array
    R_obs: Array
    T: Array
    families: dict[str, slice]

    @property
    def r(self) -> Array:
        return 1.0 - self.h

    def variance_component(self, rows: NDArray[np.bool_] | slice) -> dict[str, float]:
        """``sigma0`` of a class of rows from its residuals and redundancy."""
        e2, rr = float(np.sum(self.e[rows] ** 2)), float(np.sum(self.r[rows]))
        return {
            "sigma0": float(np.sqrt(e2 / rr)) if rr > 0 else float("nan"),
            "redundancy": rr,
            "rows": int(np.size(self.e[rows])),
        }

    def summary(
        self,
        observation_class: NDArray[np.int64] | None = None,
        class_names: dict[int, str] | None = None,
        alpha: float = W_TEST_ALPHA,
    ) -> dict[str, Any]:
        """JSON-ready: redundancy (total, per-observation quantiles), the data-snooping test (critical
        value, how many observations exceed it), variance components per class."""
        crit = critical_T(alpha)
        r_obs = np.trace(self.R_obs, axis1=1, axis2=2) / 2.0
        out: dict[str, Any] = {
            "redundancy_total": float(np.sum(self.r)),
            "observation_redundancy": {
                "min": float(r_obs.min()),
                "median": float(np.median(r_obs)),
                "below_0.1": int(np.sum(r_obs < 0.1)),
            }
            if r_obs.size
            else {},
            "data_snooping": {
                "alpha": alpha,
                "critical_T": crit,
                "flagged": int(np.sum(self.T > crit)),
                "max_T": float(self.T.max()) if self.T.size else 0.0,
            },
            "variance_components": {},
        }
        fam = self.families
        coll = np.zeros(self.e.size, bool)
        coll[fam["collinearity"]] = True
        if observation_class is not None:
            per_row = np.repeat(np.asarray(observation_class), 2)
            for c in np.unique(per_row):
                rows = np.zeros(self.e.size, bool)
                rows[fam["collinearity"]] = per_row == c
                name = (class_names or {}).get(int(c), str(int(c)))
                out["variance_components"][name + " observations"] = self.variance_component(rows)
        else:
            out["variance_components"]["observations"] = self.variance_component(coll)
        for name in ("dem", "priors"):
            if fam[name].stop > fam[name].start:
                out["variance_components"][name] = self.variance_component(fam[name])
        return out


def class_scale(used: float, factor: float, stated_share: float = 1.0) -> tuple[float, float]:
    """A class's scale on its file's stated sigma from its variance component: ``factor`` (its
    sigma0 times any rescaling, against the sigma it was weighted with), ``used`` the scale it was
    weighted with and ``stated_share`` the part ``F`` of its weighted variance that is the stated
    sigma (the DEM's: the rest is the surface fit's residual, which the scale does not touch;
    1 for the other classes). With ``factor^2 = F (k / used)^2 + 1 - F``::

        k = used sqrt((factor^2 - 1 + F) / F)

    Returns ``k`` and ``dk/k`` over ``dfactor/factor`` (``factor^2 / (factor^2 - 1 + F)``, 1 when
    ``F`` is 1), by which the scale's relative 1 sigma exceeds ``factor``'s. A factor that leaves
    the stated share no variance (``factor^2 <= 1 - F``) gives a scale of 1e-3 of ``used``."""
    f = float(np.clip(stated_share, 1e-6, 1.0))
    excess = max(float(factor) ** 2 - 1.0 + f, 1e-6 * f)
    return float(used * np.sqrt(excess / f)), float(factor) ** 2 / excess


def reliability(flat: FlatProblem, x: Array, chunk: int = 2048) -> Reliability:
    """Redundancy numbers and data-snooping statistics of the flat problem at its optimum ``x``
    (see the module docstring)."""
    blk, hlc, hcc, _, _ = flat.normal_equations(x)
    n_l3, n_c = blk.shape[0], hcc.shape[0]
    n_l = 3 * n_l3
    d_inv, g_sparse, s = schur_reduce(blk, sp.csr_matrix(hlc.reshape(n_l, n_c)), sp.csr_matrix(hcc))
    g = g_sparse.toarray().reshape(n_l3, 3, n_c)
    chol = reduced_cholesky(s)
    e = flat.residual(x)
    jac = flat.jacobian(x).tocsr()
    m = jac.shape[0]
    coo = jac[:, :n_l].tocoo()
    a_l = np.zeros((m, 3))
    lm = np.full(m, -1, np.int64)
    a_l[coo.row, coo.col % 3] = coo.data
    lm[coo.row] = coo.col // 3
    j_c = jac[:, n_l:].tocsr()
    h = np.zeros(m)
    h_pair = np.zeros(m)  # h[k, k+1] for k even (the two rows of one observation)
    for r0 in range(0, m, chunk):
        r1 = min(m, r0 + chunk + (chunk % 2))
        rows = np.arange(r0, r1)
        has = lm[rows] >= 0
        u = -j_c[rows].toarray()
        if has.any():
            u[has] += np.einsum("rk,rkc->rc", a_l[rows[has]], g[lm[rows[has]]])
        w = sla.solve_triangular(chol, u.T, lower=True)  # (n_c, rows)
        h[rows] = np.sum(w * w, axis=0)
        land = np.zeros(rows.size)
        land[has] = np.einsum("ri,rij,rj->r", a_l[rows[has]], d_inv[lm[rows[has]]], a_l[rows[has]])
        h[rows] += land
        ev = rows[(rows % 2 == 0) & (rows + 1 < r1)]
        i0, i1 = ev - r0, ev + 1 - r0
        cross = np.sum(w[:, i0] * w[:, i1], axis=0)
        same = (lm[ev] >= 0) & (lm[ev] == lm[ev + 1])
        cross[same] += np.einsum("ri,rij,rj->r", a_l[ev[same]], d_inv[lm[ev[same]]], a_l[ev[same] + 1])
        h_pair[ev] = cross
    fam = {
        "collinearity": slice(0, flat.m_coll),
        "dem": slice(flat.m_coll, flat.m_coll + flat.m_dem),
        "priors": slice(flat.m_coll + flat.m_dem, m),
    }
    k = np.arange(0, flat.m_coll, 2)
    r_obs = np.empty((k.size, 2, 2))
    r_obs[:, 0, 0] = 1.0 - h[k]
    r_obs[:, 1, 1] = 1.0 - h[k + 1]
    r_obs[:, 0, 1] = r_obs[:, 1, 0] = -h_pair[k]
    e2 = np.stack([e[k], e[k + 1]], -1)
    # an observation with (almost) no redundancy cannot be tested: T = 0 there
    det = np.linalg.det(r_obs)
    ok = det > 1e-12
    t = np.zeros(k.size)
    t[ok] = np.einsum("ni,nij,nj->n", e2[ok], np.linalg.inv(r_obs[ok]), e2[ok])
    return Reliability(e, h, r_obs, t, fam)
