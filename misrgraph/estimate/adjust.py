"""Simultaneous bundle adjustment of one orbit pass (seed section 4.2), scored against truth.

Procedure (``run_adjust``):

1. Build the graph of the pass (:func:`misrgraph.estimate.graph.build_pass_graph`) with the supplied
   (calibrated) camera model held by a tight prior, and solve with a robust (Cauchy) loss per
   observation, so blunders cannot drag the solution.
2. Reject every observation whose whitened residual norm exceeds ``reject_sigma`` (default 5)
   and report it with its normalised residual.
3. Re-solve with plain least squares without the rejected observations (robust weights would
   distort the covariance) and compute marginal covariances of every knot, the ephemeris
   model, the camera corrections and every landmark.

When the pass carries truth, the summary scores the estimate: attitude and ephemeris RMS over the
pass, check-point geolocation before/after (exact image coordinates of the check points,
geolocated onto their true height with the supplied and with the corrected navigation, so the
figure measures the navigation/camera model only), co-registration of every camera against An in
pixels, and NEES (divided by its dimension) of the knots (joint covariance) and landmarks.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from misrgraph import __version__
from misrgraph.model.camera import CameraModel, load_camera_model
from misrgraph.config import Config
from misrgraph.model.constants import ANGLES, ARCSEC, BANDS, CAMERAS
from misrgraph.model.dem import DemTiles
from misrgraph.model.errormodels import AttitudeErrorModel, EphemerisErrorModel
from misrgraph.errors import FileFormatError, InputError
from misrgraph.model.frames import ecef_to_geodetic, enu_basis
from misrgraph.model.gcp import GcpDatabase
from misrgraph.model.geolocation import PassGeometry
from misrgraph.estimate.graph import GraphConfig, PassGraph, build_pass_graph
from misrgraph.io.h5 import atomic_h5, write_dataset
from misrgraph.io.results import capped_list
from misrgraph.io.passes import KIND_CHECK, KIND_GCP, KIND_TIE, OrbitPass
from misrgraph.estimate.solver import Marginals, SolverParams, information_norm, linearize, marginal_covariances, solve

__all__ = ["AdjustConfig", "AdjustResult", "run_adjust", "adjust_pass", "corrected_geometry", "score_pass", "find_blunders"]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
RED = BANDS.index("red")


_GRAPH_DEFAULTS = GraphConfig()


@dataclass(frozen=True)
class AdjustConfig(Config):
    """Adjustment settings; the graph fields take their defaults from :class:`GraphConfig`."""

    knot_spacing_s: tuple = _GRAPH_DEFAULTS.knot_spacing_s
    threshold1: int = _GRAPH_DEFAULTS.threshold1
    threshold2: int = _GRAPH_DEFAULTS.threshold2
    knot_rule: str = _GRAPH_DEFAULTS.knot_rule
    ephemeris_segments: int = _GRAPH_DEFAULTS.ephemeris_segments
    camera_prior_px: float = _GRAPH_DEFAULTS.camera_prior_px
    use_dem: bool = _GRAPH_DEFAULTS.use_dem
    robust: str = "cauchy"
    robust_k: float = 3.0
    reject_sigma: float = 5.0
    max_iterations: int = 100
    backend: str = "auto"

    def graph_config(self, **overrides: Any) -> GraphConfig:
        base = dict(knot_spacing_s=self.knot_spacing_s, threshold1=self.threshold1, threshold2=self.threshold2,
                    knot_rule=self.knot_rule,
                    ephemeris_segments=self.ephemeris_segments, camera_prior_px=self.camera_prior_px,
                    use_dem=self.use_dem)
        base.update(overrides)
        return GraphConfig.from_dict(base)


@dataclass
class AdjustResult:
    """Everything an adjustment produced."""

    pass_graph: PassGraph
    values: gtsam.Values
    marginals: Marginals
    attitude: AttitudeErrorModel
    ephemeris: EphemerisErrorModel
    camera: CameraModel
    rejected: NDArray[np.int64]
    rejected_norm: Array
    residuals_px: Array
    iterations: int
    final_cost: float
    history: list[float]
    seconds: float
    #: landmark rows dropped whole because most of their rays were rejected (see find_blunders)
    dropped_landmarks: NDArray[np.int64] = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))


def _estimated_models(pg: PassGraph, values: gtsam.Values, camera: CameraModel) -> tuple[AttitudeErrorModel, EphemerisErrorModel, CameraModel]:
    att = AttitudeErrorModel([t.copy() for t in pg.attitude_model.knot_times],
                             [np.array([values.atVector(k) for k in pg.knot_keys(a)]) for a in range(3)])
    eph = EphemerisErrorModel(pg.ephemeris_model.boundaries.copy(), np.array([values.atVector(k) for k in pg.ephemeris_keys()]))
    cam = camera.copy()
    for c, k in pg.camera_keys.items():
        d = values.atVector(k)
        cam.delta[c] += d[0]
        cam.beta[c] += d[1]
        cam.epsilon[c] += d[2]
    cam.provenance = dict(camera.provenance, adjusted="camera corrections estimated by misrgraph adjust")
    return att, eph, cam


def corrected_geometry(orbit_pass: OrbitPass, att: AttitudeErrorModel, eph: EphemerisErrorModel, camera: CameraModel) -> PassGeometry:
    """Pass geometry with the estimated error models removed (true = measured - error)."""
    return PassGeometry(orbit_pass.ephemeris, orbit_pass.attitude, camera, t0=orbit_pass.t0,
                        attitude_delta=lambda t: -att.evaluate(t), position_delta=lambda t: -eph.evaluate(t))


def adjust_pass(
    orbit_pass: OrbitPass,
    camera: CameraModel,
    dem: DemTiles | None,
    gcps: GcpDatabase | None,
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str], None] | None = None,
) -> AdjustResult:
    """Robust solve, blunder rejection, least-squares re-solve and marginals (module docstring)."""
    t0 = time.perf_counter()
    params = SolverParams(max_iterations=cfg.max_iterations)
    obs = orbit_pass.observations
    if progress and cfg.robust != "none":
        progress("robust solve")
    rejected, norm = find_blunders(orbit_pass, camera, dem, gcps, cfg)
    blunder_mask = rejected
    rejected, dropped = drop_unsupported_landmarks(orbit_pass, rejected)
    if progress:
        progress("least-squares solve")
    pg = build_pass_graph(orbit_pass, camera, dem, gcps, cfg.graph_config(), exclude_observations=rejected)
    res = solve(pg.problem, params.replace(backend=cfg.backend))
    if progress:
        progress("marginal covariances")
    marg = marginal_covariances(pg.problem, res.values)
    r, _ = pg.collinearity.residuals(res.values)
    resid = np.full((len(obs), 2), np.nan)
    resid[pg.obs_index[pg.collinearity.order]] = r
    att, eph, cam = _estimated_models(pg, res.values, camera)
    rej = np.flatnonzero(blunder_mask)
    return AdjustResult(pg, res.values, marg, att, eph, cam, rej, norm[rej], resid, res.iterations, res.final_error,
                        res.history, time.perf_counter() - t0, dropped)


def find_blunders(orbit_pass: OrbitPass, camera: CameraModel, dem: DemTiles | None, gcps: GcpDatabase | None,
                  cfg: AdjustConfig) -> tuple[NDArray[np.bool_], Array]:
    """Robust (per-observation) solve of one pass; observations whose whitened residual norm
    exceeds ``reject_sigma`` are blunders. Returns (rejected mask, normalised residual) per observation."""
    obs = orbit_pass.observations
    rejected = np.zeros(len(obs), bool)
    norm = np.zeros(len(obs))
    if cfg.robust == "none":
        return rejected, norm
    pg_r = build_pass_graph(orbit_pass, camera, dem, gcps,
                            cfg.graph_config(group_by="observation", robust=cfg.robust, robust_k=cfg.robust_k))
    res_r = solve(pg_r.problem, SolverParams(max_iterations=cfg.max_iterations))
    r, _ = pg_r.collinearity.residuals(res_r.values)
    whit = np.linalg.norm(r / pg_r.collinearity.sigma_px[:, None], axis=1)
    idx = pg_r.obs_index[pg_r.collinearity.order]
    norm[idx] = whit
    rejected[idx] = whit > cfg.reject_sigma
    log.info("robust solve: %d iterations; %d observations rejected (> %.1f sigma)", res_r.iterations,
             int(rejected.sum()), cfg.reject_sigma)
    return rejected, norm


def drop_unsupported_landmarks(orbit_pass: OrbitPass, rejected: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Exclude every observation of a tie point that the blunder test left unsupported.

    A landmark is dropped when more than half of its observations were rejected, or when fewer
    than two cameras still see it. Then the landmark, not its rays, is what the robust solve got
    wrong: typically a wrong terrain intersection, where the good rays look like blunders. One
    ray plus the DEM would give it a confident position that may be kilometres off. GCPs keep
    their ground prior and are never dropped; check points are not in the graph. Returns the new exclusion mask and the dropped rows.
    """
    obs = orbit_pass.observations
    kinds = orbit_pass.landmarks.kind
    n_lm = len(kinds)
    total = np.bincount(obs.landmark, minlength=n_lm)
    n_rej = np.bincount(obs.landmark[rejected], minlength=n_lm)
    keep = ~rejected
    pairs = np.unique(np.stack([obs.landmark[keep], obs.camera[keep]], 1), axis=0)
    cams_left = np.bincount(pairs[:, 0], minlength=n_lm) if pairs.size else np.zeros(n_lm, np.int64)
    drop = (kinds == KIND_TIE) & (total > 0) & ((2 * n_rej > total) | (cams_left < 2))
    rows = np.flatnonzero(drop)
    if rows.size:
        log.info("dropped %d landmarks whose rays were mostly rejected (rows %s)", rows.size, rows[:20].tolist())
    return rejected | drop[obs.landmark], rows.astype(np.int64)


