"""``run_campaign``: the calibration campaign as one call (the action behind ``misrgraph campaign``).

Stages, as a task graph on Dask (:mod:`dask.distributed`)::

    inputs      the GCP month and each path's chosen repeat passes (simulated, or the user's)
    calibration the cameras, on the GCP month (one task; over years, one per window)
    versions    over years: the calibrations watched, camera-model versions by orbit range
                (:mod:`misrgraph.campaign.years`)
    noise       with ``noise_fit_passes``: the noise levels learned on the first passes adjusted
                (``misrgraph noise fit``), then used for every other pass and path
    adjust      every chosen pass with the calibrated model (one task a pass; the graph is built
                and solved on the worker)
    path        per path, the incremental state over its passes and its Projection Parameters
    report      campaign.md with tables and plots, and summary.json (here, in the client)

By default a ``LocalCluster`` of ``workers`` processes (one thread each; ``None``: one per core)
is started in this process; ``scheduler="tcp://HOST:PORT"`` uses a cluster the user started
(``dask scheduler``, ``dask worker``), whose workers must see ``out`` at the same path (a shared
filesystem); ``workers=0`` runs every task here, in order, without Dask (the reference the
cluster's results are compared with).

Resumable and exactly-once: every output is named by a digest of its inputs and configuration and
written atomically (:mod:`misrgraph.campaign.tasks`); a rerun with the same options skips what is
done and computes the rest. The summary counts planned passes, each once, whatever the number of
reruns or task retries. ``OUT/.campaign.lock`` keeps two clients off one directory.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import re
import shutil
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

import misrgraph.campaign.tasks as tasks
from misrgraph.campaign.plan import CampaignConfig, CampaignPlan, PathPlan, choose, digest, plan_campaign
from misrgraph.campaign.report import write_report
from misrgraph.errors import InputError, require_extra
from misrgraph.io.h5 import atomic_file

__all__ = [
    "run_campaign",
    "campaign_fingerprint",
    "campaign_difference",
    "plan_from_inputs",
    "PLAN_FILE",
    "SUMMARY_FILE",
]

log = logging.getLogger(__name__)

PLAN_FILE = "campaign.json"
SUMMARY_FILE = "summary.json"

Progress = Callable[[int, int, str], None]


# ---------------------------------------------------------------------------- executors
class _Lazy:
    """A task of the in-process executor: run on first ``result()`` (dependencies first)."""

    def __init__(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        self.fn, self.args, self._done, self._value = fn, args, False, None

    def result(self) -> Any:
        if not self._done:
            self._value = self.fn(*[a.result() if isinstance(a, _Lazy) else a for a in self.args])
            self._done = True
        return self._value


class _InProcess:
    """``workers=0``: every task in this process, in submission order (which is topological)."""

    def submit(self, fn: Callable[..., Any], *args: Any, key: str | None = None, priority: int = 0) -> _Lazy:
        return _Lazy(fn, args)

    def as_completed(self, futures: list[_Lazy]) -> Iterator[_Lazy]:
        for f in futures:
            f.result()
            yield f

    def describe(self) -> dict[str, Any]:
        return {"kind": "in-process (no Dask)", "workers": 0}

    def peak_rss_mb(self) -> dict[str, float]:
        return {"this process": _peak_rss_mb()}


class _Dask:
    def __init__(self, client: Any, owned: list[Any]) -> None:
        self.client, self.owned = client, owned

    def submit(self, fn: Callable[..., Any], *args: Any, key: str | None = None, priority: int = 0) -> Any:
        return self.client.submit(fn, *args, key=key, pure=False, priority=priority)

    def as_completed(self, futures: list[Any]) -> Iterator[Any]:
        from distributed import as_completed

        yield from as_completed(futures)

    def describe(self) -> dict[str, Any]:
        info = self.client.scheduler_info()
        return {
            "kind": "dask",
            "scheduler": self.client.scheduler.address,
            "workers": len(info.get("workers", {})),
            "dashboard": self.client.dashboard_link if _has_dashboard() else None,
        }

    def peak_rss_mb(self) -> dict[str, float]:
        """Peak resident memory of each worker process (MB) over its life (a restarted worker
        starts afresh)."""
        try:
            return {str(k): v for k, v in self.client.run(_peak_rss_mb).items()}
        except Exception:  # pragma: no cover - a worker lost at the very end
            return {}

    def close(self) -> None:
        for o in self.owned:
            with contextlib.suppress(Exception):
                o.close()


def _peak_rss_mb() -> float:
    import resource
    import sys

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return float(rss / 2**20 if sys.platform == "darwin" else rss / 2**10)  # bytes on macOS, KiB on Linux


def _has_dashboard() -> bool:
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return False
    return True


def _executor(workers: int | None, scheduler: str | None, client: Any) -> Any:
    if client is not None:
        return _Dask(client, [])
    if workers == 0 and scheduler is None:
        return _InProcess()
    require_extra("distributed", "campaign", "misrgraph campaign (Dask)")
    from distributed import Client, LocalCluster

    if logging.getLogger().getEffectiveLevel() > logging.INFO:  # Dask's own INFO chatter only with -v
        logging.getLogger("distributed").setLevel(logging.WARNING)

    if scheduler is not None:
        try:
            c = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError("--scheduler", scheduler, f"the address of a running Dask scheduler ({exc})") from None
        return _Dask(c, [c])
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 0:
        raise InputError("--workers", n, "a number of worker processes >= 0 (0: no Dask, this process)")
    cluster = LocalCluster(
        n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.ERROR
    )  # any free port
    c = Client(cluster)
    return _Dask(c, [c, cluster])


# ---------------------------------------------------------------------------- plan
def plan_from_inputs(cfg: CampaignConfig, inputs: Path) -> tuple[CampaignPlan, Path, dict[int, Path]]:
    """The plan over scenario directories the user brought: ``INPUTS/month`` (a ``simulate
    --scenario month`` directory) and ``INPUTS/path_PPP`` (``simulate --scenario path``) for each
    path (all such directories when ``cfg.paths`` is empty); each path's passes are its pass
    files in name order, of which :func:`misrgraph.campaign.plan.choose` picks."""
    month = inputs / "month"
    if not (month / "passes").is_dir():
        raise InputError(
            "--inputs",
            str(inputs),
            "a directory holding month/ (misrgraph simulate --scenario month) and path_PPP/ scenario directories",
        )
    found = {int(p.name[5:]): p for p in sorted(inputs.glob("path_[0-9][0-9][0-9]")) if (p / "passes").is_dir()}
    want = cfg.paths or tuple(sorted(found))
    missing = [p for p in want if p not in found]
    if missing or not want:
        raise InputError("--paths", list(want), f"paths with a scenario in {inputs} (found: {sorted(found) or 'none'})")
    plans = []
    for p in want:
        ids = [f.stem for f in sorted((found[p] / "passes").glob("*.h5"))]
        cyc = choose(len(ids), cfg)
        plans.append(PathPlan(p, len(ids), cyc, tuple(ids[k] for k in cyc)))
    return CampaignPlan(cfg, plans), month, {p: found[p] for p in want}


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    fd = os.open(out / ".campaign.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError("--out", str(out), "a campaign directory no other campaign is running in") from None
        yield
    finally:
        os.close(fd)


def _remove_debris(out: Path) -> int:
    """Hidden temporaries left by killed runs (every reader ignores them); their count."""
    n = 0
    for p in list(out.rglob(".*.tmp")):
        n += 1
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
    return n


# ---------------------------------------------------------------------------- the campaign
def run_campaign(
    out: str | os.PathLike[str],
    cfg: CampaignConfig = CampaignConfig(),
    *,
    inputs: str | os.PathLike[str] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    client: Any = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run (or resume) the campaign into ``out``; return the summary (also ``OUT/summary.json``).

    ``inputs``: scenario directories to use instead of simulating (:func:`plan_from_inputs`).
    ``workers``/``scheduler``/``client``: where the tasks run (module docstring). ``progress(done,
    total, message)`` is called as tasks finish.
    """
    t_start = time.perf_counter()
    out_dir = Path(out).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out", str(out_dir), "a directory (created if missing)")
    out_dir.mkdir(parents=True, exist_ok=True)
    if inputs is not None and cfg.recalibrate_months:
        raise InputError(
            "--inputs", str(inputs), "none with --recalibrate (a campaign over years simulates its windows)"
        )
    if inputs is not None:
        plan, month_dir, path_dirs = plan_from_inputs(cfg, Path(inputs).resolve())
    else:
        plan, month_dir, path_dirs = plan_campaign(cfg), None, {}
    if cfg.noise_fit_passes >= plan.n_passes:
        raise InputError(
            "noise_fit_passes (--noise-fit-passes)",
            cfg.noise_fit_passes,
            f"fewer than the {plan.n_passes} planned passes (the others are adjusted with what they teach)",
        )
    plan_doc = plan.to_dict() | {"inputs": str(Path(inputs).resolve()) if inputs is not None else "simulated"}
    plan_doc["digest"] = digest(plan_doc["config"], plan_doc["inputs"], plan_doc["paths"])
    with _locked(out_dir):
        f = out_dir / PLAN_FILE
        if f.exists():
            old = json.loads(f.read_text())
            if old.get("digest") != plan_doc["digest"]:
                old_cfg = old.get("config") if isinstance(old.get("config"), dict) else {}
                new_cfg = json.loads(json.dumps(plan_doc["config"]))  # as stored (tuples as lists)
                missing = sorted(set(new_cfg) - set(old_cfg))
                if missing and all(old_cfg.get(k) == v for k, v in new_cfg.items() if k in old_cfg):
                    raise InputError(
                        "--out",
                        str(out_dir),
                        "a new directory: the campaign in it was planned by an earlier "
                        f"misrgraph (its plan has no {', '.join(missing)}), whose "
                        "outputs this version does not reuse",
                    )
                raise InputError(
                    "--out",
                    str(out_dir),
                    "a new directory, or the options of the campaign already in it "
                    f"(its plan: {json.dumps(old.get('config'))})",
                )
        else:
            with atomic_file(f) as fh:
                fh.write(json.dumps(plan_doc, indent=2))
        debris = _remove_debris(out_dir)
        ex = _executor(workers, scheduler, client)
        try:
            records, cluster = _execute(ex, plan, str(out_dir), month_dir, path_dirs, progress)
        finally:
            if isinstance(ex, _Dask):
                ex.close()
        summary = _summarise(plan, records, cluster, time.perf_counter() - t_start)
        summary["debris_removed"] = debris
        summary["report"] = str(write_report(out_dir / "report", plan_doc, summary, records))
        with atomic_file(out_dir / SUMMARY_FILE) as fh:
            fh.write(json.dumps(summary, indent=2))
    return summary


