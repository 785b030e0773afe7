from __future__ import annotations

import numpy as np
import pytest

from factors.dem_height import dem_residual, dem_residual_hessian
from factors.geometry import geodetic_from_ecef
from misrgraph.model.frames import ecef_to_geodetic, geodetic_to_ecef


def _surface(lat, lon):
    h = 800 + 300 * np.sin(np.radians(lat) * 900) + 200 * np.cos(np.radians(lon) * 700)
    dlat = 300 * np.cos(np.radians(lat) * 900) * 900 * np.pi / 180
    dlon = -200 * np.sin(np.radians(lon) * 700) * 700 * np.pi / 180
    return h, dlat, dlon


def test_geodetic_from_ecef_matches_pyproj(rng):
    p = geodetic_to_ecef(rng.uniform(-85, 85, 50), rng.uniform(-180, 180, 50), rng.uniform(-500, 9000, 50))
    lat, lon, h = geodetic_from_ecef(p)
    la, lo, hh = ecef_to_geodetic(p)
    np.testing.assert_allclose(np.degrees(lat), la, atol=1e-10)
    np.testing.assert_allclose(h, hh, atol=1e-6)


def test_zero_on_the_surface_and_jacobian(rng):
    lat, lon = rng.uniform(-60, 60, 20), rng.uniform(-170, 170, 20)
    h, _, _ = _surface(lat, lon)
    p = geodetic_to_ecef(lat, lon, h)
    r, j = dem_residual(p, _surface)
    np.testing.assert_allclose(r, 0.0, atol=1e-6)
    q = p + rng.normal(size=p.shape) * 50
    r, j = dem_residual(q, _surface)
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1e-3
        num = (dem_residual(q + e, _surface, False)[0] - dem_residual(q - e, _surface, False)[0]) / 2e-3
        np.testing.assert_allclose(j[:, 0, i], num, rtol=1e-5, atol=1e-7)

    # moving straight up by 1 m lowers the residual by 1 m on flat ground
    def flat(la, lo):
        return (np.zeros_like(la), np.zeros_like(la), np.zeros_like(la))

    r0, j0 = dem_residual(p, flat)
    assert np.linalg.norm(j0[0, 0]) == pytest.approx(1.0, rel=1e-9)


def test_residual_hessian_matches_second_differences(rng):
    lat, lon = rng.uniform(-60, 60, 30), rng.uniform(-170, 170, 30)
    h, _, _ = _surface(lat, lon)
    p = geodetic_to_ecef(lat, lon, h + rng.normal(0, 40, 30))
    hess = dem_residual_hessian(p, _surface)
    np.testing.assert_allclose(hess, np.swapaxes(hess, 1, 2), atol=1e-15)
    # independent: second differences of the residual itself (no Jacobian involved)
    s = 2.0
    for a in range(3):
        for b in range(3):
            ea, eb = np.eye(3)[a] * s, np.eye(3)[b] * s

            def f(q):
                return dem_residual(q, _surface, False)[0]

            num = (f(p + ea + eb) - f(p + ea - eb) - f(p - ea + eb) + f(p - ea - eb)) / (4 * s * s)
            # curvature here is ~1e-6 / m; the residual is good to ~1e-9 m, so its second
            # differences over 2 m to ~1e-10 / m
            np.testing.assert_allclose(hess[:, a, b], num, rtol=1e-4, atol=1e-9)

    # a plane has (almost) no curvature: only the ellipsoid's ~1/R terms remain
    def plane(la, lo):
        return (np.zeros_like(la), np.zeros_like(la), np.zeros_like(la))

    assert np.abs(dem_residual_hessian(p, plane)).max() < 1e-6
