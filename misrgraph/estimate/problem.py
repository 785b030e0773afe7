"""The one problem representation, and the one marginal-covariance routine.

:class:`Problem` is what every solver consumes: the GTSAM backend eliminates its ``graph``; the
Schur backend, ``scipy.optimize.least_squares``, Ceres (``misrgraph bench sba``) and the linear
model iSAM2 is kept in step with (:mod:`misrgraph.estimate.incremental`) all use
:meth:`Problem.flat`, the same problem as one vector of unknowns with whitened residuals and a
sparse Jacobian -- built from the very same pure functions as the factors (collinearity, DEM
height) and the graph's linear priors (``PriorFactorVector``, and the attitude process prior's
``LinearContainerFactor`` between consecutive knots), with no per-factor Python callback. Rows
are tied to factors by the graph positions :meth:`Problem.add_batch` records, never by the
graph's order. The flat form covers problems whose factors are one collinearity batch, an
optional DEM batch and linear priors, with no robust loss and no factor coupling two landmarks
(the single-pass least-squares adjustment); :class:`FlatProblem` raises :class:`NotFlat` otherwise.

Marginal covariances (eq. 34 with lambda -> 0 at convergence) come from ``J^T J`` by a Schur
complement on the 3x3 landmark blocks (:func:`schur_marginals`), whether ``J`` comes from GTSAM's
linearisation (:func:`marginal_covariances`) or from the flat form (:func:`flat_marginals`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from factors.collinearity import CollinearityBatch, collinearity_residual
from factors.dem_height import DemBatch, dem_residual, dem_residual_hessian
from misrgraph.errors import DegenerateProblemError, InputError

__all__ = [
    "Problem",
    "FlatProblem",
    "NotFlat",
    "Marginals",
    "schur_reduce",
    "reduced_cholesky",
    "schur_marginals",
    "marginal_covariances",
    "flat_marginals",
    "SPD_SPLU_OPTIONS",
    "error",
    "linearize",
    "variance_factor",
]

Array = NDArray[np.float64]


@dataclass
class Problem:
    """A nonlinear least-squares problem: the one representation every solver consumes.

    ``graph`` holds GTSAM factors (the batches' ``CustomFactor`` adapters and ``PriorFactorVector``
    priors), ``initial`` the start, ``dims`` every variable's dimension, ``eliminate_first`` the
    landmark keys (3-vectors, eliminated first: the Schur order) and ``eliminate_last`` the
    variables shared by every pass (cameras). :meth:`flat` is the same problem as one vector of
    unknowns with vectorised residuals and a sparse Jacobian (for the Schur backend, scipy, Ceres
    and iSAM2's mirror); it is built from these very objects, and each of its rows knows the graph
    position of its factor (:meth:`FlatProblem.row_positions`).
    """

    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    batches: list
    eliminate_first: list[int]
    dims: dict[int, int]
    eliminate_last: list[int] = field(default_factory=list)
    #: graph positions of each batch's factors, in the order of ``batches`` (recorded as the
    #: factors are added, :meth:`add_batch`; never inferred from the graph's order)
    batch_positions: list[NDArray[np.int64]] = field(default_factory=list)

    @property
    def other_keys(self) -> list[int]:
        """Non-landmark keys: those not eliminated first, in insertion order, ``eliminate_last`` at the end."""
        first = set(self.eliminate_first)
        last = set(self.eliminate_last)
        return [k for k in self.dims if k not in first and k not in last] + [
            k for k in self.eliminate_last if k in self.dims
        ]

    def warm_start(self, previous: gtsam.Values) -> None:
        """Start from ``previous`` (an earlier optimum) wherever it holds one of this problem's
        variables; the others keep their initial values."""
        for k in self.dims:
            if previous.exists(k) and self.initial.exists(k):
                self.initial.update(k, previous.atVector(k))

    def add_batch(self, batch: Any) -> NDArray[np.int64]:
        """Append a factor batch's adapters to the graph and record their positions."""
        start = int(self.graph.size())
        for f in batch.factors():
            self.graph.add(f)
        pos = np.arange(start, int(self.graph.size()), dtype=np.int64)
        self.batches.append(batch)
        self.batch_positions.append(pos)
        return pos

    def flat(self) -> "FlatProblem":
        """This problem as a vector of unknowns (built once; raises :class:`NotFlat` when the
        problem has factors the flat form does not cover)."""
        cached = self.__dict__.get("_flat")
        if cached is None:
            cached = FlatProblem(self)
            self.__dict__["_flat"] = cached
        return cached


class NotFlat(ValueError):
    """The problem has factors the flat formulation does not cover."""


@dataclass
class _Prior:
    """A linear Gaussian factor, whitened: rows ``sum_k a_k x_k - b`` (a ``PriorFactorVector`` has
    one key, ``a = R`` and ``b = R mean``; a process prior between knots has two)."""

    keys: tuple[int, ...]
    a: tuple[Array, ...]
    b: Array

    @classmethod
    def from_factor(cls, f: Any, dims: dict[int, int]) -> "_Prior":
        """From a ``PriorFactorVector`` or a ``LinearContainerFactor`` linearised at zero
        (:func:`factors.priors.linear_factor`)."""
        if isinstance(f, gtsam.PriorFactorVector):
            r = np.asarray(f.noiseModel().R())
            return cls((int(f.keys()[0]),), (r,), r @ np.asarray(f.prior()))
        a, b = gtsam.JacobianFactor(f.factor()).jacobian()
        keys = tuple(int(k) for k in f.keys())
        splits = np.cumsum([dims[k] for k in keys])[:-1]
        return cls(keys, tuple(np.split(np.asarray(a), splits, axis=1)), np.asarray(b))

    def rows(self, x: Array, offset: dict[int, int]) -> Array:
        """Whitened residual rows at the flat vector ``x``."""
        return sum(a @ x[offset[k] : offset[k] + a.shape[1]] for k, a in zip(self.keys, self.a)) - self.b


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
        landmark_cols = 3 * len(problem.eliminate_first)  # landmarks come first
        for i in range(problem.graph.size()):
            f = problem.graph.at(i)
            if isinstance(f, (gtsam.PriorFactorVector, gtsam.LinearContainerFactor)):
                p = _Prior.from_factor(f, problem.dims)
                if sum(self.offset[k] < landmark_cols for k in p.keys) > 1:
                    raise NotFlat(
                        "a linear factor coupling two landmarks (the landmark block would not be block diagonal)"
                    )
                self.priors.append(p)
            elif isinstance(f, gtsam.CustomFactor):
                n_custom += 1
            else:
                raise NotFlat(f"factor of type {type(f).__name__} is not covered by the flat formulation")
        if n_custom != self.coll.layout.n_factors + (len(self.dem) if self.dem is not None else 0):
            raise NotFlat("the graph holds custom factors outside the problem's batches")
        if len(problem.batch_positions) != len(problem.batches):
            raise NotFlat("the problem does not record its batches' graph positions (build it with Problem.add_batch)")
        self._positions = {self.family_of(bt): pos for bt, pos in zip(problem.batches, problem.batch_positions)}
        b = self.coll
        self._slot_cols = []
        for s, d in enumerate(b.slot_dims):
            keys_s = b.slot_keys[s]
            start = np.array([self.offset.get(int(k), -1) if k >= 0 else -1 for k in keys_s], np.int64)
            self._slot_cols.append(np.where(start[:, None] >= 0, start[:, None] + np.arange(d)[None, :], -1))
        # observations sharing the same navigation columns (camera, knot brackets, ephemeris
        # segment) are summed before the scatter into H_cc: a few hundred groups, not 10^4 rows
        n_l = 3 * len(problem.eliminate_first)
        nav_cols = np.concatenate(
            [np.where(self._slot_cols[s] >= 0, self._slot_cols[s] - n_l, -1) for s in range(1, len(b.slot_dims))],
            axis=1,
        )
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
        self.m = self.m_coll + self.m_dem + sum(p.b.size for p in self.priors)

    @staticmethod
    def family_of(batch: object) -> str:
        """The :meth:`family_rows` name of a factor batch (``"other"`` for anything else)."""
        return (
            "collinearity"
            if isinstance(batch, CollinearityBatch)
            else "dem"
            if isinstance(batch, DemBatch)
            else "other"
        )

    def row_positions(self) -> dict[str, NDArray[np.int64]]:
        """Graph position of the factor behind each row of the collinearity and DEM families:
        a collinearity factor (one landmark's views) owns two rows per observation, a DEM factor one."""
        lay = self.coll.layout
        per_obs = np.repeat(np.arange(lay.n_factors), lay.obs_stop - lay.obs_start)
        out = {"collinearity": np.repeat(self._positions["collinearity"][per_obs], 2)}
        out["dem"] = self._positions["dem"] if self.dem is not None else np.zeros(0, np.int64)
        return out

    def initial(self) -> Array:
        return self.from_values(self.problem.initial)

    def from_values(self, values: gtsam.Values, partial: bool = False) -> Array:
        """The flat vector ``(n,)`` of ``values``; with ``partial``, keys ``values`` lacks are left
        at zero (for evaluating families that do not involve them)."""
        x = np.zeros(self.n)
        for k in self.keys:
            if partial and not values.exists(k):
                continue
            x[self.offset[k] : self.offset[k] + self.problem.dims[k]] = values.atVector(k)
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

    def landmark_jacobians(self, x: Array) -> tuple[Array, Array, NDArray[np.int64]]:
        """Each collinearity observation's (batch order) Jacobian of its predicted (line, sample)
        with respect to its landmark, ``(N, 2, 3)`` px/m (not whitened), its 1 sigma ``(N, 2)`` px
        (as weighted), and its landmark's index in ``problem.eliminate_first`` ``(N,)``."""
        b = self.coll
        _, j = collinearity_residual(*self._gather(x), b.const, jacobians=True)
        sigma = np.broadcast_to(np.asarray(b.sigma_px, float).reshape(len(b), -1), (len(b), 2))
        return b._blocks(j)[0], np.array(sigma), self._slot_cols[0][:, 0] // 3

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

    def family_rows(
        self, x: Array, family: str, jacobian: bool, raw: tuple[Array, Any] | None = None
    ) -> tuple[Array, sp.csr_matrix | None]:
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
            r = (r / b.sigma_px).ravel()
            if j is not None:
                n = len(b)
                rr = (2 * np.arange(n))[:, None, None] + np.arange(2)[None, :, None]
                w = 1.0 / b.sigma_px[:, :, None]
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
                d = p.b.size
                parts.append(p.rows(x, self.offset))
                if jacobian:
                    for k, a in zip(p.keys, p.a):
                        rows.append(np.repeat(row0 + np.arange(d), a.shape[1]))
                        cols.append(np.tile(self.offset[k] + np.arange(a.shape[1]), d))
                        vals.append(a.ravel())
                row0 += d
            r = np.concatenate(parts) if parts else np.zeros(0)
            m = row0
        if not jacobian:
            return r, None

        def cat(a, t):
            return np.concatenate(a) if a else np.zeros(0, t)

        return r, sp.csr_matrix((cat(vals, float), (cat(rows, np.int64), cat(cols, np.int64))), shape=(m, self.n))

    def cost(self, x: Array) -> float:
        r = self.residual(x)
        return float(0.5 * r @ r)

    def normal_equations(
        self, x: Array, use_numba: bool = True, second_order: bool = False, curvature_floor: float = 0.0
    ) -> tuple[Array, Array, Array, Array, float]:
        """``J^T J`` and ``J^T r`` accumulated from the per-observation blocks, in Schur form.

        Returns ``(H_ll (L,3,3), H_lc (L,3,n_c) dense, H_cc (n_c,n_c), g (n,), cost)`` with the
        landmarks first (L = number of landmarks, n_c the other unknowns). Each observation touches
        one landmark, so ``H_ll`` is block diagonal. The sums run in a numba kernel when numba is
        installed (:mod:`misrgraph.estimate._kernels`), else with batched matmul and ``np.bincount``.

        ``second_order=True`` adds the term Gauss-Newton neglects for the DEM factors,
        ``sum_i (r_i / sigma_i^2) d^2 r_i / dP^2`` (3x3 per landmark, see
        :meth:`dem_curvature`), i.e. the exact Hessian of the DEM part of the cost, wherever the
        landmark's block stays positive definite with it -- and, with ``curvature_floor`` f > 0,
        only where the term leaves at least f of the block's information in every direction
        (``H_new >= f H_GN``; the marginals use 0.5: a landmark the term would make almost
        undetermined is one whose local quadratic model is not to be trusted).
        """
        b = self.coll
        n_l = 3 * len(self.problem.eliminate_first)
        nl3, n_c = n_l // 3, self.n - n_l
        r, j = collinearity_residual(*self._gather(x), b.const, jacobians=True)
        w = 1.0 / b.sigma_px
        r = r * w
        blocks = [blk * w[:, :, None] for blk in b._blocks(j)]
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
            hlc = np.bincount(
                ((lm[:, None, None] * 3 + np.arange(3)[None, :, None]) * n_c + cc[:, None, :]).ravel(),
                weights=(blt @ bc).ravel(),
                minlength=nl3 * 3 * n_c,
            ).reshape(nl3, 3, n_c)
            grouped = np.add.reduceat((bct @ bc)[self._grp_order], self._grp_starts, axis=0)
            gc_ = np.where(self._grp_cols >= 0, self._grp_cols, 0)
            hcc = np.bincount(
                (gc_[:, :, None] * n_c + gc_[:, None, :]).ravel(), weights=grouped.ravel(), minlength=n_c * n_c
            ).reshape(n_c, n_c)
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
            rp = p.rows(x, self.offset)
            cost += float(0.5 * rp @ rp)
            for k, a in zip(p.keys, p.a):
                o, d = self.offset[k], a.shape[1]
                g[o : o + d] += a.T @ rp
                for k2, a2 in zip(p.keys, p.a):
                    o2 = self.offset[k2]
                    if o < n_l and o2 < n_l:  # a landmark with itself (at most one landmark per factor)
                        blk[o // 3] += a.T @ a2
                    elif o < n_l:  # landmark x other (a GCP and its scene's offset)
                        hlc[o // 3, :, o2 - n_l : o2 - n_l + a2.shape[1]] += a.T @ a2
                    elif o2 >= n_l:  # other x other (H_lc holds the landmark rows only)
                        hcc[o - n_l : o - n_l + d, o2 - n_l : o2 - n_l + a2.shape[1]] += a.T @ a2
        if second_order and self.dem is not None and len(self.dem):
            li, corr = self.dem_curvature(x)
            per_lm = np.zeros_like(blk)
            np.add.at(per_lm, li, corr)
            u = np.unique(li)
            new = blk[u] + per_lm[u]
            ok = np.linalg.eigvalsh(new)[:, 0] > 0.0
            if curvature_floor > 0:
                rel = np.full(u.size, -np.inf)
                rel[ok] = np.linalg.eigvals(np.linalg.solve(blk[u[ok]], new[ok])).real.min(axis=1)
                ok &= rel >= curvature_floor
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
            v.insert(int(k), x[self.offset[k] : self.offset[k] + self.problem.dims[k]].copy())
        return v


@dataclass
class Marginals:
    """Marginal covariances of every variable (dict key -> (d, d)) and the joint of the
    non-landmark variables (``joint``, ordered as ``joint_keys``).

    When all of them were computed (:func:`schur_marginals` without ``joint_keys``) the
    landmarks' response to the other variables comes too: ``landmark_response`` ``G = H_ll^-1 H_lc``
    (sparse ``(3L, n_c)``, row block ``landmark_index[key]``, columns in ``joint`` order), so that
    two landmarks' cross-covariance is ``G_i joint G_j^T`` (:meth:`landmark_response_of`)."""

    cov: dict[int, Array]
    joint: Array
    joint_keys: list[int]
    joint_offsets: dict[int, int]
    landmark_response: sp.csr_matrix | None = None
    landmark_index: dict[int, int] = field(default_factory=dict)

    def landmark_response_of(self, keys: list[int]) -> Array:
        """``(n, 3, n_c)``: the landmarks' responses ``G_i`` (columns in ``joint`` order); two
        landmarks ``i != j`` have the cross-covariance ``G_i joint G_j^T``."""
        if self.landmark_response is None:
            raise InputError(
                "marginals", "joint-only", "marginals of every variable (schur_marginals without joint_keys)"
            )
        missing = [int(k) for k in keys if int(k) not in self.landmark_index]
        if missing:
            raise InputError("keys", missing[:3], "landmark keys of the problem")
        rows = (
            np.concatenate([3 * self.landmark_index[int(k)] + np.arange(3) for k in keys])
            if keys
            else np.zeros(0, np.int64)
        )
        return self.landmark_response[rows].toarray().reshape(len(keys), 3, -1)

    def __getitem__(self, key: int) -> Array:
        return self.cov[int(key)]

    def joint_of(self, keys: list[int]) -> Array:
        """Joint covariance of several non-landmark variables."""
        idx = np.concatenate(
            [np.arange(self.joint_offsets[k], self.joint_offsets[k] + self.cov[k].shape[0]) for k in keys]
        )
        return self.joint[np.ix_(idx, idx)]


def _with_cache(problem: Problem, values: gtsam.Values, jacobians: bool, fn: Callable[[], Any]):
    try:
        for b in problem.batches:
            b.evaluate(values, jacobians)
        return fn()
    finally:
        for b in problem.batches:
            b.clear()


def error(problem: Problem, values: gtsam.Values) -> float:
    """Total error ``0.5 sum ||whitened residual||^2`` (robust losses included)."""
    return float(_with_cache(problem, values, False, lambda: problem.graph.error(values)))


def linearize(problem: Problem, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
    """The whitened linear system at ``values``, Python factors evaluated in one vectorised pass."""
    return _with_cache(problem, values, True, lambda: problem.graph.linearize(values))


def variance_factor(problem: Problem, final_error: float) -> dict[str, float | int]:
    """A-posteriori variance factor of a least-squares solution and its chi-square test.

    With ``m`` whitened residual rows (every factor's dimension) and ``n`` unknowns, the cost at the
    optimum ``2 E = sum r^2`` is chi-square with ``m - n`` degrees of freedom when the weights are
    right, so ``sigma0 = sqrt(2 E / (m - n))`` is 1 in expectation. ``p_value`` is the upper tail
    ``P(chi2_(m-n) >= 2 E)``: small means the residuals are larger than their sigmas say (weights
    too optimistic, or model error); close to 1 means smaller (weights too pessimistic).
    """
    from scipy import stats

    m = int(sum(problem.graph.at(i).dim() for i in range(problem.graph.size())))
    n = int(sum(problem.dims.values()))
    dof = m - n
    chi2 = 2.0 * float(final_error)
    out: dict[str, float | int] = {"rows": m, "unknowns": n, "dof": dof, "chi2": chi2}
    if dof > 0:
        out.update(sigma0=float(np.sqrt(chi2 / dof)), p_value=float(stats.chi2.sf(chi2, dof)))
    return out


def _blocks_from_linear(problem: Problem, lin: gtsam.GaussianFactorGraph) -> tuple[Array, sp.csr_matrix, sp.csr_matrix]:
    """``H_ll (L, 3, 3)``, ``H_lc (3L, n_c)`` and ``H_cc (n_c, n_c)`` (sparse) of ``J^T J`` from a
    linearised graph, landmarks in ``problem.eliminate_first`` order, the others in
    ``problem.other_keys`` order."""
    lm_index = {int(k): i for i, k in enumerate(problem.eliminate_first)}
    off, n_c = _offsets(problem.other_keys, problem.dims)
    h_ll = np.zeros((len(lm_index), 3, 3))
    lc_r, lc_c, lc_v, cc_r, cc_c, cc_v = [], [], [], [], [], []
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        a, _ = f.jacobian()
        c0, lms, oth_cols, oth_blocks = 0, [], [], []
        for k in (int(k) for k in f.keys()):
            d = problem.dims[k]
            if k in lm_index:
                lms.append((lm_index[k], a[:, c0 : c0 + d]))
            else:
                oth_cols.append(np.arange(off[k], off[k] + d))
                oth_blocks.append(a[:, c0 : c0 + d])
            c0 += d
        if len(lms) > 1:
            raise DegenerateProblemError(
                "marginals: a factor couples two landmarks (the Schur form needs one per factor)"
            )
        if oth_cols:
            cols = np.concatenate(oth_cols)
            a_o = np.concatenate(oth_blocks, axis=1)
            cc_r.append(np.repeat(cols, cols.size))
            cc_c.append(np.tile(cols, cols.size))
            cc_v.append((a_o.T @ a_o).ravel())
        if lms:
            j, a_l = lms[0]
            h_ll[j] += a_l.T @ a_l
            if oth_cols:
                lc_r.append(np.repeat(3 * j + np.arange(3), cols.size))
                lc_c.append(np.tile(cols, 3))
                lc_v.append((a_l.T @ a_o).ravel())

    def cat(x, t):
        return np.concatenate(x) if x else np.zeros(0, t)

    n_l = 3 * len(lm_index)
    h_lc = sp.csr_matrix((cat(lc_v, float), (cat(lc_r, np.int64), cat(lc_c, np.int64))), shape=(n_l, n_c))
    h_cc = sp.csr_matrix((cat(cc_v, float), (cat(cc_r, np.int64), cat(cc_c, np.int64))), shape=(n_c, n_c))
    return h_ll, h_lc, h_cc


def _offsets(keys: list[int], dims: dict[int, int]) -> tuple[dict[int, int], int]:
    off, n = {}, 0
    for k in keys:
        off[int(k)] = n
        n += dims[int(k)]
    return off, n


def schur_reduce(h_ll: Array, h_lc: sp.spmatrix, h_cc: sp.spmatrix) -> tuple[Array, sp.csr_matrix, sp.csc_matrix]:
    """The Schur complement on the 3x3 landmark blocks of ``J^T J``: ``H_ll^-1 (L, 3, 3)``,
    ``G = H_ll^-1 H_lc`` (sparse, ``(3L, n_c)``) and ``S = H_cc - H_cl G`` (sparse). Shared by the
    marginals and the reliability (:mod:`misrgraph.estimate.reliability`)."""
    n_l, n_c = h_ll.shape[0], h_cc.shape[0]
    try:
        h_ll_inv = np.linalg.inv(h_ll) if n_l else h_ll
    except np.linalg.LinAlgError as exc:
        raise DegenerateProblemError("a landmark is not determined (singular 3x3 information block)") from exc
    if not n_l:
        return h_ll_inv, sp.csr_matrix((0, n_c)), sp.csc_matrix(h_cc)
    g = (sp.block_diag(list(h_ll_inv), format="csr") @ h_lc).tocsr()
    return h_ll_inv, g, (h_cc - h_lc.T @ g).tocsc()


def reduced_cholesky(s: sp.spmatrix) -> Array:
    """Dense lower Cholesky factor of the reduced system ``S`` (symmetrised)."""
    s_dense = s.toarray()
    try:
        return np.linalg.cholesky(0.5 * (s_dense + s_dense.T))
    except np.linalg.LinAlgError as exc:
        raise DegenerateProblemError(
            "the navigation/camera variables are not determined (reduced system not positive definite)"
        ) from exc


#: ``scipy.sparse.linalg.splu`` options for the reduced system ``S`` (symmetric positive
#: definite): the factorisation of its symmetric permutation without pivoting (a standard month's
#: S: 0.78 s against 6.2 s for SuperLU's default unsymmetric LU, the same covariance to 3e-10;
#: ``misrgraph bench calibration``)
SPD_SPLU_OPTIONS: dict = {"permc_spec": "COLAMD", "diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}


#: the largest separator (landmarks seen by several passes, 3 each, plus the joint variables)
#: :func:`_joint_by_separator` inverts densely
MAX_SEPARATOR = 3000


def _joint_by_separator(h_ll: Array, h_lc: sp.spmatrix, h_cc: sp.spmatrix, idx: NDArray[np.int64]) -> Array | None:
    """The joint covariance of the non-landmark variables ``idx`` by nested elimination, or None
    where it does not apply. The other non-landmark variables fall into independent groups (a
    month's passes: their knots and ephemeris); a landmark seen by one group is eliminated first
    (its fill stays inside the group), each group's variables next (a block-diagonal sparse
    factorisation), which leaves the dense system of the separator: ``idx`` and the landmarks
    seen by several groups (the GCPs seen by several passes). Its inverse's ``idx`` block is the
    joint covariance: the same as the sparse LU of the whole reduced system, without that
    system's fill (a 90-day window's is too large for SuperLU)."""
    from scipy.sparse import csgraph

    n_l, n_c = h_ll.shape[0], h_cc.shape[0]
    joint = np.zeros(n_c, bool)
    joint[idx] = True
    inner = np.flatnonzero(~joint)
    if n_l == 0 or inner.size == 0:
        return None
    h_cc = sp.csr_matrix(h_cc)
    h_lc = sp.csr_matrix(h_lc)
    n_groups, group = csgraph.connected_components(h_cc[inner][:, inner], directed=False)
    if n_groups < 2:
        return None
    col_group = np.full(n_c, -1)
    col_group[inner] = group
    coo = h_lc.tocoo()
    keep = col_group[coo.col] >= 0
    pairs = np.unique(np.stack([coo.row[keep] // 3, col_group[coo.col[keep]]], 1), axis=0)
    seen_by = np.bincount(pairs[:, 0], minlength=n_l) if pairs.size else np.zeros(n_l, int)
    multi = np.flatnonzero(seen_by > 1)
    single = np.flatnonzero(seen_by <= 1)
    if 3 * multi.size + idx.size > MAX_SEPARATOR:
        return None

    def rows(lm: NDArray[np.int64]) -> NDArray[np.int64]:  # the 3 rows of each landmark in h_lc
        return (3 * lm[:, None] + np.arange(3)).ravel()

    _, _, s_c = schur_reduce(h_ll[single], h_lc[rows(single)], h_cc)
    if multi.size:
        h_mc = h_lc[rows(multi)]
        full = sp.bmat([[s_c, h_mc.T], [h_mc, sp.block_diag(list(h_ll[multi]))]], format="csr")
    else:
        full = sp.csr_matrix(s_c)
    sep = np.concatenate([idx, n_c + np.arange(3 * multi.size)])
    rest = np.setdiff1d(np.arange(full.shape[0]), sep)
    a_rest = full[rest]
    try:
        lu = spla.splu(a_rest[:, rest].tocsc(), **SPD_SPLU_OPTIONS)
        a_is = a_rest[:, sep].toarray()
        s_sep = full[sep][:, sep].toarray() - a_is.T @ lu.solve(a_is)
        chol = np.linalg.cholesky(0.5 * (s_sep + s_sep.T))
    except (RuntimeError, np.linalg.LinAlgError) as exc:
        raise DegenerateProblemError(
            "the navigation/camera variables are not determined (reduced system not positive definite)"
        ) from exc
    inv = np.linalg.inv(chol)
    cov = inv.T @ inv
    return cov[: idx.size, : idx.size]


def schur_marginals(
    h_ll: Array,
    h_lc: sp.spmatrix,
    h_cc: sp.spmatrix,
    landmark_keys: list[int],
    other_keys: list[int],
    dims: dict[int, int],
    joint_keys: list[int] | None = None,
) -> Marginals:
    """The project's one marginal-covariance routine (eq. 34 at convergence), from ``J^T J`` in
    Schur form: landmark blocks ``h_ll (L, 3, 3)``, ``h_lc (3L, n_c)`` and ``h_cc (n_c, n_c)``.

    ``S = H_cc - H_cl H_ll^-1 H_lc`` is formed sparse. With ``joint_keys=None`` every marginal is
    returned: ``Sigma_cc = S^-1`` densely (by Cholesky) and each landmark's
    ``Sigma_ll = H_ll^-1 + G Sigma_cc G^T`` with ``G = H_ll^-1 H_lc``; ``joint`` is then all of
    ``Sigma_cc``. With ``joint_keys`` (non-landmark keys) only their joint covariance is computed,
    for problems whose ``S`` is too large to invert (a month of calibration passes): by nested
    elimination where the other variables fall into independent groups
    (:func:`_joint_by_separator`), else by a sparse LU solve of ``S X = E`` for their columns.
    Equal to ``gtsam.Marginals`` (tested).
    """
    n_l = len(landmark_keys)
    off, n_c = _offsets(other_keys, dims)
    if joint_keys is not None:
        bad = [int(k) for k in joint_keys if int(k) not in off]
        if bad:
            raise InputError("joint_keys", bad[:3], "non-landmark keys of the problem")
        idx = np.concatenate([np.arange(off[int(k)], off[int(k)] + dims[int(k)]) for k in joint_keys])
        joint = _joint_by_separator(h_ll, h_lc, h_cc, idx)
        if joint is None:
            s = schur_reduce(h_ll, h_lc, h_cc)[2]
            try:
                lu = spla.splu(s, **SPD_SPLU_OPTIONS)
                rhs = np.zeros((n_c, idx.size))
                rhs[idx, np.arange(idx.size)] = 1.0
                joint = lu.solve(rhs)[idx]
            except RuntimeError as exc:
                raise DegenerateProblemError(
                    "the navigation/camera variables are not determined (reduced system singular)"
                ) from exc
            except MemoryError:
                raise DegenerateProblemError(
                    f"the reduced system ({n_c} variables) is too large to factorise in memory; use a shorter window"
                ) from None
        joint = 0.5 * (joint + joint.T)
        if not np.all(np.isfinite(joint)) or not np.all(np.diag(joint) > 0):
            raise DegenerateProblemError(
                "the navigation/camera variables are not determined (reduced system not positive definite)"
            )
        j_off, o = {}, 0
        cov = {}
        for k in joint_keys:
            j_off[int(k)] = o
            cov[int(k)] = joint[o : o + dims[int(k)], o : o + dims[int(k)]].copy()
            o += dims[int(k)]
        return Marginals(cov, joint, [int(k) for k in joint_keys], j_off)
    h_ll_inv, g, s = schur_reduce(h_ll, h_lc, h_cc)
    inv_l = np.linalg.inv(reduced_cholesky(s))
    sigma_cc = inv_l.T @ inv_l
    cov = {
        int(k): sigma_cc[off[int(k)] : off[int(k)] + dims[int(k)], off[int(k)] : off[int(k)] + dims[int(k)]].copy()
        for k in other_keys
    }
    if n_l:
        gd = g.toarray().reshape(n_l, 3, n_c)
        gs = (gd.reshape(3 * n_l, n_c) @ sigma_cc).reshape(n_l, 3, n_c)
        sl = h_ll_inv + np.einsum("lib,ljb->lij", gs, gd)
        for j, k in enumerate(landmark_keys):
            cov[int(k)] = sl[j]
    return Marginals(
        cov, sigma_cc, [int(k) for k in other_keys], off, g.tocsr(), {int(k): j for j, k in enumerate(landmark_keys)}
    )


def marginal_covariances(
    problem: Problem,
    values: gtsam.Values,
    lin: gtsam.GaussianFactorGraph | None = None,
    joint_keys: list[int] | None = None,
) -> Marginals:
    """Marginal covariances at ``values`` from the problem's linearised graph (any factor types
    with at most one landmark each): :func:`schur_marginals` of its ``J^T J``."""
    if lin is None:
        lin = linearize(problem, values)
    h_ll, h_lc, h_cc = _blocks_from_linear(problem, lin)
    return schur_marginals(
        h_ll, h_lc, h_cc, [int(k) for k in problem.eliminate_first], problem.other_keys, problem.dims, joint_keys
    )


def flat_marginals(
    flat: "FlatProblem", x: Array, joint_keys: list[int] | None = None, second_order: bool = False
) -> Marginals:
    """Marginal covariances at the flat vector ``x``: :func:`schur_marginals` of the normal
    equations the flat form accumulates (the same ``J^T J``; no GTSAM linearisation), or with
    ``second_order=True`` of the exact Hessian of the cost: ``J^T J`` plus the DEM residuals'
    curvature (:meth:`FlatProblem.dem_curvature`) wherever a landmark's block stays positive
    definite with it -- the Laplace approximation at the optimum, which differs from ``J^T J``
    where a landmark sits on terrain curved at the scale of its uncertainty."""
    blk, hlc, hcc, _, _ = flat.normal_equations(
        x, second_order=second_order, curvature_floor=0.5 if second_order else 0.0
    )
    n_l = blk.shape[0]
    prob = flat.problem
    return schur_marginals(
        blk,
        sp.csr_matrix(hlc.reshape(3 * n_l, -1)),
        sp.csr_matrix(hcc),
        [int(k) for k in prob.eliminate_first],
        prob.other_keys,
        prob.dims,
        joint_keys,
    )
