from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.frames import ecef_to_geodetic, geodetic_to_ecef
from misrgraph.model.geolocation import PassGeometry, ray_ellipsoid
from misrgraph.model.orbit import AttitudeSeries


def _line_range(geo: PassGeometry, c: int, b: int) -> tuple[float, float]:
    # lines whose ground point is seen by all cameras within the pass: the middle third
    n = geo.lines_in_pass(c, b)
    return 0.35 * n, 0.65 * n


# Canonical pixels: the along-track image moves at least 0.39 detector pitch per line (D cameras),
# so a point whose fraction is within +-0.15 of its exposure is nearest that exposure's centre.
CANONICAL_FRAC = 0.15


@given(
    c=st.integers(0, 8),
    b=st.integers(0, 3),
    u=st.floats(0.0, 1.0),
    frac=st.floats(-CANONICAL_FRAC, CANONICAL_FRAC),
    s=st.floats(0.0, 1503.0),
)
def test_pixel_ground_pixel_round_trip(reference_pass, c, b, u, frac, s):
    lo, hi = _line_range(reference_pass, c, b)
    line = np.floor(lo + u * (hi - lo)) + frac
    g = reference_pass.pixel_to_ground(c, b, line, s)
    ln, sm, vis, exp, _ = reference_pass.ground_to_pixel(c, b, g)
    assert vis[0]
    assert abs(ln[0] - line) < 1e-3
    assert abs(sm[0] - s) < 1e-3
    assert exp[0] == np.floor(line + 0.5)


def test_round_trip_vectorised_all_cameras_bands(reference_pass, rng):
    n = 400
    c = rng.integers(0, 9, n)
    b = rng.integers(0, 4, n)
    nl = np.array([reference_pass.lines_in_pass(ci, bi) for ci, bi in zip(c, b)])
    line = np.floor(rng.uniform(0.35, 0.65, n) * nl) + rng.uniform(-CANONICAL_FRAC, CANONICAL_FRAC, n)
    s = rng.uniform(0, 1503, n)
    g = reference_pass.pixel_to_ground(c, b, line, s, height=350.0)
    lat, lon, h = ecef_to_geodetic(g)
    np.testing.assert_allclose(h, 350.0, atol=1e-3)
    ln, sm, vis, _, _ = reference_pass.ground_to_pixel(c, b, g)
    assert vis.all()
    assert np.max(np.abs(ln - line)) < 1e-3
    assert np.max(np.abs(sm - s)) < 1e-3


def test_ground_pixel_ground_round_trip_any_point(reference_pass, rng):
    """Every visible ground point re-projects exactly through its canonical pixel (all cameras)."""
    an = CAMERAS.index("An")
    mid = 0.5 * reference_pass.lines_in_pass(an, 2)
    centre = reference_pass.pixel_to_ground(an, 2, mid, 751.5)[0]
    lat0, lon0, _ = ecef_to_geodetic(centre)
    n = 200
    g = geodetic_to_ecef(lat0 + rng.uniform(-1, 1, n), lon0 + rng.uniform(-1.5, 1.5, n), rng.uniform(0, 2000, n))
    for c in range(9):
        for b in range(4):
            ln, sm, vis, exp, _ = reference_pass.ground_to_pixel(c, b, g)
            assert vis.mean() > 0.5
            back = reference_pass.pixel_to_ground(
                c, b, ln[vis], sm[vis], height=ecef_to_geodetic(g[vis])[2], exposure=exp[vis]
            )
            assert np.max(np.linalg.norm(back - g[vis], axis=1)) < 1e-3


def test_oblique_cameras_see_a_point_in_several_lines(reference_pass):
    """Eq. 2 with whole-line timing is many-to-one for D: lines L+0.45 and the canonical pixel
    of its ground point differ, yet both rays pass through the same ground point."""
    df = CAMERAS.index("Df")
    line = np.floor(0.5 * reference_pass.lines_in_pass(df, 2)) + 0.45
    g = reference_pass.pixel_to_ground(df, 2, line, 700.0)
    ln, sm, vis, exp, _ = reference_pass.ground_to_pixel(df, 2, g)
    assert vis[0] and abs(ln[0] - line) > 0.5
    back = reference_pass.pixel_to_ground(df, 2, ln, sm, exposure=exp)
    assert np.linalg.norm(back - g) < 1e-3


