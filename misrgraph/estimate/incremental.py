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
budget) and stop once the total is at most ``linearization_tol**2``. The tolerance bounds the
linearisation error of a round, not the distance to the optimum; ``misrgraph bench
incremental`` measures that distance against the converged batch.

Shared variables: the camera corrections and GCPs (one key each for every pass), and the tie
points of repeat passes of the same path (keyed by path and feature id).

Keeping the update flat as passes accumulate (issue 20):

* **Ordering.** Every update constrains the shared variables to be eliminated last
  (``constrainedKeys``), so each pass's own variables (knots, ephemeris) form a subtree below a root
  of shared variables. A new pass then re-eliminates only its own subtree and the root; the other
  passes' subtrees enter through their cached marginals. iSAM2's default ordering put the newest
  variables last and re-eliminated a growing top of the tree.
* **Full back-substitution.** iSAM2's wildfire threshold (0.001 by default, in the variables' own
  units) stops propagating a change once it is smaller than that -- every knot (radians) is
  smaller, so after a new pass the older passes' knots kept stale values (up to 0.084 sigma from
  the optimum on a 20-pass path, measured). The threshold is 0: back-substitution through every
  clique is cheap.
* **Settled passes are marginalised.** In the first update after ``settle_after`` newer passes
  have arrived, a pass's own variables (knots, ephemeris) leave the tree
  (``ISAM2.marginalizeLeavesWithIndices``, cheap: the shared variables are eliminated last, so they
  are leaves and their marginal is the cached factor of their subtree), and the marginal factors
  of every settled pass are summed into one ``HessianFactor`` on the shared variables. The tree's
  root then receives one factor for all settled passes instead of one per pass, so its
  re-elimination does not grow with the number of passes.
  The pass's DEM factors (on its landmarks; the DEM curves at its posting scale) and GCP priors
  stay live. Its knots and ephemeris keep estimates and marginals through their conditional on
  the shared variables (:class:`_Conditional`; exact, as the own variables enter no other
  factor): :attr:`IncrementalSolver.estimate` and :meth:`IncrementalSolver.marginal_covariance`
  cover them. The approximation is that a settled pass's collinearity is not re-linearised
  again; collinearity is nearly linear over the moves left after ``settle_after`` passes, and
  the distance from the converged batch is measured by ``misrgraph bench incremental``.

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
from scipy.linalg import cho_factor, cho_solve

from factors import keys as K
from misrgraph.errors import InputError
from misrgraph.estimate.adjust import AdjustConfig, AdjustResult, estimated_models
from misrgraph.estimate.graph import PassGraph, build_pass_graph, merge_flat, merge_problems
from misrgraph.estimate.problem import FlatProblem, Marginals, NotFlat
from misrgraph.estimate.solver import SolverParams, solve
from misrgraph.io.passes import OrbitPass
from misrgraph.model.camera import CameraModel
from misrgraph.model.dem import DemTiles
from misrgraph.model.gcp import GcpDatabase

__all__ = ["IncrementalSolver", "batch_solution", "DEFAULT_LINEARIZATION_TOL", "DEFAULT_SETTLE_AFTER"]

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

#: Passes are marginalised in the first update after this many newer passes (module docstring).
DEFAULT_SETTLE_AFTER = 3

#: Key letters of the variables shared between passes (eliminated last).
_SHARED_LETTERS = frozenset(ord(c) for c in (K.LANDMARK, K.GCP, K.GCP_SCENE, K.CAMERA, K.OMEGA))
#: Key letters of ground points (tie points and GCPs).
_POINT_LETTERS = frozenset(ord(c) for c in (K.LANDMARK, K.GCP))

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


