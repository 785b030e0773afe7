"""Rendered imagery: the footprint mean against brute-force sampling, and the window convention
(pixel (r, q) is image line line0 + r, sample sample0 + q) against the geometry's own projection."""

from __future__ import annotations

import numpy as np

from misrgraph.io.imagery import read_imagery
from misrgraph.match.lsm import lsm
from misrgraph.sim.imagery import SceneRadiance, render_chip, render_window
from misrgraph.sim.simulate import load_scenario
from misrgraph.sim.terrain import SyntheticTerrain


def _flat(lat, lon):
    return np.zeros(np.shape(lat))


def test_footprint_mean_matches_brute_force_sampling():
    """The analytic footprint mean (a sinc per wave) against the mean over a 24 x 24 x 24 grid of
    points in the footprint, on flat ground (shading 1) with no BRDF."""
    scene = SceneRadiance(5, _flat, brdf_strength=0.0)
    from misrgraph.model.frames import geodetic_to_ecef

    g = geodetic_to_ecef(np.array([40.0, 40.01]), np.array([-100.0, -99.98]), np.zeros(2))
    east = np.array([[-np.sin(np.radians(-100.0)), np.cos(np.radians(-100.0)), 0.0]] * 2) * 275.0
    d_line = np.cross(g / np.linalg.norm(g, axis=1, keepdims=True), east)  # 275 m to the north
    rate = 0.4
    analytic = scene.ground_reflectance(g, d_line, east, rate)
    s = (np.arange(24) + 0.5) / 24 - 0.5
    u, v, w = np.meshgrid(s, s / rate, s, indexing="ij")
    a, w = (u + v).ravel(), w.ravel()
    pts = g[:, None, :] + a[None, :, None] * d_line[:, None, :] + w[None, :, None] * east[:, None, :]
    brute = scene.ground_reflectance(pts).mean(axis=1)
    np.testing.assert_allclose(analytic, brute, rtol=2e-3)


def test_each_band_has_its_own_reflectance():
    """Water has each band's own level exactly; on land the bands share the texture but NIR follows
    vegetation the other way: related patterns (correlated, so a band can be matched) that are
    not scaled copies of red's."""
    from misrgraph.model.frames import geodetic_to_ecef
    from misrgraph.sim.imagery import LAND_REFLECTANCE, WATER_REFLECTANCE
    from misrgraph.sim.terrain import land_mask

    scene = SceneRadiance(5, _flat, brdf_strength=0.0)
    ocean = geodetic_to_ecef(np.array([0.0]), np.array([-140.0]), np.zeros(1))  # mid-Pacific
    assert not land_mask(np.array([0.0]), np.array([-140.0]))[0]
    np.testing.assert_allclose([scene.ground_reflectance(ocean, band=b)[0] for b in range(4)], WATER_REFLECTANCE)
    lat, lon = np.meshgrid(40.0 + np.arange(60) * 0.002, -100.0 + np.arange(60) * 0.0025, indexing="ij")
    land = geodetic_to_ecef(lat.ravel(), lon.ravel(), np.zeros(lat.size))  # ~13 x 13 km of Kansas
    refl = np.array([scene.ground_reflectance(land, band=b) for b in range(4)])
    level = refl.mean(axis=1) / np.asarray(LAND_REFLECTANCE)
    # the same texture, each band's own level: NIR's 0.25 vegetation response averages to < 0.05 over 13 km
    np.testing.assert_allclose(level, level[2], rtol=0.05)
    rho = np.corrcoef(refl)
    assert 0.5 < rho[2, 3] < 0.97, rho[2, 3]  # NIR against red
    assert rho[2, 3] < rho[2, 1], rho  # green stays closer to red than NIR does
    # red is the texture alone: unchanged by the other bands' vegetation response
    np.testing.assert_array_equal(refl[2], scene.ground_reflectance(land))


