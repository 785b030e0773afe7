"""``misrgraph cgm``: camera-model versions by orbit range (:mod:`misrgraph.io.cgm`).

``add`` stores a camera-model file (``calibrate --out``) as a version valid for a range of
orbits; ``list`` lists the versions; ``show`` gives one version's pointing angles per camera
(``delta``, ``beta``, ``epsilon``, arcsec) with their 1-sigma from the calibration's covariance
when the file carries one, and each camera's pointing 1-sigma in pixels (RMS over the swath,
propagated from that covariance as ``calibrate`` does); ``diff`` gives, per camera, what changed
between two versions: the angles (arcsec), the pointing change in pixels (RMS over the swath of
the angle between the two models' lines of sight, in units of the cross-track IFOV, red band),
its 1-sigma from the two covariances taken as independent (two calibrations on different
windows), and their ratio ``z``.

:func:`resolve_camera_model` is how ``adjust``, ``update`` and ``products`` read a
``--camera-model`` that names a store: the version valid for the pass's orbit, unless a version
is named.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from misrgraph.errors import InputError
from misrgraph.io.cgm import CgmStore, CgmVersion, add_version, is_cgm_store, open_store, version_for_orbit
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import CAMERAS

__all__ = [
    "run_cgm_add",
    "run_cgm_list",
    "run_cgm_show",
    "run_cgm_diff",
    "resolve_camera_model",
    "resolve_for_passes",
    "version_summary",
]

_ARCSEC = 180.0 / math.pi * 3600.0
_ANGLES = ("delta", "beta", "epsilon")


def _entry(v: CgmVersion) -> dict[str, Any]:
    return {
        "id": v.id,
        "first_orbit": v.first_orbit,
        "last_orbit": v.last_orbit,
        "created_utc": v.created_utc,
        "reason": v.reason,
        "source": v.source,
        "file": v.file,
        "sha256": v.sha256,
    }


def resolve_camera_model(spec: str | os.PathLike[str], orbit: int) -> tuple[Path | str, dict[str, Any] | None]:
    """``(camera-model file or built-in name, version entry or None)``: a store's version valid
    for ``orbit``, else ``spec`` itself (a file or a built-in model's name), with no version. To
    use another version, give its file (``STORE/versions/<id>.h5``)."""
    if not is_cgm_store(spec):
        return spec if isinstance(spec, str) else Path(spec), None
    store = open_store(spec)
    v, path = version_for_orbit(store, int(orbit))
    return path, {**_entry(v), "chosen": f"valid for orbit {int(orbit)}"}


def resolve_for_passes(
    spec: str | os.PathLike[str], orbits: list[int], field: str = "--camera-model"
) -> tuple[Path | str, dict[str, Any] | None]:
    """:func:`resolve_camera_model` for work that uses one camera model for several passes (an
    ROI, an incremental state): InputError when their orbits fall in different versions."""
    if not orbits:
        if is_cgm_store(spec):
            raise InputError(field, str(spec), "a camera-model file when there is no pass to pick a version for")
        return resolve_camera_model(spec, 0)
    picked = [resolve_camera_model(spec, o) for o in orbits]
    ids = sorted({v["id"] for _, v in picked if v is not None})
    if len(ids) > 1:
        raise InputError(
            field,
            str(spec),
            f"one version for all these passes (orbits {min(orbits)}-{max(orbits)} span {', '.join(ids)})",
        )
    return picked[0]


def run_cgm_add(
    store: str | os.PathLike[str],
    camera_model: str | os.PathLike[str],
    first_orbit: int,
    last_orbit: int | None = None,
    reason: str = "",
) -> dict[str, Any]:
    """Add ``camera_model`` to ``store`` (created if needed) as a version for ``first_orbit`` ..
    ``last_orbit``; return ``{"added": entry, "versions": [entries]}``."""
    v = add_version(store, camera_model, first_orbit, last_orbit, reason)
    return {"added": _entry(v), "versions": [_entry(x) for x in open_store(store).versions]}


def run_cgm_list(store: str | os.PathLike[str]) -> dict[str, Any]:
    """``{"store", "versions": [entries in the order added]}``."""
    s = open_store(store)
    return {"store": str(s.root), "versions": [_entry(v) for v in s.versions]}


def _pick(s: CgmStore, version: str | None, orbit: int | None) -> tuple[CgmVersion, Path]:
    if (version is None) == (orbit is None):
        raise InputError("VERSION / --orbit", version if version is not None else orbit, "exactly one of them")
    if version is not None:
        v = s.get(version)
        return v, s.path_of(v)
    return version_for_orbit(s, int(orbit))  # type: ignore[arg-type]


def _levels(path: Path) -> tuple[CameraModel, dict[str, float], dict[str, float], bool]:
    """A stored version's model (a table: at its first temperature), the 1-sigma (SI) of each
    label of its calibration covariance, each camera's pointing 1-sigma (px), and whether the
    file carries a covariance (both dicts empty when not)."""
    from misrgraph.io.camera import load_camera_model, read_calibration_prior

    model = load_camera_model(path)
    model = model.at_temperature(model.temperature_c)
    prior = read_calibration_prior(path)
    if prior is None:
        return model, {}, {}, False
    labels, cov = prior
    return model, dict(zip(labels, np.sqrt(np.diag(cov)))), _pointing_sigma_px(model, labels, cov), True


def _pointing_sigma_px(model: CameraModel, labels: list[str], cov: np.ndarray) -> dict[str, float]:
    """Each camera's pointing 1-sigma (px, RMS over the swath, red band) from the covariance of
    its corrections: the root sum over the columns of the Cholesky factor of the squared
    pointing change they cause (as ``calibrate``'s ``sigma_px``)."""
    from misrgraph.estimate.calibrate import pointing_error_px

    chol = np.linalg.cholesky(0.5 * (cov + cov.T))
    out: dict[str, float] = {}
    for c, name in enumerate(CAMERAS):
        rows = [(i, lab.split(".", 1)[1]) for i, lab in enumerate(labels) if lab.split(".", 1)[0] == name]
        if not rows:
            continue
        total = 0.0
        for k in range(chol.shape[1]):
            if not any(chol[i, k] != 0.0 for i, _ in rows):
                continue
            moved = model.copy()
            for i, p in rows:
                moved.add_correction(p, c, None, float(chol[i, k]))
            total += pointing_error_px(moved, model, c) ** 2
        out[name] = math.sqrt(total)
    return out


def version_summary(path: Path) -> dict[str, Any]:
    """Per camera the pointing angles (arcsec) with their 1-sigma where the file has a
    calibration covariance, and the pointing 1-sigma in pixels."""
    model, sig, spx, has_cov = _levels(path)
    cams: dict[str, Any] = {}
    for c, name in enumerate(CAMERAS):
        cams[name] = {
            p: {
                "arcsec": float(getattr(model, p)[c] * _ARCSEC),
                "sigma_arcsec": float(sig[f"{name}.{p}"] * _ARCSEC) if f"{name}.{p}" in sig else None,
            }
            for p in _ANGLES
        }
        cams[name]["sigma_px"] = spx.get(name)
    return {"covariance": has_cov, "temperature_c": float(model.temperature_c), "cameras": cams}


def run_cgm_show(store: str | os.PathLike[str], version: str | None = None, orbit: int | None = None) -> dict[str, Any]:
    """One version (named, or the one valid for ``orbit``): its entry and :func:`version_summary`."""
    s = open_store(store)
    v, path = _pick(s, version, orbit)
    return {**_entry(v), **version_summary(path)}


def run_cgm_diff(store: str | os.PathLike[str], a: str, b: str) -> dict[str, Any]:
    """What changed from version ``a`` to version ``b``, per camera (see the module docstring):
    ``{"from", "to", "cameras": {cam: {"delta"|"beta"|"epsilon": {"arcsec", "sigma_arcsec", "z"},
    "pointing_px", "sigma_px", "z"}}, "largest": {"camera", "pointing_px", "z"}}``; a sigma and
    z are None where a version has no covariance."""
    from misrgraph.estimate.calibrate import pointing_error_px

    s = open_store(store)
    va, vb = s.get(a), s.get(b)
    ma, sa, pa, _ = _levels(s.path_of(va))
    mb, sb, pb, _ = _levels(s.path_of(vb))
    cams: dict[str, Any] = {}
    for c, name in enumerate(CAMERAS):
        entry: dict[str, Any] = {}
        for p in _ANGLES:
            d = float((getattr(mb, p)[c] - getattr(ma, p)[c]) * _ARCSEC)
            key = f"{name}.{p}"
            sd = math.hypot(sa[key], sb[key]) * _ARCSEC if key in sa and key in sb else None
            entry[p] = {"arcsec": d, "sigma_arcsec": sd, "z": d / sd if sd else None}
        px = pointing_error_px(mb, ma, c)
        spx = math.hypot(pa[name], pb[name]) if name in pa and name in pb else None
        entry.update({"pointing_px": px, "sigma_px": spx, "z": px / spx if spx else None})
        cams[name] = entry
    worst = max(cams, key=lambda k: cams[k]["pointing_px"])
    return {
        "from": _entry(va),
        "to": _entry(vb),
        "cameras": cams,
        "largest": {"camera": worst, "pointing_px": cams[worst]["pointing_px"], "z": cams[worst]["z"]},
    }