# ---------------------------------------------------------------------------- scoring
def _horizontal_error(est: Array, truth: Array) -> Array:
    lat, lon, _ = ecef_to_geodetic(truth)
    enu = np.einsum("nji,nj->ni", enu_basis(lat, lon), est - truth)
    return np.hypot(enu[:, 0], enu[:, 1])


def score_pass(orbit_pass: OrbitPass, res: AdjustResult, supplied_camera: CameraModel, whole_state: bool = True) -> dict[str, Any]:
    """Accuracy against the simulator's truth (see the module docstring). ``whole_state``: also the
    joint NEES of the pass's whole state (only meaningful when the pass is the whole problem)."""
    truth = orbit_pass.truth
    if truth is None:
        return {}
    pg = res.pass_graph
    out: dict[str, Any] = {}
    t = np.arange(*orbit_pass.span, 1.024)
    d_att = res.attitude.evaluate(t) - truth.attitude_error.evaluate(t)
    out["attitude_rms_arcsec"] = {a: float(np.sqrt(np.mean(d_att[:, i] ** 2)) / ARCSEC) for i, a in enumerate(ANGLES)}
    # where the pass has data: within 30 s of an adjusted observation (elsewhere only the prior speaks)
    t_obs = np.sort(orbit_pass.observation_times()[pg.obs_index])
    j = np.clip(np.searchsorted(t_obs, t), 1, t_obs.size - 1)
    near = np.minimum(np.abs(t - t_obs[j - 1]), np.abs(t - t_obs[j])) < 30.0
    out["attitude_rms_arcsec_observed"] = {a: float(np.sqrt(np.mean(d_att[near, i] ** 2)) / ARCSEC) for i, a in enumerate(ANGLES)}
    out["observed_fraction_of_pass"] = float(near.mean())
    d_eph = res.ephemeris.evaluate(t) - truth.ephemeris_error.evaluate(t)
    out["ephemeris_rms_m"] = float(np.sqrt(np.mean(np.sum(d_eph**2, axis=1))))
    out["ephemeris_rms_m_axis"] = {ax: float(np.sqrt(np.mean(d_eph[:, i] ** 2))) for i, ax in enumerate(("along", "cross", "nadir"))}
    # check points: exact image coordinates from the truth geometry
    true_geo = orbit_pass.geometry(truth.camera_model, truth=True)
    supplied = orbit_pass.geometry(supplied_camera)
    corrected = corrected_geometry(orbit_pass, res.attitude, res.ephemeris, res.camera)
    chk = np.flatnonzero(orbit_pass.landmarks.kind == KIND_CHECK)
    cp: dict[str, Any] = {}
    coreg: dict[str, float] = {}
    if chk.size:
        g = truth.landmark_ecef[chk]
        h = ecef_to_geodetic(g)[2]
        an = CAMERAS.index("An")
        ln_an, sm_an, vis_an, ex_an, _ = true_geo.ground_to_pixel(an, RED, g)
        for c, name in enumerate(CAMERAS):
            ln, sm, vis, ex, cross_true = true_geo.ground_to_pixel(c, RED, g)
            if not vis.any():
                continue
            before = _horizontal_error(supplied.pixel_to_ground(c, RED, ln[vis], sm[vis], height=h[vis], exposure=ex[vis]), g[vis])
            after = _horizontal_error(corrected.pixel_to_ground(c, RED, ln[vis], sm[vis], height=h[vis], exposure=ex[vis]), g[vis])
            cp[name] = {"n": int(vis.sum()), "before": {"mean": float(before.mean()), "std": float(before.std())},
                        "after": {"mean": float(after.mean()), "std": float(after.std())},
                        "ratio_before_over_after": float(before.mean() / max(after.mean(), 1e-9)),
                        "_after_rms": float(np.sqrt(np.mean(after**2)))}
            # co-registration: An's view of the point geolocated with the corrected model,
            # projected into camera c with the corrected model, against the true pixel in c
            both = vis & vis_an
            if name != "An" and both.any():
                p_an = corrected.pixel_to_ground(an, RED, ln_an[both], sm_an[both], height=h[both], exposure=ex_an[both])
                _, s2, ok, _, cross2 = corrected.ground_to_pixel(c, RED, p_an)
                # continuous along-track image position (lines) and sample, against the truth
                dl = cross2[ok] - cross_true[both][ok]
                ds = s2[ok] - sm[both][ok]
                coreg[name] = float(np.sqrt(np.mean(dl**2 + ds**2)))
    if chk.size and cp:
        pred = predicted_checkpoint_rms(orbit_pass, res, g, h, true_geo)
        for name, v in pred.items():
            cp[name]["after"]["predicted_rms"] = v
            cp[name]["after"]["rms"] = cp[name].pop("_after_rms")
    out["checkpoint_geolocation_m"] = cp
    out["coregistration_px"] = coreg
    # NEES: knots with their joint covariance, landmarks with their 3x3 marginals
    keys, err = [], []
    for a in range(3):
        kt = res.attitude.knot_times[a]
        tv = np.stack([truth.attitude_error.evaluate(kt)[:, a], truth.attitude_error.rate(kt)[:, a]], -1)
        for j, k in enumerate(pg.knot_keys(a)):
            keys.append(k)
            err.append(res.values.atVector(k) - tv[j])
    e = np.concatenate(err)
    cov = res.marginals.joint_of(keys)
    nees_knots = float(e @ np.linalg.solve(cov, e) / e.size)
    lm_nees = []
    for key, row in zip(pg.landmark_keys, pg.landmark_rows):
        d = res.values.atVector(int(key)) - truth.landmark_ecef[row]
        lm_nees.append(d @ np.linalg.solve(res.marginals[int(key)], d))
    out["nees"] = {"knots": nees_knots, "landmarks": float(np.mean(lm_nees) / 3.0),
                   "knots_dim": int(e.size), "landmarks_dim": int(3 * len(lm_nees))}
    if whole_state:
        out["nees"].update(_state_nees(orbit_pass, res, supplied_camera))
    blunders = truth.blunder
    if blunders.any() or res.rejected.size:
        rej = np.zeros(blunders.size, bool)
        rej[res.rejected] = True
        out["blunders"] = {"injected": int(blunders.sum()), "rejected": int(rej.sum()),
                           "rejected_that_were_blunders": int((rej & blunders).sum())}
    return out


