"""Matching pipeline bookkeeping that needs no imagery."""

from __future__ import annotations

import numpy as np

from misrgraph.match.pipeline import AN, MatchConfig, MatchedObservations, TieFeature, _drop_inconsistent
from misrgraph.match.precision import PrecisionFit
from misrgraph.model.constants import BANDS

RED = BANDS.index("red")


def test_inconsistent_conjugates_are_dropped_and_features_renumbered():
    """Feature 0 loses one of four conjugates (kept); feature 1 loses one of two and falls below
    3 cameras (dropped whole); feature 2 is untouched and becomes feature 1."""
    out = MatchedObservations(candidates=9)
    rows = []
    for f, cams in enumerate(([0, 1, 2, 3], [0, 1], [5, 6, 7])):
        out.add(f, AN, 100.0 * f, 50.0, 0.05, RED)
        for c in cams:
            out.add(f, c, 100.0 * f + c, 50.0 + c, 0.1, RED)
            rows.append(len(out) - 1)
    out.pending_rows = np.array(rows)
    bad = np.zeros(len(rows), bool)
    bad[[1, 4]] = True  # feature 0 camera 1; feature 1 camera 0
    out.precision = PrecisionFit(outlier=bad)
    feats = [TieFeature(10 + f, 100.0 * f, 50.0) for f in range(3)]
    kept_f, kept = _drop_inconsistent(feats, out, MatchConfig(min_cameras=3))
    assert [f.window_row for f in kept_f] == [10, 12]
    assert kept.reasons["inconsistent with the pass (redundancy check)"] == 2
    assert kept.reasons["seen in fewer than 3 cameras"] == 1
    pairs = sorted(zip(kept.feature, kept.camera))
    assert pairs == sorted([(0, AN), (0, 0), (0, 2), (0, 3), (1, AN), (1, 5), (1, 6), (1, 7)])
    # positions travel with their observations
    i = [k for k, (f, c) in enumerate(zip(kept.feature, kept.camera)) if (f, c) == (1, 6)][0]
    assert kept.line[i] == 206.0 and kept.sample[i] == 56.0 and kept.band[i] == RED


def test_conjugates_hidden_by_a_ridge_are_predicted_from_the_dem(imagery_pass_dir):
    """A 2 km ridge across the track (Gaussian, 1.5 km wide). Ground points on a line along the
    track through its crest: the matcher's prediction (the supplied ray into the camera, searched
    for the DEM in front of the point) against the along-track profile in closed form -- a point
    at ``s`` is hidden where ``h(s') > h(s) + |s' - s| tan(e)`` for some ``s'`` between it and the
    camera, with ``e`` the ray's elevation in the along-track plane. They agree except within
    150 m of the shadow's ends; Da has a shadow, An none."""
    from misrgraph.match.pipeline import _hidden_by_terrain
    from misrgraph.model.constants import CAMERAS
    from misrgraph.sim.simulate import load_scenario

    sc = load_scenario(imagery_pass_dir)
    geo = sc.load_truth(0).geometry(sc.load_pass(0))
    mid = 0.5 * float(geo.lines_in_pass(AN, 2))
    g0 = geo.pixel_to_ground(np.array([AN]), np.array([2]), np.array([mid]), np.array([750.0]), height=0.0)[0]
    g1 = geo.pixel_to_ground(np.array([AN]), np.array([2]), np.array([mid + 100]), np.array([750.0]), height=0.0)[0]
    up = g0 / np.linalg.norm(g0)
    along = g1 - g0 - ((g1 - g0) @ up) * up
    along /= np.linalg.norm(along)
    profile = lambda s: 2000.0 * np.exp(-0.5 * (np.asarray(s) / 1500.0) ** 2)  # noqa: E731

    def ridge(lat, lon):
        from misrgraph.model.frames import geodetic_to_ecef

        q = geodetic_to_ecef(np.ravel(lat), np.ravel(lon), np.zeros(np.size(lat)))
        return profile((q - g0) @ along).reshape(np.shape(lat))

    s_pts = np.arange(-10000.0, 10001.0, 200.0)
    shadows = {}
    for name in ("Da", "An"):
        cam = CAMERAS.index(name)
        got, expect, near_edge = [], [], []
        for s in s_pts:
            ground = g0 + s * along + profile(s) * up
            pred = geo.ground_to_pixel(np.array([cam]), 2, ground[None], continuous=True)
            got.append(bool(_hidden_by_terrain(geo, np.array([cam]), 2, pred, ground, ridge)[0]))
            o, d = geo.pixel_rays(np.array([cam]), np.array([2]), pred.line, pred.sample, np.full(1, np.nan))
            to_cam = -d[0]
            tan_e = (to_cam @ up) / abs(to_cam @ along)
            side = np.sign(to_cam @ along)
            s_between = s + side * np.arange(1.0, 20000.0, 10.0)
            clearance = profile(s) + np.abs(s_between - s) * tan_e - profile(s_between)
            expect.append(bool(np.any(clearance < 0)))
            near_edge.append(bool(np.min(np.abs(clearance)) < 150.0 * tan_e))
        got, expect, near_edge = map(np.array, (got, expect, near_edge))
        assert np.all((got == expect) | near_edge), (name, s_pts[(got != expect) & ~near_edge])
        shadows[name] = int(expect.sum())
    assert shadows["Da"] >= 10 and shadows["An"] == 0, shadows


