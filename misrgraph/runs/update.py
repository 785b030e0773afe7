"""``run_update``: add orbit passes to a persistent state and re-solve incrementally (the action
behind ``misrgraph update``), with the state's files and their integrity.

The estimate is :class:`misrgraph.estimate.incremental.IncrementalSolver`'s, which never sees truth;
a simulated pass's summary adds the scores of :mod:`misrgraph.evaluate.score`.

Persistent state (directory ``STATE``)::

    STATE/state.json                    the manifest: inputs (camera model, GCPs, DEM) with their
                                        SHA-256, config, the observation set ("simulated", or
                                        "matched": what 'misrgraph match' measured in each pass's
                                        imagery), the estimate file and the ordered passes, each
                                        named with its SHA-256
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gtsam
import numpy as np

from misrgraph import __version__
from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.adjust import AdjustConfig, AdjustResult, find_blunders, tie_point_terms
from misrgraph.estimate.incremental import DEFAULT_LINEARIZATION_TOL, IncrementalSolver, batch_solution
from misrgraph.evaluate.score import score_pass
from misrgraph.io.camera import is_builtin_model, load_camera_model
from misrgraph.io.cgm import is_cgm_store, open_store
from misrgraph.io.dem import read_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.h5 import (
    atomic_file,
    atomic_h5,
    fsync_directory,
    open_h5,
    read_attr,
    read_dataset,
    stored_file_sha256,
    write_dataset,
)
from misrgraph.io.imagery import OBSERVATION_SETS
from misrgraph.io.passes import PASS_ID_PATTERN
from misrgraph.io.truth import load_pass_observations
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import ANGLES, ARCSEC
from misrgraph.runs.adjust import camera_prior_of, matched_tie_offset
from misrgraph.runs.cgm import resolve_for_passes

__all__ = ["run_update", "load_state", "restore_state", "State"]

log = logging.getLogger(__name__)


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
    return what == "camera_model" and is_builtin_model(spec)


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
            raise FileFormatError(
                f, f"input_sha256.{key} is {sha.get(key) if isinstance(sha, dict) else sha!r}; expected 64 hex digits"
            )
    if meta.get("observations", "simulated") not in OBSERVATION_SETS:
        raise FileFormatError(f, f"observations is {meta['observations']!r}; expected one of {OBSERVATION_SETS}")
    files = [("estimate", meta["estimate"])] if meta["estimate"] is not None else []
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
        raise FileFormatError(
            path, f"SHA-256 {got[:12]}... differs from state.json's {entry['sha256'][:12]}...; the state is damaged"
        )
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
        raise FileFormatError(
            f,
            f"state version {meta.get('version')!r}; expected {STATE_VERSION} (version 1 states "
            "hold camera corrections in the retired T_ic = Rz(delta) Ry(beta) convention, version 2 "
            "states name no file by digest; start a new state)",
        )
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
            raise InputError(
                "STATE", str(d), "a state no other update is using (another update holds its lock)"
            ) from exc
        yield
    finally:
        if locked and created and not (d / "state.json").exists():
            # a first update that failed leaves nothing behind (not even the lock or the directory)
            shutil.rmtree(d, ignore_errors=True)
        fh.close()


def _collect_garbage(d: Path, meta: dict[str, Any]) -> None:
    """Remove state files the manifest does not name (left by earlier updates or by crashes)."""
    keep = {d / e["file"] for e in meta["passes"]} | ({d / meta["estimate"]["file"]} if meta["estimate"] else set())
    for p in [
        *d.glob("estimate-*.h5"),
        *d.glob(".estimate*"),
        *d.glob(".*.tmp"),
        *(d / "passes").glob("*.h5"),
        *(d / "passes").glob(".*.tmp"),
    ]:
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


def _restore(
    d: Path, meta: dict[str, Any], linearization_tol: float | None, progress: Callable[[str], None] | None
) -> tuple[IncrementalSolver, CameraModel, list[Path]]:
    """The solver of a state with its passes replayed (warm from the saved estimate, one update),
    its camera model and its pass files; the inputs are checked against the state's digests."""
    for key in _INPUTS:  # the inputs must be the ones the state was built on
        if meta.get(key) is None:
            continue
        if not _is_builtin(key, meta[key]) and not Path(meta[key]).is_file():
            raise InputError(key, meta[key], "the file this state was created with (it is missing)")
        now = _input_sha256(meta[key], key)
        if now != meta["input_sha256"][key]:
            raise InputError(
                key,
                meta[key],
                f"the input this state was created with (SHA-256 "
                f"{meta['input_sha256'][key][:12]}...; it is now {now[:12]}...: restore it "
                "or start a new state)",
            )
    conf = dict(meta["config"])
    if "graph" not in conf:
        # a state whose settings are flat predates settings it does not name and keeps the
        # behaviour it was created with: the raw DEM (no low-pass) and the per-camera prior
        conf.setdefault("dem_smoothing_postings", 0.0)
        conf.setdefault("camera_prior_from_calibration", False)
    cfg = AdjustConfig.from_dict(conf)
    camera = load_camera_model(meta["camera_model"])
    if not isinstance(camera, CameraModel):
        raise InputError(
            "--camera-model", meta["camera_model"], "a single-temperature camera model (not a temperature table)"
        )
    gcps = read_gcp_database(meta["gcps"])
    dem = read_dem(meta["dem"]) if meta.get("dem") else None
    solver = IncrementalSolver(
        camera,
        gcps,
        dem,
        cfg,
        DEFAULT_LINEARIZATION_TOL if linearization_tol is None else linearization_tol,
        camera_prior=camera_prior_of(meta["camera_model"], cfg),
    )
    # replay the state (warm start from the saved estimate), in one update
    files = [_checked_file(d, p) for p in meta["passes"]]
    old = [load_pass_observations(f, _observation_set(meta))[0] for f in files]
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
    return solver, camera, files


