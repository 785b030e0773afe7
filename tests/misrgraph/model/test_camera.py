from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.camera import read_camera_file, save_camera_model
from misrgraph.io.h5 import reseal
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import BANDS, CAMERAS, FOCAL_LENGTH_M, PITCH_CROSS_M, SAMPLE_DIRECTION
from misrgraph.model.nominal import nominal_camera_model, preflight_camera_model


def test_nominal_beta_matches_table1_df(nominal_camera):
    # Table 1 pre-flight Df beta = 58.1266 deg; derived from the 70.5 deg view angle at the surface
    assert np.degrees(nominal_camera.beta[CAMERAS.index("Df")]) == pytest.approx(58.1266, abs=0.05)
    assert np.degrees(nominal_camera.beta[CAMERAS.index("Da")]) == pytest.approx(-57.9879, abs=0.5)
    assert nominal_camera.beta[CAMERAS.index("An")] == 0.0


def test_nominal_delta_compensates_earth_rotation_by_roll(nominal_camera):
    # T_ic = Ry(beta) Rx(delta): on a descending pass the ground track drifts west (right of the
    # flight direction), so fore cameras roll right (delta < 0) and aft cameras left (delta > 0),
    # as Table 1's Df -2.8030 / Da +2.7314 deg. The derivation makes the compensation exact at
    # 30 deg latitude; the derived delta moves by ~0.27 deg per 5 deg of latitude there, so 0.15 deg
    # allows a ~3 deg difference between our idealised orbit/optics and MISR's.
    d = np.degrees(nominal_camera.delta)
    assert np.all(d[:4] < 0) and np.all(d[5:] > 0)
    assert d[CAMERAS.index("An")] == 0.0
    assert d[CAMERAS.index("Df")] == pytest.approx(-2.8030, abs=0.15)
    assert d[CAMERAS.index("Da")] == pytest.approx(2.7314, abs=0.15)
    # magnitude grows with the view angle on each side
    assert np.all(np.diff(np.abs(d[:5])) < 0) and np.all(np.diff(np.abs(d[4:])) > 0)


def test_boresight_cross_track_component_is_minus_sin_delta(rng):
    # closed form of Ry(beta) Rx(delta) [0, 0, 1] = [sin b cos d, -sin d, cos b cos d] for any beta
    m = nominal_camera_model().copy()
    m.omega[:] = 0.0
    m.epsilon[:] = 0.0
    m.delta[:] = np.radians(rng.uniform(-4, 4, 9))
    m.beta[:] = np.radians(rng.uniform(-70, 70, 9))
    rays = m.detector_to_spacecraft(np.arange(9)) @ np.array([0.0, 0.0, 1.0])
    want = np.stack([np.sin(m.beta) * np.cos(m.delta), -np.sin(m.delta), np.cos(m.beta) * np.cos(m.delta)], axis=-1)
    np.testing.assert_allclose(rays, want, atol=1e-15)


def test_preflight_model_holds_table1_as_printed():
    from misrgraph.io.camera import load_camera_model
    from misrgraph.model.nominal import TABLE1

    m = load_camera_model("preflight")
    red = BANDS.index("red")
    for cam, row in TABLE1.items():
        c = CAMERAS.index(cam)
        assert np.degrees(m.delta[c]) == pytest.approx(row["delta_deg"], abs=1e-12)
        assert np.degrees(m.beta[c]) == pytest.approx(row["beta_deg"], abs=1e-12)
        assert np.degrees(m.epsilon[c]) == pytest.approx(row["epsilon_deg"], abs=1e-12)
        assert m.focal_length[c, red] * 1e3 == pytest.approx(row["f_mm"], rel=1e-12)
        assert np.degrees(np.arctan(m.k[c, red] / m.focal_length[c, red])) == pytest.approx(row["k_deg"], abs=1e-12)
        # alpha_0 (tan of the first pixel's field angle) is where the boresight sample lies; the
        # first pixel is on -y in An and the fore cameras, on +y in the aft ones
        side = -SAMPLE_DIRECTION[cam]
        assert side * m.focal_plane_y(c, red, 0.0) / m.focal_length[c, red] == pytest.approx(row["alpha0"], rel=1e-12)
    np.testing.assert_allclose(np.degrees(m.omega), [-0.0658333, -0.041111, 0.006666])
    # the other cameras follow the table's sides: fore delta < 0, aft > 0, |delta| rising with view angle
    d = np.degrees(m.delta)
    assert np.all(d[:4] < 0) and np.all(d[5:] > 0)
    assert np.all(np.diff(np.abs(d[:4])) < 0) and np.all(np.diff(np.abs(d[5:])) > 0)


