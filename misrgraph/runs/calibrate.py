"""``run_calibrate``: a month of GCP passes from files to a recalibrated camera model and a JSON
summary (the action behind ``misrgraph calibrate``; notebooks import it too).

The calibration itself (:func:`misrgraph.estimate.calibrate.calibrate_passes`) never sees truth;
when the scenario holds the simulator's true camera model (``camera_truth.h5``) the summary adds
the scores of :mod:`misrgraph.evaluate.calibration`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np

from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.calibrate import CalibrateConfig, calibrate_passes, summarise
from misrgraph.evaluate.calibration import score_calibration
from misrgraph.io.camera import load_camera_model, write_camera_group, write_camera_groups
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.h5 import atomic_h5, write_dataset
from misrgraph.io.passes import OrbitPass
from misrgraph.io.truth import load_pass_observations
from misrgraph.model.camera import CameraModel

__all__ = ["run_calibrate"]


def run_calibrate(
    scenario_dir: str | os.PathLike[str],
    camera_model: str | os.PathLike[str] | None = None,
    gcp_file: str | os.PathLike[str] | None = None,
    out: str | os.PathLike[str] | None = None,
    cfg: CalibrateConfig = CalibrateConfig(),
    max_passes: int | None = None,
    progress: Callable[[str], None] | None = None,
    observations: str = "simulated",
) -> dict[str, Any]:
    """Calibrate from every pass of a scenario directory; write the recalibrated model when ``out``.

    ``observations``: ``"simulated"`` (each pass's own) or ``"matched"`` (what ``misrgraph match``
    measured in the imagery of a month simulated with ``--imagery``); a pass whose matching kept
    no observation is left out."""
    d = Path(scenario_dir)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate --scenario month'")
    files = sorted((d / "passes").glob("*.h5"))
    if not files:
        raise FileFormatError(d / "passes", "no pass files (*.h5)")
    if max_passes is not None:
        files = files[:max_passes]
    cam_path = Path(camera_model) if camera_model else d / "camera_model.h5"
    table = load_camera_model(cam_path)
    gcps = read_gcp_database(gcp_file or d / "gcp.h5")
    passes = []
    for i, f in enumerate(files):
        if progress and i % 25 == 0:
            progress(f"reading pass {i + 1}/{len(files)}")
        if observations == "simulated":
            passes.append(OrbitPass.load(f))
            continue
        p, _ = load_pass_observations(f, observations)
        if len(p.observations):
            passes.append(p)
    if not passes:
        raise InputError("--observations", observations, "a set with observations in at least one pass")
    supplied = (
        table
        if isinstance(table, CameraModel)
        else table.at_temperature(float(np.median([p.temperature_c for p in passes])))
    )
    truth_path = d / "camera_truth.h5"
    truth = load_camera_model(truth_path) if truth_path.exists() else None
    res = calibrate_passes(
        passes, supplied, gcps, cfg, progress, table=None if isinstance(table, CameraModel) else table
    )
    summary = summarise(res, cfg, supplied)
    summary["observation_set"] = observations
    if truth is not None:
        score_calibration(summary, res, cfg, supplied, truth)
    if out is not None:
        summary["rejected_observations"]["full_list"] = f"{out}:/calibration/rejected"
        with atomic_h5(out, "camera_model") as f:
            for m in res.table.models if res.table is not None else [res.camera]:
                m.provenance.update(
                    {
                        "scenario": str(d),
                        "camera_model_in": str(cam_path),
                        "config": json.dumps(dataclasses.asdict(cfg)),
                    }
                )
            if res.table is not None:  # thermal: one model per temperature bin
                write_camera_groups(f, res.table)
            else:
                write_camera_group(f.create_group("camera_model"), res.camera)
            g = f.create_group("calibration")
            g.attrs["solver_status"] = res.status  # "converged": the covariance is that of an optimum
            g.create_dataset("labels", data=np.array(res.labels, dtype=object), dtype=h5py.string_dtype())
            write_dataset(g, "corrections", res.values, units="rad (angles), m (f), pixel^-i (alpha_i)")
            write_dataset(g, "covariance", res.covariance)
            write_dataset(g, "correlation", np.asarray(summary["correlation"]["matrix"]))
            rej = np.array([(p, o, r) for p, o, r in res.rejected], float).reshape(-1, 3)
            r = g.create_group("rejected")
            write_dataset(
                r, "pass_index", rej[:, 0].astype(np.int64), meaning="index of the pass in the month (file order)"
            )
            write_dataset(r, "observation", rej[:, 1].astype(np.int64), meaning="observation index within the pass")
            write_dataset(r, "normalised_residual", rej[:, 2], units="sigma")
            g.attrs["summary_json"] = json.dumps({k: v for k, v in summary.items() if k != "correlation"})
    return summary
