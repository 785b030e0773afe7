from __future__ import annotations

import h5py
import numpy as np
import pytest

from misrgraph.camera import CameraModel
from misrgraph.constants import BANDS, CAMERAS, FOCAL_LENGTH_M, PITCH_CROSS_M
from misrgraph.errors import FileFormatError, InputError


def test_nominal_beta_matches_table1_df(nominal_camera):
    # Table 1 pre-flight Df beta = 58.1266 deg; derived from the 70.5 deg view angle at the surface
    assert np.degrees(nominal_camera.beta[CAMERAS.index("Df")]) == pytest.approx(58.1266, abs=0.05)
    assert np.degrees(nominal_camera.beta[CAMERAS.index("Da")]) == pytest.approx(-57.9879, abs=0.5)
    assert nominal_camera.beta[CAMERAS.index("An")] == 0.0


def test_nominal_delta_compensates_earth_rotation_like_a_yaw(nominal_camera):
    d = np.degrees(nominal_camera.delta)
    # Earth-rotation compensation is a rotation about nadir: the same sign fore and aft,
    # magnitude close to the crab angle (~3.9 deg * cos(lat)); Table 1 magnitudes are 2.7-2.8 deg.
    fore, aft = d[:4], d[5:]
    assert np.all(np.sign(fore) == np.sign(aft[0]))
    assert np.all((np.abs(d[[0, 8]]) > 1.5) & (np.abs(d[[0, 8]]) < 4.0))
    assert d[CAMERAS.index("An")] == 0.0


def test_nominal_ifov_matches_seed_ground_sampling(nominal_camera):
    # 21 um / 58.9 mm * 705 km ~ 250 m at nadir for An (seed: 250 m)
    an = CAMERAS.index("An")
    ifov = nominal_camera.ifov_cross_rad(an, 2, 751.5)
    assert ifov * 705e3 == pytest.approx(250.0, rel=0.02)
    assert nominal_camera.focal_length[an, 0] == FOCAL_LENGTH_M["An"]
    np.testing.assert_allclose(nominal_camera.alpha[..., 1] * nominal_camera.focal_length, PITCH_CROSS_M)


def test_boresight_directions(nominal_camera):
    an = CAMERAS.index("An")
    red = BANDS.index("red")
    d = nominal_camera.direction_scs(an, red, 0.0, 751.5)
    # nadir within omega (0.08 deg) and the red band's -0.05 deg along-track offset
    assert np.degrees(np.arccos(d[2])) < 0.15
    df = nominal_camera.direction_scs(0, red, 0.0, 751.5)
    assert df[0] > 0.8  # Df looks forward


def test_focal_plane_inverse(nominal_camera, rng):
    m = nominal_camera.copy()
    m.alpha[..., 3] = 1e-12
    s = rng.uniform(0, 1503, 50)
    c = rng.integers(0, 9, 50)
    b = rng.integers(0, 4, 50)
    y = m.focal_plane_y(c, b, s)
    np.testing.assert_allclose(m.sample_from_focal_plane_y(c, b, y), s, atol=1e-9)
    h = 1e-4
    num = (m.focal_plane_y(c, b, s + h) - m.focal_plane_y(c, b, s - h)) / (2 * h)
    np.testing.assert_allclose(m.focal_plane_dy_ds(c, b, s), num, rtol=1e-7)


def test_save_load_round_trip(nominal_camera, tmp_path):
    path = tmp_path / "cgm.h5"
    nominal_camera.save(path)
    back = CameraModel.load(path)
    for name in CameraModel._SHAPES:
        np.testing.assert_array_equal(getattr(back, name), getattr(nominal_camera, name))
    assert back.provenance["source"] == "misrgraph.nominal.derive_camera_model"
    assert back.line_time == nominal_camera.line_time


def test_bad_shape_rejected(nominal_camera):
    with pytest.raises(InputError, match="CameraModel.delta"):
        CameraModel(**{**{n: getattr(nominal_camera, n) for n in CameraModel._SHAPES}, "delta": np.zeros(8)})


def test_missing_field_and_wrong_kind(nominal_camera, tmp_path):
    path = tmp_path / "cgm.h5"
    nominal_camera.save(path)
    with h5py.File(path, "a") as f:
        del f["camera_model/beta"]
    with pytest.raises(FileFormatError, match="camera_model/beta"):
        CameraModel.load(path)
    with h5py.File(path, "a") as f:
        f.attrs["misrgraph_kind"] = "dem"
    with pytest.raises(FileFormatError, match="misrgraph_kind"):
        CameraModel.load(path)
    with pytest.raises(FileFormatError, match="does not exist"):
        CameraModel.load(tmp_path / "nope.h5")


def test_tabulated_model_interpolates_linearly_and_round_trips(nominal_camera, tmp_path):
    from misrgraph.camera import TabulatedCameraModel

    cold, warm = nominal_camera.copy(), nominal_camera.copy()
    cold.temperature_c, warm.temperature_c = -5.0, 15.0
    warm.focal_length += 20e-6
    warm.beta += 1e-5
    table = TabulatedCameraModel([warm, cold])  # any order
    mid = table.at_temperature(0.0)  # a quarter of the way from -5 to 15
    np.testing.assert_allclose(mid.focal_length, cold.focal_length + 5e-6, atol=1e-15)
    np.testing.assert_allclose(mid.beta, cold.beta + 2.5e-6, atol=1e-15)
    np.testing.assert_allclose(table.at_temperature(40.0).beta, warm.beta)  # clamped
    table.save(tmp_path / "t.h5")
    back = TabulatedCameraModel.load_any(tmp_path / "t.h5")
    np.testing.assert_allclose(back.at_temperature(0.0).beta, mid.beta)
    assert isinstance(TabulatedCameraModel.load_any(tmp_path / "t.h5"), TabulatedCameraModel)
    with pytest.raises(InputError, match="temperature table"):
        TabulatedCameraModel([cold])
