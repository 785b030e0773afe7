"""Scoring a pass adjustment against the simulator's truth.

:func:`score_pass` gives attitude and ephemeris RMS over the pass, check-point geolocation
before/after (exact image coordinates of the check points from the true geometry, geolocated onto
their true height with the supplied and with the corrected navigation, so the figure measures the
navigation/camera model only), co-registration of every camera against An in pixels, the
check-point RMS the posterior covariance predicts (:func:`predicted_checkpoint_rms`), and NEES
(divided by its dimension) of the knots (joint covariance), the landmarks and the whole state.
"""

from __future__ import annotations

from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.collinearity import camera_param_scale
from misrgraph.estimate.adjust import AdjustResult, corrected_geometry, estimated_models, supplied_camera_of
from misrgraph.estimate.calibrate import param_value
from misrgraph.estimate.solver import information_norm_split, linearize
from misrgraph.evaluate.landmarks import LANDMARK_GROUP_S, landmark_nees_split, time_groups
from misrgraph.io.passes import KIND_CHECK, OrbitPass
from misrgraph.io.truth import PassTruth
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import ANGLES, ARCSEC, BANDS, CAMERAS
from misrgraph.model.errormodels import AttitudeErrorModel, spline_design
from misrgraph.model.frames import ecef_to_geodetic, enu_basis
from misrgraph.model.geolocation import PassGeometry

__all__ = [
    "score_pass",
    "geolocation_errors",
    "predicted_checkpoint_rms",
    "landmark_split",
    "horizontal_error",
    "true_knots",
]

Array = NDArray[np.float64]
RED = BANDS.index("red")


def horizontal_error(est: Array, truth: Array) -> Array:
    lat, lon, _ = ecef_to_geodetic(truth)
    enu = np.einsum("nji,nj->ni", enu_basis(lat, lon), est - truth)
    return np.hypot(enu[:, 0], enu[:, 1])