def _pass_orbit(f: str | os.PathLike[str]) -> int:
    """The orbit number of a pass file (its root attribute)."""
    with open_h5(f, "orbit_pass") as h:
        return int(read_attr(h, "orbit"))


def _observation_set(meta: dict[str, Any]) -> str:
    """The observation set a state adjusts (states from before the field existed: "simulated")."""
    return str(meta.get("observations", "simulated"))


def _fit_noise(
    solver: IncrementalSolver,
    files: list[Path],
    camera: CameraModel,
    observations: str,
    out: str | os.PathLike[str],
    progress: Callable[[str], None] | None,
) -> dict[str, Any]:
    """The noise levels learned from every pass of the state (``run_update``'s ``noise_fit``)."""
    from misrgraph.io.noise import SECTIONS
    from misrgraph.model.noise import NoiseModel
    from misrgraph.runs.noise import fit_and_save, pass_levels_of

    if not solver.passes:
        raise InputError("--noise-fit", str(out), "a state holding at least one pass")
    levels = []
    for i, p in enumerate(solver.passes):
        if progress:
            progress(f"noise fit: pass {i + 1}/{len(solver.passes)}")
        res = _pass_result(solver, i, files[i], camera, observations)
        levels.append(pass_levels_of(res, solver.cfg.graph, p.pass_id))
    base = NoiseModel.from_graph(solver.cfg.graph)
    return fit_and_save(levels, out, base, {s: "input" for s in SECTIONS})


