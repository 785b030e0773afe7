"""Names and nominal instrument/orbit numbers fixed by the project's conventions (docs/explanation/conventions.md).

Everything numeric that describes the *nominal* instrument lives here; derived parameters (the
camera geometric model) are computed from these in :mod:`misrgraph.model.camera`.
"""

from __future__ import annotations

import math

__all__ = [
    "CAMERAS",
    "BANDS",
    "ANGLES",
    "N_PIXELS",
    "VIEW_ANGLE_DEG",
    "FOCAL_LENGTH_M",
    "SAMPLE_DIRECTION",
    "PITCH_CROSS_M",
    "PITCH_ALONG_M",
    "LINE_TIME_S",
    "NAV_SAMPLE_S",
    "ORBIT_ALTITUDE_M",
    "ORBIT_INCLINATION_DEG",
    "REPEAT_DAYS",
    "REPEAT_PATHS",
    "NODAL_PERIOD_S",
    "ARCSEC",
    "camera_index",
    "band_index",
]

CAMERAS: tuple[str, ...] = ("Df", "Cf", "Bf", "Af", "An", "Aa", "Ba", "Ca", "Da")
BANDS: tuple[str, ...] = ("blue", "green", "red", "nir")
ANGLES: tuple[str, ...] = ("roll", "pitch", "yaw")
N_PIXELS = 1504

# View angle at the surface (deg), signed: forward cameras positive, aft negative.
VIEW_ANGLE_DEG: dict[str, float] = {
    "Df": 70.5,
    "Cf": 60.0,
    "Bf": 45.6,
    "Af": 26.1,
    "An": 0.0,
    "Aa": -26.1,
    "Ba": -45.6,
    "Ca": -60.0,
    "Da": -70.5,
}
_F = {"A": 58.9e-3, "B": 73.4e-3, "C": 95.3e-3, "D": 123.7e-3}
FOCAL_LENGTH_M: dict[str, float] = {c: _F[c[0]] for c in CAMERAS}

# Which way a camera's samples run across the focal plane: +1 where the cross-track focal-plane
# coordinate y of eq. 2 grows with the sample number (An and the fore cameras), -1 where it
# falls (the aft cameras, which look backwards: sample 0 of Da lies on the side of the swath
# opposite to sample 0 of Df, so that the seed's Table 3 gives mirrored sensitivities for the
# fore and aft cameras at pixel 0). It is the sign of the nominal alpha_1.
SAMPLE_DIRECTION: dict[str, int] = {c: (-1 if VIEW_ANGLE_DEG[c] < 0 else 1) for c in CAMERAS}

PITCH_CROSS_M = 21e-6  # detector pitch across track (sample direction)
PITCH_ALONG_M = 18e-6  # detector pitch along track (line direction), d_x of eq. 2
LINE_TIME_S = 40.8e-3  # line repeat time
NAV_SAMPLE_S = 1.024  # ephemeris/attitude sampling

ORBIT_ALTITUDE_M = 705e3
ORBIT_INCLINATION_DEG = 98.2
REPEAT_DAYS = 16
REPEAT_PATHS = 233
NODAL_PERIOD_S = REPEAT_DAYS * 86400.0 / REPEAT_PATHS

ARCSEC = math.pi / 180.0 / 3600.0


def camera_index(name: str) -> int:
    """Index of a camera name in :data:`CAMERAS`; raises :class:`InputError` naming the choices."""
    from misrgraph.errors import InputError

    if name not in CAMERAS:
        raise InputError("camera", name, CAMERAS)
    return CAMERAS.index(name)


def band_index(name: str) -> int:
    """Index of a band name in :data:`BANDS`; raises :class:`InputError` naming the choices."""
    from misrgraph.errors import InputError

    if name not in BANDS:
        raise InputError("band", name, BANDS)
    return BANDS.index(name)