@dataclass
class _Conditional:
    """A marginalised pass's own variables (knots, ephemeris) given the shared ones it touches.

    From the pass's affine rows ``r = J x + c`` (whitened; the very quadratic iSAM2 held), split
    into its own columns ``o`` and shared columns ``s``: with ``H = J_o^T J_o`` (dense Cholesky),
    ``B = J_o^T J_s`` (sparse) and ``h = J_o^T c``, the conditional mean is
    ``x_o = -H^-1 (B x_s + h)`` and the conditional covariance ``H^-1``. The own variables enter
    no other factor, so this is exact: the estimate at any ``x_s`` and, with the shared keys'
    joint covariance ``S``, the marginal covariance ``H^-1 + A S A^T`` with ``A = H^-1 B``."""

    own_keys: list[int]
    own_dims: list[int]
    shared_keys: list[int]
    shared_cols: NDArray[np.int64]  # columns of the pass's flat vector, in ``shared_keys`` order
    chol: tuple[Array, bool]  # scipy.linalg.cho_factor of H
    B: sp.csr_matrix
    h: Array

    def mean(self, x_s: Array) -> Array:
        """The own variables' estimate ``(n_o,)`` at the shared variables ``x_s`` ``(n_s,)``."""
        return -cho_solve(self.chol, self.B @ x_s + self.h)