def test_table1_tracks_meet_near_30_degrees_and_cross_over():
    # Acceptance of the convention: through the public geolocation API, Table 1's Df and Da see
    # An's boresight track within 5 km at 30 deg latitude; at the equator Earth rotation is
    # under-compensated and at 60 deg over-compensated, so each camera's miss changes sign, and
    # fore and aft lie on opposite sides at both.
    from misrgraph.model.nominal import compensation_miss_km

    miss = compensation_miss_km(preflight_camera_model(), [0.0, 30.0, 60.0])
    df, da = miss["Df"], miss["Da"]
    assert abs(df[1]) < 5.0 and abs(da[1]) < 5.0
    assert np.sign(df[0]) == -np.sign(da[0]) and np.sign(df[2]) == -np.sign(da[2])
    assert np.sign(df[0]) == -np.sign(df[2])
    assert min(abs(df[0]), abs(da[0]), abs(df[2]), abs(da[2])) > 5.0


def test_old_convention_files_are_refused(nominal_camera, tmp_path):
    path = tmp_path / "old.h5"
    save_camera_model(nominal_camera, path)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 1
    reseal(path)
    with pytest.raises(FileFormatError, match=r"format_version is 1.*Rz\(delta\) Ry\(beta\)"):
        read_camera_file(path)


def test_nominal_ifov_matches_seed_ground_sampling(nominal_camera):
    # 21 um / 58.9 mm * 705 km ~ 250 m at nadir for An (seed: 250 m)
    an = CAMERAS.index("An")
    ifov = nominal_camera.ifov_cross_rad(an, 2, 751.5)
    assert ifov * 705e3 == pytest.approx(250.0, rel=0.02)
    assert nominal_camera.focal_length[an, 0] == FOCAL_LENGTH_M["An"]
    # the pixel pitch, signed by the camera's sample direction (aft cameras' samples run the other way)
    direction = np.array([SAMPLE_DIRECTION[c] for c in CAMERAS])[:, None]
    np.testing.assert_allclose(
        nominal_camera.alpha[..., 1] * nominal_camera.focal_length, np.broadcast_to(direction * PITCH_CROSS_M, (9, 4))
    )
    assert list(direction[:, 0]) == [1, 1, 1, 1, 1, -1, -1, -1, -1]


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
    save_camera_model(nominal_camera, path)
    back = read_camera_file(path)
    for name in CameraModel._SHAPES:
        np.testing.assert_array_equal(getattr(back, name), getattr(nominal_camera, name))
    assert back.provenance["source"] == "misrgraph.model.nominal.derive_camera_model"
    assert back.line_time == nominal_camera.line_time


def test_bad_shape_rejected(nominal_camera):
    with pytest.raises(InputError, match="CameraModel.delta"):
        CameraModel(**{**{n: getattr(nominal_camera, n) for n in CameraModel._SHAPES}, "delta": np.zeros(8)})