def _state_nees(orbit_pass: OrbitPass, res: AdjustResult, supplied_camera: CameraModel) -> dict[str, Any]:
    """The whole state jointly: e^T H e / dim with H the information matrix at the solution."""
    truth = orbit_pass.truth
    assert truth is not None
    pg = res.pass_graph
    delta: dict[int, Array] = {}
    for a in range(3):
        kt = res.attitude.knot_times[a]
        tv = np.stack([truth.attitude_error.evaluate(kt)[:, a], truth.attitude_error.rate(kt)[:, a]], -1)
        for j, k in enumerate(pg.knot_keys(a)):
            delta[k] = res.values.atVector(k) - tv[j]
    for s_, k in enumerate(pg.ephemeris_keys()):
        delta[k] = res.values.atVector(k) - truth.ephemeris_error.params[s_]
    for c, k in pg.camera_keys.items():
        tc, sc_ = truth.camera_model, supplied_camera
        delta[k] = res.values.atVector(k) - np.array([tc.delta[c] - sc_.delta[c], tc.beta[c] - sc_.beta[c], tc.epsilon[c] - sc_.epsilon[c]])
    for key, row in zip(pg.landmark_keys, pg.landmark_rows):
        delta[int(key)] = res.values.atVector(int(key)) - truth.landmark_ecef[row]
    state_dim = sum(pg.problem.dims.values())
    nees_state = information_norm(pg.problem, linearize(pg.problem, res.values), delta) / state_dim
    return {"state": nees_state, "state_dim": int(state_dim)}