class IncrementalSolver:
    """iSAM2 over linearised factors with our own re-linearisation rule (module docstring).

    ``linearization_tol`` (sigma units): rounds stop once the square root of the summed staleness
    of all factors is at most this -- a proxy for the distance (in sigma) between the estimate and
    the optimum. After each update, ``last_linearization_error`` holds that figure,
    ``last_rounds`` the number of rounds and ``last_costs`` the live factors' nonlinear cost before
    each round and at the end. ``settle_after``: passes are marginalised in the first update after
    this many newer passes (module docstring); None keeps every factor live. ``camera_prior``:
    the camera model's calibration covariance, the joint prior of the camera corrections
    (:func:`misrgraph.estimate.graph.build_pass_graph`; the first pass that has a camera adds it).
    """

    def __init__(
        self,
        camera: CameraModel,
        gcps: GcpDatabase,
        dem: DemTiles | None,
        cfg: AdjustConfig = AdjustConfig(),
        linearization_tol: float = DEFAULT_LINEARIZATION_TOL,
        max_rounds: int = 20,
        settle_after: int | None = DEFAULT_SETTLE_AFTER,
        camera_prior: tuple[list[str], Array] | None = None,
    ) -> None:
        if not linearization_tol > 0:
            raise InputError("linearization_tol", linearization_tol, "a positive number (sigma units)")
        if settle_after is not None and not (isinstance(settle_after, int) and settle_after >= 1):
            raise InputError("settle_after", settle_after, "a whole number of passes >= 1, or None (never marginalise)")
        self.camera, self.gcps, self.dem, self.cfg = camera, gcps, dem, cfg
        self.camera_prior = camera_prior
        self.linearization_tol = float(linearization_tol)
        self.max_rounds = max_rounds
        self.settle_after = settle_after
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(1e12)  # our containers are re-linearised by this class
        p.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))  # full back-substitution (module docstring)
        self.isam = gtsam.ISAM2(p)
        self._shared_groups = gtsam.KeyGroupMap()  # shared variables: eliminated last (module docstring)
        self.settled: set[int] = set()  # passes marginalised out of iSAM2 (module docstring)
        self._conditionals: dict[int, _Conditional] = {}  # per settled pass: its own variables given the shared
        self._owner: dict[int, int] = {}  # own key of a settled pass -> that pass
        self._merged: int | None = None  # iSAM2 index of the one factor holding every settled pass's marginal
        self._unmerged: list[int] = []  # iSAM2 indices of marginal factors not merged yet (the next update does)
        # the landmark information (keys, 3x3 blocks) from settled passes' frozen collinearity rows
        self._settled_info: tuple[NDArray[np.int64], Array] = (np.zeros(0, np.int64), np.zeros((0, 3, 3)))
        self._record_ranges: list[tuple[int, int]] = []  # per pass: its records' index range
        self.graphs: list[PassGraph] = []
        self.passes: list[OrbitPass] = []
        self.exclusions: list[NDArray[np.bool_]] = []
        self.records: list[_Record] = []
        self._models: list[_PassModel] = []
        self.last_costs: list[float] = []
        self.last_linearization_error = 0.0
        self.owned: set[int] = set()
        # landmark/GCP key -> the initial position of the pass that added it (ECEF m): later passes
        # evaluate their line scale there instead of ray casting (the same graphs on a replay)
        self._first_position: dict[int, Array] = {}
        self._live = gtsam.Values()  # iSAM2's estimate (the variables it still holds)
        self._full: gtsam.Values | None = None  # :attr:`estimate`, built on first use after an update
        self.last_rounds = 0

    @property
    def estimate(self) -> gtsam.Values:
        """The estimate of every variable of every pass: iSAM2's for the variables it holds; a
        settled pass's knots and ephemeris from its conditional at iSAM2's estimate of the shared
        variables (:class:`_Conditional`; built on first use after an update, not part of it)."""
        if self._full is None:
            full = gtsam.Values(self._live)
            for cond in self._conditionals.values():
                x_s = np.concatenate([self._live.atVector(k) for k in cond.shared_keys])
                for k, v in zip(cond.own_keys, np.split(cond.mean(x_s), np.cumsum(cond.own_dims)[:-1])):
                    full.insert(k, v)
            self._full = full
        return self._full

    def _refresh(self) -> None:
        self._live = self.isam.calculateEstimate()
        self._full = None

    # ------------------------------------------------------------------ building
    def _graph(self, orbit_pass: OrbitPass, index: int, exclude: NDArray[np.bool_]) -> PassGraph:
        pg = build_pass_graph(
            orbit_pass,
            self.camera,
            self.dem,
            self.gcps,
            self.cfg.graph_config(),
            pass_index=index,
            shared=self.owned,
            exclude_observations=exclude,
            known_landmarks=self._first_position,
            camera_prior=self.camera_prior,
        )
        for k in pg.problem.initial.keys():
            self.owned.add(int(k))
            if gtsam.Symbol(int(k)).chr() in _POINT_LETTERS:
                self._first_position[int(k)] = pg.problem.initial.atVector(int(k))
        return pg

    def standalone_graph(self, index: int) -> PassGraph:
        """Pass ``index``'s graph as an adjustment of that pass alone builds it: the same keys,
        exclusions and landmark line scales as the solver's, but with every variable's prior (the
        solver's own graph leaves the priors of variables an earlier pass owns to that pass, so on
        its own it may not determine them). For statistics of one pass at the joint estimate,
        such as its redundancy numbers; a tie point other passes also see keeps only this pass's rays."""
        return build_pass_graph(
            self.passes[index],
            self.camera,
            self.dem,
            self.gcps,
            self.cfg.graph_config(),
            pass_index=index,
            exclude_observations=self.exclusions[index],
            known_landmarks=self._first_position,
            camera_prior=self.camera_prior,
        )

    def _linearize(
        self, pass_index: int, values: gtsam.Values, positions: NDArray[np.int64]
    ) -> gtsam.NonlinearFactorGraph:
        """The factors at ``positions`` of a pass as ``LinearContainerFactor`` s at ``values``, and
        the same rows of the pass's flat linear model refreshed at ``values``. Each family these
        positions belong to is evaluated once, vectorised, and serves both; the others are not
        evaluated (their factors are not called)."""
        prob = self.graphs[pass_index].problem
        m = self._models[pass_index]
        x = m.flat.from_values(values, partial=pass_index in self.settled)  # a settled pass: DEM rows only
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
        for i in range(len(positions)):  # a container keeps only its own keys' values
            graph.add(gtsam.LinearContainerFactor(lin.at(i), values))
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
        return _PassModel(
            flat,
            {f: sp.csr_matrix((p.size, flat.n)) for f, p in pos.items()},
            {f: np.zeros(p.size) for f, p in pos.items()},
            pos,
            {f: first_record + p for f, p in pos.items()},
        )

    def _update(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, remove: list[int] | None = None
    ) -> gtsam.ISAM2Result:
        """One iSAM2 update with the shared variables constrained last (module docstring)."""
        for k in values.keys():
            if gtsam.Symbol(int(k)).chr() in _SHARED_LETTERS:
                self._shared_groups.insert2(int(k), 1)
        params = gtsam.ISAM2UpdateParams()
        params.constrainedKeys = self._shared_groups
        if remove:
            params.removeFactorIndices = remove
        return self.isam.update(graph, values, params)

    def _marginalise(self, pass_index: int) -> list[int]:
        """Marginalise a settled pass's own variables (knots, ephemeris) out of iSAM2 and keep
        their conditional on the shared variables (:class:`_Conditional`) for the estimate and
        marginals; return the iSAM2 indices of the marginal factors iSAM2 added (to be merged,
        :meth:`_merge`). Its DEM factors (on landmarks) and GCP priors stay live. The landmark
        information of its collinearity rows (gone from the tree) is kept for the DEM staleness term.
        The marginal factors are also queued for the next update's merge."""
        m = self._models[pass_index]
        flat = m.flat
        dims = self.graphs[pass_index].problem.dims
        own = [k for k in flat.keys if gtsam.Symbol(k).chr() not in _SHARED_LETTERS]
        shared = [k for k in flat.keys if gtsam.Symbol(k).chr() in _SHARED_LETTERS]

        def cols(keys: list[int]) -> NDArray[np.int64]:
            return np.concatenate([np.zeros(0, np.int64)] + [flat.offset[k] + np.arange(dims[k]) for k in keys]).astype(
                np.int64
            )

        oc, sc = cols(own), cols(shared)
        x = flat.from_values(self._live)
        r_p, J_p = flat.family_rows(x, "priors", True)
        assert J_p is not None
        fams = [f for f in _NONLINEAR if f in m.J]
        J = sp.vstack([m.J[f] for f in fams] + [J_p], format="csc")
        c = np.concatenate([m.c[f] for f in fams] + [r_p - J_p @ x])
        Jo, Js = J[:, oc], J[:, sc]
        cond = _Conditional(
            own, [dims[k] for k in own], shared, sc, cho_factor((Jo.T @ Jo).toarray()), (Jo.T @ Js).tocsr(), Jo.T @ c
        )
        k, b = self._landmark_information(m)
        self._settled_info = _information_sum(
            [self._settled_info[0], k], [self._settled_info[1], b[:, :, None] * b[:, None, :]]
        )
        leaves = gtsam.KeyList()
        for key in own:
            leaves.push_back(key)
        marginal, deleted = self.isam.marginalizeLeavesWithIndices(leaves)
        gone = set(int(i) for i in deleted)
        start, stop = self._record_ranges[pass_index]
        for j in range(start, stop):
            if self.records[j].isam_index in gone:
                self.records[j].isam_index = -1
        self._conditionals[pass_index] = cond
        self._owner.update((key, pass_index) for key in own)
        self.settled.add(pass_index)
        self._unmerged.extend(int(i) for i in marginal)
        return [int(i) for i in marginal]

    def _merge(self, marginal: list[int]) -> tuple[gtsam.LinearContainerFactor, list[int]]:
        """The marginal factors at ``marginal`` and the merged factor so far summed into one
        ``HessianFactor`` on the shared variables (exact: each is a quadratic, taken at iSAM2's
        linearisation point), and the iSAM2 indices it replaces. The tree's root then receives
        one factor for every settled pass together instead of one per pass."""
        factors = self.isam.getFactorsUnsafe()
        theta = self.isam.getLinearizationPoint()
        replace = list(marginal) + ([self._merged] if self._merged is not None else [])
        gfg = gtsam.GaussianFactorGraph()
        for i in replace:
            gfg.push_back(factors.at(i).linearize(theta))
        return gtsam.LinearContainerFactor(gtsam.HessianFactor(gfg), theta), replace

    @staticmethod
    def _landmark_information(m: _PassModel) -> tuple[NDArray[np.int64], Array]:
        """Each collinearity row's landmark key and whitened Jacobian block (rows x 3) of a pass's
        linear model: the landmarks' information from the pass's views is the sum of ``b^T b``."""
        lm_cols = np.repeat(m.flat._slot_cols[0], 2, axis=0)
        keys = np.repeat(m.flat.coll.slot_keys[0], 2)
        return keys, m.J["collinearity"][np.arange(lm_cols.shape[0])[:, None], lm_cols].toarray()

    def add_passes(
        self,
        passes: list[OrbitPass],
        exclusions: list[NDArray[np.bool_]] | None = None,
        initial: gtsam.Values | None = None,
    ) -> float:
        """Add passes in one iSAM2 update (then re-linearise); return the seconds spent. Passes
        that ``settle_after`` newer passes have followed are marginalised out first, their
        marginals merged in the same update (module docstring)."""
        t0 = time.perf_counter()
        new_values = gtsam.Values()
        batch = gtsam.NonlinearFactorGraph()
        remove: list[int] = []
        due = (
            []
            if self.settle_after is None
            else [i for i in range(len(self.graphs) - self.settle_after) if i not in self.settled]
        )
        first = len(self.graphs)
        for j, p in enumerate(passes):
            idx = len(self.graphs)
            exclude = exclusions[j] if exclusions is not None else np.zeros(len(p.observations), bool)
            pg = self._graph(p, idx, exclude)
            self.graphs.append(pg)
            self.passes.append(p)
            self.exclusions.append(exclude)
            for k in pg.problem.initial.keys():
                v = (
                    initial.atVector(int(k))
                    if initial is not None and initial.exists(int(k))
                    else pg.problem.initial.atVector(int(k))
                )
                new_values.insert(int(k), v)
        # the new graphs are built (bad input has been refused): settled passes leave the tree
        for i in due:
            self._marginalise(i)
        marginal, self._unmerged = self._unmerged, []
        if marginal:
            merged, gone = self._merge(marginal)
            batch.add(merged)
            remove.extend(gone)
        # linearise every new pass at the current estimate plus the new variables' initial values
        at = gtsam.Values(self._live)
        at.insert(new_values)
        pending: list[tuple[int, int]] = []
        for pi in range(first, len(self.graphs)):
            n = int(self.graphs[pi].problem.graph.size())
            start = len(self.records) + len(pending)
            self._record_ranges.append((start, start + n))
            self._models.append(self._new_model(self.graphs[pi], start))
            g = self._linearize(pi, at, np.arange(n))
            for i in range(n):
                batch.add(g.at(i))
                pending.append((pi, i))
        res = self._update(batch, new_values, remove)
        indices = list(res.getNewFactorsIndices())
        if marginal:
            self._merged = int(indices[0])
        self.records.extend(
            _Record(pi, pos, int(fi)) for (pi, pos), fi in zip(pending, indices[1 if marginal else 0 :])
        )
        self._refresh()
        self._relinearize()
        return time.perf_counter() - t0

    def linearization_errors(self, values: gtsam.Values) -> tuple[Array, float]:
        """Staleness of every live record's factor at ``values`` and their cost ``0.5 ||r(x)||^2``.

        Staleness (whitened, squared; a vector over records) is ``||e_i||^2`` with
        ``e_i = r_i(x) - (J_i x + c_i)`` the error of the factor's linear model, plus for a DEM
        factor the step its stale gradient would cause on its landmark alone,
        ``g_i^T H_l^-1 g_i`` with ``g_i = J_i(x)^T r_i(x) - J_i^T (J_i x + c_i)`` and ``H_l`` the
        landmark's information from every factor on it (module docstring). The records a settled
        pass's marginalisation removed are not evaluated (staleness 0) and the cost is that of the
        live factors (the merged marginal's quadratic is left out)."""
        e2 = np.zeros(len(self.records))
        cost = 0.0
        dem_terms = []
        info_keys, info_blocks = [], []
        for pi, m in enumerate(self._models):
            settled = pi in self.settled
            if settled and not m.record.get("dem", np.zeros(0)).size:
                continue  # nothing of it is live
            x = m.flat.from_values(values, partial=settled)  # a settled pass: its DEM rows only
            for f in ("dem",) if settled else FlatProblem.FAMILIES:
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
                    info_blocks.append(j0[:, :, None] * j0[:, None, :])
            if not settled:  # a settled pass's blocks are frozen (self._settled_info)
                k, b = self._landmark_information(m)
                info_keys.append(k)
                info_blocks.append(b[:, :, None] * b[:, None, :])
        if dem_terms:
            keys, H = _information_sum([self._settled_info[0], *info_keys], [self._settled_info[1], *info_blocks])
            for rec, k, g in dem_terms:
                h = H[np.searchsorted(keys, k)]
                e2[rec] += np.einsum("ni,ni->n", g, np.linalg.solve(h, g[:, :, None])[:, :, 0])
        return e2, cost

    def _relinearize(self) -> None:
        """Re-linearisation rounds (module docstring): re-linearise the stalest factors until the
        total staleness is at most ``linearization_tol**2`` (or ``max_rounds`` is reached)."""
        self.last_rounds = 0
        self.last_costs = []
        tol2 = self.linearization_tol**2
        while True:
            e2, cost = self.linearization_errors(self._live)
            self.last_costs.append(cost)
            total = float(e2.sum())
            self.last_linearization_error = float(np.sqrt(total))
            log.debug("round %d: cost %.6f, linearisation error %.3g sigma", self.last_rounds, cost, np.sqrt(total))
            if total <= tol2:
                return
            if self.last_rounds == self.max_rounds:
                log.warning(
                    "re-linearisation did not settle in %d rounds (linearisation error %.3g sigma > %.3g)",
                    self.max_rounds,
                    np.sqrt(total),
                    self.linearization_tol,
                )
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
                g = self._linearize(pi, self._live, np.array([r.position for r in recs], np.int64))
                for i, r in enumerate(recs):
                    graph.add(g.at(i))
                    swap.append(r)
            res = self._update(graph, gtsam.Values(), [r.isam_index for r in swap])
            for r, fi in zip(swap, res.getNewFactorsIndices()):
                r.isam_index = int(fi)
            self._refresh()

    # ------------------------------------------------------------------ results
    def marginal_covariance(self, key: int) -> Array:
        """Marginal covariance of one variable (its own units), held by iSAM2 or settled."""
        return self.joint_marginal_covariance([int(key)])

    def joint_marginal_covariance(self, keys: list[int]) -> Array:
        """Joint marginal covariance of ``keys`` (dense, blocks in their order). A settled pass's
        own variable ``x_o = -A x_s + e`` (:class:`_Conditional`; ``e`` independent of the shared
        ``x_s`` with covariance ``H^-1``): the joint covariance is ``T S T^T + D`` with ``S`` iSAM2's
        joint covariance of the shared keys involved and the keys asked for that it holds, ``T``
        the map from those to ``keys`` and ``D`` the settled passes' ``H^-1`` blocks."""
        keys = [int(k) for k in keys]
        involved = sorted({self._owner[k] for k in keys if k in self._owner})
        if not involved:
            if len(keys) == 1:
                return np.asarray(self.isam.marginalCovariance(keys[0]))
            return np.asarray(self.isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix())
        held = list(
            dict.fromkeys(
                [k for k in keys if k not in self._owner]
                + [k for i in involved for k in self._conditionals[i].shared_keys]
            )
        )
        dim = {k: int(self._live.atVector(k).size) for k in held}
        for i in involved:
            dim.update(zip(self._conditionals[i].own_keys, self._conditionals[i].own_dims))
        off_s = dict(zip(held, np.concatenate([[0], np.cumsum([dim[k] for k in held])[:-1]]).astype(int)))
        n_s = sum(dim[k] for k in held)
        S = (
            np.asarray(self.isam.marginalCovariance(held[0]))
            if len(held) == 1
            else np.asarray(self.isam.jointMarginalCovariance(gtsam.KeyVector(held)).fullMatrix())
        )
        A, Hinv, own_off, s_cols = {}, {}, {}, {}
        for i in involved:
            c = self._conditionals[i]
            A[i] = cho_solve(c.chol, c.B.toarray())
            Hinv[i] = cho_solve(c.chol, np.eye(sum(c.own_dims)))
            own_off[i] = dict(zip(c.own_keys, np.concatenate([[0], np.cumsum(c.own_dims)[:-1]]).astype(int)))
            s_cols[i] = np.concatenate([off_s[k] + np.arange(dim[k]) for k in c.shared_keys])
        off = np.concatenate([[0], np.cumsum([dim[k] for k in keys])]).astype(int)
        T = np.zeros((off[-1], n_s))
        D = np.zeros((off[-1], off[-1]))
        rows: dict[int, tuple[list[NDArray[np.int64]], list[NDArray[np.int64]]]] = {i: ([], []) for i in involved}
        for a, k in enumerate(keys):
            ra = np.arange(off[a], off[a + 1])
            if k not in self._owner:
                T[ra, off_s[k] + np.arange(dim[k])] = 1.0
                continue
            i = self._owner[k]
            own = own_off[i][k] + np.arange(dim[k])
            T[ra[:, None], s_cols[i][None, :]] = -A[i][own]
            rows[i][0].append(ra)
            rows[i][1].append(own)
        for i, (out, own) in rows.items():  # e is independent between passes and of x_s
            o, w = np.concatenate(out), np.concatenate(own)
            D[np.ix_(o, o)] = Hinv[i][np.ix_(w, w)]
        return T @ S @ T.T + D

    def pass_result(self, index: int, seconds: float = 0.0) -> AdjustResult:
        """The newest (or any earlier) pass's error models and marginals from the current estimate."""
        pg = self.graphs[index]
        v = self.estimate
        keys = [k for k in pg.problem.dims]
        knots = [k for a in range(3) for k in pg.knot_keys(a)]
        joint_keys = knots + pg.ephemeris_keys() + list(pg.camera_keys.values())
        # one joint covariance of all the pass's variables, sliced: iSAM2 gives it in the time of
        # two or three single-key marginals (key by key is far slower on a long path), and a
        # settled pass's own keys need the shared keys' joint anyway
        order = list(dict.fromkeys(joint_keys + keys))
        full = self.joint_marginal_covariance(order)
        o = np.concatenate([[0], np.cumsum([pg.problem.dims[k] for k in order])]).astype(int)
        cov = {k: full[o[i] : o[i + 1], o[i] : o[i + 1]] for i, k in enumerate(order)}
        jm = full[: o[len(joint_keys)], : o[len(joint_keys)]]
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
        return AdjustResult(
            pass_graph=pg,
            values=v,
            marginals=marg,
            attitude=att,
            ephemeris=eph,
            camera=cam,
            rejected=rej,
            rejected_norm=np.zeros(rej.size),
            residuals_px=resid,
            iterations=self.last_rounds,
            final_cost=float(self.isam.getFactorsUnsafe().error(v)),
            history=[],
            seconds=seconds,
            unresolved_attitude_rad=self.cfg.graph.unresolved_attitude_rad(pg.attitude_model.knot_times),
        )