def score_pass(
    orbit_pass: OrbitPass,
    truth: PassTruth,
    res: AdjustResult,
    supplied_camera: CameraModel,
    whole_state: bool = True,
    points: bool = False,
) -> dict[str, Any]:
    """Accuracy against the simulator's truth (see the module docstring). ``whole_state``: also the
    joint NEES of the pass's whole state (only meaningful when the pass is the whole problem).
    ``points``: also ``checkpoint_points`` -- each check point's geodetic ``lat``/``lon`` (deg) and
    ``rms_m``, the RMS over the cameras that see it of its horizontal error after adjustment (the
    campaign's world map)."""
    pg = res.pass_graph
    out: dict[str, Any] = {}
    t = np.arange(*orbit_pass.span, 1.024)
    d_att = res.attitude.evaluate(t) - truth.attitude_error.evaluate(t)
    out["attitude_rms_arcsec"] = {a: float(np.sqrt(np.mean(d_att[:, i] ** 2)) / ARCSEC) for i, a in enumerate(ANGLES)}
    # where the pass has data: within 30 s of an adjusted observation (elsewhere only the prior speaks)
    t_obs = np.sort(orbit_pass.observation_times()[pg.obs_index])
    j = np.clip(np.searchsorted(t_obs, t), 1, t_obs.size - 1)
    near = np.minimum(np.abs(t - t_obs[j - 1]), np.abs(t - t_obs[j])) < 30.0
    out["attitude_rms_arcsec_observed"] = {
        a: float(np.sqrt(np.mean(d_att[near, i] ** 2)) / ARCSEC) for i, a in enumerate(ANGLES)
    }
    out["observed_fraction_of_pass"] = float(near.mean())
    d_eph = res.ephemeris.evaluate(t) - truth.ephemeris_error.evaluate(t)
    out["ephemeris_rms_m"] = float(np.sqrt(np.mean(np.sum(d_eph**2, axis=1))))
    out["ephemeris_rms_m_axis"] = {
        ax: float(np.sqrt(np.mean(d_eph[:, i] ** 2))) for i, ax in enumerate(("along", "cross", "nadir"))
    }
    # check points: exact image coordinates from the truth geometry
    true_geo = truth.geometry(orbit_pass)
    supplied = orbit_pass.geometry(supplied_camera)
    corrected = corrected_geometry(orbit_pass, res.attitude, res.ephemeris, res.camera)
    chk = np.flatnonzero(orbit_pass.landmarks.kind == KIND_CHECK)
    cp: dict[str, Any] = {}
    coreg: dict[str, float] = {}
    if chk.size:
        g = truth.landmark_ecef[chk]
        h = ecef_to_geodetic(g)[2]
        sq_sum, n_seen = np.zeros(chk.size), np.zeros(chk.size)
        for c, name, vis, (before, after), co in _checkpoint_errors(true_geo, [supplied, corrected], g, h):
            sq_sum[vis] += after**2
            n_seen[vis] += 1
            cp[name] = {
                "n": int(vis.sum()),
                "before": {"mean": float(before.mean()), "std": float(before.std())},
                "after": {"mean": float(after.mean()), "std": float(after.std())},
                "ratio_before_over_after": float(before.mean() / max(after.mean(), 1e-9)),
                "_after_rms": float(np.sqrt(np.mean(after**2))),
            }
            if co is not None:
                coreg[name] = float(np.sqrt(np.mean(co**2)))
    if chk.size and cp:
        pred = predicted_checkpoint_rms(orbit_pass, res, g, h, true_geo)
        for name, v in pred.items():
            cp[name]["after"]["predicted_rms"] = v
            cp[name]["after"]["rms"] = cp[name].pop("_after_rms")
    out["checkpoint_geolocation_m"] = cp
    out["coregistration_px"] = coreg
    if points and chk.size:
        lat, lon, _ = ecef_to_geodetic(g)
        seen = n_seen > 0
        out["checkpoint_points"] = {
            "lat": np.round(lat[seen], 5).tolist(),
            "lon": np.round(lon[seen], 5).tolist(),
            "rms_m": np.round(np.sqrt(sq_sum[seen] / n_seen[seen]), 2).tolist(),
        }
    # NEES per class, each with its (joint) covariance. Parameter-wise ephemeris and whole-state
    # NEES need the truth in the estimator's own parameterisation (the same eq. 19 segments); an
    # independent truth has none.
    same_eph = truth.ephemeris_error.boundaries.shape == res.ephemeris.boundaries.shape and np.allclose(
        truth.ephemeris_error.boundaries, res.ephemeris.boundaries
    )
    delta = _true_deltas(truth, res, supplied_camera, same_eph)
    knot_keys = [k for a in range(3) for k in pg.knot_keys(a)]
    out["nees"] = _joint_nees(res, delta, knot_keys, "knots")
    lm_nees = [delta[int(k)] @ np.linalg.solve(res.marginals[int(k)], delta[int(k)]) for k in pg.landmark_keys]
    out["nees"].update(landmarks=float(np.mean(lm_nees) / 3.0), landmarks_dim=int(3 * len(lm_nees)))
    split = landmark_split(orbit_pass, truth, res, delta)
    if split is not None:
        out["landmark_split"] = split
        out["nees"].update(landmarks_common=split["common"], landmarks_common_dim=split["common_dim"])
        if split["within_dim"]:
            out["nees"].update(landmarks_within=split["within"], landmarks_within_dim=split["within_dim"])
    if same_eph:
        out["nees"].update(_joint_nees(res, delta, pg.ephemeris_keys(), "ephemeris"))
    if pg.camera_keys:
        out["nees"].update(_joint_nees(res, delta, list(pg.camera_keys.values()), "camera"))
    if cp and all("predicted_rms" in v["after"] for v in cp.values()):
        n = np.array([v["n"] for v in cp.values()], float)
        act = np.array([v["after"]["rms"] for v in cp.values()])
        pred = np.array([v["after"]["predicted_rms"] for v in cp.values()])
        out["checkpoint_rms_over_predicted"] = float(np.sqrt(np.sum(n * act**2) / np.sum(n * pred**2)))
    out["truth_in_estimator_parameterisation"] = bool(same_eph)
    if whole_state and same_eph:
        state_dim = sum(pg.problem.dims.values())
        lm_keys = [int(k) for k in pg.landmark_keys]
        lm_dim = sum(pg.problem.dims[k] for k in lm_keys)
        part, rest = information_norm_split(linearize(pg.problem, res.values), delta, lm_keys, res.landmark_extra_cov)
        # the whole state's NEES split exactly: the landmarks given the other variables' errors
        # (triangulation with exact navigation and camera) and the others jointly
        out["nees"].update(
            state=(part + rest) / state_dim,
            state_dim=int(state_dim),
            state_landmarks_given_rest=part / max(lm_dim, 1),
            state_landmarks_given_rest_dim=int(lm_dim),
            state_rest=rest / max(state_dim - lm_dim, 1),
            state_rest_dim=int(state_dim - lm_dim),
        )
    blunders = truth.blunder
    if blunders.any() or res.rejected.size:
        rej = np.zeros(blunders.size, bool)
        rej[res.rejected] = True
        # observations of a tie point dropped whole (most of its rays rejected) are out of the solution too
        excluded = rej | np.isin(orbit_pass.observations.landmark, res.dropped_landmarks)
        out["blunders"] = {
            "injected": int(blunders.sum()),
            "rejected": int(rej.sum()),
            "rejected_that_were_blunders": int((rej & blunders).sum()),
            "left_in_solution": int((blunders & ~excluded).sum()),
        }
    return out


