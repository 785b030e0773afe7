"""Pure, vectorised geometry shared by the factors and by :mod:`misrgraph`.

Everything here is numpy-only (no GTSAM), arrays in and arrays out, so it can be tested alone and
imported by both packages without cycles.

Conventions (docs/explanation/conventions.md):

* Rotation matrices are *active* right-handed rotations; ``rot_z(a) @ v`` rotates ``v`` by ``a``
  about +z. Angles are radians. Leading dimensions broadcast: an angle array of shape ``(N,)``
  gives matrices of shape ``(N, 3, 3)``.
* Attitude (eq. 5): ``T_os = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` maps spacecraft -> orbital frame.
* Orbital frame (eqs. 3-4, EOS convention): ``z = -P/|P|`` (toward geocentric nadir),
  ``y = z x V / |z x V|``, ``x = y x z``; ``T_go = [x y z]`` maps orbital -> inertial.
* Camera model (eq. 2): ``r_scs = T_si @ T_ic @ T_cd @ d`` with ``T_si = Rz(wz) Ry(wy) Rx(wx)``,
  ``T_ic = Ry(beta) Rx(delta)`` (delta rolls the camera about its along-track line axis, then beta
  tilts it fore/aft; MISR's heritage convention), ``T_cd = Rz(eps)`` and the detector vector
  ``d = [-(k + (l - INT(l + 0.5)) dx), f * sum_i alpha_i (s - c_y)^i, f]`` (metres).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "rot_x",
    "rot_y",
    "rot_z",
    "drot_x",
    "drot_y",
    "drot_z",
    "attitude_matrix",
    "attitude_matrix_derivatives",
    "orbital_frame",
    "hermite_weights",
    "line_fraction",
    "detector_vector",
    "skew",
    "geodetic_from_ecef",
    "geodetic_jacobians",
]

Array = NDArray[np.float64]


def _cs(a: ArrayLike) -> tuple[Array, Array, Array, Array]:
    a = np.asarray(a, dtype=float)
    return np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)


def _stack(rows: list[list[Array]]) -> Array:
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rot_x(a: ArrayLike) -> Array:
    """Active rotation about +x by ``a`` radians; shape ``a.shape + (3, 3)``."""
    c, s, z, o = _cs(a)
    return _stack([[o, z, z], [z, c, -s], [z, s, c]])


def rot_y(a: ArrayLike) -> Array:
    """Active rotation about +y by ``a`` radians; shape ``a.shape + (3, 3)``."""
    c, s, z, o = _cs(a)
    return _stack([[c, z, s], [z, o, z], [-s, z, c]])


def rot_z(a: ArrayLike) -> Array:
    """Active rotation about +z by ``a`` radians; shape ``a.shape + (3, 3)``."""
    c, s, z, o = _cs(a)
    return _stack([[c, -s, z], [s, c, z], [z, z, o]])


def drot_x(a: ArrayLike) -> Array:
    """Derivative of :func:`rot_x` with respect to the angle."""
    c, s, z, _ = _cs(a)
    return _stack([[z, z, z], [z, -s, -c], [z, c, -s]])


def drot_y(a: ArrayLike) -> Array:
    """Derivative of :func:`rot_y` with respect to the angle."""
    c, s, z, _ = _cs(a)
    return _stack([[-s, z, c], [z, z, z], [-c, z, -s]])


def drot_z(a: ArrayLike) -> Array:
    """Derivative of :func:`rot_z` with respect to the angle."""
    c, s, z, _ = _cs(a)
    return _stack([[-s, -c, z], [c, -s, z], [z, z, z]])


def attitude_matrix(roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> Array:
    """``T_os`` of eq. 5: spacecraft -> orbital frame, ``Rz(yaw) Ry(pitch) Rx(roll)``.

    Angles in radians, broadcast together; returns ``(..., 3, 3)``.
    """
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def attitude_matrix_derivatives(roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """``T_os`` and its partial derivatives with respect to roll, pitch and yaw.

    Returns ``(T, dT/droll, dT/dpitch, dT/dyaw)``, each ``(..., 3, 3)``.
    """
    rx, ry, rz = rot_x(roll), rot_y(pitch), rot_z(yaw)
    drx, dry, drz = drot_x(roll), drot_y(pitch), drot_z(yaw)
    return rz @ ry @ rx, rz @ ry @ drx, rz @ dry @ rx, drz @ ry @ rx


def orbital_frame(position: ArrayLike, velocity: ArrayLike) -> Array:
    """``T_go`` of eqs. 3-4 from inertial position and velocity (m, m/s), shape ``(..., 3)``.

    Columns are the orbital axes expressed in the inertial frame: x ~ along velocity, y = cross
    track (to the right of the flight direction when looking down), z = toward geocentric nadir.
    """
    p = np.asarray(position, dtype=float)
    v = np.asarray(velocity, dtype=float)
    z = -p / np.linalg.norm(p, axis=-1, keepdims=True)
    y = np.cross(z, v)
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def hermite_weights(tau: ArrayLike, dt: ArrayLike) -> Array:
    """Weights of ``(a_i, a'_i, a_{i+1}, a'_{i+1})`` in the cubic Hermite segment of eqs. 23-27.

    ``a(t) = w0 a_i + w1 a'_i + w2 a_{i+1} + w3 a'_{i+1}`` with ``tau = (t - t_i)/(t_{i+1} - t_i)``
    in [0, 1] and ``dt = t_{i+1} - t_i`` (s); rates are per second. Expanding eqs. 24-27:
    ``w0 = 1 - 3 tau^2 + 2 tau^3``, ``w1 = dt (tau - 2 tau^2 + tau^3)``,
    ``w2 = 3 tau^2 - 2 tau^3``, ``w3 = dt (tau^3 - tau^2)``. Returns ``(..., 4)``.
    """
    t = np.asarray(tau, dtype=float)
    d = np.asarray(dt, dtype=float)
    t2 = t * t
    t3 = t2 * t
    return np.stack(
        np.broadcast_arrays(1 - 3 * t2 + 2 * t3, d * (t - 2 * t2 + t3), 3 * t2 - 2 * t3, d * (t3 - t2)),
        axis=-1,
    )


def line_fraction(line: ArrayLike) -> tuple[Array, Array]:
    """Split an image line coordinate into the exposed line ``INT(l + 0.5)`` and ``l - INT(l+0.5)``.

    Lines are non-negative, so ``INT`` is ``floor``. The fraction lies in [-0.5, 0.5).
    """
    ln = np.asarray(line, dtype=float)
    whole = np.floor(ln + 0.5)
    return whole, ln - whole


def detector_vector(
    line: ArrayLike,
    sample: ArrayLike,
    k: ArrayLike,
    dx: ArrayLike,
    f: ArrayLike,
    alpha: ArrayLike,
    cy: ArrayLike,
    exposure: ArrayLike | None = None,
) -> Array:
    """The detector-frame vector of eq. 2 (metres), shape ``(..., 3)``.

    ``d = [-(k + (l - L) dx), f * sum_{i=0}^{5} alpha_i (s - c_y)^i, f]`` with the exposure index
    ``L = INT(l + 0.5)`` unless given explicitly.

    ``k`` band offset (m), ``dx`` along-track pitch (m), ``f`` focal length (m), ``alpha``
    ``(..., 6)`` polynomial coefficients (``alpha_i`` in pixel^-i), ``cy`` boresight sample.
    """
    if exposure is None:
        _, frac = line_fraction(line)
    else:
        frac = np.asarray(line, dtype=float) - np.asarray(exposure, dtype=float)
    s = np.asarray(sample, dtype=float) - np.asarray(cy, dtype=float)
    a = np.asarray(alpha, dtype=float)
    powers = s[..., None] ** np.arange(a.shape[-1])
    poly = np.sum(a * powers, axis=-1)
    f = np.asarray(f, dtype=float)
    x = -(np.asarray(k, dtype=float) + frac * np.asarray(dx, dtype=float))
    return np.stack(np.broadcast_arrays(x, f * poly, f), axis=-1)


def skew(v: ArrayLike) -> Array:
    """Cross-product matrix ``[v]x`` with ``[v]x @ w = v x w``; ``(..., 3) -> (..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros_like(v[..., 0])
    return _stack([[z, -v[..., 2], v[..., 1]], [v[..., 2], z, -v[..., 0]], [-v[..., 1], v[..., 0], z]])


#: WGS84 ellipsoid: semi-major axis (m), flattening, semi-minor axis (m), first eccentricity squared.
#: The project's one definition (:mod:`misrgraph.model.frames` re-exports it).
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def enu_basis(lat: ArrayLike, lon: ArrayLike) -> Array:
    """Local East-North-Up unit vectors in ECEF at geodetic ``lat, lon`` (rad): ``(..., 3, 3)``
    with columns E, N, U."""
    sl, cl = np.sin(np.asarray(lat, dtype=float)), np.cos(np.asarray(lat, dtype=float))
    so, co = np.sin(np.asarray(lon, dtype=float)), np.cos(np.asarray(lon, dtype=float))
    e = np.stack(np.broadcast_arrays(-so, co, np.zeros_like(so)), axis=-1)
    n = np.stack(np.broadcast_arrays(-sl * co, -sl * so, cl), axis=-1)
    u = np.stack(np.broadcast_arrays(cl * co, cl * so, sl), axis=-1)
    return np.stack(np.broadcast_arrays(e, n, u), axis=-1)


def enu_covariance(lat: ArrayLike, lon: ArrayLike, sigma_enu: ArrayLike) -> Array:
    """ECEF covariance ``C = R diag(s^2) R^T`` (m^2) from 1 sigma per ENU axis (m; ``(..., 3)`` or
    broadcastable) at geodetic ``lat, lon`` (rad); ``R`` is :func:`enu_basis`. Shape ``(..., 3, 3)``."""
    r = enu_basis(lat, lon)
    s2 = np.broadcast_to(np.asarray(sigma_enu, dtype=float), r.shape[:-1]) ** 2
    return np.einsum("...ij,...j,...kj->...ik", r, s2, r)


def geodetic_from_ecef(xyz: ArrayLike, iterations: int = 6) -> tuple[Array, Array, Array]:
    """WGS84 geodetic latitude, longitude (rad) and height (m) from ECEF (m), numpy only.

    Fixed-point iteration on latitude; six iterations are exact to < 1e-12 rad within 1000 km
    of the surface (checked against pyproj in the tests).
    """
    p = np.asarray(xyz, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    rho = np.hypot(x, y)
    lon = np.arctan2(y, x)
    lat = np.arctan2(z, rho * (1 - WGS84_E2))
    for _ in range(iterations):
        s = np.sin(lat)
        n = WGS84_A / np.sqrt(1 - WGS84_E2 * s * s)
        h = rho / np.cos(lat) - n
        lat = np.arctan2(z, rho * (1 - WGS84_E2 * n / (n + h)))
    s = np.sin(lat)
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * s * s)
    h = rho / np.cos(lat) - n
    return lat, lon, h


def geodetic_jacobians(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> tuple[Array, Array, Array]:
    """Gradients (w.r.t. ECEF, ``(..., 3)``) of latitude (rad/m), longitude (rad/m) and height (m/m)."""
    la, lo, hh = (np.asarray(a, dtype=float) for a in (lat, lon, h))
    s, c = np.sin(la), np.cos(la)
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * s * s)
    m = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s * s) ** 1.5
    east = np.stack([-np.sin(lo), np.cos(lo), np.zeros_like(lo)], -1)
    north = np.stack([-s * np.cos(lo), -s * np.sin(lo), c], -1)
    up = np.stack([c * np.cos(lo), c * np.sin(lo), s], -1)
    return north / (m + hh)[..., None], east / ((n + hh) * c)[..., None], up
