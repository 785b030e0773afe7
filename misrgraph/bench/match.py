"""``misrgraph bench match``: the matching front end on a standard pass with imagery.

* Rendering: the simulation with ``--imagery`` against the same simulation without (same seed),
  so the ratio is what imagery costs.
* Matching (``misrgraph match``): candidates, matched, errors against truth, error / sigma, wrong
  matches, seconds.
* GCP chips per second and accuracy of our NCC + least-squares matching against a plain
  ``skimage.feature.match_template`` on the same chips and windows (integer peak refined by the
  usual three-point parabola per axis), side by side.
* The adjustment of the matched observations against the same adjustment of the simulated ones:
  check-point RMS ratio and co-registration.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from misrgraph.bench.work import bench_workdir
from misrgraph.io.imagery import read_imagery
from misrgraph.match.lsm import lsm, ncc_search
from misrgraph.runs.adjust import run_adjust
from misrgraph.runs.match import run_match
from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

__all__ = ["run_bench_match"]


def _parabola(cc: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """Sub-pixel peak offsets by a three-point parabola along each axis (0 at the border)."""

    def off(a: float, b: float, c: float) -> float:
        d = a - 2 * b + c
        return 0.5 * (a - c) / d if d < 0 else 0.0

    di = off(cc[i - 1, j], cc[i, j], cc[i + 1, j]) if 0 < i < cc.shape[0] - 1 else 0.0
    dj = off(cc[i, j - 1], cc[i, j], cc[i, j + 1]) if 0 < j < cc.shape[1] - 1 else 0.0
    return di, dj


def _chips_side_by_side(scenario: Path) -> dict[str, Any]:
    """Both matchers on every GCP window: per-coordinate error RMS against truth and chips/s."""
    from skimage.feature import match_template

    sc = load_scenario(scenario)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    im = read_imagery(sc.pass_files[0])
    geo = tp.geometry(p)
    chip_of = im.chip_index()
    jobs = []
    for k in range(len(im.gcp)):
        row, cam, band = int(im.gcp.landmark[k]), int(im.gcp.camera[k]), int(im.gcp.band[k])
        chip = im.chips[chip_of[(row, band)], cam]
        if not np.all(np.isfinite(chip)):
            continue
        ip = geo.ground_to_pixel(cam, band, tp.landmark_ecef[row][None], continuous=True)
        if ip.visible[0]:
            jobs.append(
                (
                    im.gcp.pixels[k].astype(float),
                    chip.astype(float),
                    float(ip.line[0] - im.gcp.line0[k]),
                    float(ip.sample[0] - im.gcp.sample0[k]),
                )
            )
    out: dict[str, Any] = {"chips": len(jobs)}
    if not jobs:
        return out
    half = (jobs[0][1].shape[0] - 1) / 2.0
    t0 = time.perf_counter()
    plain = []
    for img, chip, r, c in jobs:
        cc = match_template(img, chip)
        i, j = np.unravel_index(int(np.argmax(cc)), cc.shape)
        di, dj = _parabola(cc, int(i), int(j))
        plain.append((i + di + half - r, j + dj + half - c))
    t_plain = time.perf_counter() - t0
    t0 = time.perf_counter()
    ours = []
    for img, chip, r, c in jobs:
        pk = ncc_search(img, chip)
        res = lsm(img, chip, pk.row, pk.col) if pk is not None else None
        ours.append((res.row - r, res.col - c) if res is not None and res.converged else (np.nan, np.nan))
    t_ours = time.perf_counter() - t0

    def rms(e):
        return float(np.sqrt(np.nanmean(np.square(np.asarray(e)))))

    out.update(
        {
            "ncc_lsm": {
                "error_rms_px": rms(ours),
                "chips_per_second": len(jobs) / t_ours,
                "converged": int(np.sum(np.isfinite(np.asarray(ours)[:, 0]))),
            },
            "skimage_parabola": {"error_rms_px": rms(plain), "chips_per_second": len(jobs) / t_plain},
            "time_ratio_ncc_lsm_over_skimage": t_ours / t_plain,
        }
    )
    return out


def run_bench_match(
    tie_points: int = 1000,
    seed: int = 0,
    duration_s: float = 2700.0,
    cloud_fraction: float = 0.0,
    check_points: int = 100,
    workdir: str | Path | None = None,
) -> dict[str, Any]:
    """Render, match and adjust one pass (see the module docstring); returns the figures."""
    with bench_workdir(workdir, "misrgraph-bench-match-") as base:
        cfg = dict(
            scenario="pass",
            seed=seed,
            n_tie_points=tie_points,
            n_check_points=check_points,
            duration_s=duration_s,
            cloud_fraction=cloud_fraction,
            truth="model",
        )
        t0 = time.perf_counter()
        run_simulate(ScenarioConfig(**cfg), base / "plain")
        t_plain = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_simulate(ScenarioConfig(**cfg, imagery=True), base / "imagery")
        t_img = time.perf_counter() - t0
        res = run_match(base / "imagery")
        summary = {k: v for k, v in res.items() if k != "passes"}
        for kind in ("gcp", "tie"):
            summary[kind]["rejected"] = res["passes"][0][kind]["rejected"]
        for key in ("per_camera", "sigma_scale"):
            summary["tie"][key] = res["passes"][0]["tie"].get(key)
        summary["gcp"]["sigma_scale"] = res["passes"][0]["gcp"].get("sigma_scale")
        sim = run_adjust(base / "imagery")
        mat = run_adjust(base / "imagery", observations="matched")

        def pooled(s: dict[str, Any]) -> float:
            v = s["checkpoint_geolocation_m"].values()
            return float(np.sqrt(np.mean([x["after"]["rms"] ** 2 for x in v])))

        return {
            "pass": {
                "tie_points": tie_points,
                "duration_s": duration_s,
                "cloud_fraction": cloud_fraction,
                "seed": seed,
            },
            "simulate_seconds": {
                "without_imagery": t_plain,
                "with_imagery": t_img,
                "rendering": t_img - t_plain,
                "ratio": t_img / t_plain,
            },
            "match": summary,
            "gcp_chips": _chips_side_by_side(base / "imagery"),
            "adjust": {
                "simulated": {
                    "checkpoint_rms_m": pooled(sim),
                    "coregistration_px_max": max(sim["coregistration_px"].values()),
                    "nees": sim.get("nees"),
                },
                "matched": {
                    "checkpoint_rms_m": pooled(mat),
                    "coregistration_px_max": max(mat["coregistration_px"].values()),
                    "nees": mat.get("nees"),
                    "blunders": mat.get("blunders"),
                    "observations": mat["observations"],
                    "tie_height": mat["tie_height"],
                },
                "checkpoint_ratio_matched_over_simulated": pooled(mat) / pooled(sim),
            },
        }
