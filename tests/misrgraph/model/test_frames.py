from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from misrgraph.errors import InputError
from misrgraph.model.frames import (
    OMEGA_EARTH,
    WGS84_A,
    WGS84_B,
    EarthOrientation,
    ecef_to_geodetic,
    enu_basis,
    geodetic_to_ecef,
    parse_epoch,
)


def test_geodetic_known_points():
    np.testing.assert_allclose(geodetic_to_ecef(0, 0, 0), [WGS84_A, 0, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(90, 0, 0), [0, 0, WGS84_B], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(0, 90, 100.0), [0, WGS84_A + 100.0, 0], atol=1e-6)


@given(st.floats(-89.9, 89.9), st.floats(-180, 180), st.floats(-500, 9000))
def test_geodetic_round_trip(lat, lon, h):
    p = geodetic_to_ecef(lat, lon, h)
    la, lo, hh = ecef_to_geodetic(p)
    assert la == pytest.approx(lat, abs=1e-9)
    assert (lo - lon + 180) % 360 - 180 == pytest.approx(0, abs=1e-9)
    assert hh == pytest.approx(h, abs=1e-6)


def test_enu_is_orthonormal_and_up_is_normal():
    b = enu_basis(np.array([10.0, -45.0]), np.array([20.0, 170.0]))
    for m in b:
        np.testing.assert_allclose(m.T @ m, np.eye(3), atol=1e-14)
    # up is the ellipsoid normal: moving 1 m up changes only the height
    p0 = geodetic_to_ecef(10.0, 20.0, 0.0)
    p1 = p0 + b[0][:, 2]
    assert ecef_to_geodetic(p1)[2] == pytest.approx(1.0, abs=1e-9)


def test_eci_ecef_round_trip_and_orthonormal():
    eo = EarthOrientation("2001-06-15T17:00:00Z", dut1=0.3, xp=0.1, yp=0.3)
    t = np.linspace(0, 3000, 57)
    m = eo.eci_to_ecef(t)
    np.testing.assert_allclose(m @ np.swapaxes(m, 1, 2), np.broadcast_to(np.eye(3), m.shape), atol=1e-14)
    r = np.array([7.0e6, -1.2e6, 3.3e5])
    back = np.einsum("nij,nj->ni", eo.ecef_to_eci(t), np.einsum("nij,j->ni", m, r))
    assert np.max(np.abs(back - r)) < 1e-3  # < 1 mm


def test_interpolated_earth_orientation_matches_direct_erfa():
    eo = EarthOrientation("2001-06-15T17:00:00Z", dut1=-0.2, xp=0.05, yp=0.4)
    t = np.linspace(0, 2700, 41) + 0.37
    diff = eo.eci_to_ecef(t) - eo.direct_c2t(t)
    # at the Earth's surface: < 0.1 mm
    assert np.max(np.abs(diff)) * WGS84_A < 1e-4


def test_earth_rotation_rate():
    eo = EarthOrientation("2001-06-15T17:00:00Z")
    era = np.unwrap(eo.era(np.array([0.0, 100.0])))
    assert (era[1] - era[0]) / 100.0 == pytest.approx(OMEGA_EARTH, rel=1e-6)


def test_parse_epoch_rejects_garbage():
    with pytest.raises(InputError, match="epoch_utc"):
        parse_epoch("yesterday")
    j1, j2 = parse_epoch("2000-01-01T12:00:00Z")
    assert j1 + j2 == pytest.approx(2451545.0)


def test_ecef_to_geodetic_shape_error():
    with pytest.raises(InputError, match="xyz"):
        ecef_to_geodetic(np.zeros((3, 2)))
