"""``misrgraph bench roi``: Reference Orbit Imagery at the seed's size -- standard repeat passes of
one path (45 minutes, 1000 tie points, 120 GCPs), whole-line imagery of all nine cameras over
consecutive blocks -- built end to end, with the time of every stage and the co-registration
measured on the ROI and against the simulator's truth."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from misrgraph.bench.work import bench_workdir
from misrgraph.errors import InputError

__all__ = ["run_bench_roi", "FIRST_BLOCK"]

#: The first block of the study (path 37: ~37 deg N, over land in the simulator's world).
FIRST_BLOCK = 62


def run_bench_roi(
    passes: int = 4,
    blocks: int = 2,
    seed: int = 0,
    workdir: str | Path | None = None,
    cloud_fraction: float = 0.2,
    tie_points: int = 1000,
    progress: Callable[[str, int, int], None] | None = None,
    first_block: int = FIRST_BLOCK,
) -> dict[str, Any]:
    """Simulate (or reuse, in ``workdir``) ``passes`` standard passes of path 37 with strips over
    ``blocks`` blocks from ``first_block`` (the pass's last tie points are in block 69: from there
    on the aft cameras image the ground after the pass's last observation), then ``run_products(..., roi=True)``;
    returns the stage times (``simulate`` is None when the scenario was reused), per-pass PP errors, the ROI's
    co-registration (matched and true) and the blocks' clear fractions."""
    from misrgraph.runs.products import RoiOptions, run_products
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    if passes < 4:
        raise InputError("--passes", passes, "at least 4 (the ROI is made of four or more passes)")
    if not 1 <= blocks <= 20:
        raise InputError("--blocks", blocks, "1..20")
    if not 1 <= first_block <= 181 - blocks:
        raise InputError("--first-block", first_block, f"1..{181 - blocks} (the path's blocks are 1-180)")
    last = first_block + blocks - 1
    with bench_workdir(workdir, "misrgraph-bench-roi-") as wd:
        tag = "" if first_block == FIRST_BLOCK else f"_b{first_block}"
        scen = wd / f"path_{passes}_{blocks}_{seed}_{tie_points}{tag}"
        t_sim = None
        if not (scen / "scenario.json").is_file():
            t0 = time.perf_counter()
            run_simulate(
                ScenarioConfig(
                    truth="model",
                    scenario="path",
                    seed=seed,
                    n_passes=passes,
                    n_tie_points=tie_points,
                    imagery=True,
                    cloud_fraction=cloud_fraction,
                    feature_windows=False,
                    roi_blocks=(first_block, last),
                ),
                scen,
                progress=progress,
            )
            t_sim = time.perf_counter() - t0
        out = wd / f"products_{passes}_{blocks}_{seed}_{tie_points}{tag}"
        res = run_products(
            scen, out, roi=True, roi_options=RoiOptions(geotiff=True, quicklooks=True), progress=progress
        )
    return {
        "study": {
            "passes": passes,
            "blocks": [first_block, last],
            "cameras": 9,
            "seed": seed,
            "tie_points": tie_points,
            "cloud_fraction": cloud_fraction,
            "pass_duration_s": 2700.0,
        },
        "seconds": {"simulate": t_sim, **res["seconds"]},
        "pp_error_m": {
            r["pass_id"]: {c: round(v["rms"], 1) for c, v in r.get("pp_error_m", {}).items()} for r in res["passes"]
        },
        "pp_predicted_m": {
            r["pass_id"]: {c: round(v["predicted_rms"], 1) for c, v in r.get("pp_error_m", {}).items()}
            for r in res["passes"]
        },
        "roi_coregistration_px": res["roi_coregistration_px"],
        "roi_truth": res.get("roi_truth", {}),
        "roi_predicted_px": res.get("roi_predicted_px", {}),
        "roi_predicted_px_by_block": res.get("roi_predicted_px_by_block", {}),
        "roi_truth_by_block": res.get("roi_truth_by_block", {}),
        "roi_truth_obscured": res.get("roi_truth_obscured", {}),
        "obscured_fraction": res["roi"].get("obscured_fraction"),
        "roi_coregistration": res["roi_coregistration"],
        "roi_coregistration_by_block": res.get("roi_coregistration_by_block", {}),
        "clear_fraction": res["roi"].get("clear_fraction"),
        "chosen_pass": res["roi"].get("chosen_pass"),
    }