def _pass_result(
    solver: IncrementalSolver, index: int, pass_file: Path, camera: CameraModel, observations: str, seconds: float = 0.0
) -> AdjustResult:
    """Pass ``index``'s error models and marginals from the solver's current estimate. With
    matched observations its tie landmarks' covariances also carry the shared height error and
    the conjugates' shared offset, as ``adjust --observations matched`` adds them
    (:func:`misrgraph.estimate.adjust.tie_point_terms`, the solver's config, on the pass's
    standalone graph at the joint estimate, :meth:`IncrementalSolver.standalone_graph`: the height
    error estimated from its DEM residuals and redundancy numbers, the offset as ``misrgraph
    match`` measured it for the pass)."""
    res = solver.pass_result(index, seconds)
    if observations == "matched":
        s_o, own = matched_tie_offset(pass_file)
        res.tie_height, res.tie_offset, res.landmark_extra_cov = tie_point_terms(
            solver.passes[index],
            camera,
            solver.standalone_graph(index),
            res.values,
            res.marginals,
            solver.cfg,
            True,
            s_o,
            own,
        )
    return res


def restore_state(
    state_dir: str | os.PathLike[str], progress: Callable[[str], None] | None = None
) -> tuple[IncrementalSolver, CameraModel, list[Path]]:
    """Read-only: the solver of the update state in ``state_dir`` with every pass replayed, its
    camera model and its (digest-checked) pass files, for products and reports."""
    d = Path(state_dir)
    if not (d / "state.json").is_file():
        raise InputError("STATE_DIR", str(d), "a directory written by 'misrgraph update' (it holds state.json)")
    with _state_lock(d):
        state = load_state(d)
        assert state is not None
        return _restore(d, state.meta, None, progress)


