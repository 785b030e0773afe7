from __future__ import annotations

import erfa
import numpy as np
import pytest

from factors.geometry import rot_z
from misrgraph.errors import InputError
from misrgraph.model.constants import NODAL_PERIOD_S
from misrgraph.model.frames import WGS84_A, EarthOrientation, ecef_to_geodetic, parse_epoch
from misrgraph.model.orbit import (
    AttitudeSeries,
    Ephemeris,
    orbit_from_tle,
    path_node_longitude,
    terra_like_orbit,
)


@pytest.fixture(scope="module")
def sso() -> Ephemeris:
    return terra_like_orbit(epoch_date="2001-06-15", path=37, start_lat_deg=75.0, duration_s=3000.0)


def test_terra_like_orbit_geometry(sso):
    r = np.linalg.norm(sso.position, axis=1)
    assert np.ptp(r) < 1e-3  # circular
    assert 690e3 < r.mean() - WGS84_A < 710e3
    h = np.cross(sso.position, sso.velocity)
    inc = np.degrees(np.arccos(h[:, 2] / np.linalg.norm(h, axis=1)))
    # node regression tilts the osculating plane by ~raan_rate/n = 2e-4 rad
    np.testing.assert_allclose(inc, 98.2, atol=0.02)
    # velocity is the derivative of position
    dp = (sso.position[2:] - sso.position[:-2]) / (sso.t[2:] - sso.t[:-2])[:, None]
    assert np.max(np.abs(dp - sso.velocity[1:-1])) < 0.02
    # sampled every 1.024 s like the navigation data
    np.testing.assert_allclose(np.diff(sso.t), 1.024)


def test_pass_is_descending_from_start_latitude(sso):
    eo = EarthOrientation(sso.epoch_utc)
    ecef = np.einsum("nij,nj->ni", eo.eci_to_ecef(sso.t), sso.position)
    geocentric = np.degrees(np.arcsin(ecef[:, 2] / np.linalg.norm(ecef, axis=1)))
    assert geocentric[0] == pytest.approx(75.0, abs=0.01)  # start latitude is geocentric
    assert np.all(np.diff(geocentric[:2000]) < 0)


def test_descending_node_at_1030_local_time_and_path_longitude():
    eph = terra_like_orbit(epoch_date="2001-06-15", path=100, start_lat_deg=10.0, duration_s=600.0)
    eo = EarthOrientation(eph.epoch_utc)
    ecef = np.einsum("nij,nj->ni", eo.eci_to_ecef(eph.t), eph.position)
    lat, lon, _ = ecef_to_geodetic(ecef)
    i = np.argmin(np.abs(lat))
    t_node = np.interp(0.0, -lat, eph.t)
    lon_node = np.interp(t_node, eph.t, np.unwrap(np.radians(lon)))
    assert np.degrees(lon_node) == pytest.approx(path_node_longitude(100), abs=0.05)
    u1, u2 = parse_epoch(eph.epoch_utc)
    utc_hours = ((u1 - 0.5) % 1 + u2 + t_node / 86400.0) % 1 * 24
    lst = (utc_hours + np.degrees(lon_node) / 15.0) % 24
    assert lst == pytest.approx(10.5, abs=0.02)
    del i


def test_nodal_period_is_the_repeat_cycle():
    assert NODAL_PERIOD_S * 233 == pytest.approx(16 * 86400)


def test_hermite_interpolation_between_samples(sso):
    coarse = Ephemeris(sso.epoch_utc, sso.t[::2], sso.position[::2], sso.velocity[::2])
    p, v = coarse.interpolate(sso.t[1:-1:2])
    assert np.max(np.abs(p - sso.position[1:-1:2])) < 1e-3
    assert np.max(np.abs(v - sso.velocity[1:-1:2])) < 1e-3


def test_interpolation_outside_span_is_an_error(sso):
    with pytest.raises(InputError, match="t"):
        sso.interpolate([sso.t[-1] + 10.0])


def test_attitude_interpolation_exact_for_cubic():
    t = np.arange(0, 20.0, 1.024)

    def f(x):
        return 1e-5 * (x**3 - 3 * x)

    def df(x):
        return 1e-5 * (3 * x**2 - 3)

    a = np.stack([f(t), 2 * f(t), -f(t)], 1)
    r = np.stack([df(t), 2 * df(t), -df(t)], 1)
    s = AttitudeSeries(t, a, r)
    tq = np.array([0.3, 5.5, 17.9])
    np.testing.assert_allclose(s.interpolate(tq)[:, 1], 2 * f(tq), atol=1e-15)


def test_tle_orbit_is_terra_and_agrees_with_classic_teme_to_ecef():
    eph = orbit_from_tle(duration_s=600.0)
    alt = np.linalg.norm(eph.position, axis=1) - WGS84_A
    assert 680e3 < alt.mean() < 730e3
    h = np.cross(eph.position, eph.velocity)
    inc = np.degrees(np.arccos(h[:, 2] / np.linalg.norm(h, axis=1)))
    assert inc.mean() == pytest.approx(98.21, abs=0.1)
    # independent route: TEME -> PEF with GMST82 (Vallado), PEF ~ ITRF without polar motion
    from sgp4.api import Satrec

    from misrgraph.model.orbit import TERRA_TLE

    sat = Satrec.twoline2rv(*TERRA_TLE)
    u1, u2 = parse_epoch(eph.epoch_utc)
    t = eph.t[::60]
    _, r_teme, _ = sat.sgp4_array(np.full(t.shape, u1), u2 + t / 86400.0)
    gmst = erfa.gmst82(u1, u2 + t / 86400.0)
    pef = np.einsum("nij,nj->ni", rot_z(-gmst), r_teme * 1e3)
    ours = np.einsum("nij,nj->ni", EarthOrientation(eph.epoch_utc).eci_to_ecef(t), eph.position[::60])
    assert np.max(np.linalg.norm(ours - pef, axis=1)) < 30.0


def test_path_validation():
    with pytest.raises(InputError, match="path"):
        path_node_longitude(0)
    with pytest.raises(InputError, match="path"):
        terra_like_orbit(path=234)


def test_bad_tle():
    with pytest.raises(InputError, match="tle"):
        orbit_from_tle("1 garbage", "2 garbage")