def _checkpoint_errors(true_geo: PassGeometry, geometries: list[PassGeometry], g: Array, h: Array):
    """Per camera that sees any of the check points ``g`` (ECEF m, ``(P, 3)``; ellipsoidal heights
    ``h`` m): ``(camera index, name, visible (P,) bool, [horizontal error (m) of each geometry of
    ``geometries`` at the visible points], co-registration error (px) of the last geometry or None)``.

    Each check point's exact image coordinates come from the true geometry; each geometry
    geolocates them onto the point's true height. Co-registration (not for An): An's view of the
    point geolocated with the last geometry and projected into the camera with it, against the
    true continuous line and sample there."""
    an = CAMERAS.index("An")
    ln_an, sm_an, vis_an, ex_an, _ = true_geo.ground_to_pixel(an, RED, g)
    last = geometries[-1]
    for c, name in enumerate(CAMERAS):
        ln, sm, vis, ex, cross_true = true_geo.ground_to_pixel(c, RED, g)
        if not vis.any():
            continue
        errs = [
            horizontal_error(geo.pixel_to_ground(c, RED, ln[vis], sm[vis], height=h[vis], exposure=ex[vis]), g[vis])
            for geo in geometries
        ]
        co = None
        both = vis & vis_an
        if name != "An" and both.any():
            p_an = last.pixel_to_ground(an, RED, ln_an[both], sm_an[both], height=h[both], exposure=ex_an[both])
            _, s2, ok, _, cross2 = last.ground_to_pixel(c, RED, p_an)
            co = np.hypot(cross2[ok] - cross_true[both][ok], s2[ok] - sm[both][ok])
        yield c, name, vis, errs, co


def geolocation_errors(
    orbit_pass: OrbitPass, truth: PassTruth, attitude: AttitudeErrorModel, ephemeris: Any, camera: CameraModel
) -> dict[str, float | None]:
    """Check-point geolocation and co-registration of a pass corrected with the given error
    models (as :func:`score_pass` measures them), pooled over cameras: ``checkpoint_rms_m`` (RMS
    horizontal error, m, over every camera's view of every check point) and ``coregistration_px``
    (RMS over every camera but An, px); None where the pass has no check points."""
    chk = np.flatnonzero(orbit_pass.landmarks.kind == KIND_CHECK)
    if not chk.size:
        return {"checkpoint_rms_m": None, "coregistration_px": None}
    g = truth.landmark_ecef[chk]
    h = ecef_to_geodetic(g)[2]
    corrected = corrected_geometry(orbit_pass, attitude, ephemeris, camera)
    after, co = [], []
    for _, _, _, (err,), c in _checkpoint_errors(truth.geometry(orbit_pass), [corrected], g, h):
        after.append(err)
        if c is not None:
            co.append(c)

    def rms(a):
        return float(np.sqrt(np.mean(np.concatenate(a) ** 2))) if a else None

    return {"checkpoint_rms_m": rms(after), "coregistration_px": rms(co)}


def true_knots(truth: PassTruth, knot_times: Array, angle: int, step_s: float = 1.0) -> Array:
    """The true values ``(K, 2)`` (rad, rad/s) of the estimator's knots of one angle.

    When the truth is a spline on the same knots (``truth="model"``) these are its knots. Otherwise
    (an independent truth, e.g. with jitter) the estimator's spline cannot represent the truth, and
    the value it estimates is the truth's least-squares projection onto the spline space: the knots
    whose spline is closest to the true error sampled every ``step_s`` over the knots' span (within
    the pass)."""
    tt = truth.attitude_error.knot_times[angle]
    if tt.shape == knot_times.shape and np.allclose(tt, knot_times):
        return truth.attitude_error.knots[angle]
    # sampled where the truth is defined (the estimator's end knots may lie beyond the pass)
    t = np.arange(max(knot_times[0], tt[0]), min(knot_times[-1], tt[-1]) + 0.5 * step_s, step_s)
    sol, *_ = np.linalg.lstsq(spline_design(knot_times, t), truth.attitude_error.evaluate(t)[:, angle], rcond=None)
    return sol.reshape(-1, 2)