def test_closed_form_nadir_of_an(nominal_camera):
    """With a distortion-free An on the optical axis and zero attitude, the ray is geocentric nadir:
    it meets the ellipsoid at r_e(u) u with 1/r_e^2 = (ux^2+uy^2)/a^2 + uz^2/b^2."""
    from misrgraph.model.frames import WGS84_A, WGS84_B
    from misrgraph.model.orbit import terra_like_orbit

    m = nominal_camera.copy()
    m.omega[:] = 0.0
    an = CAMERAS.index("An")
    m.k[an, :] = 0.0
    eph = terra_like_orbit(duration_s=200.0, start_lat_deg=40.0)
    geo = PassGeometry(eph, AttitudeSeries.zeros(eph.t), m)
    line = np.array([10.0, 1000.0, 3000.0])
    g = geo.pixel_to_ground(an, 0, line, m.cy[an, 0])
    origin, direction = geo.pixel_rays(an, 0, line, m.cy[an, 0])
    u = -origin / np.linalg.norm(origin, axis=1, keepdims=True)
    np.testing.assert_allclose(direction, u, atol=1e-12)
    re = 1 / np.sqrt((u[:, 0] ** 2 + u[:, 1] ** 2) / WGS84_A**2 + u[:, 2] ** 2 / WGS84_B**2)
    np.testing.assert_allclose(g, -u * re[:, None], atol=1e-3)


def test_ray_casting_onto_a_height_field(reference_pass, rng):
    def surface(lat, lon):
        return 1500.0 + 800.0 * np.sin(np.radians(lat) * 300) * np.cos(np.radians(lon) * 250)

    n = 60
    c = rng.integers(0, 9, n)
    b = rng.integers(0, 4, n)
    nl = np.array([reference_pass.lines_in_pass(ci, bi) for ci, bi in zip(c, b)])
    line = np.floor(rng.uniform(0.4, 0.6, n) * nl) + rng.uniform(-0.5, 0.5, n)
    s = rng.uniform(0, 1503, n)
    g = reference_pass.pixel_to_ground(c, b, line, s, surface=surface)
    lat, lon, h = ecef_to_geodetic(g)
    np.testing.assert_allclose(h, surface(lat, lon), atol=1e-3)
    ln, sm, vis, exp, _ = reference_pass.ground_to_pixel(c, b, g)
    assert vis.all()
    back = reference_pass.pixel_to_ground(c, b, ln, sm, surface=surface, exposure=exp)
    assert np.max(np.linalg.norm(back - g, axis=1)) < 1e-3


def test_invisible_points(reference_pass):
    # the antipode of the pass is never seen; a point far off the swath is not either
    nav = reference_pass.nav_state(np.array([900.0]))
    sub = nav.eci_to_ecef[0] @ nav.position[0]
    lat, lon, _ = ecef_to_geodetic(sub)
    far = geodetic_to_ecef(-lat, lon + 180.0, 0.0)
    side = geodetic_to_ecef(lat, lon + 15.0, 0.0)
    ln, sm, vis, _, _ = reference_pass.ground_to_pixel(4, 2, np.stack([far, side]))
    assert not vis.any() and np.isnan(ln).all()


def test_ray_ellipsoid_miss():
    lam = ray_ellipsoid(np.array([[1e7, 0, 0]]), np.array([[0.0, 1.0, 0.0]]))
    assert np.isnan(lam[0])


def test_corrections_move_the_ground_point(reference_pass):
    """A +10 arcsec pitch correction moves An's nadir point forward by ~H * 10 arcsec."""
    base = reference_pass
    an, red = CAMERAS.index("An"), BANDS.index("red")
    line = 0.5 * base.lines_in_pass(an, red)
    d = np.radians(10 / 3600)
    pert = PassGeometry(
        base.ephemeris,
        base.attitude,
        base.camera,
        base.earth,
        base.t0,
        attitude_delta=lambda t: np.broadcast_to([0.0, d, 0.0], (np.size(t), 3)),
    )
    g0 = base.pixel_to_ground(an, red, line, 751.5)
    g1 = pert.pixel_to_ground(an, red, line, 751.5)
    origin, _ = base.pixel_rays(an, red, line, 751.5)
    height = np.linalg.norm(origin - g0)
    assert np.linalg.norm(g1 - g0) == pytest.approx(height * d, rel=0.01)


def test_bad_indices(reference_pass):
    from misrgraph.errors import InputError

    with pytest.raises(InputError, match="camera"):
        reference_pass.pixel_to_ground(9, 0, 10.0, 5.0)
    with pytest.raises(InputError, match="ground"):
        reference_pass.ground_to_pixel(0, 0, np.zeros((2, 2)))


def test_camera_model_default_used(nominal_camera):
    assert isinstance(nominal_camera, CameraModel)
