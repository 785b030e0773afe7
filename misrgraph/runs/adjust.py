"""``run_adjust``: one pass from files to RESULT.h5 and a JSON summary (the action behind
``misrgraph adjust``; notebooks import it too).

Reads the pass, camera model, GCP database and DEM; adjusts (:func:`misrgraph.estimate.adjust.adjust_pass`,
which never sees truth); for a simulated pass then scores the estimate against the truth
(:mod:`misrgraph.evaluate.score`) and writes the result atomically.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from factors.collinearity import camera_param_scale
from misrgraph import __version__
from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.adjust import AdjustConfig, AdjustResult, adjust_pass, attitude_sigma_summary
from misrgraph.evaluate.score import score_pass
from misrgraph.io.camera import load_camera_model, read_calibration_prior, write_camera_group
from misrgraph.io.dem import read_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.h5 import atomic_h5, write_dataset
from misrgraph.io.passes import KIND_GCP, OrbitPass
from misrgraph.io.results import capped_list
from misrgraph.io.truth import PassTruth, load_pass_observations
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import ANGLES, CAMERAS
from misrgraph.model.dem import DemTiles
from misrgraph.model.gcp import GcpDatabase
from misrgraph.model.noise import NoiseModel
from misrgraph.runs.cgm import resolve_camera_model

__all__ = [
    "run_adjust",
    "run_tie_height_pool",
    "write_adjust_result",
    "matched_tie_offset",
    "camera_prior_of",
    "adjust_observation_set",
]


def write_adjust_result(
    path: Path,
    orbit_pass: OrbitPass,
    res: AdjustResult,
    summary: dict[str, Any],
    provenance: dict[str, str],
    truth: PassTruth | None = None,
) -> None:
    """Write RESULT.h5 (HDF5 kind ``adjustment_result``, docs/reference/data-model.md) atomically; with
    ``truth`` also ``/landmarks/truth_ecef`` for the views."""
    pg = res.pass_graph
    with atomic_h5(path, "adjustment_result") as f:
        f.attrs["pass_id"] = orbit_pass.pass_id
        f.attrs["software"] = f"misrgraph {__version__}"
        f.attrs["summary_json"] = json.dumps(summary)
        f.attrs["solver_status"] = res.status  # "converged": the covariances are those of an optimum
        prov = f.create_group("provenance")
        for k, v in provenance.items():
            prov.attrs[k] = str(v)
        a = f.create_group("attitude_error")
        for i, name in enumerate(ANGLES):
            g = a.create_group(name)
            keys = pg.knot_keys(i)
            write_dataset(g, "knot_times", res.attitude.knot_times[i], units="s")
            write_dataset(g, "knots", res.attitude.knots[i], units="rad, rad/s")
            write_dataset(
                g, "covariance", np.stack([res.marginals[k] for k in keys]), units="rad^2, rad^2/s, rad^2/s^2"
            )
            write_dataset(g, "joint_covariance", res.marginals.joint_of(keys), order="knot-major (value, rate)")
            write_dataset(g, "removed_knots", pg.removed_knots[i], meaning="indices on the uniform grid, eqs. 28-29")
            write_dataset(
                g,
                "grid_spacing",
                np.array(
                    float(pg.attitude_model.knot_times[i][1] - pg.attitude_model.knot_times[i][0])
                    if pg.removed_knots[i].size == 0
                    else np.nan
                ),
                units="s",
            )
        e = f.create_group("ephemeris_error")
        write_dataset(e, "boundaries", res.ephemeris.boundaries, units="s")
        write_dataset(e, "params", res.ephemeris.params, units="m/s (a), m (b)", order="a_x,a_y,a_z,b_x,b_y,b_z")
        write_dataset(e, "covariance", np.stack([res.marginals[k] for k in pg.ephemeris_keys()]))
        c = f.create_group("camera_corrections")
        cams = sorted(pg.camera_keys)
        write_dataset(c, "camera", np.array(cams, np.int64))
        n_par = len(pg.camera_params)
        scale = camera_param_scale(pg.camera_params)
        si = pg.camera_corrections(res.values)
        units = "rad (delta, beta, epsilon), m (f), alpha_i as the camera model stores them"
        write_dataset(
            c,
            "values",
            np.array([si[k] for k in cams]).reshape(-1, n_par),
            units=units,
            order=",".join(pg.camera_params),
        )
        write_dataset(
            c,
            "covariance",
            np.array([res.marginals[pg.camera_keys[k]] * np.outer(scale, scale) for k in cams]).reshape(
                -1, n_par, n_par
            ),
            units="the values' units squared",
        )
        lm = f.create_group("landmarks")
        write_dataset(lm, "row", pg.landmark_rows)
        write_dataset(lm, "kind", orbit_pass.landmarks.kind[pg.landmark_rows], meaning="0 tie, 1 GCP")
        write_dataset(lm, "ecef", np.array([res.values.atVector(int(k)) for k in pg.landmark_keys]), units="m")
        write_dataset(lm, "covariance", np.array([res.marginals[int(k)] for k in pg.landmark_keys]), units="m^2")
        if truth is not None:
            write_dataset(lm, "truth_ecef", truth.landmark_ecef[pg.landmark_rows], units="m")
        o = f.create_group("observations")
        write_dataset(o, "residual_px", res.residuals_px, units="pixel", order="along,cross; NaN = not adjusted")
        write_dataset(o, "camera", orbit_pass.observations.camera.astype(np.int8))
        write_dataset(o, "rejected", res.rejected, meaning="observation indices rejected as blunders")
        write_dataset(o, "rejected_normalised_residual", res.rejected_norm, units="sigma")
        h = f.create_group("convergence")
        write_dataset(
            h, "error", np.asarray(res.history), meaning="0.5 * sum of squared whitened residuals per iteration"
        )
        write_camera_group(f.create_group("camera_model"), res.camera)


def matched_tie_offset(pass_file: str | os.PathLike[str]) -> tuple[float | None, dict[str, float] | None]:
    """The offset the matched tie points' conjugates share (px, 1 sigma), as ``misrgraph match``
    measured it for this pass (``tie.shared_offset`` of its summary), and its conjugates'
    own-scale ratio per camera name (:mod:`misrgraph.estimate.tieoffset`); None when it has none
    (matched before the measurement existed, or too little redundancy)."""
    from misrgraph.io.imagery import read_matched_summary

    summary = read_matched_summary(pass_file) or {}
    so = (summary.get("tie") or {}).get("shared_offset") or {}
    if not so.get("estimated"):
        return None, None
    return float(so["sigma_px"]), so.get("own_scale_ratio")


def camera_prior_of(camera_model: str | os.PathLike[str], cfg: AdjustConfig) -> tuple[list[str], np.ndarray] | None:
    """The joint covariance of the calibration a camera model file carries
    (:func:`misrgraph.io.camera.read_calibration_prior`), when ``cfg.camera_prior_from_calibration``
    asks for it as the prior of the camera corrections; None otherwise (or when it has none)."""
    return read_calibration_prior(camera_model) if cfg.camera_prior_from_calibration else None


def adjust_observation_set(
    orbit_pass: OrbitPass,
    pass_file: str | os.PathLike[str],
    camera: CameraModel,
    dem: DemTiles | None,
    gcps: GcpDatabase | None,
    cfg: AdjustConfig,
    observations: str,
    camera_prior: tuple[list[str], np.ndarray] | None,
    progress: Callable[[str], None] | None = None,
) -> AdjustResult:
    """:func:`~misrgraph.estimate.adjust.adjust_pass` of ``orbit_pass`` as loaded with its
    ``observations`` set from ``pass_file`` (matched: with the offset ``misrgraph match`` measured
    for the pass, :func:`matched_tie_offset`), the camera corrections' prior ``camera_prior``
    (:func:`camera_prior_of`). The one adjustment of ``adjust`` and ``products``."""
    matched = observations == "matched"
    s_o, own = matched_tie_offset(pass_file) if matched else (None, None)
    return adjust_pass(
        orbit_pass,
        camera,
        dem,
        gcps,
        cfg,
        progress,
        ties_matched=matched,
        tie_offset_px=s_o,
        tie_offset_own_ratio=own,
        camera_prior=camera_prior,
    )


def run_adjust(
    scenario_dir: str | os.PathLike[str],
    camera_model: str | os.PathLike[str] | None = None,
    pass_file: str | os.PathLike[str] | None = None,
    gcp_file: str | os.PathLike[str] | None = None,
    dem_file: str | os.PathLike[str] | None = None,
    out: str | os.PathLike[str] | None = None,
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str], None] | None = None,
    score_points: bool = False,
    observations: str = "simulated",
) -> dict[str, Any]:
    """Adjust one pass of a scenario directory; write RESULT.h5 when ``out`` is given; return the summary.

    ``observations``: ``"simulated"`` (the pass's own) or ``"matched"`` (what ``misrgraph match``
    measured in the imagery, scored against their own truth).

    ``score_points``: with truth, the summary also lists each check point's error
    (``checkpoint_points``, :func:`misrgraph.evaluate.score.score_pass`).

    ``pass_file`` may be left out only when the scenario holds a single pass. When the pass file
    carries the simulator's truth the summary adds its scores (:func:`misrgraph.evaluate.score.score_pass`);
    the estimate itself never sees it."""
    d = Path(scenario_dir)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate'")
    cam_spec = Path(camera_model) if camera_model else d / "camera_model.h5"
    if pass_file is None:
        passes = sorted((d / "passes").glob("*.h5"))
        if not passes:
            raise FileFormatError(d / "passes", "no pass files (*.h5)")
        if len(passes) > 1:
            names = ", ".join(p.name for p in passes[:5]) + (", ..." if len(passes) > 5 else "")
            raise InputError(
                "PASS_FILE", None, f"one of the scenario's {len(passes)} pass files ({names}): name it with --pass"
            )
        pass_file = passes[0]
    orbit_pass, truth = load_pass_observations(pass_file, observations)
    cam_path, cgm_version = resolve_camera_model(cam_spec, orbit_pass.orbit)
    camera = load_camera_model(cam_path).at_temperature(orbit_pass.temperature_c)
    gcps = read_gcp_database(gcp_file or d / "gcp.h5")
    dem = read_dem(dem_file or d / "dem.h5")
    prior = camera_prior_of(cam_path, cfg)
    res = adjust_observation_set(orbit_pass, pass_file, camera, dem, gcps, cfg, observations, prior, progress)
    pg = res.pass_graph
    snooped = set(res.snooped.tolist())
    summary: dict[str, Any] = {
        "pass_id": orbit_pass.pass_id,
        "observation_set": observations,
        "camera_model": str(cam_path),
        "camera_model_version": cgm_version,
        "camera_prior": "the camera model's calibration covariance"
        if prior is not None
        else "camera_prior_px per camera",
        "solver_status": res.status,
        "covariance": res.reliability.get("covariance", "gauss_newton"),
        "variance_factor": res.variance_factor,
        "reliability": res.reliability,
        "iterations": res.iterations,
        "final_cost": res.final_cost,
        "seconds": res.seconds,
        "observations": int(len(pg.collinearity)),
        "landmarks": int(pg.landmark_keys.size),
        "dropped_tie_points": int(res.dropped_landmarks.size),
        "knots": {
            a: {"kept": int(res.attitude.knot_times[i].size), "removed": int(pg.removed_knots[i].size)}
            for i, a in enumerate(ANGLES)
        },
        "rejected_observations": capped_list(
            [
                {
                    "index": int(i),
                    "camera": CAMERAS[int(orbit_pass.observations.camera[i])],
                    "landmark_kind": "gcp"
                    if orbit_pass.landmarks.kind[orbit_pass.observations.landmark[i]] == KIND_GCP
                    else "tie",
                    "normalised_residual": float(n),
                    "by": "data snooping" if i in snooped else "robust screen",
                }
                for i, n in zip(res.rejected, res.rejected_norm)
            ],
            f"{out}:/observations/rejected" if out is not None else None,
            group_by=("camera", "landmark_kind"),
        ),
        "attitude_sigma": attitude_sigma_summary(res, cfg.graph_config().attitude_sigma_arcsec),
        # the levels the pass was adjusted with, for 'misrgraph noise fit'
        "noise_levels": {k: getattr(cfg.graph, k) for k in (*NoiseModel().graph_fields(), "knot_prior")},
        "tie_height": res.tie_height,
        "tie_offset": res.tie_offset,
        "ephemeris": {
            "params": res.ephemeris.params.tolist(),
            "sigma": [np.sqrt(np.diag(res.marginals[k])).tolist() for k in pg.ephemeris_keys()],
        },
    }
    diagnostics = []
    obs = orbit_pass.observations
    is_gcp = orbit_pass.landmarks.kind[obs.landmark] == KIND_GCP
    n_gcp = int(is_gcp.sum())
    n_gcp_rej = int(is_gcp[res.rejected].sum()) if res.rejected.size else 0
    if n_gcp == 0:
        diagnostics.append(
            "no GCP observations on this pass: absolute accuracy rests on the DEM and the navigation priors"
        )
    elif n_gcp_rej == n_gcp:
        diagnostics.append(
            f"all {n_gcp} GCP observations were rejected as blunders: absolute accuracy rests on the DEM "
            "and the navigation priors; check the GCP database"
        )
    removed = sum(int(r.size) for r in pg.removed_knots)
    if removed:
        diagnostics.append(
            f"{removed} knots removed by eqs. 28-29 (too few tie points or cameras): the spline spans the gaps"
        )
    if "reason" in res.tie_height:
        diagnostics.append(
            f"the tie points' shared height error was not estimated ({res.tie_height['reason']}): "
            "their heights' covariance leaves it out (--tie-height-sigma-m sets it)"
        )
    if res.status != "converged":
        diagnostics.insert(
            0,
            f"the least-squares solve ended {res.status.replace('_', ' ')} (accepted with "
            "--accept-unconverged): the covariances are not those of an optimum",
        )
    summary["diagnostics"] = diagnostics
    if truth is not None:
        summary.update(score_pass(orbit_pass, truth, res, camera, points=score_points))
    if out is not None:
        write_adjust_result(
            Path(out),
            orbit_pass,
            res,
            summary,
            {
                "scenario": str(d),
                "pass_file": str(pass_file),
                "camera_model": str(cam_path),
                **({"cgm_version": cgm_version["id"]} if cgm_version else {}),
                "config": json.dumps(dataclasses.asdict(cfg)),
                "software": f"misrgraph {__version__}",
            },
            truth,
        )
    return summary


def run_tie_height_pool(results: list[str | os.PathLike[str]]) -> dict[str, Any]:
    """Pool the matched tie points' shared height variance over passes
    (:func:`misrgraph.estimate.tieheight.pool_shared_height`), from RESULT.h5 files that
    ``adjust --observations matched --out`` wrote (each estimates it for its own pass).

    Returns ``sigma_m`` (the 1 sigma to fix with ``adjust --tie-height-sigma-m``), ``variance_m2``,
    ``unclipped_variance_m2``, ``standard_error_m2``, ``dem_factors`` (total), ``passes`` (used) and
    ``per_pass`` (file -> its estimate and count); results that did not estimate it (simulated
    observations, a fixed value, no DEM factors) are listed in ``skipped`` with the reason."""
    from misrgraph.estimate.tieheight import pool_shared_height
    from misrgraph.io.h5 import open_h5

    per_pass: dict[str, Any] = {}
    skipped: dict[str, str] = {}
    for r in results:
        path = Path(r)
        with open_h5(path, "adjustment_result") as f:  # kind, version and checksums checked
            summary = json.loads(f.attrs["summary_json"])
        th = summary.get("tie_height", {})
        if th.get("source") != "estimated" or not np.isfinite(th.get("unclipped_variance_m2", np.nan)):
            skipped[str(path)] = f"tie height {th.get('source', 'absent')}" + (
                f" ({th['reason']})" if "reason" in th else ""
            )
            continue
        per_pass[str(path)] = {
            "unclipped_variance_m2": float(th["unclipped_variance_m2"]),
            "standard_error_m2": float(th["standard_error_m2"]),
            "dem_factors": int(th["dem_factors"]),
        }
    if len(per_pass) < 2:
        raise InputError(
            "results",
            f"{len(per_pass)} with an estimate (skipped: {skipped})",
            "at least 2 results of adjust --observations matched that estimated the tie height",
        )
    pooled = pool_shared_height(
        [v["unclipped_variance_m2"] for v in per_pass.values()], [v["dem_factors"] for v in per_pass.values()]
    )
    return {
        "sigma_m": pooled.sigma_m,
        "variance_m2": pooled.variance_m2,
        "unclipped_variance_m2": pooled.unclipped_m2,
        "standard_error_m2": pooled.standard_error_m2,
        "dem_factors": pooled.n,
        "passes": len(per_pass),
        "per_pass": per_pass,
        "skipped": skipped,
    }