def _execute(
    ex: Any, plan: CampaignPlan, out: str, month_dir: Path | None, path_dirs: dict[int, Path], progress: Progress | None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    cfg = plan.config
    run_id = uuid.uuid4().hex[:8]  # task keys unique to this run (a client may run several)
    futs: list[Any] = []
    labels: dict[int, tuple[str, str]] = {}

    def submit(stage: str, name: str, fn: Callable[..., Any], *args: Any, priority: int = 0) -> Any:
        fut = ex.submit(fn, *args, key=f"{stage}-{name}-{run_id}".replace(" ", "_"), priority=priority)
        futs.append(fut)
        labels[len(futs) - 1] = (stage, name)
        return fut

    if month_dir is not None:
        month = submit("inputs", "month", tasks.existing_inputs, "month", str(month_dir), cfg.observations, priority=10)
    else:
        month = submit("inputs", "month", tasks.simulate_month, out, cfg, priority=10)
    noise = None if cfg.noise is None else cfg.noise.to_dict()
    if cfg.recalibrate_months:  # over years: a calibration per window, versions from the monitor
        from misrgraph.campaign.years import window_starts

        cals = [
            submit(
                "calibration", "window 1", tasks.calibrate, out, month, cfg.observations, noise, "window 1", priority=9
            )
        ]
        for w in range(1, len(window_starts(cfg))):
            mw = submit("inputs", f"month {w + 1}", tasks.simulate_month, out, cfg, w, month, priority=10)
            name = f"window {w + 1}"
            cals.append(
                submit("calibration", name, tasks.calibrate, out, mw, cfg.observations, noise, name, priority=9)
            )
        cal = submit("versions", "camera model", tasks.camera_versions, out, cfg, *cals, priority=8)
    else:
        cal = submit("calibration", "month", tasks.calibrate, out, month, cfg.observations, noise, priority=9)
    pins = {}
    for pp in plan.paths:
        if pp.path in path_dirs:
            pins[pp.path] = submit(
                "inputs",
                f"path {pp.path}",
                tasks.existing_inputs,
                f"path {pp.path}",
                str(path_dirs[pp.path]),
                cfg.observations,
            )
        else:
            pins[pp.path] = submit(
                "inputs", f"path {pp.path}", tasks.simulate_path, out, cfg, pp.path, pp.cycles, month, priority=5
            )
    path_of = {pid: pp.path for pp in plan.paths for pid in pp.pass_ids}
    fit_ids = plan.fit_pass_ids()
    learned = noise
    if fit_ids:  # the noise levels learned on the first passes, used for all the others
        fits = [
            submit(
                "adjust", pid, tasks.adjust, out, path_of[pid], pid, pins[path_of[pid]], cal, cfg.observations, noise
            )
            for pid in fit_ids
        ]
        learned = submit("noise", "fit", tasks.fit_noise, out, noise, *fits, priority=7)
    for pp in plan.paths:
        if cfg.products:  # the longest tasks first, so that they do not end the campaign alone
            submit(
                "path",
                f"path {pp.path}",
                tasks.path_products,
                out,
                pp.path,
                pp.pass_ids,
                pins[pp.path],
                cal,
                cfg.blocks,
                cfg.roi,
                cfg.observations,
                learned,
                priority=2,
            )
        for pid in pp.pass_ids:
            if pid not in fit_ids:
                submit("adjust", pid, tasks.adjust, out, pp.path, pid, pins[pp.path], cal, cfg.observations, learned)
    cluster = ex.describe()
    if progress and cluster.get("dashboard"):
        progress(0, len(futs), f"Dask dashboard: {cluster['dashboard']}")
    index = {id(f): i for i, f in enumerate(futs)}
    records: list[dict[str, Any] | None] = [None] * len(futs)
    for n, f in enumerate(ex.as_completed(futs), 1):
        i = index[id(f)]
        stage, name = labels[i]
        try:
            rec = f.result()
        except Exception as exc:  # the task's worker died too often (KilledWorker) or the cluster failed
            rec = {
                "stage": stage,
                "name": name,
                "status": "failed",
                "skipped": False,
                "output": None,
                "seconds": 0.0,
                "reason": f"{exc.__class__.__name__}: {exc}",
            }
        records[i] = rec
        if progress:
            progress(n, len(futs), f"{stage} {name}: {rec['status']}{' (found done)' if rec.get('skipped') else ''}")
    cluster["peak_rss_mb"] = ex.peak_rss_mb()
    cluster["task_pids"] = sorted({int(r["worker_pid"]) for r in records if r is not None and "worker_pid" in r})
    return [r for r in records if r is not None], cluster


def _rms(values: Iterable[float | None]) -> float | None:
    v = np.array([x for x in values if x is not None], float)
    return float(np.sqrt(np.mean(v**2))) if v.size else None


def _roi_entry(path_dir: str, roi: dict[str, Any] | None) -> dict[str, Any] | None:
    """A path's ROI in the campaign summary: its file, blocks and worst co-registration (matched
    on the ROI; and against the truth when simulated), or None when not built."""
    if roi is None:
        return None
    truth = roi.get("truth_px") or {}
    worst_truth = [v for kind in ("between_cameras_px", "between_passes_px") for v in (truth.get(kind) or {}).values()]
    return {
        "file": str(Path(path_dir) / roi["file"]),
        "blocks": roi["blocks"],
        "coregistration_px_max": max(roi["coregistration_px"].values()) if roi["coregistration_px"] else None,
        "truth_coregistration_px_max": max(worst_truth) if worst_truth else None,
    }


def _summarise(
    plan: CampaignPlan, records: list[dict[str, Any]], cluster: dict[str, Any], seconds: float
) -> dict[str, Any]:
    by = {(r["stage"], r["name"]): r for r in records}
    planned = [(pp.path, pid) for pp in plan.paths for pid in pp.pass_ids]
    adj = {pid: by.get(("adjust", pid)) for _, pid in planned}
    done = sorted(pid for pid, r in adj.items() if r and r["status"] == "done")
    failed = [
        {"stage": r["stage"], "name": r["name"], "reason": r.get("reason", "")}
        for r in records
        if r["status"] != "done"
    ]
    cal = by.get(("calibration", "month")) or by.get(("calibration", "window 1"), {})
    cameras: dict[str, dict[str, Any]] = {}
    for pid in done:
        for c, v in (adj[pid]["summary"].get("checkpoint_m") or {}).items():
            e = cameras.setdefault(c, {"passes": 0, "_rms": [], "_pred": [], "_before": []})
            e["passes"] += 1
            e["_rms"].append(v["rms"])
            e["_pred"].append(v.get("predicted_rms"))
            e["_before"].append(v["before_mean"])
    for c, e in cameras.items():
        e["checkpoint_rms_m"] = _rms(e.pop("_rms"))
        e["predicted_rms_m"] = _rms(e.pop("_pred"))
        e["supplied_mean_m"] = float(np.mean(e.pop("_before")))
    paths: dict[str, Any] = {}
    for pp in plan.paths:
        rs = [adj[pid] for pid in pp.pass_ids]
        ok = [r for r in rs if r and r["status"] == "done"]
        cp = [v["rms"] for r in ok for v in (r["summary"].get("checkpoint_m") or {}).values()]
        coreg = [x for r in ok for x in (r["summary"].get("coregistration_px") or {}).values()]
        entry: dict[str, Any] = {
            "passes": {"planned": len(pp.pass_ids), "done": len(ok), "failed": len(rs) - len(ok)},
            "checkpoint_rms_m": _rms(cp),
            "coregistration_px_max": max(coreg) if coreg else None,
            "adjusted": [r["output"] for r in ok],
        }
        pr = by.get(("path", f"path {pp.path}"))
        if pr is not None:
            entry["products"] = (
                {
                    "status": "done",
                    "dir": pr["output"],
                    "pp_error_rms_m": _rms(
                        v["rms"] for v in (pr["summary"]["products"].get("pp_error_m") or {}).values()
                    ),
                    "pp_blocks": pr["summary"]["products"]["blocks"],
                    "roi": _roi_entry(pr["output"], pr["summary"]["products"].get("roi")),
                }
                if pr["status"] == "done"
                else {"status": "failed", "reason": pr.get("reason")}
            )
        paths[str(pp.path)] = entry
    stages: dict[str, Any] = {}
    for r in records:
        s = stages.setdefault(
            r["stage"], {"tasks": 0, "done": 0, "found_done": 0, "failed": 0, "task_seconds": 0.0, "_t": []}
        )
        s["tasks"] += 1
        if "started" in r:
            s["_t"] += [r["started"], r["ended"]]
        s["done" if r["status"] == "done" else "failed"] += 1
        s["found_done"] += int(bool(r.get("skipped")))
        s["task_seconds"] += float(r.get("seconds", 0.0))
    for s in stages.values():  # from the first task's start to the last one's end
        t = s.pop("_t")
        s["wall_seconds"] = float(max(t) - min(t)) if t else 0.0
    return {
        "passes": {"planned": len(planned), "done": len(done), "failed": len(planned) - len(done)},
        "calibration": (
            {"status": "done", "file": cal["output"], **cal["summary"]}
            if cal.get("status") == "done"
            else {"status": "failed", "reason": cal.get("reason")}
        ),
        "cameras": cameras,
        "paths": paths,
        **({"years": _years(plan, by, adj)} if plan.config.recalibrate_months else {}),
        **({"noise_fit": _noise_fit(plan, by)} if plan.config.noise_fit_passes else {}),
        "failed": failed,
        "stages": stages,
        "cluster": cluster,
        "seconds": seconds,
    }


def _noise_fit(plan: CampaignPlan, by: dict[tuple[str, str], Any]) -> dict[str, Any]:
    """The noise levels learned on the campaign's first passes: the file, the passes, each level."""
    rec = by.get(("noise", "fit"))
    if rec is None or rec["status"] != "done":
        return {"status": "failed", "reason": None if rec is None else rec.get("reason")}
    return {"status": "done", "file": rec["output"], "passes": plan.fit_pass_ids(), "levels": rec["summary"]["levels"]}


def _years(plan: CampaignPlan, by: dict[tuple[str, str], Any], adj: dict[str, Any]) -> dict[str, Any]:
    """The campaign over years: the windows, the monitor's alarms, the versions, which version
    each pass was adjusted with, and the stale passes (:mod:`misrgraph.campaign.years`)."""
    from misrgraph.campaign.years import stale_passes

    rec = by.get(("versions", "camera model"))
    if rec is None or rec["status"] != "done":
        return {"status": "failed", "reason": None if rec is None else rec.get("reason")}
    m = rec["summary"]
    used = {
        pid: (r["summary"].get("camera_model_version") or {}).get("id")
        for pid, r in adj.items()
        if r and r["status"] == "done"
    }
    return {
        "status": "done",
        "store": rec["output"],
        "windows": m["windows"],
        "series": m["series"],
        "levels": m["levels"],
        "alarms": m["alarms"],
        "versions": m["versions"],
        "pass_versions": used,
        "stale_passes": stale_passes(plan.config, used, m["alarms"]),
    }


# ---------------------------------------------------------------------------- comparison
def _outputs(out: str | os.PathLike[str]) -> dict[str, Path]:
    """Every HDF5 output of a campaign (calibration, adjusted passes, path states and products),
    keyed by its path relative to ``out`` with the 12-digit digest suffixes taken out (they
    depend on provenance such as the directory)."""
    root = Path(out)
    files = (
        sorted(root.glob("calibration/*.h5"))
        + sorted(root.glob("adjusted/*/*.h5"))
        + sorted(root.glob("paths/*/**/*.h5"))
    )
    return {
        re.sub(r"-[0-9a-f]{12}(?=[./]|$)", "", str(f.relative_to(root))): f
        for f in files
        if not any(part.startswith(".") for part in f.relative_to(root).parts)
    }


def _datasets(f: Path) -> dict[str, Any]:
    import h5py

    found: dict[str, Any] = {}
    with h5py.File(f, "r") as hf:
        hf.visititems(lambda name, obj: found.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return found


def campaign_fingerprint(out: str | os.PathLike[str]) -> dict[str, str]:
    """SHA-256 of every dataset of every output of a campaign (:func:`_outputs` names them);
    attributes (timings, provenance) are left out. Equal fingerprints: the same numbers, bit for bit."""
    fp: dict[str, str] = {}
    for key, f in _outputs(out).items():
        h = hashlib.sha256()
        for name, v in sorted(_datasets(f).items()):
            h.update(name.encode())
            h.update(
                np.ascontiguousarray(v).tobytes()
                if getattr(v, "dtype", None) is not None and v.dtype.kind != "O"
                else repr(np.asarray(v).tolist()).encode()
            )
        fp[key] = h.hexdigest()
    return fp


def campaign_difference(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> dict[str, Any]:
    """How far two campaigns' numbers are apart: ``{"missing": outputs in one only,
    "max_relative": the largest |x - y| / max|x| over every floating-point dataset (scaled by the
    dataset's largest value), "where": its output and dataset, "other": non-float datasets that
    differ}``. A run on Dask workers (one BLAS thread each) and one in this process (several)
    differ by round-off only."""
    oa, ob = _outputs(a), _outputs(b)
    worst, where, other = 0.0, None, []
    for key in sorted(set(oa) & set(ob)):
        da, db = _datasets(oa[key]), _datasets(ob[key])
        for name in sorted(set(da) | set(db)):
            x, y = da.get(name), db.get(name)
            if x is None or y is None or np.shape(x) != np.shape(y):
                other.append(f"{key}:{name}")
                continue
            x, y = np.asarray(x), np.asarray(y)
            if x.dtype.kind == "f":
                scale = float(np.nanmax(np.abs(x))) if x.size and np.isfinite(x).any() else 0.0
                if not np.array_equal(np.isnan(x), np.isnan(y)):
                    other.append(f"{key}:{name} (NaN pattern)")
                    continue
                d = float(np.nanmax(np.abs(x - y))) / scale if scale > 0 else 0.0
                if d > worst:
                    worst, where = d, f"{key}:{name}"
            elif x.tolist() != y.tolist():
                other.append(f"{key}:{name}")
    return {"missing": sorted(set(oa) ^ set(ob)), "max_relative": worst, "where": where, "other": other}