def run_update(
    state_dir: str | os.PathLike[str],
    new_passes: list[str | os.PathLike[str]],
    camera_model: str | os.PathLike[str] | None = None,
    gcp_file: str | os.PathLike[str] | None = None,
    dem_file: str | os.PathLike[str] | None = None,
    cfg: AdjustConfig | None = None,
    compare_batch: bool = False,
    progress: Callable[[str], None] | None = None,
    crash_before_commit: bool = False,
    report: str | None = None,
    linearization_tol: float | None = None,
    observations: str | None = None,
    noise_fit: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Add passes to a persistent state and re-solve incrementally; summary of each new pass.

    The first call creates the state and needs ``camera_model`` and ``gcp_file`` (and optionally
    ``dem_file``); later calls reuse what the state names. ``observations``: the set every pass of
    the state is adjusted with, fixed when the state is created (default ``"simulated"``, the
    pass's own; ``"matched"``, what ``misrgraph match`` measured in its imagery, with the tie
    points' height and offset terms in their covariance as ``adjust`` adds them); a later call
    may repeat it but not change it. ``report`` names an earlier pass whose
    error models, marginals and scores (from the current estimate) are returned under
    ``"report"``. ``crash_before_commit`` (tests only) raises after the work is done but before
    ``state.json`` is replaced. ``cfg``: the adjustment settings of a new state (default
    :class:`AdjustConfig`'s); a state keeps the settings it was created with, and another ``cfg``
    for it is refused. ``linearization_tol`` (sigma units, default
    :data:`DEFAULT_LINEARIZATION_TOL`): see :class:`IncrementalSolver`. ``noise_fit``: after the
    update, learn the noise levels from every pass of the state at the current estimate (the
    attitude and ephemeris priors' marginal likelihood, :func:`misrgraph.runs.noise.fit_and_save`;
    ``update`` keeps the stated sigmas, so the observation scales are not fitted) and write them
    to this noise-model file, the state's own levels kept for what the passes do not carry. The
    state keeps the levels it was created with; the file is for the next state, ``adjust`` or
    ``campaign`` (``--noise-model``). Its summary is returned under ``"noise_fit"``.
    """
    d = Path(state_dir)
    with _state_lock(d):
        return _run_update_locked(
            d,
            new_passes,
            camera_model,
            gcp_file,
            dem_file,
            cfg,
            compare_batch,
            progress,
            crash_before_commit,
            report,
            linearization_tol,
            observations,
            noise_fit,
        )


def _run_update_locked(
    d: Path,
    new_passes: list[str | os.PathLike[str]],
    camera_model: str | os.PathLike[str] | None,
    gcp_file: str | os.PathLike[str] | None,
    dem_file: str | os.PathLike[str] | None,
    cfg: AdjustConfig | None,
    compare_batch: bool,
    progress: Callable[[str], None] | None,
    crash_before_commit: bool,
    report: str | None,
    linearization_tol: float | None,
    observations: str | None,
    noise_fit: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    if observations is not None and observations not in OBSERVATION_SETS:
        raise InputError("--observations", observations, OBSERVATION_SETS)
    state = load_state(d)
    if state is None:
        if camera_model is None or gcp_file is None:
            raise InputError("--camera-model/--gcps", None, "both, when creating a new state")
        cam_spec, cgm = (
            resolve_for_passes(camera_model, [_pass_orbit(f) for f in new_passes])
            if is_cgm_store(camera_model)
            else (camera_model, None)
        )
        (d / "passes").mkdir(parents=True, exist_ok=True)
        specs = {
            "camera_model": _model_spec(cam_spec),
            "gcps": str(Path(gcp_file).resolve()),
            "dem": str(Path(dem_file).resolve()) if dem_file else None,
        }
        for key, flag in zip(_INPUTS, ("--camera-model", "--gcps", "--dem")):
            spec = specs[key]
            if spec is not None and not _is_builtin(key, spec) and not Path(spec).is_file():
                raise InputError(flag, spec, "an existing file")
        meta = {
            "version": STATE_VERSION,
            "software": f"misrgraph {__version__}",
            **specs,
            "input_sha256": {k: _input_sha256(v, k) for k, v in specs.items() if v is not None},
            "config": dataclasses.asdict(cfg or AdjustConfig()),
            "observations": observations or "simulated",
            "estimate": None,
            "passes": [],
        }
        if cgm is not None:  # the state's passes must stay in this version's range
            meta["cgm"] = {
                "store": str(Path(camera_model).resolve()),
                **{k: cgm[k] for k in ("id", "first_orbit", "last_orbit")},
            }  # the range as added; the store's current range wins while the store is there
        state = State(d, meta)
    meta = state.meta
    if cfg is not None and json.dumps(dataclasses.asdict(cfg), sort_keys=True) != json.dumps(
        meta["config"], sort_keys=True
    ):
        raise InputError(
            "--config",
            "settings that differ from the state's",
            "the settings the state was created with (a state keeps them; start a new state for others)",
        )
    obs_set = _observation_set(meta)
    if observations is not None and observations != obs_set:
        raise InputError(
            "--observations",
            observations,
            f"{obs_set!r}, the observation set this state adjusts (a state keeps one; start a new state for the other)",
        )
    if meta.get("cgm"):
        v = dict(meta["cgm"])
        if is_cgm_store(v["store"]):  # a later version may have closed this one's range
            now = open_store(v["store"]).get(v["id"])
            v.update(first_orbit=now.first_orbit, last_orbit=now.last_orbit)
        for f in new_passes:
            o = _pass_orbit(f)
            if o < v["first_orbit"] or (v["last_orbit"] is not None and o > v["last_orbit"]):
                last = "" if v["last_orbit"] is None else v["last_orbit"]
                raise InputError(
                    "PASS",
                    f"{f} (orbit {o})",
                    f"a pass of orbits {v['first_orbit']}-{last}, the range of camera-model version {v['id']} "
                    f"this state adjusts with (start a new state for the other version of {v['store']})",
                )
    solver, camera, files = _restore(d, meta, linearization_tol, progress)
    summaries = []
    added = []
    for f in new_passes:
        p, truth = load_pass_observations(f, obs_set)
        if p.pass_id in state.pass_ids or p.pass_id in [a["pass_id"] for a in added]:
            summaries.append({"pass_id": p.pass_id, "status": "already in the state; not added again"})
            continue
        if progress:
            progress(f"pass {p.pass_id}: blunder screening")
        rejected, norms = find_blunders(p, camera, solver.dem, solver.gcps, solver.cfg, solver.camera_prior)
        if progress:
            progress(f"pass {p.pass_id}: iSAM2 update")
        seconds = solver.add_passes([p], [rejected])
        idx = len(solver.graphs) - 1
        res = _pass_result(solver, idx, Path(f), camera, obs_set, seconds)
        res.rejected_norm = norms[res.rejected]
        s = {
            "pass_id": p.pass_id,
            "status": "added",
            "update_seconds": seconds,
            "relinearization_rounds": solver.last_rounds,
            "linearization_error_sigma": solver.last_linearization_error,
            "passes_in_state": len(solver.passes),
            "knots": {
                a: {"kept": int(res.attitude.knot_times[i].size), "removed": int(res.pass_graph.removed_knots[i].size)}
                for i, a in enumerate(ANGLES)
            },
            "rejected_observations": int(res.rejected.size),
            "iterations": solver.last_rounds,
            "final_cost": res.final_cost,
            "observation_set": obs_set,
            "tie_height": res.tie_height,
            "tie_offset": res.tie_offset,
        }
        if truth is not None:
            s.update(score_pass(p, truth, res, camera, whole_state=False))
        if compare_batch:
            prob, bres, bsec = batch_solution(solver)
            from misrgraph.estimate.problem import marginal_covariances

            m = None
            try:
                m = marginal_covariances(prob, bres.values)
            except Exception:  # pragma: no cover - fall back to iSAM2's sigma
                m = None
            worst = 0.0
            for k in prob.dims:
                sig = np.sqrt(np.diag(m[k])) if m is not None else np.sqrt(np.diag(solver.marginal_covariance(k)))
                worst = max(worst, float(np.max(np.abs(solver.estimate.atVector(k) - bres.values.atVector(k)) / sig)))
            s["batch"] = {"seconds": bsec, "ratio_update_over_batch": seconds / bsec, "max_difference_in_sigma": worst}
        summaries.append(s)
        entry = _store_by_digest(Path(f), d, f"passes/{p.pass_id}")
        added.append({"pass_id": p.pass_id, **entry, "rejected_indices": [int(i) for i in np.flatnonzero(rejected)]})
        files.append(d / entry["file"])
    out: dict[str, Any] = {}
    if report is not None:
        ids = [p.pass_id for p in solver.passes]
        if report not in ids:
            raise InputError("--report", report, ids or "a pass id already in the state")
        i = ids.index(report)
        res = _pass_result(solver, i, files[i], camera, obs_set)
        rep = {
            "pass_id": report,
            "knots": {
                a: {"kept": int(res.attitude.knot_times[j].size), "removed": int(res.pass_graph.removed_knots[j].size)}
                for j, a in enumerate(ANGLES)
            },
            "ephemeris": {
                "params": res.ephemeris.params.tolist(),
                "sigma": [np.sqrt(np.diag(res.marginals[k])).tolist() for k in res.pass_graph.ephemeris_keys()],
            },
            "attitude_knot_sigma_arcsec": {
                a: [float(np.sqrt(res.marginals[k][0, 0]) / ARCSEC) for k in res.pass_graph.knot_keys(j)]
                for j, a in enumerate(ANGLES)
            },
            "observation_set": obs_set,
            "tie_height": res.tie_height,
            "tie_offset": res.tie_offset,
        }
        truth = load_pass_observations(files[i], obs_set)[1]
        if truth is not None:
            rep.update(score_pass(solver.passes[i], truth, res, camera, whole_state=False))
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
    if noise_fit is not None:
        out["noise_fit"] = _fit_noise(solver, files, camera, obs_set, noise_fit, progress)
    return {
        "state": str(d),
        "passes_in_state": len(meta["passes"]),
        "observation_set": obs_set,
        "updates": summaries,
        **out,
    }