def test_missing_field_and_wrong_kind(nominal_camera, tmp_path):
    path = tmp_path / "cgm.h5"
    save_camera_model(nominal_camera, path)
    from misrgraph.io.h5 import stamp_content_digest

    with h5py.File(path, "a") as f:
        del f["camera_model/beta"]
    with pytest.raises(FileFormatError, match="file checksum mismatch"):  # an edit is damage
        read_camera_file(path)
    reseal(path)
    with pytest.raises(FileFormatError, match="content digest mismatch"):  # ... at both levels
        read_camera_file(path)
    with h5py.File(path, "a") as f:
        stamp_content_digest(f)  # a well-formed file whose writer left a field out
    reseal(path)
    with pytest.raises(FileFormatError, match="camera_model/beta"):
        read_camera_file(path)
    with h5py.File(path, "a") as f:
        f.attrs["misrgraph_kind"] = "dem"
    reseal(path)
    with pytest.raises(FileFormatError, match="misrgraph_kind"):
        read_camera_file(path)
    with pytest.raises(FileFormatError, match="does not exist"):
        read_camera_file(tmp_path / "nope.h5")


def test_tabulated_model_interpolates_linearly_and_round_trips(nominal_camera, tmp_path):
    from misrgraph.model.camera import TabulatedCameraModel

    cold, warm = nominal_camera.copy(), nominal_camera.copy()
    cold.temperature_c, warm.temperature_c = -5.0, 15.0
    warm.focal_length += 20e-6
    warm.beta += 1e-5
    table = TabulatedCameraModel([warm, cold])  # any order
    mid = table.at_temperature(0.0)  # a quarter of the way from -5 to 15
    np.testing.assert_allclose(mid.focal_length, cold.focal_length + 5e-6, atol=1e-15)
    np.testing.assert_allclose(mid.beta, cold.beta + 2.5e-6, atol=1e-15)
    np.testing.assert_allclose(table.at_temperature(40.0).beta, warm.beta)  # clamped
    save_camera_model(table, tmp_path / "t.h5")
    back = read_camera_file(tmp_path / "t.h5")
    np.testing.assert_allclose(back.at_temperature(0.0).beta, mid.beta)
    assert isinstance(read_camera_file(tmp_path / "t.h5"), TabulatedCameraModel)
    with pytest.raises(InputError, match="temperature table"):
        TabulatedCameraModel([cold])


def test_linear_thermal_table_is_exact_and_extrapolates_within_its_range(nominal_camera):
    from misrgraph.model.camera import TabulatedCameraModel

    slopes = {"delta": np.linspace(-1e-5, 1e-5, 9), "beta": np.full(9, 2e-6), "focal_scale": np.full(9, 2e-5)}
    t = TabulatedCameraModel.linear(nominal_camera, slopes, (-10.0, 20.0))
    for temp in (-10.0, 3.7, 20.0):
        m = t.at_temperature(temp)
        dt = temp - nominal_camera.temperature_c
        np.testing.assert_allclose(m.delta - nominal_camera.delta, slopes["delta"] * dt, atol=1e-15)
        np.testing.assert_allclose(m.focal_length / nominal_camera.focal_length, 1 + 2e-5 * dt, rtol=1e-12)
        # the physical focal-plane polynomial f * alpha_i stays (to second order in the scale)
        np.testing.assert_allclose(
            m.focal_length * m.alpha[..., 1], nominal_camera.focal_length * nominal_camera.alpha[..., 1], rtol=1e-6
        )
    # a table with a wider valid range extends its end segments linearly, and clamps beyond
    ext = TabulatedCameraModel([t.at_temperature(0.0), t.at_temperature(10.0)], valid_range_c=(-5.0, 15.0))
    np.testing.assert_allclose(ext.at_temperature(-5.0).delta, t.at_temperature(-5.0).delta, atol=1e-15)
    np.testing.assert_allclose(ext.at_temperature(40.0).delta, t.at_temperature(15.0).delta, atol=1e-15)
    with pytest.raises(InputError, match="valid_range_c"):
        TabulatedCameraModel([t.at_temperature(0.0), t.at_temperature(10.0)], valid_range_c=(2.0, 15.0))
    with pytest.raises(InputError, match="slopes"):
        TabulatedCameraModel.linear(nominal_camera, {"gamma": np.zeros(9)}, (0.0, 1.0))


