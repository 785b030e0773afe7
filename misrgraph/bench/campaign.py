"""Benchmarks and fault trials of ``misrgraph campaign``.

* :func:`run_bench_campaign`: throughput (passes per minute) of the adjustment stage on a
  ``LocalCluster`` of 1 and of 2 workers on the same passes (the inputs and the calibration are
  prepared once and found done by both runs, so only the per-pass work is timed), the scaling
  ratio, the peak memory per worker, and an estimate of the full plan (233 paths, six months,
  30 %) from the measured rates.
* :func:`run_campaign_kill_trials`: the campaign killed at random points and resumed. ``client``
  trials SIGKILL the whole ``misrgraph campaign`` process group (client, scheduler, nannies and
  workers: what a lost job or machine does) at a time drawn uniformly over an uninterrupted
  run, then rerun the command; ``worker`` trials SIGKILL one worker process of a running
  campaign, whose lost tasks Dask reschedules. Every trial must end with outputs identical, bit
  for bit, to an uninterrupted run on the same kind of cluster, exactly one output per planned
  pass, path and calibration, and every planned pass counted once.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

import misrgraph.campaign.tasks as tasks
from misrgraph.bench.faults import _cli, _run_and_kill
from misrgraph.bench.work import bench_workdir
from misrgraph.campaign.plan import DAYS_PER_MONTH, REPEAT_DAYS, CampaignConfig, choose, plan_campaign
from misrgraph.campaign.run import PLAN_FILE, campaign_fingerprint, run_campaign
from misrgraph.errors import InputError
from misrgraph.model.orbit import REPEAT_PATHS

__all__ = ["run_bench_campaign", "run_campaign_kill_trials", "prepare_campaign_inputs"]

log = logging.getLogger(__name__)


def prepare_campaign_inputs(directory: Path, cfg: CampaignConfig) -> Path:
    """Simulate the campaign's inputs once (in-process) and lay them out as ``--inputs`` expects:
    ``DIRECTORY/inputs/month`` and ``DIRECTORY/inputs/path_PPP``. Returns the inputs directory."""
    inputs = directory / "inputs"
    if (inputs / "month" / "scenario.json").exists() and all(
        (inputs / f"path_{p:03d}" / "scenario.json").exists() for p in cfg.paths
    ):
        return inputs
    sim = directory / "simulated"
    month = tasks.simulate_month(str(sim), cfg)
    recs = [month] + [tasks.simulate_path(str(sim), cfg, pp.path, pp.cycles, month) for pp in plan_campaign(cfg).paths]
    failed = [r for r in recs if r["status"] != "done"]
    if failed:
        raise RuntimeError(f"simulating the campaign's inputs failed: {failed[0].get('reason')}")
    inputs.mkdir(parents=True, exist_ok=True)
    for d in (sim / "inputs").iterdir():
        name = d.name.split("-")[0]  # month-<digest> -> month, path_037-<digest> -> path_037
        if not (inputs / name).exists():
            shutil.copytree(d, inputs / name)
    shutil.rmtree(sim)
    return inputs


def _seed_calibration(src: Path, dst: Path) -> None:
    """Copy a finished campaign's calibration into a new campaign directory (found done there)."""
    (dst / "calibration").mkdir(parents=True, exist_ok=True)
    for f in (src / "calibration").glob("*.h5"):
        shutil.copy2(f, dst / "calibration" / f.name)


