"""A Problem as one vector of unknowns: vectorised whitened residuals and a sparse Jacobian.

Built from the very same pure functions as the factors (collinearity, DEM height) and the graph's
``PriorFactorVector`` priors, with no per-factor Python callback. Used by the solver core's
``schur`` backend (:func:`misrgraph.estimate.solver.solve`) and by the scipy alternative of
``misrgraph bench sba``. Supports problems whose factors are one collinearity batch, an optional
DEM batch and vector priors, with no robust loss and no factor coupling two landmarks (the
single-pass least-squares adjustment); :class:`FlatProblem` raises :class:`NotFlat` otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from factors.collinearity import CollinearityBatch, collinearity_residual
from factors.dem_height import DemBatch, dem_residual, dem_residual_hessian
from misrgraph.errors import InputError
from misrgraph.estimate.graph import Problem

__all__ = ["FlatProblem", "NotFlat", "knot_marginals_sparse"]

Array = NDArray[np.float64]


class NotFlat(ValueError):
    """The problem has factors the flat formulation does not cover."""


@dataclass
class _Prior:
    key: int
    mean: Array
    r: Array  # whitening (upper triangular sqrt information)


class FlatProblem:
    """A Problem as ``x -> r(x)`` (whitened) and a sparse ``J(x)``."""

    #: The factor families, in the order of their rows in :meth:`residual` and :meth:`jacobian`.
    FAMILIES = ("collinearity", "dem", "priors")

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        keys = list(problem.eliminate_first) + problem.other_keys
        self.offset: dict[int, int] = {}
        n = 0
        for k in keys:
            self.offset[k] = n
            n += problem.dims[k]
        self.n = n
        self.keys = keys
        colls = [b for b in problem.batches if isinstance(b, CollinearityBatch)]
        dems = [b for b in problem.batches if isinstance(b, DemBatch)]
        if len(colls) != 1 or len(dems) > 1 or len(problem.batches) != len(colls) + len(dems):
            raise NotFlat("the flat formulation needs exactly one collinearity batch and at most one DEM batch")
        self.coll = colls[0]
        if self.coll.robust is not None:
            raise NotFlat("robust losses are not covered by the flat formulation")
        self.dem = dems[0] if dems else None
        self.priors: list[_Prior] = []
        n_custom = 0
        for i in range(problem.graph.size()):
            f = problem.graph.at(i)
            if isinstance(f, gtsam.PriorFactorVector):
                self.priors.append(_Prior(int(f.keys()[0]), np.asarray(f.prior()), np.asarray(f.noiseModel().R())))
            elif isinstance(f, gtsam.CustomFactor):
                n_custom += 1
            else:
                raise NotFlat(f"factor of type {type(f).__name__} is not covered by the flat formulation")
        if n_custom != self.coll.layout.n_factors + (len(self.dem) if self.dem is not None else 0):
            raise NotFlat("the graph holds custom factors outside the problem's batches")
        b = self.coll
        self._slot_cols = []
        for s, d in enumerate(b.slot_dims):
            keys_s = b.slot_keys[s]
            start = np.array([self.offset.get(int(k), -1) if k >= 0 else -1 for k in keys_s], np.int64)
            self._slot_cols.append(np.where(start[:, None] >= 0, start[:, None] + np.arange(d)[None, :], -1))
        # observations sharing the same navigation columns (camera, knot brackets, ephemeris
        # segment) are summed before the scatter into H_cc: a few hundred groups, not 10^4 rows
        n_l = 3 * len(problem.eliminate_first)
        nav_cols = np.concatenate([np.where(self._slot_cols[s] >= 0, self._slot_cols[s] - n_l, -1)
                                   for s in range(1, len(b.slot_dims))], axis=1)
        keep = np.any(nav_cols >= 0, axis=0)
        self._nav_keep = keep
        nav_cols = nav_cols[:, keep]
        _, first, inv = np.unique(nav_cols, axis=0, return_index=True, return_inverse=True)
        inv = inv.ravel()
        self._grp_order = np.argsort(inv, kind="stable")
        self._grp_starts = np.searchsorted(inv[self._grp_order], np.arange(first.size))
        self._grp_cols = nav_cols[first]
        self._nav_cols = nav_cols
        self.m_coll = 2 * len(b)
        self.m_dem = len(self.dem) if self.dem is not None else 0
        # columns of each DEM factor's landmark (landmarks come first: landmark index = column // 3)
        dem_keys = self.dem.keys if self.dem is not None else np.zeros(0, np.int64)
        self._dem_cols = np.array([self.offset[int(k)] for k in dem_keys], np.int64)[:, None] + np.arange(3)
        self._dem_lm = self._dem_cols[:, 0] // 3
        self.m = self.m_coll + self.m_dem + sum(p.mean.size for p in self.priors)

    @staticmethod
    def family_of(batch: object) -> str:
        """The :meth:`family_rows` name of a factor batch (``"other"`` for anything else)."""
        return "collinearity" if isinstance(batch, CollinearityBatch) else "dem" if isinstance(batch, DemBatch) else "other"

    def initial(self) -> Array:
        return self.from_values(self.problem.initial)

    def from_values(self, values: gtsam.Values) -> Array:
        x = np.zeros(self.n)
        for k in self.keys:
            x[self.offset[k]: self.offset[k] + self.problem.dims[k]] = values.atVector(k)
        return x

    def _gather(self, x: Array) -> tuple[Array, ...]:
        b = self.coll
        cols = [np.where(c >= 0, x[np.maximum(c, 0)], 0.0) for c in self._slot_cols]
        land, theta = cols[0], cols[1]
        knots = np.stack([np.concatenate([cols[2 + 2 * a], cols[3 + 2 * a]], -1) for a in range(3)], 1)
        cam = b.camera_supplied.copy()
        if np.any(b.slot_keys[8] >= 0):
            cam[:, list(b.camera_select)] += cols[8] * b.camera_scale
        om = np.broadcast_to(b.omega_supplied, (len(b), 3)) + cols[9]
        return land, theta, knots, cam, om

    def residual(self, x: Array) -> Array:
        """Whitened residual ``(m,)``: collinearity rows, then DEM rows, then prior rows."""
        return np.concatenate([self.family_rows(x, f, False)[0] for f in self.FAMILIES])

    def jacobian(self, x: Array) -> sp.csr_matrix:
        """Whitened Jacobian ``(m, n)``, rows as in :meth:`residual`."""
        return sp.vstack([self.family_rows(x, f, True)[1] for f in self.FAMILIES], format="csr")

    def raw(self, x: Array, family: str, jacobian: bool) -> tuple[Array, Any]:
        """The pure function behind a nonlinear family at ``x``, unwhitened, as the factor batches
        cache it: ``collinearity_residual`` (``(N, 2)`` px, Jacobian dict) or ``dem_residual``
        (``(L,)`` m, ``(L, 1, 3)``); ``dem`` requires a DEM batch."""
        if family == "collinearity":
            return collinearity_residual(*self._gather(x), self.coll.const, jacobians=jacobian)
        if family == "dem" and self.dem is not None:
            return dem_residual(x[self._dem_cols], self.dem.surface, jacobian)
        raise InputError("family", family, "collinearity, or dem when the problem has DEM factors")

    def family_rows(self, x: Array, family: str, jacobian: bool, raw: tuple[Array, Any] | None = None) -> tuple[Array, sp.csr_matrix | None]:
        """One factor family's block of rows of :meth:`residual` (and :meth:`jacobian` when asked):
        ``family`` is ``"collinearity"`` (``m_coll`` rows), ``"dem"`` (``m_dem``) or ``"priors"``.
        ``raw``: :meth:`raw` of this family at ``x`` (with Jacobians if asked), when already made."""
        if family not in self.FAMILIES:
            raise InputError("family", family, self.FAMILIES)
        rows: list[Array] = []
        cols: list[Array] = []
        vals: list[Array] = []
        if family == "collinearity":
            b = self.coll
            r, j = raw if raw is not None else self.raw(x, family, jacobian)
            r = (r / b.sigma_px[:, None]).ravel()
            if j is not None:
                n = len(b)
                rr = (2 * np.arange(n))[:, None, None] + np.arange(2)[None, :, None]
                w = 1.0 / b.sigma_px[:, None, None]
                for s, blk in enumerate(b._blocks(j)):
                    c = self._slot_cols[s]
                    used = c[:, 0] >= 0
                    d = blk.shape[-1]
                    rows.append(np.broadcast_to(rr, (n, 2, d))[used].ravel())
                    cols.append(np.broadcast_to(c[:, None, :], (n, 2, d))[used].ravel())
                    vals.append((blk * w)[used].ravel())
            m = self.m_coll
        elif family == "dem":
            m = self.m_dem
            r = np.zeros(0)
            if self.dem is not None:
                rd, jd = raw if raw is not None else self.raw(x, family, jacobian)
                r = rd / self.dem.sigma_m
                if jd is not None:
                    rows.append(np.repeat(np.arange(m), 3))
                    cols.append(self._dem_cols.ravel())
                    vals.append((jd[:, 0, :] / self.dem.sigma_m[:, None]).ravel())
        else:
            parts, row0 = [], 0
            for p in self.priors:
                d = p.mean.size
                o = self.offset[p.key]
                parts.append(p.r @ (x[o:o + d] - p.mean))
                if jacobian:
                    rows.append(np.repeat(row0 + np.arange(d), d))
                    cols.append(np.tile(o + np.arange(d), d))
                    vals.append(p.r.ravel())
                row0 += d
            r = np.concatenate(parts) if parts else np.zeros(0)
            m = row0
        if not jacobian:
            return r, None
        cat = (lambda a, t: np.concatenate(a) if a else np.zeros(0, t))
        return r, sp.csr_matrix((cat(vals, float), (cat(rows, np.int64), cat(cols, np.int64))), shape=(m, self.n))

    def cost(self, x: Array) -> float:
        r = self.residual(x)
        return float(0.5 * r @ r)

    def normal_equations(self, x: Array, use_numba: bool = True,
                         second_order: bool = False) -> tuple[Array, Array, Array, Array, float]:
        """``J^T J`` and ``J^T r`` accumulated from the per-observation blocks, in Schur form.

        Returns ``(H_ll (L,3,3), H_lc (L,3,n_c) dense, H_cc (n_c,n_c), g (n,), cost)`` with the
        landmarks first (L = number of landmarks, n_c the other unknowns). Each observation touches
        one landmark, so ``H_ll`` is block diagonal. The sums run in a numba kernel when numba is
        installed (:mod:`misrgraph.estimate._kernels`), else with batched matmul and ``np.bincount``.

        ``second_order=True`` adds the term Gauss-Newton neglects for the DEM factors,
        ``sum_i (r_i / sigma_i^2) d^2 r_i / dP^2`` (3x3 per landmark, see
        :meth:`dem_curvature`), i.e. the exact Hessian of the DEM part of the cost, wherever the
        landmark's block stays positive definite with it. Marginals must use the default
        (``J^T J``, what ``gtsam.Marginals`` returns).
        """
        b = self.coll
        n_l = 3 * len(self.problem.eliminate_first)
        nl3, n_c = n_l // 3, self.n - n_l
        r, j = collinearity_residual(*self._gather(x), b.const, jacobians=True)
        w = 1.0 / b.sigma_px
        r = r * w[:, None]
        blocks = [blk * w[:, None, None] for blk in b._blocks(j)]
        lm = self._slot_cols[0][:, 0] // 3
        bl = blocks[0]
        bc = np.concatenate([blk for s, blk in enumerate(blocks) if s > 0], axis=2)[:, :, self._nav_keep]
        cc = self._nav_cols
        used = cc >= 0
        bc = np.where(used[:, None, :], bc, 0.0)
        cc = np.where(used, cc, 0)
        from misrgraph.estimate._kernels import accumulate

        fast = accumulate(bl, bc, r, lm, self._nav_cols, nl3, n_c) if use_numba else None
        g = np.zeros(self.n)
        if fast is not None:
            blk, hlc, hcc, gl, gcv = fast
            g[:n_l] = gl.ravel()
            g[n_l:] = gcv
        else:
            blt, bct = np.swapaxes(bl, 1, 2), np.swapaxes(bc, 1, 2)
            idx9 = (lm[:, None, None] * 9 + np.arange(3)[None, :, None] * 3 + np.arange(3)[None, None, :]).ravel()
            blk = np.bincount(idx9, weights=(blt @ bl).ravel(), minlength=nl3 * 9).reshape(nl3, 3, 3)
            hlc = np.bincount(((lm[:, None, None] * 3 + np.arange(3)[None, :, None]) * n_c + cc[:, None, :]).ravel(),
                              weights=(blt @ bc).ravel(), minlength=nl3 * 3 * n_c).reshape(nl3, 3, n_c)
            grouped = np.add.reduceat((bct @ bc)[self._grp_order], self._grp_starts, axis=0)
            gc_ = np.where(self._grp_cols >= 0, self._grp_cols, 0)
            hcc = np.bincount((gc_[:, :, None] * n_c + gc_[:, None, :]).ravel(), weights=grouped.ravel(),
                              minlength=n_c * n_c).reshape(n_c, n_c)
            gl = (blt @ r[:, :, None])[:, :, 0]
            g[:n_l] += np.bincount((lm[:, None] * 3 + np.arange(3)).ravel(), weights=gl.ravel(), minlength=n_l)
            g[n_l:] += np.bincount(cc.ravel(), weights=(bct @ r[:, :, None]).ravel(), minlength=n_c)
        cost = float(0.5 * np.sum(r * r))
        if self.dem is not None:
            rd, jd = dem_residual(x[self._dem_cols], self.dem.surface, True)
            rd = rd / self.dem.sigma_m
            jd = jd[:, 0, :] / self.dem.sigma_m[:, None]
            li = self._dem_lm
            np.add.at(blk, li, np.einsum("ni,nj->nij", jd, jd))
            np.add.at(g, self._dem_cols.ravel(), (jd * rd[:, None]).ravel())
            cost += float(0.5 * np.sum(rd * rd))
        for p in self.priors:
            o = self.offset[p.key]
            d = p.mean.size
            rp = p.r @ (x[o:o + d] - p.mean)
            hp = p.r.T @ p.r
            cost += float(0.5 * rp @ rp)
            g[o:o + d] += p.r.T @ rp
            if o < n_l:
                blk[o // 3] += hp
            else:
                hcc[o - n_l:o - n_l + d, o - n_l:o - n_l + d] += hp
        if second_order and self.dem is not None and len(self.dem):
            li, corr = self.dem_curvature(x)
            per_lm = np.zeros_like(blk)
            np.add.at(per_lm, li, corr)
            u = np.unique(li)
            new = blk[u] + per_lm[u]
            ok = np.linalg.eigvalsh(new)[:, 0] > 0.0
            blk[u[ok]] = new[ok]
        return blk, hlc, hcc, g, cost

    def dem_curvature(self, x: Array) -> tuple[NDArray[np.int64], Array]:
        """The DEM factors' second-order term: landmark index ``(N,)`` and
        ``(r_i / sigma_i^2) d^2 r_i / dP^2`` ``(N, 3, 3)`` (whitened cost units per m^2)."""
        assert self.dem is not None
        p = x[self._dem_cols]
        rd, _ = dem_residual(p, self.dem.surface, False)
        hess = dem_residual_hessian(p, self.dem.surface)
        corr = (rd / self.dem.sigma_m**2)[:, None, None] * hess
        corr[~np.all(np.isfinite(corr), axis=(1, 2))] = 0.0  # within 1 m of a DEM edge: Gauss-Newton there
        return self._dem_lm, corr

    def to_values(self, x: Array) -> gtsam.Values:
        v = gtsam.Values()
        for k in self.keys:
            v.insert(int(k), x[self.offset[k]: self.offset[k] + self.problem.dims[k]].copy())
        return v


def knot_marginals_sparse(flat: FlatProblem, x: Array, keys: list[int]) -> dict[int, Array]:
    """Marginal covariances of non-landmark variables: ``S^-1`` of the landmark Schur complement
    of the normal equations (the same quantity ``gtsam.Marginals`` returns)."""
    blk, hlc, hcc, _, _ = flat.normal_equations(x)
    n_l = 3 * blk.shape[0]
    n_c = hcc.shape[0]
    ig = np.linalg.inv(blk) @ hlc
    s = hcc - hlc.reshape(-1, n_c).T @ ig.reshape(-1, n_c)
    cov = np.linalg.inv(s)
    out = {}
    for k in keys:
        o = flat.offset[k] - n_l
        d = flat.problem.dims[k]
        out[k] = cov[o:o + d, o:o + d]
    return out
