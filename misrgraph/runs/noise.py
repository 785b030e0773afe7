"""``misrgraph noise fit``: a noise model learned from adjusted passes (:mod:`misrgraph.estimate.noisefit`)."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from misrgraph.errors import FileFormatError
from misrgraph.estimate.noisefit import NoiseFit, PassLevels, fit_noise_model
from misrgraph.model.constants import ANGLES
from misrgraph.model.noise import LEVELS, NoiseModel

__all__ = ["read_pass_levels", "pass_levels_of", "fit_and_save", "run_noise_fit"]

log = logging.getLogger(__name__)


def _classes(rel: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The observation classes' variance components in an adjustment's reliability summary:
    ``{name: {"kind", "factor" (scale * sigma0), "redundancy"}}``; the DEM's ``factor`` is its
    sigma0 alone, with the pass's ``"scale"`` on its DEM scale and ``"stated_share"`` beside it
    (:class:`PassLevels`, :func:`~misrgraph.estimate.reliability.class_scale`)."""
    classes: dict[str, dict[str, Any]] = {}
    for name, v in ((rel.get("observation_sigma") or {}).get("classes") or {}).items():
        classes[name] = {
            "kind": "gcp" if name == "GCP" else "tie",
            "factor": float(v["scale"]) * float(v["sigma0"]),
            "redundancy": float(v["redundancy"]),
        }
    if not classes:  # a result written before the per-class variance components: the stated sigmas
        for name, v in (rel.get("variance_components") or {}).items():
            if name in ("tie-point observations", "GCP observations"):
                classes[name] = {
                    "kind": "gcp" if name.startswith("GCP") else "tie",
                    "factor": float(v["sigma0"]),
                    "redundancy": float(v["redundancy"]),
                }
    vcs = rel.get("variance_components") or {}
    for name, kind in (("dem", "dem"), ("GCP positions", "gcp_position")):
        v = vcs.get(name)
        if v and v.get("redundancy", 0) > 0:
            classes[name if name != "dem" else "DEM"] = {
                "kind": kind,
                "factor": float(v["sigma0"]),
                "redundancy": float(v["redundancy"]),
                # the DEM's stated sigma's share of its factors' variance (1: a result that does not
                # say) and the factor the pass's variance components put on its DEM scale
                **({"stated_share": float(v["stated_share"])} if "stated_share" in v else {}),
                **({"scale": float((rel.get("dem_sigma") or {}).get("scale", 1.0))} if kind == "dem" else {}),
            }
    return classes


def read_pass_levels(path: str | os.PathLike[str]) -> PassLevels:
    """What an adjustment result (RESULT.h5 of ``misrgraph adjust --out``) tells about the levels.

    Raises
    ------
    FileFormatError
        When the file is not an adjustment result, is damaged, or lacks a field the fit needs.
    """
    from misrgraph.io.h5 import open_h5

    p = Path(path)
    with open_h5(p, "adjustment_result") as f:
        try:
            summary = json.loads(f.attrs["summary_json"])
            times = [np.asarray(f[f"attitude_error/{a}/knot_times"]) for a in ANGLES]
            knots = [np.asarray(f[f"attitude_error/{a}/knots"]) for a in ANGLES]
            cov = [np.asarray(f[f"attitude_error/{a}/joint_covariance"]) for a in ANGLES]
            edges = np.asarray(f["ephemeris_error/boundaries"])
            eph = np.asarray(f["ephemeris_error/params"])
            eph_cov = np.asarray(f["ephemeris_error/covariance"])
        except KeyError as exc:
            raise FileFormatError(p, f"lacks {exc.args[0]!r}, which the noise fit needs") from None
    classes = _classes(summary.get("reliability") or {})
    used = summary.get("noise_levels")
    if used is None:
        log.warning("%s does not say which noise levels it was adjusted with; taking the pre-flight ones", p)
        used = NoiseModel().graph_fields()
    return PassLevels(
        name=str(p),
        knot_times=times,
        knots=knots,
        knot_cov=cov,
        ephemeris_boundaries=edges,
        ephemeris=eph,
        ephemeris_cov=eph_cov,
        classes=classes,
        used=used,
    )


def pass_levels_of(res: Any, graph: Any, name: str) -> PassLevels:
    """What an adjustment result in memory (:class:`~misrgraph.estimate.adjust.AdjustResult`, e.g.
    one pass of an ``update`` state) tells about the levels, as :func:`read_pass_levels` reads it
    from RESULT.h5; ``graph``: the :class:`~misrgraph.estimate.graph.GraphConfig` it was adjusted
    with."""
    pg = res.pass_graph
    eph_keys = pg.ephemeris_keys()
    return PassLevels(
        name=name,
        knot_times=[np.asarray(t, float) for t in res.attitude.knot_times],
        knots=[np.asarray(k, float) for k in res.attitude.knots],
        knot_cov=[res.marginals.joint_of(pg.knot_keys(a)) for a in range(len(ANGLES))],
        ephemeris_boundaries=np.asarray(res.ephemeris.boundaries, float),
        ephemeris=np.asarray(res.ephemeris.params, float),
        ephemeris_cov=np.stack([res.marginals[k] for k in eph_keys]),
        classes=_classes(res.reliability or {}),
        used={k: getattr(graph, k) for k in (*NoiseModel().graph_fields(), "knot_prior")},
    )


def fit_and_save(
    passes: list[PassLevels],
    out: str | os.PathLike[str] | None,
    base_model: NoiseModel,
    base_source: dict[str, str],
    learn_attitude_shape: bool | None = None,
) -> dict[str, Any]:
    """Fit the noise model on ``passes`` with ``base_model`` for what they do not carry, write it to
    ``out`` (unless None) with each section's source, and return :func:`run_noise_fit`'s summary."""
    from misrgraph.io.noise import SECTIONS, save_noise_model

    fit: NoiseFit = fit_noise_model(passes, base_model, learn_attitude_shape)
    if out is not None:
        source = {s: ("learned" if s in fit.learned_sections else base_source.get(s, "pre-flight")) for s in SECTIONS}
        save_noise_model(fit.model, out, source, fit={"passes": fit.passes, "levels": fit.levels})
    fitted = {".".join(k.split(".")[:2]) for k in fit.levels}  # "section.field" of "section.field.axis"
    return {
        "passes": len(fit.passes),
        "levels": fit.levels,
        "not_fitted": [f"{s}.{n}" for (s, n) in LEVELS if f"{s}.{n}" not in fitted],
        "out": str(out) if out is not None else None,
    }


def run_noise_fit(
    results: list[str | os.PathLike[str]],
    out: str | os.PathLike[str] | None = None,
    base: str | os.PathLike[str] | None = None,
    learn_attitude_shape: bool | None = None,
) -> dict[str, Any]:
    """Fit the noise model on adjusted passes (:func:`~misrgraph.estimate.noisefit.fit_noise_model`)
    and, with ``out``, write it as a noise-model file that ``--noise-model`` reads; the levels the
    passes do not carry come from ``base`` (a noise-model file; default the pre-flight model), and
    so does the attitude process's shape unless the passes reject it (``learn_attitude_shape``
    None) or ``learn_attitude_shape`` is True.

    Returns ``{"passes", "levels": {"section.field[.axis]": {"value", "sigma", "previous",
    "passes", "unit"}}, "not_fitted": [...], "out"}``."""
    from misrgraph.io.noise import read_noise_model

    base_model, base_source = (NoiseModel(), {}) if base is None else read_noise_model(base)
    return fit_and_save([read_pass_levels(r) for r in results], out, base_model, base_source, learn_attitude_shape)