def run_bench_campaign(
    paths: int = 4,
    months: float = 2.0,
    size: str = "reduced",
    seed: int = 0,
    workdir: str | Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Adjustment throughput with 1 and 2 workers on the same ``paths`` x (passes per path) passes."""
    if paths < 1:
        raise InputError("paths", paths, "at least 1")
    with bench_workdir(workdir, "misrgraph-bench-campaign-") as work:
        cfg = CampaignConfig(paths=tuple(range(37, 37 + paths)), months=months, size=size, seed=seed, products=False)
        if progress:
            progress("simulating the inputs and calibrating (in-process, once)")
        inputs = prepare_campaign_inputs(work, cfg)
        ref = work / "reference"
        if not (ref / "summary.json").exists():
            run_campaign(ref, cfg, inputs=inputs, workers=0)
        runs: dict[str, Any] = {}
        for n in (1, 2):
            out = work / f"workers_{n}"
            shutil.rmtree(out, ignore_errors=True)
            _seed_calibration(ref, out)
            if progress:
                progress(f"{n} worker{'s' if n > 1 else ''}")
            s = run_campaign(out, cfg, inputs=inputs, workers=n)
            st = s["stages"]["adjust"]
            if s["passes"]["failed"] or st["found_done"]:
                raise RuntimeError(
                    f"bench campaign: the {n}-worker run did not adjust every pass afresh: {s['passes']}, "
                    f"{s['failed'][:3]}"
                )
            runs[str(n)] = {
                "passes": s["passes"]["done"],
                "adjust_wall_seconds": st["wall_seconds"],
                "passes_per_minute": 60.0 * s["passes"]["done"] / st["wall_seconds"],
                "task_seconds_per_pass": st["task_seconds"] / s["passes"]["done"],
                "peak_rss_mb_per_worker": s["cluster"]["peak_rss_mb"],
                "total_seconds": s["seconds"],
            }
        ratio = runs["2"]["passes_per_minute"] / runs["1"]["passes_per_minute"]
        # the full plan: 233 paths, six months, 30 % (at least 4 per path), at the 2-worker rate
        full = CampaignConfig()
        available = math.ceil(full.months * DAYS_PER_MONTH / REPEAT_DAYS - 1e-9)
        n_full = REPEAT_PATHS * len(choose(available, full))
        est_h = n_full / runs["2"]["passes_per_minute"] / 60.0
        return {
            "size": size,
            "paths": paths,
            "passes": runs["1"]["passes"],
            "workers": runs,
            "scaling_1_to_2": ratio,
            "full_plan": {
                "passes": n_full,
                "adjust_hours_at_2_workers": est_h,
                "note": f"adjustment stage only, at the measured {size}-size rate; the per-path products "
                "and the calibration come on top",
            },
        }


# ---------------------------------------------------------------------------- kill trials
def _check(out: Path, reference: dict[str, str], plan: dict[str, Any]) -> dict[str, Any]:
    """Compare a finished campaign with the reference fingerprint; count duplicates and debris."""
    fp = campaign_fingerprint(out)
    dup = 0
    for path, pp in plan["paths"].items():
        for pid in pp["pass_ids"]:
            dup += max(0, len(list((out / "adjusted" / f"path_{int(path):03d}").glob(f"{pid}-*.h5"))) - 1)
        dup += max(0, len(list((out / "paths").glob(f"path_{int(path):03d}-*"))) - 1)
    dup += max(0, len(list((out / "calibration").glob("*.h5"))) - 1)
    summary = json.loads((out / "summary.json").read_text())
    counted = summary["passes"]["done"]
    return {
        "identical": fp == reference,
        "differing": sorted(k for k in set(fp) | set(reference) if fp.get(k) != reference.get(k)),
        "duplicates": dup,
        "counted": counted,
        "planned": plan["passes_planned"],
        "debris": len([p for p in out.rglob(".*.tmp")]),
    }  # a killed writer's temporaries (the next run removes them)


def run_campaign_kill_trials(
    trials: int = 10,
    kinds: tuple[str, ...] = ("client", "worker"),
    seed: int = 0,
    workdir: str | Path | None = None,
    paths: int = 2,
    months: float = 2.0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """``trials`` kill-and-resume trials of each kind (module docstring) on a reduced campaign of
    ``paths`` paths; the outcome per trial and the failures (must be none)."""
    bad = [k for k in kinds if k not in ("client", "worker")]
    if bad:
        raise InputError("kinds", bad, ("client", "worker"))
    with bench_workdir(workdir, "misrgraph-kill-campaign-") as work:
        cfg = CampaignConfig(paths=tuple(range(37, 37 + paths)), months=months, size="reduced", seed=seed, pp_blocks=1)
        inputs = prepare_campaign_inputs(work, cfg)
        args = [
            "campaign",
            "--inputs",
            str(inputs),
            "--paths",
            ",".join(map(str, cfg.paths)),
            "--months",
            str(months),
            "--size",
            "reduced",
            "--seed",
            str(seed),
            "--pp-blocks",
            "1",
            "--workers",
            "2",
        ]
        # the reference: an uninterrupted run on a 2-worker cluster (the trials' kind of cluster)
        ref = work / "reference"
        shutil.rmtree(ref, ignore_errors=True)
        t0 = time.perf_counter()
        r = subprocess.run(_cli(*args, "--out", str(ref)), capture_output=True, text=True)
        t_full = time.perf_counter() - t0
        if r.returncode != 0:
            raise RuntimeError(f"the uninterrupted campaign failed: {r.stderr.strip()[-800:]}")
        reference = campaign_fingerprint(ref)
        plan = json.loads((ref / PLAN_FILE).read_text())
        rng = np.random.default_rng(seed)
        rows: list[dict[str, Any]] = []
        for kind in kinds:
            for i in range(trials):
                out = work / f"{kind}_{i}"
                shutil.rmtree(out, ignore_errors=True)
                if progress:
                    progress(f"{kind} kill trial {i + 1}/{trials}")
                if kind == "client":
                    after = float(rng.uniform(2.0, t_full))
                    killed = _run_and_kill(_cli(*args, "--out", str(out)), after, group=True)
                    r = subprocess.run(_cli(*args, "--out", str(out)), capture_output=True, text=True)
                    row = {
                        "kind": kind,
                        "after_s": after,
                        "killed_while_running": killed,
                        "rerun_ok": r.returncode == 0,
                    }
                else:
                    row = _worker_trial(out, cfg, inputs, float(rng.uniform(1.0, 0.8 * t_full)), int(rng.integers(2)))
                if (out / "summary.json").exists():
                    row.update(_check(out, reference, plan))
                rows.append(row)
        failures = [
            r
            for r in rows
            if not (
                r.get("rerun_ok")
                and r.get("identical")
                and r.get("duplicates") == 0
                and r.get("counted") == r.get("planned")
            )
        ]
        return {
            "trials": rows,
            "failures": failures,
            "uninterrupted_seconds": t_full,
            "killed_while_running": sum(bool(r.get("killed_while_running")) for r in rows),
        }


def _worker_trial(out: Path, cfg: CampaignConfig, inputs: Path, after_s: float, victim: int) -> dict[str, Any]:
    """Run the campaign on an in-process 2-worker LocalCluster and SIGKILL worker ``victim`` (0 or
    1, by process id order) ``after_s`` seconds in; the nanny restarts it and Dask reschedules
    the tasks it held."""
    from distributed import Client, LocalCluster

    logging.getLogger("distributed").setLevel(logging.ERROR)
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster,
        Client(cluster) as client,
    ):
        result: dict[str, Any] = {}

        def go() -> None:
            try:
                result["summary"] = run_campaign(out, cfg, inputs=inputs, client=client)
            except Exception as exc:  # reported as a failed trial
                result["error"] = f"{exc.__class__.__name__}: {exc}"

        th = threading.Thread(target=go)
        th.start()
        th.join(after_s)
        killed = False
        if th.is_alive():
            pids = sorted(client.run(os.getpid).values())
            os.kill(pids[victim % len(pids)], signal.SIGKILL)
            killed = True
        th.join()
    return {
        "kind": "worker",
        "after_s": after_s,
        "killed_while_running": killed,
        "rerun_ok": "summary" in result,
        **({"error": result["error"]} if "error" in result else {}),
    }
