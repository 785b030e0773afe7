"""The pass graph's observation weights (``misrgraph.estimate.graph``)."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.estimate.adjust import AdjustConfig
from misrgraph.estimate.graph import GraphConfig, build_pass_graph
from misrgraph.model.constants import ARCSEC, CAMERAS
from misrgraph.model.errormodels import ATTITUDE_RATE_FACTOR, unresolved_attitude, unresolved_process_sigma


def test_observation_sigma_carries_the_unresolved_jitter_through_the_pointing_sensitivity(small_pass):
    """The default graph weights each observation by the matcher's sigma and the jitter the knots
    cannot follow: per camera, the added line and sample variance equals
    ``sigma_u^2 |d(line, sample) / d(roll, pitch, yaw)|^2`` with the derivatives taken
    independently, by central differences through the Projection Parameters' ground-to-image
    crossing (``products.pp.image_derivatives``), within 3 %; the D cameras' lines feel it most.
    Without the jitter (or with ``jitter_in_weights=False``) the weights are the matcher's sigma."""
    from misrgraph.products.pp import image_derivatives

    sc, p = small_pass
    cfg0 = AdjustConfig().graph_config()
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, cfg0)
    sigma_u = cfg0.unresolved_attitude_rad(pg.attitude_model.knot_times)
    # the jitter's share (0.86 of its 1 arcsec on 60 s knots) and the slow process's between the
    # knots, in quadrature
    jitter_u = unresolved_attitude(pg.attitude_model.knot_times, 1.0)
    assert 0.8 * ARCSEC < jitter_u < 0.95 * ARCSEC
    process_u = [
        unresolved_process_sigma(kt, s * ARCSEC, ATTITUDE_RATE_FACTOR, cfg0.knot_prior_damping)
        for kt, s in zip(pg.attitude_model.knot_times, cfg0.attitude_sigma_arcsec)
    ]
    assert sigma_u == pytest.approx(np.sqrt(jitter_u**2 + np.mean(np.square(process_u))), rel=1e-9)
    rows = pg.obs_index[pg.collinearity.order]
    o = p.observations
    extra = pg.collinearity.sigma_px**2 - o.sigma_px[rows, None] ** 2
    geo = p.geometry(sc.camera_model)
    t = p.observation_times()
    truth = sc.load_truth(0).landmark_ecef
    line_extra = {}
    for c in range(len(CAMERAS)):
        m = np.flatnonzero(o.camera[rows] == c)[:60]
        if m.size == 0:
            continue
        r = rows[m]
        d = image_derivatives(geo, c, int(o.band[r[0]]), truth[o.landmark[r]], t[r])[:, :, :3]
        want = sigma_u**2 * np.sum(d**2, axis=2)
        np.testing.assert_allclose(extra[m].mean(axis=0), want.mean(axis=0), rtol=0.03)
        line_extra[CAMERAS[c]] = float(np.sqrt(want[:, 0].mean()))
    assert line_extra["Df"] > 4 * line_extra["An"] and line_extra["Da"] > 4 * line_extra["An"]
    for cfg in (AdjustConfig(jitter_in_weights=False).graph_config(), GraphConfig()):
        plain = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, cfg)
        np.testing.assert_array_equal(plain.collinearity.sigma_px, np.stack([o.sigma_px[rows]] * 2, axis=1))
    with pytest.raises(InputError, match="attitude_jitter_periods_s"):
        GraphConfig(attitude_jitter_arcsec=1.0, attitude_jitter_periods_s=(120.0, 8.0))