def _true_deltas(
    truth: PassTruth, res: AdjustResult, supplied_camera: CameraModel, with_ephemeris: bool
) -> dict[int, Array]:
    """Estimate minus truth for every knot (against :func:`true_knots`), camera correction
    (truth minus supplied model), landmark and, ``with_ephemeris``, ephemeris segment."""
    pg = res.pass_graph
    delta: dict[int, Array] = {}
    for a in range(3):
        tv = true_knots(truth, res.attitude.knot_times[a], a)
        for j, k in enumerate(pg.knot_keys(a)):
            delta[k] = res.values.atVector(k) - tv[j]
    if with_ephemeris:
        for s_, k in enumerate(pg.ephemeris_keys()):
            delta[k] = res.values.atVector(k) - truth.ephemeris_error.params[s_]
    tc, sc_ = truth.camera_model, supplied_camera
    scale = camera_param_scale(pg.camera_params)
    for c, k in pg.camera_keys.items():  # camera-level corrections (the red band's values)
        true_corr = np.array([_camera_level(tc, p, c) - _camera_level(sc_, p, c) for p in pg.camera_params])
        delta[k] = res.values.atVector(k) - true_corr / scale
    for key, row in zip(pg.landmark_keys, pg.landmark_rows):
        delta[int(key)] = res.values.atVector(int(key)) - truth.landmark_ecef[row]
    return delta


def _camera_level(m: CameraModel, param: str, c: int) -> float:
    """Camera ``c``'s camera-level value of ``param`` (SI): an angle without any band's offset, f
    and alpha_i the red band's (:func:`misrgraph.estimate.calibrate.param_value`)."""
    return float(getattr(m, param)[c]) if param in ("delta", "beta", "epsilon") else param_value(m, param, c, RED)


def _joint_nees(res: AdjustResult, delta: dict[int, Array], keys: list[int], name: str) -> dict[str, Any]:
    """NEES/dim of several variables with their joint covariance: ``{name, name_dim}``."""
    e = np.concatenate([delta[k] for k in keys])
    return {name: float(e @ np.linalg.solve(res.marginals.joint_of(keys), e) / e.size), f"{name}_dim": int(e.size)}


def landmark_split(
    orbit_pass: OrbitPass,
    truth: PassTruth,
    res: AdjustResult,
    delta: dict[int, Array],
    window_s: float = LANDMARK_GROUP_S,
) -> dict[str, Any] | None:
    """The landmark NEES split into the part landmarks seen within ``window_s`` of each other
    share and the part each has alone (:func:`misrgraph.evaluate.landmarks.landmark_nees_split`),
    in each landmark's local east, north, up, over the landmarks with adjusted observations
    (grouped by their mean observation time). ``delta``: estimate minus truth per landmark key.
    None when the marginals hold no landmark response (joint-only marginals)."""
    pg = res.pass_graph
    if res.marginals.landmark_response is None or not len(pg.landmark_keys):
        return None
    obs = orbit_pass.observations
    rows = obs.landmark[pg.obs_index]
    t = orbit_pass.observation_times()[pg.obs_index]
    n_rows = len(orbit_pass.landmarks.kind)
    count = np.bincount(rows, minlength=n_rows)
    mean_t = np.bincount(rows, weights=t, minlength=n_rows) / np.maximum(count, 1)
    lm_rows = np.asarray(pg.landmark_rows)
    seen = count[lm_rows] > 0
    keys = [int(k) for k, ok in zip(pg.landmark_keys, seen) if ok]
    if not keys:
        return None
    lat, lon, _ = ecef_to_geodetic(truth.landmark_ecef[lm_rows[seen]])
    enu = enu_basis(lat, lon)  # (L, 3, 3), columns east, north, up
    err = np.einsum("lij,li->lj", enu, np.array([delta[k] for k in keys]))
    cov = np.einsum("lji,ljk,lkm->lim", enu, np.array([res.marginals[k] for k in keys]), enu)
    resp = np.einsum("lji,ljc->lic", enu, res.marginals.landmark_response_of(keys))
    out = landmark_nees_split(err, cov, resp, res.marginals.joint, time_groups(mean_t[lm_rows[seen]], window_s))
    return {"window_s": float(window_s), "landmarks": len(keys), **out}