def test_window_pixels_sit_at_the_geometry_s_image_coordinates(imagery_pass_dir):
    """A chip rendered through the true geometry centred on a GCP's true continuous position, matched
    by LSM in the GCP's window (rendered independently, with noise), lands at that position
    (line - line0, sample - sample0) to a few hundredths of a pixel in every camera."""
    sc = load_scenario(imagery_pass_dir)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    im = read_imagery(sc.pass_files[0])
    geo = tp.geometry(p)
    terrain = SyntheticTerrain(seed=3)
    scene = SceneRadiance(3, terrain.height)
    from misrgraph.model.constants import CAMERAS, VIEW_ANGLE_DEG

    errs = []
    for k in range(len(im.gcp)):
        row, cam = int(im.gcp.landmark[k]), int(im.gcp.camera[k])
        ip = geo.ground_to_pixel(cam, 2, tp.landmark_ecef[row][None], continuous=True)
        chip = render_chip(
            geo,
            scene.for_view(VIEW_ANGLE_DEG[CAMERAS[cam]]),
            cam,
            2,
            float(ip.line[0]),
            float(ip.sample[0]),
            32,
            terrain.height,
            gain=1.0,
            offset_dn=0.0,
        )
        r0, c0 = ip.line[0] - im.gcp.line0[k], ip.sample[0] - im.gcp.sample0[k]
        res = lsm(im.gcp.pixels[k].astype(float), chip, float(r0), float(c0))
        assert res.converged, res.reason
        errs.append(np.hypot(res.row - r0, res.col - c0))
    # a convention slip (half a pixel, a swapped axis) shows as >= 0.5 px; noise (SNR 200) leaves ~0.03
    assert len(errs) >= 9 and np.sqrt(np.mean(np.square(errs))) < 0.05 and np.max(errs) < 0.15


def test_render_window_is_deterministic_and_14_bit(imagery_pass_dir):
    sc = load_scenario(imagery_pass_dir)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    geo = tp.geometry(p)
    terrain = SyntheticTerrain(seed=3)
    scene = SceneRadiance(3, terrain.height)
    a = render_window(geo, scene, 4, 2, 5000, 700, 16, terrain.height, np.random.default_rng(0))
    b = render_window(geo, scene, 4, 2, 5000, 700, 16, terrain.height, np.random.default_rng(0))
    assert a.dtype == np.uint16 and a.max() <= 2**14 - 1 and np.array_equal(a, b) and a.std() > 50


def test_windows_cast_together_equal_windows_cast_alone(imagery_pass_dir):
    """render_windows (the rays of several windows cast side by side) against render_window one
    window at a time, same generator: the same counts bit for bit, for a fore, the nadir and an aft
    camera (the aft ones sweep backward), under clouds, and whatever the batch size."""
    from misrgraph.sim.imagery import render_windows

    sc = load_scenario(imagery_pass_dir)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    geo = tp.geometry(p)
    terrain = SyntheticTerrain(seed=3)
    scene = SceneRadiance(3, terrain.height, cloud_fraction=0.3)
    line0, sample0 = np.array([5000, 5013, 4980]), np.array([700, 120, 1400])
    for cam in (0, 4, 8):
        alone = np.stack(
            [
                render_window(geo, scene, cam, 2, int(a), int(b), 24, terrain.height, rng)
                for rng in [np.random.default_rng(5)]
                for a, b in zip(line0, sample0)
            ]
        )
        for batch in (2, 64):
            together = render_windows(
                geo, scene, cam, 2, line0, sample0, 24, terrain.height, np.random.default_rng(5), batch=batch
            )
            assert together.shape == (3, 24, 24) and together.dtype == np.uint16
            assert np.array_equal(together, alone), (cam, batch, np.abs(together.astype(int) - alone).max())


def test_strip_equals_the_window_renderer(imagery_pass_dir):
    """A whole-line strip (rays per line, secant casting from the previous line) against the window
    renderer (per-pixel navigation, bracketed casting) on the same pixels, noise-free: the same
    counts wherever the two casts find the same ground point. Where a ray crosses the terrain
    more than once (a D camera over a slope facing away, a coastal cliff) the two may pick
    different crossings: at most 2 % of the pixels (measured 0.9 % in Da)."""
    from misrgraph.sim.imagery import _counts, _rate, _render, render_strip

    sc = load_scenario(imagery_pass_dir)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    geo = tp.geometry(p)
    terrain = SyntheticTerrain(seed=3)
    scene = SceneRadiance(3, terrain.height, cloud_fraction=0.3)
    for cam, view in ((4, 0.0), (8, -70.5)):
        sv = scene.for_view(view)
        strip = render_strip(
            geo, sv, cam, 2, 5000, 40, 600, 96, terrain.height, np.random.default_rng(0), snr=1e12, chunk=16
        )
        lines, samples = 5000 + np.arange(40.0), 600 + np.arange(96.0)
        rate = _rate(geo, cam, 2, 5008.0, 648.0, terrain.height)  # the strip's first chunk's centre
        ref = _counts(_render(geo, sv, cam, 2, lines, samples, terrain.height, rate), np.random.default_rng(0), 1e12)
        diff = np.abs(strip.astype(float) - ref)
        assert strip.shape == (40, 96) and strip.std() > 50
        # the along-track extent is taken per 16-line chunk, not per window: a few counts at most
        assert np.median(diff) <= 1 and np.mean(diff > 8) < 0.02, (cam, np.median(diff), np.mean(diff > 8))


