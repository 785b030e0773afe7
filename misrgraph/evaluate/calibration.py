"""Scoring a camera calibration against the simulator's true camera model.

:func:`score_calibration` adds to the estimator's summary (:func:`misrgraph.estimate.calibrate.summarise`):
per camera the pointing error of the calibrated and of the supplied model against the truth
(pixels, RMS over the swath, worst over the passes' temperatures and the calibrated bands), the
largest of them, the NEES of the corrections (truth minus supplied model, each temperature bin at
its temperature), the mean squared error of each camera's angle *given the other cameras'*
(``nees_given_others``: ``z_c = (e_c - b^T e_o) / s'_c`` of
:func:`misrgraph.evaluate.drift.conditional_series`, pooled over the cameras and the angles
``delta``, ``beta``, ``epsilon``; 1 when the covariance's share of error between cameras is
right, which the drift monitor's conditional view relies on) and, with temperature bins, each
slope's true value and z-score and the slopes' joint NEES (the true slope is the truth's change
across the bins' extreme temperatures, exact for a truth linear in temperature).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from misrgraph.estimate.calibrate import (
    RED,
    CalibrateConfig,
    CalibrationResult,
    calibrated_bands,
    calibrated_models,
    camera_keys,
    decode_camera_key,
    evaluation_grid,
    param_value,
    pointing_error_px,
    slope_estimates,
    supplied_models_at,
)
from misrgraph.model.camera import CameraModel, TabulatedCameraModel
from misrgraph.model.constants import CAMERAS

__all__ = ["score_calibration", "true_corrections", "given_others_z"]

Array = NDArray[np.float64]


def score_calibration(
    summary: dict[str, Any],
    res: CalibrationResult,
    cfg: CalibrateConfig,
    supplied: CameraModel,
    truth: CameraModel | TabulatedCameraModel,
) -> dict[str, Any]:
    """``summary`` with the scores against ``truth`` added (in place; also returned)."""
    grid = evaluation_grid(res, supplied, thermal=isinstance(truth, TabulatedCameraModel))
    est_at = calibrated_models(res, cfg, supplied, grid)
    sup_at = supplied_models_at(res, supplied, grid)
    for name, entry in summary["cameras"].items():
        c = CAMERAS.index(name)
        bands = calibrated_bands(res, cfg, c)
        entry["pointing_error_px"] = max(
            pointing_error_px(e, truth.at_temperature(t), c, b) for e, t in zip(est_at, grid) for b in bands
        )
        entry["pointing_error_before_px"] = max(
            pointing_error_px(m, truth.at_temperature(t), c, b) for m, t in zip(sup_at, grid) for b in bands
        )
    if "thermal" in summary:
        _score_slopes(summary["thermal"], res, cfg, truth)
    summary["max_pointing_error_px"] = max(v["pointing_error_px"] for v in summary["cameras"].values())
    e = res.values - true_corrections(res, cfg, supplied, truth)
    summary["nees"] = float(e @ np.linalg.solve(res.covariance, e) / e.size)
    summary["nees_dim"] = int(e.size)
    z = given_others_z(res.labels, e, res.covariance)
    if z.size:
        summary["nees_given_others"] = float(np.mean(z**2))
        summary["nees_given_others_dim"] = int(z.size)
    return summary


def given_others_z(
    labels: list[str], e: Array, cov: Array, params: tuple[str, ...] = ("delta", "beta", "epsilon")
) -> Array:
    """Each camera's standardised error given the other cameras' (``(9 * len(params),)``, camera
    by camera within each parameter; empty when the labels do not hold every camera's camera-level
    ``"<camera>.<param>"``): errors ``e`` and covariance ``cov`` over ``labels``."""
    from misrgraph.evaluate.drift import conditional_series

    try:
        idx = {par: [labels.index(f"{cam}.{par}") for cam in CAMERAS] for par in params}
    except ValueError:
        return np.zeros(0)
    one = np.zeros(1)
    series = {(cam, par): (one, e[i : i + 1], one) for par in params for cam, i in zip(CAMERAS, idx[par])}
    cond, _ = conditional_series(series, {par: cov[np.ix_(ix, ix)][None] for par, ix in idx.items()}, CAMERAS)
    return np.array([cond[cam, par][1][0] / cond[cam, par][2][0] for par in params for cam in CAMERAS])


def _score_slopes(
    thermal: dict[str, Any], res: CalibrationResult, cfg: CalibrateConfig, truth: CameraModel | TabulatedCameraModel
) -> None:
    est = slope_estimates(res, cfg)
    sig_s = np.sqrt(np.diag(est.cov))
    true_s = []
    for (cam, p), (c, band, j, t) in zip(est.names, est.groups):
        b = RED if band is None else band
        lo, hi = truth.at_temperature(float(t.min())), truth.at_temperature(float(t.max()))
        true_s.append((param_value(hi, p, c, b) - param_value(lo, p, c, b)) / (t.max() - t.min()))
    for i, (cam, p) in enumerate(est.names):
        thermal["slopes"][cam][p].update(
            true_slope_per_c=float(true_s[i]), z=float((est.slope[i] - true_s[i]) / sig_s[i])
        )
    err = est.slope - np.array(true_s)
    thermal["nees"] = float(err @ np.linalg.solve(est.cov, err) / err.size)
    thermal["nees_dim"] = int(err.size)


def true_corrections(
    res: CalibrationResult, cfg: CalibrateConfig, supplied: CameraModel, truth: "CameraModel | TabulatedCameraModel"
) -> Array:
    """Truth minus supplied model for every estimated correction, each bin at its temperature."""
    out = []
    bases = res.supplied_models or [supplied]
    for ck in camera_keys(res, cfg):
        t_bin, c, band = decode_camera_key(ck, cfg)
        b = RED if band is None else band
        base = bases[t_bin]
        tm = truth.at_temperature(float(res.bin_temperatures_c[t_bin]))
        for p in cfg.params:
            out.append(param_value(tm, p, c, b) - param_value(base, p, c, b))
    if cfg.estimate_omega:
        tm = truth.at_temperature(float(res.bin_temperatures_c[0]))
        out += list(tm.omega - bases[0].omega)
    return np.array(out)