def predicted_checkpoint_rms(
    orbit_pass: OrbitPass, res: AdjustResult, g: Array, h: Array, true_geo: PassGeometry, rel_step: float = 1.0
) -> dict[str, float]:
    """Per camera, the horizontal RMS geolocation error (m) of the check points ``g`` (ECEF m,
    ``(P, 3)``, ellipsoidal heights ``h`` m, seen at their true image positions) that the
    posterior predicts: the joint covariance ``S = L L^T`` of the knots, ephemeris and camera
    variables, plus the attitude error the knots cannot follow (``res.unresolved_attitude_rad``
    per angle, independent between check-point views), propagated linearly through the
    geolocation.

    With ``e(x)`` the points' horizontal displacements (m) when the state moves to ``x``, the
    predicted mean square is ``sum_i |e(x + rel_step l_i) - e(x)|^2 / rel_step^2`` over the
    columns ``l_i`` of ``L`` (exact to first order: ``tr(G S G^T)`` with ``G = de/dx``), plus
    ``sigma_u^2 sum_a |de/d(angle a)|^2`` with each angle offset by ``sigma_u`` over the whole
    pass (a view's displacement depends on the angle at its own time only). ``rel_step``: the step
    in units of 1 sigma (the geolocation is linear over it). One geolocation per column: no
    sampling error, unlike a Monte Carlo of a few draws, whose error would be the same in every
    pass scored with the same draws."""
    pg = res.pass_graph
    keys = [k for a in range(3) for k in pg.knot_keys(a)] + pg.ephemeris_keys() + list(pg.camera_keys.values())
    cov = res.marginals.joint_of(keys)
    mean = np.concatenate([res.values.atVector(k) for k in keys])
    sizes = np.cumsum([res.values.atVector(k).size for k in keys])[:-1]
    chol = np.linalg.cholesky(0.5 * (cov + cov.T) + 1e-30 * np.eye(cov.shape[0]))
    supplied = supplied_camera_of(res)
    # every camera's views of the check points, stacked: one geolocation call per state column
    views = [
        (c, p, np.flatnonzero(p.visible))
        for c, p in ((c, true_geo.ground_to_pixel(c, RED, g)) for c in range(len(CAMERAS)))
        if p.visible.any()
    ]
    if not views:
        return {}
    cam_of = np.concatenate([np.full(i.size, c) for c, _, i in views])
    line, sample, expo = (
        np.concatenate([getattr(p, a)[i] for _, p, i in views]) for a in ("line", "sample", "exposure")
    )
    height = np.concatenate([h[i] for _, _, i in views])

    def ground(
        att: AttitudeErrorModel, eph: Any, cam: CameraModel, extra: Callable[[Array], Array] | None = None
    ) -> Array:
        geo = corrected_geometry(orbit_pass, att, eph, cam, attitude_extra=extra)
        return geo.pixel_to_ground(cam_of, RED, line, sample, height=height, exposure=expo)

    def models_at(x: Array) -> tuple[AttitudeErrorModel, Any, CameraModel]:
        v = gtsam.Values()
        for k, seg in zip(keys, np.split(x, sizes)):
            v.insert(k, seg)
        return estimated_models(pg, v, supplied)

    base = ground(res.attitude, res.ephemeris, res.camera)
    sq = np.zeros(base.shape[0])
    for i in range(mean.size):
        sq += horizontal_error(ground(*models_at(mean + rel_step * chol[:, i])), base) ** 2
    sig = float(res.unresolved_attitude_rad)
    if sig > 0:
        for a in range(3):
            off = np.zeros(3)
            off[a] = sig * rel_step
            sq += (
                horizontal_error(
                    ground(
                        res.attitude, res.ephemeris, res.camera, lambda t, o=off: np.broadcast_to(o, (np.size(t), 3))
                    ),
                    base,
                )
                ** 2
            )
    sq /= rel_step**2
    return {CAMERAS[c]: float(np.sqrt(np.mean(sq[cam_of == c]))) for c, _, _ in views}