def predicted_checkpoint_rms(orbit_pass: OrbitPass, res: AdjustResult, g: Array, h: Array, true_geo: PassGeometry,
                             draws: int = 40, seed: int = 0) -> dict[str, float]:
    """Horizontal RMS geolocation error of the check points predicted by the posterior covariance
    of the navigation and camera variables (Monte Carlo through the geolocation, fixed seed)."""
    pg = res.pass_graph
    keys = [k for a in range(3) for k in pg.knot_keys(a)] + pg.ephemeris_keys() + list(pg.camera_keys.values())
    cov = res.marginals.joint_of(keys)
    mean = np.concatenate([res.values.atVector(k) for k in keys])
    rng = np.random.default_rng(seed)
    chol = np.linalg.cholesky(0.5 * (cov + cov.T) + 1e-30 * np.eye(cov.shape[0]))
    base_geo = corrected_geometry(orbit_pass, res.attitude, res.ephemeris, res.camera)
    supplied = _supplied_of(res)
    sq: dict[str, list[Array]] = {}
    pix = {c: true_geo.ground_to_pixel(c, RED, g) for c in range(len(CAMERAS))}
    base = {c: base_geo.pixel_to_ground(c, RED, p.line[p.visible], p.sample[p.visible], height=h[p.visible],
                                        exposure=p.exposure[p.visible]) for c, p in pix.items() if p.visible.any()}
    for _ in range(draws):
        x = mean + chol @ rng.standard_normal(mean.size)
        v = gtsam.Values()
        for k, seg in zip(keys, np.split(x, np.cumsum([res.values.atVector(k).size for k in keys])[:-1])):
            v.insert(k, seg)
        att, eph, cam = _estimated_models(pg, v, supplied)
        geo = corrected_geometry(orbit_pass, att, eph, cam)
        for c, p in pix.items():
            if c not in base:
                continue
            gd = geo.pixel_to_ground(c, RED, p.line[p.visible], p.sample[p.visible], height=h[p.visible], exposure=p.exposure[p.visible])
            sq.setdefault(CAMERAS[c], []).append(_horizontal_error(gd, base[c]) ** 2)
    return {name: float(np.sqrt(np.mean(v))) for name, v in sq.items()}