def test_pixels_show_the_first_ground_their_rays_meet(imagery_pass_dir):
    """A 2 km ridge across the track (Gaussian, 1.5 km wide: back slopes to 39 deg, steeper than
    the C and D cameras' rays) in the middle of the pass. The windows' rows, cast in each camera's
    sweep direction, land where a march down every ray from 4 km above the ground first meets
    the ridge (:func:`cast_first`, from an end point below all terrain), in every camera; the
    bracketed search alone lands on hidden ground for some of the aft cameras' pixels (what
    the renderer showed before)."""
    from misrgraph.model.constants import CAMERAS
    from misrgraph.model.frames import geodetic_to_ecef
    from misrgraph.model.geolocation import cast_first, ray_ellipsoid
    from misrgraph.sim.imagery import _cast_grid

    sc = load_scenario(imagery_pass_dir)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    geo = tp.geometry(p)
    mid = 0.5 * float(geo.lines_in_pass(4, 2))  # An's middle line: every camera sees the ridge
    g0 = geo.pixel_to_ground(np.array([4]), np.array([2]), np.array([mid]), np.array([750.0]), height=0.0)[0]
    nadir_next = geo.pixel_to_ground(
        np.array([4]), np.array([2]), np.array([mid + 100]), np.array([750.0]), height=0.0
    )[0]
    along = (nadir_next - g0) / np.linalg.norm(nadir_next - g0)

    def ridge(lat, lon):
        q = geodetic_to_ecef(np.ravel(lat), np.ravel(lon), np.zeros(np.size(lat)))
        return (2000.0 * np.exp(-0.5 * (((q - g0) @ along) / 1500.0) ** 2)).reshape(np.shape(lat))

    crest = g0 + 2000.0 * g0 / np.linalg.norm(g0)
    hidden_by_bracketing = {}
    for cam, name in enumerate(CAMERAS):
        ip = geo.ground_to_pixel(cam, 2, crest[None], continuous=True)
        assert ip.visible[0], name
        ll, ss = np.meshgrid(ip.line[0] + np.arange(-50.0, 50.0), ip.sample[0] + np.arange(-8.0, 8.0), indexing="ij")
        got = _cast_grid(geo, cam, 2, ll, ss, ridge).reshape(-1, 3)
        o, d = geo.pixel_rays(
            np.full(ll.size, cam), np.full(ll.size, 2), ll.ravel(), ss.ravel(), np.full(ll.size, np.nan)
        )
        first = cast_first(o, d, ridge, ray_ellipsoid(o, d, np.full(ll.size, -100.0)), climb_m=4000.0)
        assert np.all(np.linalg.norm(got - first, axis=1) < 1.0), name
        any_root = geo.pixel_to_ground(
            np.full(ll.size, cam),
            np.full(ll.size, 2),
            ll.ravel(),
            ss.ravel(),
            surface=ridge,
            exposure=np.full(ll.size, np.nan),
            tol_m=0.05,
        )
        hidden_by_bracketing[name] = int(np.sum(np.linalg.norm(any_root - first, axis=1) > 1.0))
    assert hidden_by_bracketing["Da"] > 0 or hidden_by_bracketing["Ca"] > 0, hidden_by_bracketing


def test_cast_from_a_poor_guess_agrees_with_the_bracketed_cast(imagery_pass_dir):
    """Secant casting from guesses 300 m off (and NaN guesses, cast by the bracketed search) lands
    on the bracketed search's ground points to the tolerance."""
    from misrgraph.model.geolocation import cast_from

    sc = load_scenario(imagery_pass_dir)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    geo = tp.geometry(p)
    terrain = SyntheticTerrain(seed=3)
    s = np.linspace(0, 1503, 64)
    origin, direction = geo.line_rays(1, 2, np.array([6000.0]), s)
    o, d = np.repeat(origin, s.size, 0), direction[0]
    ref = geo.pixel_to_ground(
        np.full(s.size, 1),
        np.full(s.size, 2),
        np.full(s.size, 6000.0),
        s,
        surface=terrain.height,
        exposure=np.full(s.size, 6000.0),
        tol_m=1e-3,
    )
    lam = np.einsum("ni,ni->n", ref - o, d)
    guess = lam + np.where(np.arange(s.size) % 2, 300.0, -300.0)
    guess[::7] = np.nan
    got = cast_from(o, d, guess, terrain.height, tol_m=1e-3)
    assert np.max(np.linalg.norm(got - ref, axis=1)) < 0.05
