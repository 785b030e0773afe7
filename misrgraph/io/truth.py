"""The simulator's truth, kept apart from the data the estimator sees.

A simulated pass file carries ``/truth`` beside its observations and a simulated GCP database
``/truth/ecef``; real data carry neither. Only the simulator writes these groups and only the
evaluation (:mod:`misrgraph.evaluate`), the views and the tests read them, through this module:
:class:`~misrgraph.io.passes.OrbitPass` has no truth field, and nothing under
:mod:`misrgraph.estimate` imports this module (checked by ``tests/test_layout.py``).

Pass file ``/truth`` layout: ``ephemeris_error/{boundaries (S+1,) s, params (S, 6)}``,
``attitude_error/{roll,pitch,yaw}/{knot_times (K,) s, knots (K, 2) rad, rad/s}``,
``landmark_ecef (M, 3)`` m, ``blunder (N,)`` bool, ``camera_model`` (group as in a camera file).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.camera import read_camera_group, write_camera_group
from misrgraph.io.h5 import atomic_h5, open_h5, read_dataset, require_group, write_dataset
from misrgraph.io.passes import OrbitPass
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import ANGLES
from misrgraph.model.errormodels import AttitudeErrorModel, EphemerisErrorModel
from misrgraph.model.geolocation import PassGeometry

if TYPE_CHECKING:
    from misrgraph.io.imagery import PassImagery

__all__ = [
    "PassTruth",
    "write_pass_truth",
    "save_pass_with_truth",
    "read_pass_truth",
    "pass_truth_in",
    "read_gcp_truth",
    "has_truth",
    "load_pass_observations",
]

Array = NDArray[np.float64]


@dataclass
class PassTruth:
    """What the simulator injected into one pass: the navigation errors (supplied = true + error),
    the true landmark positions ``(M, 3)`` m ECEF (rows as the pass's landmarks), which
    observations are blunders ``(N,)`` and the true camera model of the pass."""

    ephemeris_error: EphemerisErrorModel
    attitude_error: AttitudeErrorModel
    landmark_ecef: Array
    blunder: NDArray[np.bool_]
    camera_model: CameraModel

    def geometry(self, orbit_pass: OrbitPass, camera: CameraModel | None = None) -> PassGeometry:
        """The pass's true geometry: supplied navigation with the injected errors removed, and the
        true camera model (or ``camera``)."""
        e, a = self.ephemeris_error, self.attitude_error
        return PassGeometry(
            orbit_pass.ephemeris,
            orbit_pass.attitude,
            camera or self.camera_model,
            t0=orbit_pass.t0,
            attitude_delta=lambda t: -a.evaluate(t),
            position_delta=lambda t: -e.evaluate(t),
        )

    def subset(self, keep: NDArray[np.bool_]) -> "PassTruth":
        """The truth of the pass whose observations are ``keep`` (landmarks unchanged)."""
        return PassTruth(
            self.ephemeris_error, self.attitude_error, self.landmark_ecef, self.blunder[keep], self.camera_model
        )


def write_pass_truth(f: Any, truth: PassTruth, n_landmarks: int, n_observations: int) -> None:
    """Write ``/truth`` into an open pass file."""
    if truth.landmark_ecef.shape != (n_landmarks, 3) or truth.blunder.shape != (n_observations,):
        raise InputError(
            "truth",
            (truth.landmark_ecef.shape, truth.blunder.shape),
            f"landmark_ecef ({n_landmarks}, 3) and blunder ({n_observations},)",
        )
    t = f.create_group("truth")
    e = t.create_group("ephemeris_error")
    write_dataset(e, "boundaries", truth.ephemeris_error.boundaries, units="s")
    write_dataset(
        e,
        "params",
        truth.ephemeris_error.params,
        units="m/s (a), m (b)",
        order="a_x,a_y,a_z,b_x,b_y,b_z (orbital frame; z toward nadir)",
    )
    a = t.create_group("attitude_error")
    for i, name in enumerate(ANGLES):
        ga = a.create_group(name)
        write_dataset(ga, "knot_times", truth.attitude_error.knot_times[i], units="s")
        write_dataset(ga, "knots", truth.attitude_error.knots[i], units="rad, rad/s")
    write_dataset(t, "landmark_ecef", truth.landmark_ecef, units="m", frame="ECEF")
    write_dataset(t, "blunder", truth.blunder.astype(np.uint8))
    write_camera_group(t.create_group("camera_model"), truth.camera_model)


def save_pass_with_truth(
    orbit_pass: OrbitPass, truth: PassTruth | None, path: str | os.PathLike[str], imagery: "PassImagery | None" = None
) -> None:
    """Write a simulated pass, its truth and (optionally) its imagery atomically into one
    ``orbit_pass`` file."""
    with atomic_h5(path, "orbit_pass") as f:
        orbit_pass.write_into(f)
        if truth is not None:
            write_pass_truth(f, truth, len(orbit_pass.landmarks), len(orbit_pass.observations))
        if imagery is not None:
            from misrgraph.io.imagery import write_imagery

            write_imagery(f, imagery)


def read_pass_truth(path: str | os.PathLike[str]) -> PassTruth | None:
    """The truth of a simulated pass file (``None`` for a pass without ``/truth``)."""
    with open_h5(path, "orbit_pass") as f:
        return pass_truth_in(f)


def pass_truth_in(f: Any) -> PassTruth | None:
    """:func:`read_pass_truth` from a pass file already opened (and validated) by ``open_h5``."""
    if "truth" not in f:
        return None
    n_lm = require_group(f, "landmarks")["id"].shape[0]
    n_obs = require_group(f, "observations")["landmark"].shape[0]
    tg = require_group(f, "truth")
    e = require_group(tg, "ephemeris_error")
    eem = EphemerisErrorModel(read_dataset(e, "boundaries", (None,)), read_dataset(e, "params", (None, 6)))
    a = require_group(tg, "attitude_error")
    aem = AttitudeErrorModel(
        [read_dataset(require_group(a, name), "knot_times", (None,)) for name in ANGLES],
        [read_dataset(require_group(a, name), "knots", (None, 2)) for name in ANGLES],
    )
    return PassTruth(
        eem,
        aem,
        read_dataset(tg, "landmark_ecef", (n_lm, 3)),
        read_dataset(tg, "blunder", (n_obs,), dtype=bool),
        read_camera_group(require_group(tg, "camera_model")),
    )


def read_gcp_truth(path: str | os.PathLike[str]) -> Array | None:
    """True GCP positions ``(G, 3)`` m ECEF of a simulated GCP database (``None`` for real data)."""
    with open_h5(path, "gcp_database") as f:
        if "truth" not in f:
            return None
        n = require_group(f, "gcp")["id"].shape[0]
        return read_dataset(require_group(f, "truth"), "ecef", (n, 3))


def has_truth(path: str | os.PathLike[str], kind: str) -> bool:
    """Whether a pass file (``kind="orbit_pass"``) or GCP database (``"gcp_database"``) carries truth."""
    with open_h5(path, kind) as f:
        return "truth" in f


def load_pass_observations(
    path: str | os.PathLike[str], observations: str = "simulated"
) -> tuple[OrbitPass, PassTruth | None]:
    """A pass with the chosen observation set, and its truth (None for real data): ``"simulated"``
    the pass's own; ``"matched"`` the ``/matched`` group (landmarks and observations replaced, the
    truth's landmarks and blunder flags those of the matched set)."""
    from misrgraph.io.imagery import OBSERVATION_SETS, read_matched

    if observations not in OBSERVATION_SETS:
        raise InputError("--observations", observations, OBSERVATION_SETS)
    p = OrbitPass.load(path)
    truth = read_pass_truth(path)
    if observations == "simulated":
        return p, truth
    m = read_matched(path, with_truth=truth is not None)
    p = dataclasses.replace(p, landmarks=m.landmarks, observations=m.observations)
    if truth is not None:
        if m.truth_landmark_ecef is None or m.truth_blunder is None:
            raise FileFormatError(path, "/matched has no /truth/matched (re-run 'misrgraph match')")
        truth = PassTruth(
            truth.ephemeris_error, truth.attitude_error, m.truth_landmark_ecef, m.truth_blunder, truth.camera_model
        )
    return p, truth
