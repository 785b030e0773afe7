"""One orbit pass as data: supplied navigation, camera/band timing, observations.

HDF5 layout (kind ``orbit_pass``, see docs/reference/data-model.md)::

    /                 attrs: pass_id, path, orbit, temperature_c, epoch_utc
    /ephemeris        t (s), position (m, J2000), velocity (m/s)
    /attitude         t (s), angles (rad; roll, pitch, yaw vs orbital frame), rates (rad/s)
    /timing           t0 (9, 4) s of line 0 per camera/band; attr line_time (s)
    /landmarks        id (M,), kind (M,) 0 tie / 1 GCP / 2 check point, gcp_index (M,) (-1 if not a GCP)
    /observations     landmark (N,) row into /landmarks, camera (N,), band (N,), line, sample,
                      exposure (N,) whole exposure index or NaN (continuous), sigma_px (N,)
    /truth            (simulated passes only) written and read by :mod:`misrgraph.io.truth`,
                      never by :meth:`OrbitPass.load`
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_h5, open_h5, read_attr, read_dataset, write_dataset
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.geolocation import PassGeometry
from misrgraph.model.orbit import AttitudeSeries, Ephemeris

__all__ = [
    "PASS_ID_PATTERN",
    "Observations",
    "Landmarks",
    "OrbitPass",
    "KIND_TIE",
    "KIND_GCP",
    "KIND_CHECK",
    "KIND_NAMES",
]

Array = NDArray[np.float64]
KIND_TIE, KIND_GCP, KIND_CHECK = 0, 1, 2
KIND_NAMES = {KIND_TIE: "tie", KIND_GCP: "gcp", KIND_CHECK: "check"}
#: What a pass id may be: it names files (the update state keeps ``passes/<pass_id>.h5``).
PASS_ID_PATTERN = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}")


def _check_rows(field: str, values: NDArray[Any], bad: NDArray[np.bool_], expected: str) -> None:
    """Raise InputError naming the first offending row (and how many there are)."""
    if np.any(bad):
        rows = np.flatnonzero(bad)
        more = f" (and {rows.size - 1} more rows)" if rows.size > 1 else ""
        raise InputError(f"{field}[{rows[0]}]", values[rows[0]].item(), expected + more)


@dataclass
class Observations:
    """Image measurements, all ``(N,)``: ``landmark`` row index, ``camera``/``band`` indices,
    ``line``/``sample`` (pixels), ``exposure``, ``sigma_px`` (image lines and samples, 1 sigma
    per coordinate).

    ``exposure`` NaN (what a matcher measures, and what the simulator writes) marks a continuous
    image position: ``line`` is the continuous time index at which the point crossed the array
    centre (time ``t0 + line * line_time``, focal-plane fraction 0). A whole ``exposure`` L is
    eq. 2's discrete form: time ``t0 + L * line_time`` and focal-plane fraction ``line - L``.
    :attr:`exposure_index` gives L for both (docs/explanation/conventions.md, "Observations")."""

    landmark: NDArray[np.int64]
    camera: NDArray[np.int64]
    band: NDArray[np.int64]
    line: Array
    sample: Array
    exposure: Array
    sigma_px: Array

    def __post_init__(self) -> None:
        n = np.asarray(self.landmark).size
        for name, dt in (
            ("landmark", np.int64),
            ("camera", np.int64),
            ("band", np.int64),
            ("line", float),
            ("sample", float),
            ("exposure", float),
            ("sigma_px", float),
        ):
            arr = np.asarray(getattr(self, name), dtype=dt).ravel()
            if arr.size != n:
                raise InputError(f"observations.{name}", arr.size, f"{n} values (one per observation)")
            setattr(self, name, arr)
        _check_rows(
            "observations.camera",
            self.camera,
            (self.camera < 0) | (self.camera >= len(CAMERAS)),
            f"a camera index 0..{len(CAMERAS) - 1}",
        )
        _check_rows(
            "observations.band",
            self.band,
            (self.band < 0) | (self.band >= len(BANDS)),
            f"a band index 0..{len(BANDS) - 1}",
        )
        _check_rows("observations.landmark", self.landmark, self.landmark < 0, "a landmark row >= 0")
        for name in ("line", "sample"):
            arr = getattr(self, name)
            _check_rows(f"observations.{name}", arr, ~np.isfinite(arr), "a finite number of pixels")
        e = self.exposure
        _check_rows(
            "observations.exposure",
            e,
            ~np.isnan(e) & (np.isinf(e) | (e != np.round(e))),
            "a whole exposure index (or NaN: a continuous position)",
        )
        _check_rows(
            "observations.sigma_px",
            self.sigma_px,
            ~(np.isfinite(self.sigma_px) & (self.sigma_px > 0)),
            "a positive, finite sigma in pixels",
        )

    def __len__(self) -> int:
        return int(self.landmark.size)

    @property
    def exposure_index(self) -> Array:
        """Exposure (time) index of every observation: ``exposure``, or ``line`` where it is NaN."""
        return np.where(np.isnan(self.exposure), self.line, self.exposure)

    @property
    def continuous(self) -> NDArray[np.bool_]:
        """True where an observation is a continuous (matched) image position."""
        return np.isnan(self.exposure)

    def subset(self, mask: NDArray[np.bool_] | NDArray[np.int64]) -> "Observations":
        return Observations(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))


@dataclass
class Landmarks:
    """Features of a pass: ``id (M,)`` (GCP database id for GCPs), ``kind (M,)`` and ``gcp_index``."""

    id: NDArray[np.int64]
    kind: NDArray[np.int64]
    gcp_index: NDArray[np.int64]

    def __post_init__(self) -> None:
        self.id = np.asarray(self.id, dtype=np.int64).ravel()
        self.kind = np.asarray(self.kind, dtype=np.int64).ravel()
        self.gcp_index = np.asarray(self.gcp_index, dtype=np.int64).ravel()
        if not (self.id.size == self.kind.size == self.gcp_index.size):
            raise InputError("landmarks", (self.id.size, self.kind.size, self.gcp_index.size), "equal lengths")
        _check_rows(
            "landmarks.kind",
            self.kind,
            ~np.isin(self.kind, list(KIND_NAMES)),
            "a kind code " + ", ".join(f"{k} ({v})" for k, v in KIND_NAMES.items()),
        )
        _check_rows(
            "landmarks.gcp_index",
            self.gcp_index,
            (self.kind == KIND_GCP) & (self.gcp_index < 0),
            "a GCP database row >= 0 for a GCP",
        )

    def __len__(self) -> int:
        return int(self.id.size)


@dataclass
class OrbitPass:
    """One orbit pass: supplied navigation, timing, observations (what the estimator sees; a
    simulated pass's truth is read separately, :mod:`misrgraph.io.truth`)."""

    pass_id: str
    path: int
    orbit: int
    ephemeris: Ephemeris
    attitude: AttitudeSeries
    t0: Array
    line_time: float
    landmarks: Landmarks
    observations: Observations
    temperature_c: float = 5.0

    def __post_init__(self) -> None:
        self.t0 = np.asarray(self.t0, dtype=float)
        if self.t0.shape != (len(CAMERAS), len(BANDS)):
            raise InputError("timing.t0", self.t0.shape, f"shape ({len(CAMERAS)}, {len(BANDS)})")
        _check_rows(
            "observations.landmark",
            self.observations.landmark,
            self.observations.landmark >= len(self.landmarks),
            f"a landmark row < {len(self.landmarks)}",
        )
        _check_rows("timing.t0", self.t0.ravel(), ~np.isfinite(self.t0.ravel()), "finite seconds")
        if not (np.isfinite(self.line_time) and self.line_time > 0):
            raise InputError("timing.line_time", self.line_time, "a positive number of seconds")
        if not np.isfinite(self.temperature_c):
            raise InputError("temperature_c", self.temperature_c, "a finite temperature (deg C)")
        if len(self.observations):
            t = self.observation_times()
            t_lo, t_hi = self.span
            _check_rows(
                "observations.line",
                self.observations.line,
                (t < t_lo) | (t > t_hi),
                f"a line whose exposure time lies within the pass's navigation [{t_lo:.3f}, {t_hi:.3f}] s",
            )
        if not PASS_ID_PATTERN.fullmatch(str(self.pass_id)):
            raise InputError(
                "pass_id",
                self.pass_id,
                "letters, digits, '_', '-' or '.' (1-64 characters, not starting with '.'; it names files)",
            )

    # ------------------------------------------------------------------ geometry
    def geometry(self, camera: CameraModel) -> PassGeometry:
        """Pass geometry with the supplied navigation."""
        return PassGeometry(self.ephemeris, self.attitude, camera, t0=self.t0)

    def observation_times(self) -> Array:
        """Exposure time (s) of every observation."""
        o = self.observations
        return self.t0[o.camera, o.band] + o.exposure_index * self.line_time

    @property
    def span(self) -> tuple[float, float]:
        return self.ephemeris.span

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the pass atomically.

        A simulated pass with its truth: :func:`misrgraph.io.truth.save_pass_with_truth`.
        """
        with atomic_h5(path, "orbit_pass") as f:
            self.write_into(f)

    def write_into(self, f: Any) -> None:
        """Write the pass's groups into an open ``orbit_pass`` file."""
        f.attrs.update(
            {
                "pass_id": self.pass_id,
                "path": int(self.path),
                "orbit": int(self.orbit),
                "temperature_c": float(self.temperature_c),
                "epoch_utc": self.ephemeris.epoch_utc,
            }
        )
        g = f.create_group("ephemeris")
        g.attrs["epoch_utc"] = self.ephemeris.epoch_utc
        g.attrs["frame"] = "J2000"
        write_dataset(g, "t", self.ephemeris.t, units="s from epoch_utc")
        write_dataset(g, "position", self.ephemeris.position, units="m")
        write_dataset(g, "velocity", self.ephemeris.velocity, units="m/s")
        g = f.create_group("attitude")
        g.attrs["angles"] = "roll,pitch,yaw (spacecraft vs orbital frame, eq. 5)"
        write_dataset(g, "t", self.attitude.t, units="s from epoch_utc")
        write_dataset(g, "angles", self.attitude.angles, units="rad")
        write_dataset(g, "rates", self.attitude.rates, units="rad/s")
        g = f.create_group("timing")
        write_dataset(
            g, "t0", self.t0, units="s from epoch_utc", meaning="time of line 0 per camera (row) and band (column)"
        )
        g.attrs["line_time"] = float(self.line_time)
        g = f.create_group("landmarks")
        write_dataset(g, "id", self.landmarks.id)
        write_dataset(g, "kind", self.landmarks.kind, meaning="0 tie point, 1 GCP, 2 check point")
        write_dataset(g, "gcp_index", self.landmarks.gcp_index, meaning="row in the GCP database, -1 if not a GCP")
        g = f.create_group("observations")
        o = self.observations
        write_dataset(g, "landmark", o.landmark, meaning="row in /landmarks")
        write_dataset(g, "camera", o.camera.astype(np.int8), order=",".join(CAMERAS))
        write_dataset(g, "band", o.band.astype(np.int8), order=",".join(BANDS))
        write_dataset(g, "line", o.line, units="pixel")
        write_dataset(g, "sample", o.sample, units="pixel")
        write_dataset(
            g,
            "exposure",
            o.exposure,
            units="line",
            meaning="whole exposure index L (time t0 + L line_time), NaN for a continuous position (time from line)",
        )
        write_dataset(g, "sigma_px", o.sigma_px, units="pixel")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "OrbitPass":
        with open_h5(path, "orbit_pass") as f:
            for grp in ("ephemeris", "attitude", "timing", "landmarks", "observations"):
                if grp not in f:
                    raise FileFormatError(path, f"missing group /{grp}")
            g = f["ephemeris"]
            t = read_dataset(g, "t", (None,))
            eph = Ephemeris(
                str(read_attr(g, "epoch_utc")),
                t,
                read_dataset(g, "position", (t.size, 3)),
                read_dataset(g, "velocity", (t.size, 3)),
            )
            g = f["attitude"]
            ta = read_dataset(g, "t", (None,))
            att = AttitudeSeries(ta, read_dataset(g, "angles", (ta.size, 3)), read_dataset(g, "rates", (ta.size, 3)))
            g = f["timing"]
            t0 = read_dataset(g, "t0", (len(CAMERAS), len(BANDS)))
            line_time = float(read_attr(g, "line_time"))
            g = f["landmarks"]
            lid = read_dataset(g, "id", (None,), dtype=np.int64)
            lm = Landmarks(
                lid,
                read_dataset(g, "kind", (lid.size,), dtype=np.int64),
                read_dataset(g, "gcp_index", (lid.size,), dtype=np.int64),
            )
            g = f["observations"]
            n = read_dataset(g, "landmark", (None,), dtype=np.int64)
            obs = Observations(
                n,
                *(
                    read_dataset(g, k, (n.size,), dtype=dt)
                    for k, dt in (
                        ("camera", np.int64),
                        ("band", np.int64),
                        ("line", float),
                        ("sample", float),
                        ("exposure", float),
                        ("sigma_px", float),
                    )
                ),
            )
            return cls(
                str(read_attr(f, "pass_id")),
                int(read_attr(f, "path")),
                int(read_attr(f, "orbit")),
                eph,
                att,
                t0,
                line_time,
                lm,
                obs,
                float(read_attr(f, "temperature_c")),
            )