def _information_sum(keys: list[NDArray[np.int64]], blocks: list[Array]) -> tuple[NDArray[np.int64], Array]:
    """Per-key sums of 3x3 information blocks: the sorted unique keys and their summed blocks."""
    k = np.concatenate(keys)
    u, inv = np.unique(k, return_inverse=True)
    H = np.zeros((u.size, 3, 3))
    np.add.at(H, inv.ravel(), np.concatenate(blocks))
    return u, H


def batch_solution(
    solver: IncrementalSolver, params: SolverParams = SolverParams(relative_error_tol=1e-12, absolute_error_tol=1e-12)
):
    """The batch re-solve of every pass so far over the very pass graphs the solver built (LM
    core; one flat problem on the Schur backend, :func:`~misrgraph.estimate.graph.merge_flat`,
    where the passes allow it), from their initial values: the problem, the solve result and
    the seconds. (A pass graph's along-track line scale is evaluated at the landmark's initial
    position from the pass that added it, so graphs built afresh, each from its own ray casts,
    differ from these by up to ~0.4 % in that scale.)"""
    t0 = time.perf_counter()
    problems = [g.problem for g in solver.graphs]
    try:
        prob = merge_flat(problems)
    except NotFlat:
        prob = merge_problems(problems)
    res = solve(prob, params)
    return prob, res, time.perf_counter() - t0
