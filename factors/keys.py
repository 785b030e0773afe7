"""Key letters of every variable in the graph -- defined here and nowhere else.

===========  ======  =============================================  ==========================
variable     letter  index                                          type
===========  ======  =============================================  ==========================
tie point    ``l``   ``path * 10**6 + feature id`` (shared by repeats) Vector3, ECEF m
GCP          ``g``   GCP database row (shared by every pass)        Vector3, ECEF m
GCP scene    ``s``   the GCP database's source scene                Vector3, ECEF m (offset)
roll knot    ``r``   ``pass * 10**5 + knot``                        Vector2 (rad, rad/s)
pitch knot   ``p``   ``pass * 10**5 + knot``                        Vector2 (rad, rad/s)
yaw knot     ``y``   ``pass * 10**5 + knot``                        Vector2 (rad, rad/s)
ephemeris    ``e``   ``pass * 10**3 + segment``                     Vector6 (a m/s, b m)
camera       ``c``   ``bin * 1000 + camera * 10 + (band + 1 if per band else 0)`` Vector of chosen corrections
                             (``bin``: temperature bin of a thermal calibration, else 0)
instrument   ``w``   0                                              Vector3 (wx, wy, wz) rad
===========  ======  =============================================  ==========================

All variables are plain vectors (retraction is addition), stored in ``gtsam.Values`` as dynamic
vectors and read with ``Values.atVector``.
"""

from __future__ import annotations

import gtsam

__all__ = [
    "LANDMARK",
    "GCP",
    "GCP_SCENE",
    "KNOT",
    "EPHEMERIS",
    "CAMERA",
    "OMEGA",
    "landmark_key",
    "gcp_key",
    "gcp_scene_key",
    "knot_key",
    "ephemeris_key",
    "camera_key",
    "omega_key",
    "describe",
]

LANDMARK = "l"
GCP = "g"
GCP_SCENE = "s"
KNOT = ("r", "p", "y")  # roll, pitch, yaw
EPHEMERIS = "e"
CAMERA = "c"
OMEGA = "w"


def landmark_key(path: int, feature_id: int) -> int:
    """Tie point: features keep their id on repeat passes of the same WRS path, so they are shared."""
    return gtsam.symbol(LANDMARK, path * 10**6 + feature_id)


def gcp_key(gcp_row: int) -> int:
    return gtsam.symbol(GCP, gcp_row)


def gcp_scene_key(scene: int) -> int:
    """The error a source scene's GCPs share (shared by every pass, like the GCPs)."""
    return gtsam.symbol(GCP_SCENE, scene)


def knot_key(angle: int, pass_index: int, knot: int) -> int:
    return gtsam.symbol(KNOT[angle], pass_index * 10**5 + knot)


def ephemeris_key(pass_index: int, segment: int) -> int:
    return gtsam.symbol(EPHEMERIS, pass_index * 10**3 + segment)


def camera_key(camera: int, band: int | None = None, temperature_bin: int = 0) -> int:
    return gtsam.symbol(CAMERA, temperature_bin * 1000 + camera * 10 + (0 if band is None else band + 1))


def omega_key() -> int:
    return gtsam.symbol(OMEGA, 0)


def describe(key: int) -> str:
    """Human-readable name of a key, e.g. ``'p3'`` -> pitch knot."""
    s = gtsam.Symbol(key)
    return f"{chr(s.chr())}{s.index()}"
