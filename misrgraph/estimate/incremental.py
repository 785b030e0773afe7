"""Incremental bundle adjustment with iSAM2 as passes arrive, and its persistent state.

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
budget) and stop once the total is at most ``linearization_tol**2``. Measured on the 10-pass
repeat path (``misrgraph bench incremental``), the final error against a tightly converged batch
is 0.8-2 times the tolerance; the default 0.04 leaves 0.03 sigma, against 0.06 sigma for the
batch LM at its own default criterion, with one round per pass after the first.

Shared variables: the camera corrections and GCPs (one key each for every pass), and the tie
points of repeat passes of the same path (keyed by path and feature id).

Persistent state (directory ``STATE``)::

    STATE/state.json                    the manifest: inputs (camera model, GCPs, DEM) with their
                                        SHA-256, config, the estimate file and the ordered passes,
                                        each named with its SHA-256
    STATE/passes/<pass_id>-<sha12>.h5   a copy of every pass added
    STATE/estimate-<sha12>.h5           the latest estimate of every variable (warm start)
    STATE/.lock                         held by the update in progress (one at a time)

Files are named by content and never modified; an update writes its new files first and then
replaces ``state.json`` atomically (fsynced), and only after that removes the files the new
manifest no longer names. A crash at any point therefore leaves the previous manifest and every
file it names intact (the pass being added is simply not in it), and a pass id already in the
manifest is never added twice. On replay each file is checked against the manifest's SHA-256, and
each input against the SHA-256 recorded when the state was created: a camera model, GCP database
or DEM replaced since then is an error, not a silent change of meaning.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gtsam
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from misrgraph import __version__
from misrgraph.estimate.adjust import AdjustConfig, AdjustResult, _estimated_models, find_blunders, score_pass
from misrgraph.model.camera import MODEL_NAMES, CameraModel, load_camera_model
from misrgraph.model.constants import ANGLES, ARCSEC
from misrgraph.model.dem import DemTiles
from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.flat import FlatProblem, NotFlat
from misrgraph.model.gcp import GcpDatabase
from misrgraph.estimate.graph import PassGraph, build_pass_graph, merge_problems
from misrgraph.io.h5 import atomic_file, atomic_h5, fsync_directory, open_h5, read_dataset, stored_file_sha256, write_dataset
from misrgraph.io.passes import PASS_ID_PATTERN, OrbitPass
from misrgraph.estimate.solver import Marginals, SolverParams, solve

__all__ = ["IncrementalSolver", "run_update", "load_state", "batch_solution", "DEFAULT_LINEARIZATION_TOL"]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]


@dataclass
class _Record:
    pass_index: int
    position: int  # factor position within its pass problem's graph
    isam_index: int


#: Default re-linearisation tolerance (sigma units, module docstring): on the 10-pass benchmark
#: path it leaves the estimate 0.03 sigma from the optimum, closer than the batch LM at its own
#: default criterion (0.06 sigma).
DEFAULT_LINEARIZATION_TOL = 0.04

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


def _row_positions(flat: FlatProblem) -> dict[str, NDArray[np.int64]]:
    """Graph position of the factor behind each collinearity and DEM row of a pass's flat residual.

    Rows are the collinearity observations (2 each, in the batch's order), then the DEM factors;
    in the graph the collinearity factors come first among the custom factors, then the DEM
    factors (:func:`misrgraph.estimate.graph.build_pass_graph`)."""
    g = flat.problem.graph
    custom = np.array([i for i in range(g.size()) if isinstance(g.at(i), gtsam.CustomFactor)], np.int64)
    lay = flat.coll.layout
    per_obs = np.repeat(np.arange(lay.n_factors), lay.obs_stop - lay.obs_start)
    return {"collinearity": np.repeat(custom[per_obs], 2), "dem": custom[lay.n_factors:lay.n_factors + flat.m_dem]}


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
            flat = FlatProblem(pg.problem)
        except NotFlat as exc:  # pass graphs are plain least squares (blunders are screened before)
            raise InputError("pass graph", str(exc), "plain least-squares collinearity, DEM and prior factors") from exc
        pos = _row_positions(flat)
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
        att, eph, cam = _estimated_models(pg, v, self.camera)
        r, _ = pg.collinearity.residuals(v)
        resid = np.full((len(self.passes[index].observations), 2), np.nan)
        resid[pg.obs_index[pg.collinearity.order]] = r
        rej = np.flatnonzero(self.exclusions[index])
        return AdjustResult(pg, v, marg, att, eph, cam, rej, np.zeros(rej.size), resid, self.last_rounds,
                            float(self.isam.getFactorsUnsafe().error(v)), [], seconds)


def batch_solution(solver: IncrementalSolver, params: SolverParams = SolverParams(relative_error_tol=1e-12, absolute_error_tol=1e-12)):
    """The batch re-solve of every pass so far (same graphs, LM core): values and seconds."""
    t0 = time.perf_counter()
    shared: set[int] = set()
    problems = []
    for i, p in enumerate(solver.passes):
        pg = build_pass_graph(p, solver.camera, solver.dem, solver.gcps, solver.cfg.graph_config(), pass_index=i,
                              shared=shared, exclude_observations=solver.exclusions[i])
        shared |= {int(k) for k in pg.problem.initial.keys()}
        problems.append(pg.problem)
    prob = merge_problems(problems)
    res = solve(prob, params)
    return prob, res, time.perf_counter() - t0


# ---------------------------------------------------------------------------- persistent state
@dataclass
class State:
    directory: Path
    meta: dict[str, Any]

    @property
    def pass_ids(self) -> list[str]:
        return [p["pass_id"] for p in self.meta["passes"]]


def _write_json_atomic(path: Path, obj: Any) -> None:
    with atomic_file(path) as f:
        json.dump(obj, f, indent=2)


def _model_spec(camera_model: str | os.PathLike[str]) -> str:
    """A built-in model name as it is, a file as its absolute path."""
    text = os.fspath(camera_model)
    return text if _is_builtin("camera_model", text) else str(Path(text).resolve())


def _model_sha256(camera: CameraModel) -> str:
    """SHA-256 over a camera model's numbers (for built-in models, which have no file)."""
    h = hashlib.sha256()
    for f in dataclasses.fields(camera):
        v = getattr(camera, f.name)
        if isinstance(v, np.ndarray):
            h.update(f.name.encode() + np.ascontiguousarray(v, dtype=float).tobytes())
    return h.hexdigest()


def _is_builtin(what: str, spec: str) -> bool:
    """Whether an input spec names a built-in camera model (no file) rather than a file."""
    return what == "camera_model" and spec in MODEL_NAMES and not os.path.exists(spec)


def _input_sha256(spec: str, what: str) -> str:
    """SHA-256 of an input: a file's whole-file checksum, or a built-in camera model's numbers."""
    if _is_builtin(what, spec):
        return _model_sha256(load_camera_model(spec))  # type: ignore[arg-type]
    return stored_file_sha256(spec)


#: Version of ``state.json``: 2 since the camera convention became ``T_ic = Ry(beta) Rx(delta)``;
#: 3 since the manifest names every file and input by SHA-256.
STATE_VERSION = 3
_HEX64 = re.compile(r"[0-9a-f]{64}")
_INPUTS = ("camera_model", "gcps", "dem")


def _check_manifest(f: Path, meta: Any) -> None:
    """Validate state.json's structure, naming the first bad field."""
    if not isinstance(meta, dict):
        raise FileFormatError(f, "not a JSON object")
    for key in ("version", "camera_model", "gcps", "passes", "config", "input_sha256", "estimate"):
        if key not in meta:
            raise FileFormatError(f, f"missing field {key!r}")
    sha = meta["input_sha256"]
    for key in _INPUTS:
        if meta.get(key) is not None and not (isinstance(sha, dict) and _HEX64.fullmatch(str(sha.get(key)))):
            raise FileFormatError(f, f"input_sha256.{key} is {sha.get(key) if isinstance(sha, dict) else sha!r}; "
                                     "expected 64 hex digits")
    files = ([("estimate", meta["estimate"])] if meta["estimate"] is not None else [])
    if not isinstance(meta["passes"], list):
        raise FileFormatError(f, "passes is not a list")
    seen = set()
    for i, e in enumerate(meta["passes"]):
        pid = e.get("pass_id") if isinstance(e, dict) else None
        if not isinstance(pid, str) or not PASS_ID_PATTERN.fullmatch(pid):
            raise FileFormatError(f, f"passes[{i}].pass_id is {pid!r}; expected a valid pass id")
        if pid in seen:
            raise FileFormatError(f, f"passes[{i}].pass_id {pid!r} appears twice")
        seen.add(pid)
        files.append((f"passes[{i}]", e))
    for where, e in files:
        name, digest = (e.get("file"), e.get("sha256")) if isinstance(e, dict) else (None, None)
        if not isinstance(name, str) or not re.fullmatch(r"(passes/)?[A-Za-z0-9_.-]+\.h5", name) or ".." in name:
            raise FileFormatError(f, f"{where}.file is {name!r}; expected a file name inside the state directory")
        if not isinstance(digest, str) or not _HEX64.fullmatch(digest):
            raise FileFormatError(f, f"{where}.sha256 is {digest!r}; expected 64 hex digits")


def _checked_file(d: Path, entry: dict[str, Any]) -> Path:
    """The state file an entry names, after checking it against the manifest's SHA-256."""
    path = d / entry["file"]
    if not path.exists():
        raise FileFormatError(path, "named by state.json but missing; the state is damaged")
    got = stored_file_sha256(path)
    if got != entry["sha256"]:
        raise FileFormatError(path, f"SHA-256 {got[:12]}... differs from state.json's {entry['sha256'][:12]}...; "
                                    "the state is damaged")
    return path


def load_state(directory: str | os.PathLike[str]) -> State | None:
    """The state manifest in ``directory`` (None if there is none), validated."""
    d = Path(directory)
    f = d / "state.json"
    if not f.exists():
        return None
    try:
        meta = json.loads(f.read_text())
    except json.JSONDecodeError as exc:
        raise FileFormatError(f, f"invalid JSON ({exc.msg}); the state is damaged") from exc
    if isinstance(meta, dict) and meta.get("version") != STATE_VERSION:
        raise FileFormatError(f, f"state version {meta.get('version')!r}; expected {STATE_VERSION} (version 1 states "
                                 "hold camera corrections in the retired T_ic = Rz(delta) Ry(beta) convention, version 2 "
                                 "states name no file by digest; start a new state)")
    _check_manifest(f, meta)
    return State(d, meta)


@contextlib.contextmanager
def _state_lock(d: Path) -> Any:
    """Hold ``STATE/.lock`` exclusively for the duration of an update."""
    import fcntl

    created = not d.exists()
    d.mkdir(parents=True, exist_ok=True)
    fh = open(d / ".lock", "a+")
    locked = False
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            locked = True
        except OSError as exc:
            raise InputError("STATE", str(d), "a state no other update is using (another update holds its lock)") from exc
        yield
    finally:
        if locked and created and not (d / "state.json").exists():
            # a first update that failed leaves nothing behind (not even the lock or the directory)
            shutil.rmtree(d, ignore_errors=True)
        fh.close()


def _collect_garbage(d: Path, meta: dict[str, Any]) -> None:
    """Remove state files the manifest does not name (left by earlier updates or by crashes)."""
    keep = {d / e["file"] for e in meta["passes"]} | ({d / meta["estimate"]["file"]} if meta["estimate"] else set())
    for p in [*d.glob("estimate-*.h5"), *d.glob(".estimate*"), *d.glob(".*.tmp"), *(d / "passes").glob("*.h5"),
              *(d / "passes").glob(".*.tmp")]:
        if p not in keep:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()


def _store_by_digest(src: Path, d: Path, stem: str) -> dict[str, str]:
    """Copy (or move, for our own temporaries) a misrgraph file into the state as
    ``<stem>-<sha12>.h5``, durably; returns its manifest entry."""
    digest = stored_file_sha256(src)
    rel = f"{stem}-{digest[:12]}.h5"
    target = d / rel
    if src.parent == target.parent and src.name.startswith("."):
        os.replace(src, target)
        fsync_directory(target.parent)
    else:
        with atomic_file(target, binary=True) as out, open(src, "rb") as inp:
            shutil.copyfileobj(inp, out)
    return {"file": rel, "sha256": digest}


def _save_estimate(path: Path, values: gtsam.Values) -> None:
    keys = np.array([int(k) for k in values.keys()], np.uint64)
    vecs = [np.asarray(values.atVector(int(k))) for k in keys]
    dims = np.array([v.size for v in vecs], np.int64)
    with atomic_h5(path, "update_state") as f:
        write_dataset(f, "keys", keys)
        write_dataset(f, "dims", dims)
        write_dataset(f, "values", np.concatenate(vecs) if vecs else np.zeros(0))


def _load_estimate(path: Path) -> gtsam.Values:
    out = gtsam.Values()
    if not path.exists():
        return out
    with open_h5(path, "update_state") as f:
        keys = read_dataset(f, "keys", (None,), dtype=np.uint64)
        dims = read_dataset(f, "dims", (keys.size,), dtype=np.int64)
        vals = read_dataset(f, "values", (int(dims.sum()),))
    for k, v in zip(keys, np.split(vals, np.cumsum(dims)[:-1])):
        out.insert(int(k), v)
    return out


def run_update(
    state_dir: str | os.PathLike[str],
    new_passes: list[str | os.PathLike[str]],
    camera_model: str | os.PathLike[str] | None = None,
    gcp_file: str | os.PathLike[str] | None = None,
    dem_file: str | os.PathLike[str] | None = None,
    cfg: AdjustConfig = AdjustConfig(),
    compare_batch: bool = False,
    progress: Callable[[str], None] | None = None,
    crash_before_commit: bool = False,
    report: str | None = None,
    linearization_tol: float | None = None,
) -> dict[str, Any]:
    """Add passes to a persistent state and re-solve incrementally; summary of each new pass.

    The first call creates the state and needs ``camera_model`` and ``gcp_file`` (and optionally
    ``dem_file``); later calls reuse what the state names. ``report`` names an earlier pass whose
    error models, marginals and scores (from the current estimate) are returned under
    ``"report"``. ``crash_before_commit`` (tests only) raises after the work is done but before
    ``state.json`` is replaced. ``linearization_tol`` (sigma units, default
    :data:`DEFAULT_LINEARIZATION_TOL`): see :class:`IncrementalSolver`.
    """
    d = Path(state_dir)
    with _state_lock(d):
        return _run_update_locked(d, new_passes, camera_model, gcp_file, dem_file, cfg, compare_batch, progress,
                                  crash_before_commit, report, linearization_tol)


def _run_update_locked(
    d: Path, new_passes: list[str | os.PathLike[str]], camera_model: str | os.PathLike[str] | None,
    gcp_file: str | os.PathLike[str] | None, dem_file: str | os.PathLike[str] | None, cfg: AdjustConfig,
    compare_batch: bool, progress: Callable[[str], None] | None, crash_before_commit: bool, report: str | None,
    linearization_tol: float | None,
) -> dict[str, Any]:
    state = load_state(d)
    if state is None:
        if camera_model is None or gcp_file is None:
            raise InputError("--camera-model/--gcps", None, "both, when creating a new state")
        (d / "passes").mkdir(parents=True, exist_ok=True)
        specs = {"camera_model": _model_spec(camera_model), "gcps": str(Path(gcp_file).resolve()),
                 "dem": str(Path(dem_file).resolve()) if dem_file else None}
        for key, flag in zip(_INPUTS, ("--camera-model", "--gcps", "--dem")):
            spec = specs[key]
            if spec is not None and not _is_builtin(key, spec) and not Path(spec).is_file():
                raise InputError(flag, spec, "an existing file")
        meta = {"version": STATE_VERSION, "software": f"misrgraph {__version__}", **specs,
                "input_sha256": {k: _input_sha256(v, k) for k, v in specs.items() if v is not None},
                "config": dataclasses.asdict(cfg), "estimate": None, "passes": []}
        state = State(d, meta)
    meta = state.meta
    for key in _INPUTS:  # the inputs must be the ones the state was built on
        if meta.get(key) is None:
            continue
        if not _is_builtin(key, meta[key]) and not Path(meta[key]).is_file():
            raise InputError(key, meta[key], "the file this state was created with (it is missing)")
        now = _input_sha256(meta[key], key)
        if now != meta["input_sha256"][key]:
            raise InputError(key, meta[key], f"the input this state was created with (SHA-256 "
                                             f"{meta['input_sha256'][key][:12]}...; it is now {now[:12]}...: restore it "
                                             "or start a new state)")
    cfg = AdjustConfig.from_dict({k: tuple(v) if isinstance(v, list) else v for k, v in meta["config"].items()})
    camera = load_camera_model(meta["camera_model"])
    if not isinstance(camera, CameraModel):
        raise InputError("--camera-model", meta["camera_model"], "a single-temperature camera model (not a temperature table)")
    gcps = GcpDatabase.load(meta["gcps"])
    dem = DemTiles.load(meta["dem"]) if meta.get("dem") else None
    solver = IncrementalSolver(camera, gcps, dem, cfg, DEFAULT_LINEARIZATION_TOL if linearization_tol is None else linearization_tol)
    # replay the state (warm start from the saved estimate), in one update
    old = [OrbitPass.load(_checked_file(d, p)) for p in meta["passes"]]
    for p, entry in zip(old, meta["passes"]):
        if p.pass_id != entry["pass_id"]:
            raise FileFormatError(d / entry["file"], f"holds pass {p.pass_id!r}; state.json says {entry['pass_id']!r}")
    if old:
        if progress:
            progress(f"restoring {len(old)} passes")
        excl = []
        for p, entry in zip(old, meta["passes"]):
            e = np.zeros(len(p.observations), bool)
            e[np.asarray(entry.get("rejected_indices", []), dtype=np.int64)] = True
            excl.append(e)
        warm = _load_estimate(_checked_file(d, meta["estimate"])) if meta["estimate"] else gtsam.Values()
        solver.add_passes(old, excl, warm)
    summaries = []
    added = []
    for f in new_passes:
        p = OrbitPass.load(f)
        if p.pass_id in state.pass_ids or p.pass_id in [a["pass_id"] for a in added]:
            summaries.append({"pass_id": p.pass_id, "status": "already in the state; not added again"})
            continue
        if progress:
            progress(f"pass {p.pass_id}: blunder screening")
        rejected, norms = find_blunders(p, camera, dem, gcps, cfg)
        if progress:
            progress(f"pass {p.pass_id}: iSAM2 update")
        seconds = solver.add_passes([p], [rejected])
        idx = len(solver.graphs) - 1
        res = solver.pass_result(idx, seconds)
        res.rejected_norm = norms[res.rejected]
        s = {"pass_id": p.pass_id, "status": "added", "update_seconds": seconds, "relinearization_rounds": solver.last_rounds,
             "linearization_error_sigma": solver.last_linearization_error,
             "passes_in_state": len(solver.passes), "knots": {a: {"kept": int(res.attitude.knot_times[i].size),
                                                                  "removed": int(res.pass_graph.removed_knots[i].size)}
                                                              for i, a in enumerate(ANGLES)},
             "rejected_observations": int(res.rejected.size), "iterations": solver.last_rounds, "final_cost": res.final_cost}
        s.update(score_pass(p, res, camera, whole_state=False))
        if compare_batch:
            prob, bres, bsec = batch_solution(solver)
            from misrgraph.estimate.solver import marginal_covariances

            m = None
            try:
                m = marginal_covariances(prob, bres.values)
            except Exception:  # pragma: no cover - fall back to iSAM2's sigma
                m = None
            worst = 0.0
            for k in prob.dims:
                sig = np.sqrt(np.diag(m[k])) if m is not None else np.sqrt(np.diag(solver.isam.marginalCovariance(k)))
                worst = max(worst, float(np.max(np.abs(solver.estimate.atVector(k) - bres.values.atVector(k)) / sig)))
            s["batch"] = {"seconds": bsec, "ratio_update_over_batch": seconds / bsec, "max_difference_in_sigma": worst}
        summaries.append(s)
        entry = _store_by_digest(Path(f), d, f"passes/{p.pass_id}")
        added.append({"pass_id": p.pass_id, **entry, "rejected_indices": [int(i) for i in np.flatnonzero(rejected)]})
    out: dict[str, Any] = {}
    if report is not None:
        ids = [p.pass_id for p in solver.passes]
        if report not in ids:
            raise InputError("--report", report, ids or "a pass id already in the state")
        i = ids.index(report)
        res = solver.pass_result(i)
        rep = {"pass_id": report, "knots": {a: {"kept": int(res.attitude.knot_times[j].size),
                                                "removed": int(res.pass_graph.removed_knots[j].size)} for j, a in enumerate(ANGLES)},
               "ephemeris": {"params": res.ephemeris.params.tolist(),
                             "sigma": [np.sqrt(np.diag(res.marginals[k])).tolist() for k in res.pass_graph.ephemeris_keys()]},
               "attitude_knot_sigma_arcsec": {a: [float(np.sqrt(res.marginals[k][0, 0]) / ARCSEC) for k in res.pass_graph.knot_keys(j)]
                                              for j, a in enumerate(ANGLES)}}
        rep.update(score_pass(solver.passes[i], res, camera, whole_state=False))
        out["report"] = rep
    if added or not (d / "state.json").exists():
        tmp = d / f".estimate.{os.getpid()}.h5"
        _save_estimate(tmp, solver.estimate)
        new_meta = {**meta, "estimate": _store_by_digest(tmp, d, "estimate"), "passes": meta["passes"] + added}
        if crash_before_commit:
            raise RuntimeError("simulated crash before the state was committed")
        _write_json_atomic(d / "state.json", new_meta)  # the commit point
        meta = new_meta
        _collect_garbage(d, meta)
    return {"state": str(d), "passes_in_state": len(meta["passes"]), "updates": summaries, **out}
