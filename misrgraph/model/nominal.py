"""Derivation of the nominal Camera Geometric Model from the nominal instrument geometry.

Conventions: docs/explanation/conventions.md.

Given only the design numbers (view angles at the surface, focal lengths, detector pitches,
1504 pixels, band layout, a Terra-like orbit), the parameters of eq. 2 follow:

* ``alpha = [0, +-dy/f, 0, 0, 0, 0]`` (ideal optics: the cross-track focal-plane coordinate is
  ``+-dy (s - c_y)``), ``c_y = 751.5`` (centre of the 1504-pixel array), ``eps = 0``. The sign
  is the camera's sample direction (:data:`~misrgraph.model.constants.SAMPLE_DIRECTION`): +
  for An and the fore cameras, - for the aft cameras, whose samples run the other way across
  the ground (sample 0 of Da lies on the side of the swath opposite to sample 0 of Df).
* ``k = f tan(phi_band)`` with the band angles of :data:`misrgraph.model.camera.BAND_ANGLE_DEG`.
* ``omega``: the instrument-to-spacecraft angles measured once mounted (Table 1, common to all
  cameras): (wx, wy, wz) = (-0.0658333, -0.041111, 0.006666) deg.
* ``beta``: the along-track tilt that makes the boresight meet the WGS84 ellipsoid at the
  camera's nominal view (zenith) angle, with the spacecraft over the reference latitude on a
  descending daylight pass. Solved numerically on the ray-casting geometry.
* ``delta``: the roll about the camera's along-track line axis (``T_ic = Ry(beta) Rx(delta)``)
  that compensates Earth rotation: a ground point on the boresight of camera ``c`` must later
  (or earlier) be seen by An at its boresight sample, despite the Earth having turned under the
  orbit in between. The boresight's cross-track component is ``-sin(delta)``; on a descending
  pass the ground track drifts west (to the right of the flight direction), so the fore cameras
  need ``delta < 0`` and the aft cameras ``delta > 0``. Solved numerically with the inverse
  geolocation.

Both are solved for the moment the camera's boresight ground point lies at the reference
latitude, :data:`REFERENCE_LAT_DEG` = 30 deg. A fixed delta can make the compensation exact at
one latitude only (the drift scales roughly with cos(latitude)); 30 deg is where Table 1's
pre-flight delta (Df -2.8030, Da +2.7314 deg) makes it exact, and there the derived values are
Df -2.85, Da +2.85 deg (beta 58.09 and -57.83 deg against Table 1's 58.1266 and -57.9879).

:func:`preflight_camera_model` is the pre-flight model: Table 1's printed values for Df, An and
Da (red band, 5 deg C) and the other six cameras derived consistently with them.
"""

from __future__ import annotations

import functools

import numpy as np

from misrgraph.errors import ConvergenceError
from misrgraph.model.camera import BAND_ANGLE_DEG, N_ALPHA, CameraModel
from misrgraph.model.constants import (
    BANDS,
    CAMERAS,
    FOCAL_LENGTH_M,
    N_PIXELS,
    PITCH_CROSS_M,
    SAMPLE_DIRECTION,
    VIEW_ANGLE_DEG,
)

__all__ = [
    "nominal_camera_model",
    "derive_camera_model",
    "preflight_camera_model",
    "TABLE1",
    "TABLE1_OMEGA_DEG",
    "REFERENCE_LAT_DEG",
    "compensation_miss_km",
    "MODEL_NAMES",
    "builtin_camera_model",
]

#: Built-in models a user can name instead of a file (``--camera-model preflight``).
MODEL_NAMES = ("preflight", "nominal")

TABLE1_OMEGA_DEG = (-0.0658333, -0.041111, 0.006666)  # wx, wy, wz
REFERENCE_LAT_DEG = 30.0

#: Table 1 of the seed as printed (red band, 5 deg C): downtrack angle of the red line array k
#: (deg), focal length f0 (mm), alpha_0 (the tangent of the first pixel's cross-track field
#: angle, see :func:`preflight_camera_model`), epsilon, delta, beta (deg). The OCR-damaged
#: "-28030" and "-579879" read as -2.8030 and -57.9879.
TABLE1: dict[str, dict[str, float]] = {
    "Df": {
        "k_deg": -0.065,
        "f_mm": 123.67,
        "alpha0": 1.2747e-01,
        "epsilon_deg": -0.2759,
        "delta_deg": -2.8030,
        "beta_deg": 58.1266,
    },
    "An": {
        "k_deg": -0.050,
        "f_mm": 58.944,
        "alpha0": 2.71992e-01,
        "epsilon_deg": -0.1518,
        "delta_deg": 0.0022,
        "beta_deg": 0.0016,
    },
    "Da": {
        "k_deg": -0.0358,
        "f_mm": 123.653,
        "alpha0": 1.2941e-01,
        "epsilon_deg": 0.0691,
        "delta_deg": 2.7314,
        "beta_deg": -57.9879,
    },
}