def _supplied_of(res: AdjustResult) -> CameraModel:
    """The camera model before this adjustment's corrections (corrections are stored in values)."""
    cam = res.camera.copy()
    for c, k in res.pass_graph.camera_keys.items():
        d = res.values.atVector(k)
        cam.delta[c] -= d[0]
        cam.beta[c] -= d[1]
        cam.epsilon[c] -= d[2]
    return cam


# ---------------------------------------------------------------------------- I/O and entry point
def _write_result(path: Path, orbit_pass: OrbitPass, res: AdjustResult, summary: dict[str, Any], provenance: dict[str, str]) -> None:
    pg = res.pass_graph
    with atomic_h5(path, "adjustment_result") as f:
        f.attrs["pass_id"] = orbit_pass.pass_id
        f.attrs["software"] = f"misrgraph {__version__}"
        f.attrs["summary_json"] = json.dumps(summary)
        prov = f.create_group("provenance")
        for k, v in provenance.items():
            prov.attrs[k] = str(v)
        a = f.create_group("attitude_error")
        for i, name in enumerate(ANGLES):
            g = a.create_group(name)
            keys = pg.knot_keys(i)
            write_dataset(g, "knot_times", res.attitude.knot_times[i], units="s")
            write_dataset(g, "knots", res.attitude.knots[i], units="rad, rad/s")
            write_dataset(g, "covariance", np.stack([res.marginals[k] for k in keys]), units="rad^2, rad^2/s, rad^2/s^2")
            write_dataset(g, "joint_covariance", res.marginals.joint_of(keys), order="knot-major (value, rate)")
            write_dataset(g, "removed_knots", pg.removed_knots[i], meaning="indices on the uniform grid, eqs. 28-29")
            write_dataset(g, "grid_spacing", np.array(float(pg.attitude_model.knot_times[i][1] - pg.attitude_model.knot_times[i][0])
                                                       if pg.removed_knots[i].size == 0 else np.nan), units="s")
        e = f.create_group("ephemeris_error")
        write_dataset(e, "boundaries", res.ephemeris.boundaries, units="s")
        write_dataset(e, "params", res.ephemeris.params, units="m/s (a), m (b)", order="a_x,a_y,a_z,b_x,b_y,b_z")
        write_dataset(e, "covariance", np.stack([res.marginals[k] for k in pg.ephemeris_keys()]))
        c = f.create_group("camera_corrections")
        cams = sorted(pg.camera_keys)
        write_dataset(c, "camera", np.array(cams, np.int64))
        write_dataset(c, "values", np.array([res.values.atVector(pg.camera_keys[k]) for k in cams]).reshape(-1, 3), units="rad", order="delta,beta,epsilon")
        write_dataset(c, "covariance", np.array([res.marginals[pg.camera_keys[k]] for k in cams]).reshape(-1, 3, 3), units="rad^2")
        lm = f.create_group("landmarks")
        write_dataset(lm, "row", pg.landmark_rows)
        write_dataset(lm, "kind", orbit_pass.landmarks.kind[pg.landmark_rows], meaning="0 tie, 1 GCP")
        write_dataset(lm, "ecef", np.array([res.values.atVector(int(k)) for k in pg.landmark_keys]), units="m")
        write_dataset(lm, "covariance", np.array([res.marginals[int(k)] for k in pg.landmark_keys]), units="m^2")
        if orbit_pass.truth is not None:
            write_dataset(lm, "truth_ecef", orbit_pass.truth.landmark_ecef[pg.landmark_rows], units="m")
        o = f.create_group("observations")
        write_dataset(o, "residual_px", res.residuals_px, units="pixel", order="along,cross; NaN = not adjusted")
        write_dataset(o, "camera", orbit_pass.observations.camera.astype(np.int8))
        write_dataset(o, "rejected", res.rejected, meaning="observation indices rejected as blunders")
        write_dataset(o, "rejected_normalised_residual", res.rejected_norm, units="sigma")
        h = f.create_group("convergence")
        write_dataset(h, "error", np.asarray(res.history), meaning="0.5 * sum of squared whitened residuals per iteration")
        res.camera.write_group(f.create_group("camera_model"))


