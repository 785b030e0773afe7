"""Camera-model files (HDF5 kind ``camera_model``): the one reader and writer.

Layout: ``/camera_model`` holds one :class:`~misrgraph.model.camera.CameraModel` (datasets
``delta, beta, epsilon (9,)`` rad, ``band_delta, band_beta, band_epsilon (9, 4)`` rad,
``focal_length (9, 4)`` m, ``k (9, 4)`` m, ``cy (9, 4)`` pixel, ``alpha (9, 4, 6)`` pixel^-i,
``omega (3,)`` rad; attributes ``cameras``, ``bands``, ``dx``, ``dy`` m, ``line_time`` s,
``temperature_c``; a ``provenance`` group of string attributes). A model tabulated in temperature
(:class:`~misrgraph.model.camera.TabulatedCameraModel`) adds ``/temperature_table/<i>`` (one such
group per temperature, ``/camera_model`` being the first) with attribute ``valid_range_c``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from misrgraph.errors import FileFormatError
from misrgraph.io.h5 import atomic_h5, open_h5, read_attr, read_dataset, write_dataset
from misrgraph.model.camera import CameraModel, TabulatedCameraModel
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.nominal import MODEL_NAMES, builtin_camera_model

__all__ = [
    "save_camera_model",
    "load_camera_model",
    "read_camera_file",
    "read_calibration_prior",
    "is_builtin_model",
    "write_camera_group",
    "read_camera_group",
    "write_camera_groups",
    "MODEL_NAMES",
]

_UNITS = {"focal_length": "m", "k": "m", "cy": "pixel", "alpha": "pixel^-i", "omega": "rad"}


def write_camera_group(g: Any, model: CameraModel) -> None:
    """Write one model's parameters into an open HDF5 group."""
    g.attrs["cameras"] = ",".join(CAMERAS)
    g.attrs["bands"] = ",".join(BANDS)
    for name in CameraModel._SHAPES:
        write_dataset(g, name, getattr(model, name), units=_UNITS.get(name, "rad"))
    g["omega"].attrs["order"] = "wx,wy,wz"
    for name in ("dx", "dy"):
        g.attrs[name] = float(getattr(model, name))
    g.attrs["line_time"] = float(model.line_time)
    g.attrs["temperature_c"] = float(model.temperature_c)
    prov = g.create_group("provenance")
    for key, value in model.provenance.items():
        prov.attrs[key] = str(value)


def read_camera_group(g: Any) -> CameraModel:
    """Read one model from an open HDF5 group (see :func:`write_camera_group`), validating every field."""
    cams = str(read_attr(g, "cameras")).split(",")
    if tuple(cams) != CAMERAS:
        raise FileFormatError(g.file.filename, f"camera order {cams}; expected {list(CAMERAS)}")
    values = {name: read_dataset(g, name, shape) for name, shape in CameraModel._SHAPES.items()}
    prov = {k: str(v) for k, v in g["provenance"].attrs.items()} if "provenance" in g else {}
    return CameraModel(
        **values,
        dx=float(read_attr(g, "dx")),
        dy=float(read_attr(g, "dy")),
        line_time=float(read_attr(g, "line_time")),
        temperature_c=float(read_attr(g, "temperature_c")),
        provenance=prov,
    )


def write_camera_groups(f: Any, model: CameraModel | TabulatedCameraModel) -> None:
    """Write ``/camera_model`` (for a tabulated model: its first entry, plus ``/temperature_table``)
    into an open file or group."""
    if isinstance(model, TabulatedCameraModel):
        write_camera_group(f.create_group("camera_model"), model.models[0])
        g = f.create_group("temperature_table")
        g.attrs["valid_range_c"] = np.asarray(model.valid_range_c, float)
        for i, m in enumerate(model.models):
            write_camera_group(g.create_group(str(i)), m)
    else:
        write_camera_group(f.create_group("camera_model"), model)


def read_camera_groups(f: Any, where: str | os.PathLike[str] = "") -> CameraModel | TabulatedCameraModel:
    """A plain model, or a tabulated one when the open file or group has ``temperature_table``."""
    if "temperature_table" in f:
        g = f["temperature_table"]
        rng = tuple(float(v) for v in g.attrs["valid_range_c"]) if "valid_range_c" in g.attrs else None
        return TabulatedCameraModel([read_camera_group(g[k]) for k in sorted(g, key=int)], rng)
    if "camera_model" not in f:
        raise FileFormatError(where or f.file.filename, "missing group /camera_model")
    return read_camera_group(f["camera_model"])


def save_camera_model(model: CameraModel | TabulatedCameraModel, path: str | os.PathLike[str]) -> None:
    """Write a camera-model file atomically (temporary file, then rename)."""
    with atomic_h5(path, "camera_model") as f:
        write_camera_groups(f, model)


def read_camera_file(path: str | os.PathLike[str]) -> CameraModel | TabulatedCameraModel:
    """Read a camera-model file (plain or tabulated), validating kind, version, checksums and every field."""
    with open_h5(path, "camera_model") as f:
        return read_camera_groups(f, path)


def read_calibration_prior(spec: str | os.PathLike[str]) -> tuple[list[str], np.ndarray] | None:
    """The joint covariance of the corrections a calibrated camera-model file carries
    (``misrgraph calibrate --out``: ``/calibration/labels`` ``(P,)`` as ``"<camera>.<param>"`` and
    ``/calibration/covariance`` ``(P, P)``, SI: rad, m, pixel^-i), as ``(labels, covariance)``;
    None for a built-in model, a file without a calibration, or a per-band or per-temperature
    calibration (its labels name a band or a temperature bin). An adjustment with this model uses
    it as the prior of its camera corrections (``AdjustConfig.camera_prior_from_calibration``)."""
    text = os.fspath(spec)
    if is_builtin_model(text):
        return None
    with open_h5(text, "camera_model") as f:
        if "calibration" not in f or "labels" not in f["calibration"] or "covariance" not in f["calibration"]:
            return None
        g = f["calibration"]
        labels = [x.decode() if isinstance(x, bytes) else str(x) for x in g["labels"][()]]
        if any("/" in x or "@" in x for x in labels):
            return None
        cov = read_dataset(g, "covariance", (len(labels), len(labels)))
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        raise FileFormatError(text, "/calibration/covariance has a non-finite or non-positive variance")
    return labels, cov


def load_camera_model(spec: str | os.PathLike[str]) -> CameraModel | TabulatedCameraModel:
    """A camera model by name (:data:`~misrgraph.model.nominal.MODEL_NAMES`) or from a file.

    A file with a ``/temperature_table`` gives a :class:`~misrgraph.model.camera.TabulatedCameraModel`.
    A name wins over a file of the same name only when no such file exists.
    """
    text = os.fspath(spec)
    if is_builtin_model(text):
        return builtin_camera_model(text)
    return read_camera_file(text)


def is_builtin_model(spec: str | os.PathLike[str]) -> bool:
    """Whether ``spec`` names a built-in camera model (:data:`~misrgraph.model.nominal.MODEL_NAMES`)
    rather than a file: a name wins only when no file of that name exists."""
    text = os.fspath(spec)
    return text in MODEL_NAMES and not os.path.exists(text)