def test_pointing_sensitivities_against_the_projection_parameters_derivatives(small_pass):
    """The precision fit's ``J_c`` (a tilted navigation's prediction of a fixed ground point) equals
    the attitude derivatives the Projection Parameters take independently, by central differences
    through their own ground-to-image crossing (``products.pp.image_derivatives``), within 2 % of
    each camera's largest term; and ``K_c`` for An's own prediction is ``-J_An`` (every point of
    the tilted ray through An's pixel is seen by the untilted navigation ``J_An`` away, whatever
    surface the ray is cast onto), to first order."""
    from misrgraph.match.pipeline import _pointing_sensitivity
    from misrgraph.model.constants import CAMERAS
    from misrgraph.model.frames import ecef_to_geodetic
    from misrgraph.products.pp import image_derivatives

    sc, p = small_pass
    geo = p.geometry(sc.camera_model)
    truth = sc.load_truth(0).landmark_ecef[:6]
    band = 2
    h = ecef_to_geodetic(truth)[2]
    for name in ("Df", "Bf", "An", "Ca", "Da"):
        c = CAMERAS.index(name)
        cams = np.full(truth.shape[0], c)
        pred = geo.ground_to_pixel(cams, band, truth, continuous=True)
        an = geo.ground_to_pixel(np.full(truth.shape[0], AN), band, truth, continuous=True)
        ok = pred.visible & an.visible
        assert ok.sum() >= 3, name
        rows = np.flatnonzero(ok)
        level = float(h[rows].mean())
        surface = lambda lat, lon: np.full(np.shape(lat), level)  # noqa: E731 -- K_An = -J_An on any surface
        jac, kan = _pointing_sensitivity(
            geo,
            cams[rows],
            band,
            truth[rows],
            pred.line[rows],
            pred.sample[rows],
            an.line[rows],
            an.sample[rows],
            np.arange(rows.size),
            surface,
        )
        t = geo.line_time(cams[rows], band, pred.line[rows], pred.line[rows])
        want = image_derivatives(geo, c, band, truth[rows], t)[:, :, :3]
        scale = np.abs(want).max(axis=(1, 2), keepdims=True)
        np.testing.assert_allclose(jac / scale, want / scale, atol=0.02, err_msg=name)
        if name == "An":
            np.testing.assert_allclose(kan / scale, -jac / scale, atol=0.02)


def test_gcp_fit_rows_against_the_projection_parameters_derivatives(small_pass):
    """The GCP rows of the precision fit: ``d`` is matched minus the catalogue point's prediction
    (observations placed at known offsets from it), ``J_c`` equals the Projection Parameters'
    attitude derivatives and ``G``'s east and north columns their ground derivatives, both by
    central differences through the PP's own ground-to-image crossing, within 2 % of each camera's
    largest term; the up column matches a central difference through the same crossing. Only the
    band asked for is taken."""
    from misrgraph.match.pipeline import gcp_fit_rows
    from misrgraph.model.constants import CAMERAS
    from misrgraph.model.frames import ecef_to_geodetic, enu_basis
    from misrgraph.products.pp import crossing, ground_derivatives, image_derivatives

    sc, p = small_pass
    geo = p.geometry(sc.camera_model)
    catalogue = sc.load_truth(0).landmark_ecef[:6]
    offset = np.array([0.3, -0.2])
    for name in ("Df", "An", "Ca"):
        c = CAMERAS.index(name)
        pred = geo.ground_to_pixel(np.full(6, c), RED, catalogue, continuous=True)
        rows = np.flatnonzero(pred.visible)
        assert rows.size >= 3, name
        obs = MatchedObservations()
        for r in rows:
            obs.add(int(r), c, pred.line[r] + offset[0], pred.sample[r] + offset[1], 0.05, RED)
        obs.add(int(rows[0]), c, pred.line[rows[0]], pred.sample[rows[0]], 0.05, BANDS.index("nir"))  # another band
        g = gcp_fit_rows(obs, geo, catalogue, lambda row: row, RED)
        assert g.time_s.size == rows.size and g.defining_camera == AN and np.all(g.camera == c)
        np.testing.assert_allclose(g.d, np.tile(offset, (rows.size, 1)), atol=1e-6)
        ground = catalogue[rows]
        t = geo.line_time(g.camera, RED, pred.line[rows], pred.line[rows])
        want_j = image_derivatives(geo, c, RED, ground, t)[:, :, :3]
        scale_j = np.abs(want_j).max(axis=(1, 2), keepdims=True)
        np.testing.assert_allclose(g.camera_px_per_rad / scale_j, want_j / scale_j, atol=0.02, err_msg=name)
        lat, lon, _ = ecef_to_geodetic(ground)
        enu = enu_basis(lat, lon).reshape(-1, 3, 3)
        want_g = ground_derivatives(geo, c, RED, ground, enu, t)
        up = [np.stack(crossing(geo, c, RED, ground + s * 10.0 * enu[:, :, 2], t)[1:], -1) for s in (1.0, -1.0)]
        want_g = np.concatenate([want_g, ((up[0] - up[1]) / 20.0)[:, :, None]], axis=2)
        scale_g = np.abs(want_g).max(axis=(1, 2), keepdims=True)
        np.testing.assert_allclose(g.ground_px_per_m / scale_g, want_g / scale_g, atol=0.02, err_msg=name)