def test_thermal_table_round_trips_through_a_file(nominal_camera, tmp_path):
    from misrgraph.io.camera import load_camera_model
    from misrgraph.model.camera import TabulatedCameraModel

    warm = dataclasses.replace(nominal_camera.copy(), temperature_c=9.0)
    warm.delta += 4e-5  # the two entries differ, so a swapped or duplicated entry would show
    warm.focal_length *= 1.0001
    t = TabulatedCameraModel([nominal_camera.copy(), warm], valid_range_c=(0.0, 12.0))
    save_camera_model(t, tmp_path / "t.h5")
    back = load_camera_model(tmp_path / "t.h5")
    assert isinstance(back, TabulatedCameraModel) and back.valid_range_c == (0.0, 12.0)
    np.testing.assert_array_equal(back.temperatures_c, [5.0, 9.0])
    np.testing.assert_array_equal(back.models[1].delta, warm.delta)
    np.testing.assert_array_equal(back.models[0].delta, nominal_camera.delta)
    np.testing.assert_allclose(back.at_temperature(7.0).delta, nominal_camera.delta + 2e-5, rtol=0, atol=1e-15)


def test_band_offsets_act_on_their_band_only(nominal_camera, rng):
    """A band's offset equals the same change of the camera angle for that band, and leaves the
    other bands where they were."""
    m = nominal_camera.copy()
    off = np.radians(rng.uniform(-0.01, 0.01, 3))
    m.band_delta[0, 1], m.band_beta[0, 1], m.band_epsilon[0, 1] = off
    ref = nominal_camera.copy()
    ref.delta[0] += off[0]
    ref.beta[0] += off[1]
    ref.epsilon[0] += off[2]
    s = rng.uniform(0, 1503, 20)
    np.testing.assert_allclose(m.direction_scs(0, 1, 0.0, s), ref.direction_scs(0, 1, 0.0, s), atol=1e-15)
    for b in (0, 2, 3):
        np.testing.assert_array_equal(m.direction_scs(0, b, 0.0, s), nominal_camera.direction_scs(0, b, 0.0, s))


def test_corrections_add_and_remove(nominal_camera):
    """Camera-level corrections move the camera angle, per-band ones only that band's offset, and
    ``sign=-1`` undoes ``corrected`` exactly."""
    m = nominal_camera.corrected({0: [1e-5, -2e-5, 3e-5], 8: [4e-6, 0.0, 0.0]})
    np.testing.assert_allclose(m.delta[0] - nominal_camera.delta[0], 1e-5, rtol=1e-9)
    np.testing.assert_allclose(m.epsilon[0] - nominal_camera.epsilon[0], 3e-5, rtol=1e-9)
    back = m.corrected({0: [1e-5, -2e-5, 3e-5], 8: [4e-6, 0.0, 0.0]}, sign=-1.0)
    for name in ("delta", "beta", "epsilon"):
        np.testing.assert_allclose(getattr(back, name), getattr(nominal_camera, name), rtol=0, atol=1e-18)
    b = nominal_camera.copy()
    b.add_correction("beta", 2, 1, 7e-6)
    assert b.beta[2] == nominal_camera.beta[2] and b.band_beta[2, 1] - nominal_camera.band_beta[2, 1] == pytest.approx(
        7e-6
    )
    b.add_correction("alpha3", 2, None, 1e-12)
    np.testing.assert_allclose(b.alpha[2, :, 3] - nominal_camera.alpha[2, :, 3], 1e-12, rtol=1e-6)
    with pytest.raises(InputError, match="alpha0..alpha5"):
        b.add_correction("alpha9", 0, None, 1.0)
