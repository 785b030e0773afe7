"""Incremental bundle adjustment with iSAM2 as passes arrive.

The Python factors are never handed to ``ISAM2`` directly (each of its callbacks would receive a
copy of the whole ``Values``; see :mod:`misrgraph.estimate.solver`). Instead every factor enters iSAM2 as a
``gtsam.LinearContainerFactor`` -- the factor linearised in one vectorised pass at the current
estimate -- and this module decides what to re-linearise, swapping factors in through
``removeFactorIndices``.

The rule measures staleness directly instead of iSAM2's variable-motion threshold. A mirror of
the linear model iSAM2 holds is kept as flat affine rows ``J x + c`` per pass (whitened). At the
new estimate ``x`` each factor's staleness is

* ``||e_i||^2`` with ``e_i = r_i(x) - (J_i x + c_i)``: re-linearising the factor would shift the
  least-squares solution by ``(J^T J)^-1 J^T e`` to first order, whose Mahalanobis norm is at
  most ``||e||``;
* plus, for a DEM factor, ``g_i^T H_l^-1 g_i`` with ``g_i = J_i(x)^T r_i(x) - J_i^T (J_i x + c_i)``
  the change of its gradient and ``H_l`` its landmark's information: a stale Jacobian times a
  residual of order 1 sigma. The DEM surface curves at the scale of its postings, so this term
  matters there; collinearity is nearly linear over the moves of one update (its term is left
  out, as is the correlation between landmarks, so the measure is a proxy, not a bound).

Rounds re-linearise the factors with the largest staleness (until the rest holds a quarter of the
budget) and stop once the total is at most ``linearization_tol**2``. Measured on the 50-pass
repeat path (``misrgraph bench incremental --passes 50``, 2026-11-24), the default 0.01 leaves
the estimate up to 0.075 sigma (largest over every variable) from the converged batch, 0.034
sigma over the first ten passes: the tolerance bounds the linearisation error of a round, not
the distance to the optimum.

Shared variables: the camera corrections and GCPs (one key each for every pass), and the tie
points of repeat passes of the same path (keyed by path and feature id).

The persistent state behind ``misrgraph update`` is :mod:`misrgraph.runs.update`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from misrgraph.estimate.adjust import AdjustConfig, AdjustResult, estimated_models
from misrgraph.model.constants import ARCSEC
from misrgraph.model.camera import CameraModel
from misrgraph.model.dem import DemTiles
from misrgraph.errors import InputError
from misrgraph.estimate.problem import FlatProblem, NotFlat
from misrgraph.model.gcp import GcpDatabase
from misrgraph.estimate.graph import PassGraph, build_pass_graph, merge_flat, merge_problems
from misrgraph.io.passes import OrbitPass
from misrgraph.estimate.solver import SolverParams, solve
from misrgraph.estimate.problem import Marginals

__all__ = ["IncrementalSolver", "batch_solution", "DEFAULT_LINEARIZATION_TOL"]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]


@dataclass
class _Record:
    pass_index: int
    position: int  # factor position within its pass problem's graph
    isam_index: int


#: Default re-linearisation tolerance (sigma units, module docstring); 0.04 (an earlier default)
#: left 0.18 sigma after 10 passes once the knots were tied by the attitude process prior.
DEFAULT_LINEARIZATION_TOL = 0.01

#: The factor families whose residuals are nonlinear (priors are linear and never go stale).
_NONLINEAR = tuple(f for f in FlatProblem.FAMILIES if f != "priors")


@dataclass
class _PassModel:
    """The linear model iSAM2 holds for one pass's nonlinear factors, as flat affine rows.

    Per family, ``J[f] @ x + c[f]`` (whitened, for the pass's flat vector ``x``) is the residual
    the factors' ``LinearContainerFactor`` s predict: a row linearised at ``x0`` keeps
    ``J = dr/dx (x0)`` and ``c = r(x0) - J x0``, so rows linearised at different points live side
    by side. ``position[f]`` / ``record[f]``: each row's factor, as graph position and record index.
    """

    flat: FlatProblem
    J: dict[str, sp.csr_matrix]
    c: dict[str, Array]
    position: dict[str, NDArray[np.int64]]
    record: dict[str, NDArray[np.int64]]


class IncrementalSolver:
    """iSAM2 over linearised factors with our own re-linearisation rule (module docstring).

    ``linearization_tol`` (sigma units): rounds stop once the square root of the summed staleness
    of all factors is at most this -- a proxy for the distance (in sigma) between the estimate and
    the optimum. After each update, ``last_linearization_error`` holds that figure,
    ``last_rounds`` the number of rounds and ``last_costs`` the nonlinear cost before each round
    and at the end.
    """

    def __init__(self, camera: CameraModel, gcps: GcpDatabase, dem: DemTiles | None, cfg: AdjustConfig = AdjustConfig(),
                 linearization_tol: float = DEFAULT_LINEARIZATION_TOL, max_rounds: int = 20) -> None:
        if not linearization_tol > 0:
            raise InputError("linearization_tol", linearization_tol, "a positive number (sigma units)")
        self.camera, self.gcps, self.dem, self.cfg = camera, gcps, dem, cfg
        self.linearization_tol = float(linearization_tol)
        self.max_rounds = max_rounds
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(1e12)  # our containers are re-linearised by this class
        self.isam = gtsam.ISAM2(p)
        self.graphs: list[PassGraph] = []
        self.passes: list[OrbitPass] = []
        self.exclusions: list[NDArray[np.bool_]] = []
        self.records: list[_Record] = []
        self._models: list[_PassModel] = []
        self.last_costs: list[float] = []
        self.last_linearization_error = 0.0
        self.owned: set[int] = set()
        self.estimate = gtsam.Values()
        self.last_rounds = 0

    # ------------------------------------------------------------------ building
    def _graph(self, orbit_pass: OrbitPass, index: int, exclude: NDArray[np.bool_]) -> PassGraph:
        pg = build_pass_graph(orbit_pass, self.camera, self.dem, self.gcps, self.cfg.graph_config(), pass_index=index,
                              shared=self.owned, exclude_observations=exclude)
        for k in pg.problem.initial.keys():
            self.owned.add(int(k))
        return pg

    def _linearize(self, pass_index: int, values: gtsam.Values, positions: NDArray[np.int64]) -> gtsam.NonlinearFactorGraph:
        """The factors at ``positions`` of a pass as ``LinearContainerFactor`` s at ``values``, and
        the same rows of the pass's flat linear model refreshed at ``values``. Each family these
        positions belong to is evaluated once, vectorised, and serves both; the others are not
        evaluated (their factors are not called)."""
        prob = self.graphs[pass_index].problem
        m = self._models[pass_index]
        x = m.flat.from_values(values)
        fresh = {f: np.isin(m.position[f], positions) for f in _NONLINEAR}
        raw = {f: m.flat.raw(x, f, True) for f, rows in fresh.items() if rows.any()}
        batches = {FlatProblem.family_of(b): b for b in prob.batches}
        sub = gtsam.NonlinearFactorGraph()
        for i in positions:
            sub.add(prob.graph.at(int(i)))
        for f, out in raw.items():
            batches[f].cache(*out, values=values)
        try:
            lin = sub.linearize(values)
        finally:
            for f in raw:
                batches[f].clear()
        graph = gtsam.NonlinearFactorGraph()
        for i in range(len(positions)):
            gf = lin.at(i)
            lp = gtsam.Values()
            for k in gf.keys():
                lp.insert(int(k), values.atVector(int(k)))
            graph.add(gtsam.LinearContainerFactor(gf, lp))
        for f, out in raw.items():
            rows = fresh[f]
            r, J = m.flat.family_rows(x, f, True, raw=out)
            assert J is not None
            m.J[f] = (sp.diags((~rows).astype(float)) @ m.J[f] + sp.diags(rows.astype(float)) @ J).tocsr()
            m.c[f] = np.where(rows, r - J @ x, m.c[f])
        return graph

    def _new_model(self, pg: PassGraph, first_record: int) -> _PassModel:
        try:
            flat = pg.problem.flat()
        except NotFlat as exc:  # pass graphs are plain least squares (blunders are screened before)
            raise InputError("pass graph", str(exc), "plain least-squares collinearity, DEM and prior factors") from exc
        pos = flat.row_positions()
        return _PassModel(flat, {f: sp.csr_matrix((p.size, flat.n)) for f, p in pos.items()},
                          {f: np.zeros(p.size) for f, p in pos.items()}, pos, {f: first_record + p for f, p in pos.items()})

    def add_passes(self, passes: list[OrbitPass], exclusions: list[NDArray[np.bool_]] | None = None,
                   initial: gtsam.Values | None = None) -> float:
        """Add passes in one iSAM2 update (then re-linearise); return the seconds spent."""
        t0 = time.perf_counter()
        new_values = gtsam.Values()
        batch = gtsam.NonlinearFactorGraph()
        first = len(self.graphs)
        for j, p in enumerate(passes):
            idx = len(self.graphs)
            exclude = exclusions[j] if exclusions is not None else np.zeros(len(p.observations), bool)
            pg = self._graph(p, idx, exclude)
            self.graphs.append(pg)
            self.passes.append(p)
            self.exclusions.append(exclude)
            for k in pg.problem.initial.keys():
                v = initial.atVector(int(k)) if initial is not None and initial.exists(int(k)) else pg.problem.initial.atVector(int(k))
                new_values.insert(int(k), v)
        # linearise every new pass at the current estimate plus the new variables' initial values
        at = gtsam.Values(self.estimate)
        at.insert(new_values)
        pending: list[tuple[int, int]] = []
        for pi in range(first, len(self.graphs)):
            n = int(self.graphs[pi].problem.graph.size())
            self._models.append(self._new_model(self.graphs[pi], len(self.records) + len(pending)))
            g = self._linearize(pi, at, np.arange(n))
            for i in range(n):
                batch.add(g.at(i))
                pending.append((pi, i))
        res = self.isam.update(batch, new_values)
        self.records.extend(_Record(pi, pos, int(fi)) for (pi, pos), fi in zip(pending, res.getNewFactorsIndices()))
        self.estimate = self.isam.calculateEstimate()
        self._relinearize()
        return time.perf_counter() - t0

    def linearization_errors(self, values: gtsam.Values) -> tuple[Array, float]:
        """Staleness of every record's factor at ``values`` and the nonlinear cost ``0.5 ||r(x)||^2``.

        Staleness (whitened, squared; a vector over records) is ``||e_i||^2`` with
        ``e_i = r_i(x) - (J_i x + c_i)`` the error of the factor's linear model, plus for a DEM
        factor the step its stale gradient would cause on its landmark alone,
        ``g_i^T H_l^-1 g_i`` with ``g_i = J_i(x)^T r_i(x) - J_i^T (J_i x + c_i)`` and ``H_l`` the
        landmark's information from every factor on it (module docstring)."""
        e2 = np.zeros(len(self.records))
        cost = 0.0
        dem_terms = []
        info_keys, info_blocks = [], []
        for m in self._models:
            x = m.flat.from_values(values)
            for f in FlatProblem.FAMILIES:
                r, J1 = m.flat.family_rows(x, f, f == "dem")
                cost += 0.5 * float(r @ r)
                if f not in m.J:
                    continue
                p = m.J[f] @ x + m.c[f]
                e2 += np.bincount(m.record[f], weights=(r - p) ** 2, minlength=e2.size)
                if f == "dem" and r.size:
                    assert J1 is not None
                    cols = m.flat._dem_cols
                    rows = np.arange(r.size)[:, None]
                    j0, j1 = m.J[f][rows, cols].toarray(), J1[rows, cols].toarray()
                    dem_terms.append((m.record[f], m.flat.dem.keys, j1 * r[:, None] - j0 * p[:, None]))
                    info_keys.append(m.flat.dem.keys)
                    info_blocks.append(j0)
            # each collinearity row's landmark block (the landmark's information from its views)
            lm_cols = np.repeat(m.flat._slot_cols[0], 2, axis=0)
            info_keys.append(np.repeat(m.flat.coll.slot_keys[0], 2))
            info_blocks.append(m.J["collinearity"][np.arange(lm_cols.shape[0])[:, None], lm_cols].toarray())
        if dem_terms:
            keys, inv = np.unique(np.concatenate(info_keys), return_inverse=True)
            blocks = np.concatenate(info_blocks)
            H = np.zeros((keys.size, 3, 3))
            np.add.at(H, inv.ravel(), blocks[:, :, None] * blocks[:, None, :])
            for rec, k, g in dem_terms:
                h = H[np.searchsorted(keys, k)]
                e2[rec] += np.einsum("ni,ni->n", g, np.linalg.solve(h, g[:, :, None])[:, :, 0])
        return e2, cost

    def _relinearize(self) -> None:
        """Re-linearisation rounds (module docstring): re-linearise the stalest factors until the
        total staleness is at most ``linearization_tol**2`` (or ``max_rounds`` is reached)."""
        self.last_rounds = 0
        self.last_costs = []
        tol2 = self.linearization_tol ** 2
        while True:
            e2, cost = self.linearization_errors(self.estimate)
            self.last_costs.append(cost)
            total = float(e2.sum())
            self.last_linearization_error = float(np.sqrt(total))
            log.debug("round %d: cost %.6f, linearisation error %.3g sigma", self.last_rounds, cost, np.sqrt(total))
            if total <= tol2:
                return
            if self.last_rounds == self.max_rounds:
                log.warning("re-linearisation did not settle in %d rounds (linearisation error %.3g sigma > %.3g)",
                            self.max_rounds, np.sqrt(total), self.linearization_tol)
                return
            self.last_rounds += 1
            order = np.argsort(e2)[::-1]
            rest = total - np.cumsum(e2[order])
            stale = order[: int(np.argmax(rest <= 0.25 * tol2)) + 1]
            by_pass: dict[int, list[int]] = {}
            for i in stale:
                by_pass.setdefault(self.records[int(i)].pass_index, []).append(int(i))
            graph = gtsam.NonlinearFactorGraph()
            swap: list[_Record] = []
            for pi, ids in by_pass.items():
                recs = [self.records[i] for i in ids]
                g = self._linearize(pi, self.estimate, np.array([r.position for r in recs], np.int64))
                for i, r in enumerate(recs):
                    graph.add(g.at(i))
                    swap.append(r)
            res = self.isam.update(graph, gtsam.Values(), [r.isam_index for r in swap])
            for r, fi in zip(swap, res.getNewFactorsIndices()):
                r.isam_index = int(fi)
            self.estimate = self.isam.calculateEstimate()

    # ------------------------------------------------------------------ results
    def pass_result(self, index: int, seconds: float = 0.0) -> AdjustResult:
        """The newest (or any earlier) pass's error models and marginals from the current estimate."""
        pg = self.graphs[index]
        v = self.estimate
        keys = [k for k in pg.problem.dims]
        cov = {k: np.asarray(self.isam.marginalCovariance(k)) for k in keys}
        knots = [k for a in range(3) for k in pg.knot_keys(a)]
        joint_keys = knots + pg.ephemeris_keys() + list(pg.camera_keys.values())
        jm = self.isam.jointMarginalCovariance(gtsam.KeyVector(joint_keys)).fullMatrix()
        off, o = {}, 0
        for k in joint_keys:
            off[k] = o
            o += pg.problem.dims[k]
        marg = Marginals(cov, np.asarray(jm), joint_keys, off)
        att, eph, cam = estimated_models(pg, v, self.camera)
        r, _ = pg.collinearity.residuals(v)
        resid = np.full((len(self.passes[index].observations), 2), np.nan)
        resid[pg.obs_index[pg.collinearity.order]] = r
        rej = np.flatnonzero(self.exclusions[index])
        return AdjustResult(pg, v, marg, att, eph, cam, rej, np.zeros(rej.size), resid, self.last_rounds,
                            float(self.isam.getFactorsUnsafe().error(v)), [], seconds,
                            unresolved_attitude_rad=AdjustConfig().attitude_jitter_arcsec * ARCSEC)


def batch_solution(solver: IncrementalSolver, params: SolverParams = SolverParams(relative_error_tol=1e-12, absolute_error_tol=1e-12)):
    """The batch re-solve of every pass so far (same graphs, LM core; one flat problem on the Schur
    backend, :func:`~misrgraph.estimate.graph.merge_flat`, where the passes allow it): the
    problem, the solve result and the seconds."""
    t0 = time.perf_counter()
    shared: set[int] = set()
    problems = []
    for i, p in enumerate(solver.passes):
        pg = build_pass_graph(p, solver.camera, solver.dem, solver.gcps, solver.cfg.graph_config(), pass_index=i,
                              shared=shared, exclude_observations=solver.exclusions[i])
        shared |= {int(k) for k in pg.problem.initial.keys()}
        problems.append(pg.problem)
    try:
        prob = merge_flat(problems)
    except NotFlat:
        prob = merge_problems(problems)
    res = solve(prob, params)
    return prob, res, time.perf_counter() - t0