def run_adjust(
    scenario_dir: str | os.PathLike[str],
    camera_model: str | os.PathLike[str] | None = None,
    pass_file: str | os.PathLike[str] | None = None,
    gcp_file: str | os.PathLike[str] | None = None,
    dem_file: str | os.PathLike[str] | None = None,
    out: str | os.PathLike[str] | None = None,
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Adjust one pass of a scenario directory; write RESULT.h5 when ``out`` is given; return the summary."""
    d = Path(scenario_dir)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate'")
    cam_path = Path(camera_model) if camera_model else d / "camera_model.h5"
    if pass_file is None:
        passes = sorted((d / "passes").glob("*.h5"))
        if not passes:
            raise FileFormatError(d / "passes", "no pass files (*.h5)")
        pass_file = passes[0]
    orbit_pass = OrbitPass.load(pass_file)
    camera = load_camera_model(cam_path).at_temperature(orbit_pass.temperature_c)
    gcps = GcpDatabase.load(gcp_file or d / "gcp.h5")
    dem = DemTiles.load(dem_file or d / "dem.h5")
    res = adjust_pass(orbit_pass, camera, dem, gcps, cfg, progress)
    pg = res.pass_graph
    summary: dict[str, Any] = {
        "pass_id": orbit_pass.pass_id,
        "iterations": res.iterations,
        "final_cost": res.final_cost,
        "seconds": res.seconds,
        "observations": int(len(pg.collinearity)),
        "landmarks": int(pg.landmark_keys.size),
        "dropped_tie_points": int(res.dropped_landmarks.size),
        "knots": {a: {"kept": int(res.attitude.knot_times[i].size), "removed": int(pg.removed_knots[i].size)}
                  for i, a in enumerate(ANGLES)},
        "rejected_observations": capped_list(
            [{"index": int(i), "camera": CAMERAS[int(orbit_pass.observations.camera[i])],
              "landmark_kind": "gcp" if orbit_pass.landmarks.kind[orbit_pass.observations.landmark[i]] == KIND_GCP else "tie",
              "normalised_residual": float(n)} for i, n in zip(res.rejected, res.rejected_norm)],
            f"{out}:/observations/rejected" if out is not None else None, group_by=("camera", "landmark_kind")),
        "ephemeris": {"params": res.ephemeris.params.tolist(),
                      "sigma": [np.sqrt(np.diag(res.marginals[k])).tolist() for k in pg.ephemeris_keys()]},
    }
    diagnostics = []
    obs = orbit_pass.observations
    is_gcp = orbit_pass.landmarks.kind[obs.landmark] == KIND_GCP
    n_gcp = int(is_gcp.sum())
    n_gcp_rej = int(is_gcp[res.rejected].sum()) if res.rejected.size else 0
    if n_gcp == 0:
        diagnostics.append("no GCP observations on this pass: absolute accuracy rests on the DEM and the navigation priors")
    elif n_gcp_rej == n_gcp:
        diagnostics.append(f"all {n_gcp} GCP observations were rejected as blunders: absolute accuracy rests on the DEM "
                           "and the navigation priors; check the GCP database")
    removed = sum(int(r.size) for r in pg.removed_knots)
    if removed:
        diagnostics.append(f"{removed} knots removed by eqs. 28-29 (too few tie points or cameras): the spline spans the gaps")
    summary["diagnostics"] = diagnostics
    summary.update(score_pass(orbit_pass, res, camera))
    if out is not None:
        _write_result(Path(out), orbit_pass, res, summary,
                      {"scenario": str(d), "pass_file": str(pass_file), "camera_model": str(cam_path),
                       "config": json.dumps(dataclasses.asdict(cfg)), "software": f"misrgraph {__version__}"})
    return summary
