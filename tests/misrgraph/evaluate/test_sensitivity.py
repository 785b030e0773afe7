"""The sensitivity numbers follow from geometry that can be computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.evaluate.sensitivity import reference_geometry, run_sensitivity
from misrgraph.model.constants import ARCSEC, BANDS, CAMERAS


@pytest.fixture(scope="module")
def near_nadir():
    return run_sensitivity(arcsec=10.0, pixel=751.5, band="red", ephemeris_m=100.0)


@pytest.fixture(scope="module")
def edge():
    return run_sensitivity(arcsec=10.0, pixel=0.0, band="red")


def _slant_and_geometry(cam: str, pixel: float):
    geo = reference_geometry()
    c, b = CAMERAS.index(cam), BANDS.index("red")
    t_mid = 0.5 * (geo.ephemeris.t[0] + geo.ephemeris.t[-1])
    line = (t_mid - geo.t0[c, b]) / geo.camera.line_time
    g = geo.pixel_to_ground(c, b, line, pixel)[0]
    o, d = geo.pixel_rays(c, b, line, pixel)
    return g, o[0], d[0]


def test_hand_case_1_nadir_pitch_and_roll(near_nadir):
    """An at the centre pixel: a small rotation theta moves the point by H * theta
    (H = slant range ~ 705 km): 705e3 m * 10 arcsec = 34.2 m. +pitch is forward, +roll left."""
    g, o, _ = _slant_and_geometry("An", 751.5)
    h = np.linalg.norm(o - g)
    expect = h * 10 * ARCSEC
    an = near_nadir["cameras"]["An"]
    assert an["pitch"]["along_m"] == pytest.approx(expect, rel=0.01)
    assert an["roll"]["cross_m"] == pytest.approx(-expect, rel=0.01)
    assert abs(an["yaw"]["along_m"]) < 0.5 and abs(an["yaw"]["cross_m"]) < 0.5
    # a position error at nadir translates the point one for one (attitude fixed to the orbital frame)
    assert an["ephemeris"]["along"]["along_m"] == pytest.approx(100.0, rel=0.01)
    assert an["ephemeris"]["cross"]["cross_m"] == pytest.approx(100.0, rel=0.01)
    assert abs(an["ephemeris"]["radial"]["along_m"]) < 2.0


def test_hand_case_2_oblique_pitch_on_a_sphere(near_nadir):
    """Df boresight on a sphere of radius R seen from radius R+H at off-nadir angle b: the ground arc
    is s = R (asin((R+H)/R sin b) - b), so ds/db = R ((R+H)/R cos b / sqrt(1 - ((R+H)/R sin b)^2) - 1)."""
    g, o, d = _slant_and_geometry("Df", 751.5)
    r, rs = np.linalg.norm(g), np.linalg.norm(o)
    b = np.arccos(np.dot(-o / rs, d))
    q = rs / r
    ds_db = r * (q * np.cos(b) / np.sqrt(1 - (q * np.sin(b)) ** 2) - 1)
    expect = ds_db * 10 * ARCSEC
    assert near_nadir["cameras"]["Df"]["pitch"]["along_m"] == pytest.approx(expect, rel=0.02)


def test_yaw_at_swath_edge_moves_along_track(edge):
    """Yaw turns the view about nadir: at the An swath edge (cross distance X) the point moves X*theta."""
    g, o, _ = _slant_and_geometry("An", 0.0)
    gc, _, _ = _slant_and_geometry("An", 751.5)
    x = np.linalg.norm(g - gc)
    assert abs(edge["cameras"]["An"]["yaw"]["along_m"]) == pytest.approx(x * 10 * ARCSEC, rel=0.05)


def test_pitch_dominates_and_grows_with_obliquity(edge):
    cams = edge["cameras"]
    pitch = [abs(cams[c]["pitch"]["along_m"]) for c in ("An", "Af", "Bf", "Cf", "Df")]
    assert np.all(np.diff(pitch) > 0)
    for c in CAMERAS:
        assert abs(cams[c]["pitch"]["along_m"]) > abs(cams[c]["roll"]["along_m"])
        assert abs(cams[c]["roll"]["cross_m"]) > abs(cams[c]["roll"]["along_m"])


def test_linear_in_arcsec():
    a = run_sensitivity(arcsec=5.0, pixel=100.0, cameras=("Bf",))
    b = run_sensitivity(arcsec=10.0, pixel=100.0, cameras=("Bf",))
    assert b["cameras"]["Bf"]["pitch"]["along_m"] == pytest.approx(2 * a["cameras"]["Bf"]["pitch"]["along_m"], rel=1e-3)


def _side_of_track(cam: str, pixel: float) -> float:
    """Signed cross-track distance (m, > 0 right of the flight direction) of a camera's pixel from
    the same camera's boresight ground point at the same line."""
    geo = reference_geometry()
    c, b = CAMERAS.index(cam), BANDS.index("red")
    t_mid = 0.5 * (geo.ephemeris.t[0] + geo.ephemeris.t[-1])
    line = (t_mid - geo.t0[c, b]) / geo.camera.line_time
    g = geo.pixel_to_ground(c, b, line, pixel)
    g0 = geo.pixel_to_ground(c, b, line, geo.camera.cy[c, b])
    _, cross, _ = geo.track_frame(g0, geo.line_time(c, b, line))
    return float((g - g0)[0] @ cross[0])


@pytest.mark.parametrize("fore, aft", [("Af", "Aa"), ("Bf", "Ba"), ("Cf", "Ca"), ("Df", "Da")])
def test_aft_cameras_mirror_fore_cameras_at_pixel_0(edge, fore, aft):
    """The seed's Table 3 gives mirrored sensitivities at pixel 0: roll and pitch move pixel 0 of an
    aft camera as they move its fore twin's, yaw the other way. That needs the aft cameras' sample
    0 on the other side of the swath (their samples run the other way across the ground)."""
    f, a = edge["cameras"][fore], edge["cameras"][aft]
    for ang, sign in (("roll", 1.0), ("pitch", 1.0), ("yaw", -1.0)):
        for d in ("along_m", "cross_m"):
            if abs(f[ang][d]) < 1.0:
                continue
            assert a[ang][d] == pytest.approx(sign * f[ang][d], rel=0.05), (aft, ang, d)
    assert np.sign(_side_of_track(fore, 0.0)) == -np.sign(_side_of_track(aft, 0.0))
    assert abs(_side_of_track(aft, 0.0)) > 100e3