def _initial_model() -> CameraModel:
    nc, nb = len(CAMERAS), len(BANDS)
    f = np.array([[FOCAL_LENGTH_M[c]] * nb for c in CAMERAS])
    alpha = np.zeros((nc, nb, N_ALPHA))
    alpha[..., 1] = np.array([SAMPLE_DIRECTION[c] for c in CAMERAS])[:, None] * PITCH_CROSS_M / f
    band_angle = np.radians([BAND_ANGLE_DEG[b] for b in BANDS])
    k = f * np.tan(band_angle)[None, :]
    # first guess for beta: spherical Earth, R = 6371 km, H = 705 km
    theta = np.radians([VIEW_ANGLE_DEG[c] for c in CAMERAS])
    beta = np.arcsin(6371.0 / 7076.0 * np.sin(theta))
    return CameraModel(
        omega=np.radians(TABLE1_OMEGA_DEG),
        delta=np.zeros(nc),
        beta=beta,
        epsilon=np.zeros(nc),
        focal_length=f,
        alpha=alpha,
        k=k,
        cy=np.full((nc, nb), (N_PIXELS - 1) / 2.0),
        provenance={"source": "misrgraph.model.nominal.derive_camera_model"},
    )


def derive_camera_model(
    ref_lat_deg: float = REFERENCE_LAT_DEG, path: int = 37, epoch_date: str = "2001-06-15"
) -> CameraModel:
    """Derive beta and delta of every camera numerically (see the module docstring).

    For each oblique camera the geometry is taken at the moment its boresight ground point lies
    at ``ref_lat_deg`` on a descending pass (the spacecraft is then about 12 deg of latitude
    north of that point for Df and south of it for Da): beta gives the nominal view zenith angle
    there, and delta makes An see that same ground point at An's boresight sample. Both are
    re-solved until the moment is consistent with them.
    """
    from misrgraph.model.frames import ecef_to_geodetic, enu_basis
    from misrgraph.model.geolocation import PassGeometry, ray_ellipsoid
    from misrgraph.model.orbit import AttitudeSeries, terra_like_orbit

    # Pass centred on the reference latitude, long enough for Df..Da to see the same point.
    eph = terra_like_orbit(
        epoch_date=epoch_date, path=path, start_lat_deg=min(ref_lat_deg + 30.0, 81.0), duration_s=2400.0
    )
    model = _initial_model()
    geo = PassGeometry(eph, AttitudeSeries.zeros(eph.t), model)

    def boresight_ground(ci: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        nav = geo.nav_state(np.array([t]))
        origin = (nav.eci_to_ecef[0] @ nav.position[0])[None, :]
        d_scs = model.detector_to_spacecraft(ci) @ np.array([0.0, 0.0, 1.0])
        d = nav.eci_to_ecef[0] @ nav.r_eci_scs[0] @ d_scs
        lam = ray_ellipsoid(origin, d[None, :], 0.0)
        return origin[0] + lam[0] * d, d

    def ground_lat(ci: int, t: float) -> float:
        g, _ = boresight_ground(ci, t)
        return float(ecef_to_geodetic(g)[0])

    def time_at_ref(ci: int, t: float) -> float:
        # descending pass: the ground latitude decreases by about 0.06 deg/s
        for _ in range(20):
            lat0, lat1 = ground_lat(ci, t), ground_lat(ci, t + 1.0)
            step = (ref_lat_deg - lat0) / (lat1 - lat0)
            t += step
            if abs(step) < 1e-4:
                return t
        raise ConvergenceError(f"no time at which camera {CAMERAS[ci]} sees latitude {ref_lat_deg}")  # pragma: no cover

    def zenith(ci: int, t: float) -> float:
        g, d = boresight_ground(ci, t)
        lat, lon, _ = ecef_to_geodetic(g)
        up = enu_basis(lat, lon)[..., 2]
        return float(np.degrees(np.arccos(np.clip(-d @ up, -1, 1))))

    an = CAMERAS.index("An")
    red = BANDS.index("red")
    t_mid = float(eph.t[len(eph.t) // 2])
    for ci, cam in enumerate(CAMERAS):
        if cam == "An":
            continue
        want = abs(VIEW_ANGLE_DEG[cam])
        sign = np.sign(VIEW_ANGLE_DEG[cam])
        t_c = t_mid
        for _outer in range(6):
            t_prev = t_c
            t_c = time_at_ref(ci, t_c)
            b0 = model.beta[ci]
            for _ in range(30):
                z0 = zenith(ci, t_c)
                model.beta[ci] = b0 + sign * 1e-6
                z1 = zenith(ci, t_c)
                model.beta[ci] = b0
                step = (want - z0) / ((z1 - z0) / 1e-6)
                b0 = b0 + sign * step
                model.beta[ci] = b0
                if abs(step) < 1e-12:
                    break
            else:  # pragma: no cover - the map is smooth and monotonic
                raise ConvergenceError(f"beta of camera {cam} did not converge")

            # delta: An must see the boresight ground point at its boresight sample (red band)
            def an_sample_offset(dlt: float) -> float:
                model.delta[ci] = dlt
                g, _ = boresight_ground(ci, t_c)
                _, s, vis, _, _ = geo.ground_to_pixel(an, red, g[None, :])
                if not vis[0]:
                    raise ConvergenceError(f"An does not see the boresight point of {cam} during the derivation pass")
                return float(s[0] - model.cy[an, red])

            d0 = float(model.delta[ci])
            d1 = d0 - sign * np.radians(0.5)
            f0, f1 = an_sample_offset(d0), an_sample_offset(d1)
            for _ in range(30):
                if abs(f1) < 1e-6 or f1 == f0:
                    break
                d2 = d1 - f1 * (d1 - d0) / (f1 - f0)
                d0, f0 = d1, f1
                d1, f1 = d2, an_sample_offset(d2)
            model.delta[ci] = d1
            if abs(time_at_ref(ci, t_c) - t_prev) < 1e-3 and _outer > 0:
                break
    model.provenance.update(
        {
            "ref_lat_deg": str(ref_lat_deg),
            "path": str(path),
            "epoch_date": epoch_date,
            "convention": "T_ic = Ry(beta) Rx(delta)",
            "method": "beta from view zenith angle; delta from Earth-rotation compensation against An, "
            "both for the camera's boresight ground point at the reference latitude",
        }
    )
    return model


def preflight_camera_model() -> CameraModel:
    """The pre-flight Camera Geometric Model: Table 1 as printed, the other six cameras consistent.

    For Df, An and Da (every band): ``f`` = f0; ``k = f tan(k_deg + band offset)`` where the band
    offsets are those of :data:`~misrgraph.model.camera.BAND_ANGLE_DEG` relative to red; epsilon,
    delta, beta as printed; omega is the mounted value common to all cameras. Table 1's alpha_0
    is read as the coefficient of a polynomial whose origin is the array's first pixel, i.e. the
    tangent of that pixel's cross-track field angle (0.127 for the D cameras and 0.272 for An
    match half the 1504 x 21 um array over f). In eq. 2's form, ``f sum alpha_i (s - c_y)^i``,
    that is the boresight sample ``c_y = alpha_0 f / d_y`` with ``alpha = [0, d_y/f, 0...]``
    (Df 750.7, An 763.4, Da 762.0). The table does not say which way samples run; alpha_1 takes
    the sign of :data:`~misrgraph.model.constants.SAMPLE_DIRECTION` (negative for the aft
    cameras), the convention under which the sensitivities at pixel 0 of the fore and aft cameras
    mirror each other as the seed's Table 3 gives them.

    The other cameras: beta from the nominal derivation; delta the derived value scaled by
    Table 1's Df (fore cameras) or Da (aft cameras) delta over the derived one, so the whole
    instrument compensates Earth rotation at the same latitude; Af and Aa take An's focal length
    (the same optics), B and C the nominal ones; epsilon 0, the nominal k and c_y.
    """
    model = nominal_camera_model().copy()
    derived = nominal_camera_model()
    offsets = np.radians([BAND_ANGLE_DEG[b] - BAND_ANGLE_DEG["red"] for b in BANDS])
    for cam, row in TABLE1.items():
        c = CAMERAS.index(cam)
        f = row["f_mm"] * 1e-3
        model.focal_length[c, :] = f
        model.k[c, :] = f * np.tan(np.radians(row["k_deg"]) + offsets)
        model.alpha[c, :, :] = 0.0
        model.alpha[c, :, 1] = SAMPLE_DIRECTION[cam] * PITCH_CROSS_M / f
        model.cy[c, :] = row["alpha0"] * f / PITCH_CROSS_M
        model.epsilon[c] = np.radians(row["epsilon_deg"])
        model.delta[c] = np.radians(row["delta_deg"])
        model.beta[c] = np.radians(row["beta_deg"])
    fore_scale = model.delta[CAMERAS.index("Df")] / derived.delta[CAMERAS.index("Df")]
    aft_scale = model.delta[CAMERAS.index("Da")] / derived.delta[CAMERAS.index("Da")]
    for c, cam in enumerate(CAMERAS):
        if cam in TABLE1:
            continue
        model.delta[c] = derived.delta[c] * (fore_scale if VIEW_ANGLE_DEG[cam] > 0 else aft_scale)
        if cam[0] == "A":
            f = TABLE1["An"]["f_mm"] * 1e-3
            model.focal_length[c, :] = f
            model.alpha[c, :, 1] = SAMPLE_DIRECTION[cam] * PITCH_CROSS_M / f
            model.k[c, :] = f * np.tan(np.radians(BAND_ANGLE_DEG["red"]) + offsets)
    model.temperature_c = 5.0
    model.provenance = {
        "source": "pre-flight model: Table 1 (Df, An, Da, red band, 5 deg C) as printed; "
        "other cameras derived (misrgraph.model.nominal.preflight_camera_model)",
        "convention": "T_ic = Ry(beta) Rx(delta)",
    }
    return model


@functools.lru_cache(maxsize=1)
def _derived_nominal() -> CameraModel:
    return derive_camera_model()


def nominal_camera_model() -> CameraModel:
    """The nominal (design) model (a fresh copy of the model derived once per process)."""
    return _derived_nominal().copy()


def compensation_miss_km(
    model: CameraModel,
    lat_deg: "list[float] | np.ndarray",
    cameras: "tuple[str, ...]" = ("Df", "Da"),
    path: int = 37,
    epoch_date: str = "2001-06-15",
) -> dict[str, np.ndarray]:
    """How far each camera's boresight ground point lies from An's boresight track (km).

    On a descending Terra-like pass with zero attitude, for every latitude in ``lat_deg`` and
    camera in ``cameras``: the ground point ``P`` (WGS84 ellipsoid) of the camera's boresight pixel
    (red band, sample ``c_y``) when ``P`` is at that latitude; the pixel at which An sees ``P``;
    and the distance from ``P`` to An's boresight ground point on that line, signed + when ``P`` is
    right of the flight direction (An's sample above its boresight sample). Zero means the
    camera's delta compensates Earth rotation exactly at that latitude. Everything goes through
    :class:`~misrgraph.model.geolocation.PassGeometry`. Returns ``{camera: (len(lat_deg),)}``.
    """
    from misrgraph.model.frames import ecef_to_geodetic
    from misrgraph.model.geolocation import PassGeometry
    from misrgraph.model.orbit import AttitudeSeries, terra_like_orbit

    lats = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    eph = terra_like_orbit(
        epoch_date=epoch_date, path=path, start_lat_deg=min(float(lats.max()) + 25.0, 81.0), duration_s=2700.0
    )
    geo = PassGeometry(eph, AttitudeSeries.zeros(eph.t), model)
    red, an = BANDS.index("red"), CAMERAS.index("An")
    out: dict[str, np.ndarray] = {}
    for cam in cameras:
        c = CAMERAS.index(cam)
        cy = model.cy[c, red]
        lines = np.arange(0.0, geo.lines_in_pass(c, red), 200.0)
        g = geo.pixel_to_ground(np.full(lines.size, c), red, lines, np.full(lines.size, cy))
        lat_line = ecef_to_geodetic(g)[0]
        ok = np.isfinite(lat_line)
        line_at = np.interp(-lats, -lat_line[ok], lines[ok])  # descending: latitude falls with line
        line_at = np.floor(line_at + 0.5)  # whole lines: the boresight pixel's own ground point
        p = geo.pixel_to_ground(np.full(lats.size, c), red, line_at, np.full(lats.size, cy))
        ip = geo.ground_to_pixel(np.full(lats.size, an), red, p)
        if not np.all(ip.visible):
            raise ConvergenceError(f"An does not see the boresight point of {cam} at latitudes {lats[~ip.visible]}")
        q = geo.pixel_to_ground(
            np.full(lats.size, an), red, ip.line, np.full(lats.size, model.cy[an, red]), exposure=ip.exposure
        )
        out[cam] = np.sign(ip.sample - model.cy[an, red]) * np.linalg.norm(p - q, axis=-1) / 1e3
    return out


def builtin_camera_model(name: str) -> CameraModel:
    """A built-in model by name (:data:`MODEL_NAMES`): ``"preflight"`` or ``"nominal"``."""
    if name not in MODEL_NAMES:
        from misrgraph.errors import InputError

        raise InputError("camera model", name, MODEL_NAMES)
    return preflight_camera_model() if name == "preflight" else nominal_camera_model()
