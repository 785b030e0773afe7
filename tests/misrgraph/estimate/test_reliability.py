"""Redundancy numbers, data snooping and variance components, against brute force, a 1.5 px
mismatch and a known error in the weights."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from misrgraph.estimate.graph import GraphConfig, build_pass_graph
from misrgraph.estimate.reliability import W_TEST_ALPHA, reliability
from misrgraph.estimate.solver import solve
from misrgraph.io.passes import KIND_TIE, Observations, OrbitPass


def _with(p: OrbitPass, obs: Observations) -> OrbitPass:
    return OrbitPass(
        p.pass_id, p.path, p.orbit, p.ephemeris, p.attitude, p.t0, p.line_time, p.landmarks, obs, p.temperature_c
    )


def _solve(sc, p, exclude):
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=True), exclude_observations=exclude)
    res = solve(pg.problem)
    flat = pg.problem.flat()
    return pg, flat, reliability(flat, flat.from_values(res.values))


@pytest.fixture(scope="module")
def clean(small_pass):
    sc, p = small_pass
    blunder = sc.load_truth(0).blunder
    return (sc, p, blunder) + _solve(sc, p, blunder)


def test_redundancy_sums_to_the_degrees_of_freedom_and_matches_brute_force(clean):
    *_, pg, flat, rel = clean
    assert rel.r.sum() == pytest.approx(flat.m - flat.n, rel=1e-9)
    assert np.all(rel.h > -1e-12) and np.all(rel.h < 1 + 1e-9)
    x = flat.from_values(solve(pg.problem).values)
    j = flat.jacobian(x).toarray()
    hi = np.linalg.inv(j.T @ j)
    rows = np.r_[0:8, flat.m_coll : flat.m_coll + 4, flat.m - 4 : flat.m]
    np.testing.assert_allclose(np.einsum("ri,ij,rj->r", j[rows], hi, j[rows]), rel.h[rows], atol=1e-8)
    np.testing.assert_allclose(j[0] @ hi @ j[1], -rel.R_obs[0, 0, 1], atol=1e-8)


def test_a_one_and_a_half_pixel_mismatch_is_found(clean):
    """Five tie-point observations shifted by 1.5 px (7.5 sigma at 0.2 px): each exceeds the
    critical value and they are the five largest statistics; among the other observations no more
    are flagged than the test's own false-alarm rate allows (Poisson 99.99 % bound)."""
    sc, p, blunder, pg, flat, rel = clean
    obs_of_row = pg.obs_index[pg.collinearity.order]
    kind = p.landmarks.kind[p.observations.landmark[obs_of_row]]
    r_obs = np.trace(rel.R_obs, axis1=1, axis2=2) / 2
    cand = np.flatnonzero((kind == KIND_TIE) & (r_obs > 0.6) & (p.observations.camera[obs_of_row] != 4))
    chosen, seen = [], set()
    for i in cand[::7]:
        lm = int(p.observations.landmark[obs_of_row[i]])
        if lm not in seen:
            chosen.append(int(obs_of_row[i]))
            seen.add(lm)
        if len(chosen) == 5:
            break
    o = p.observations
    line = o.line.copy()
    line[chosen] += 1.5
    shifted = _with(p, Observations(o.landmark, o.camera, o.band, line, o.sample, o.exposure, o.sigma_px))
    pg2, _, rel2 = _solve(sc, shifted, blunder)
    rows2 = pg2.obs_index[pg2.collinearity.order]
    crit = stats.chi2.isf(W_TEST_ALPHA, 2)
    t_of = dict(zip(rows2.tolist(), rel2.T))
    assert all(t_of[i] > crit for i in chosen), [t_of[i] for i in chosen]
    top5 = set(rows2[np.argsort(-rel2.T)[:5]].tolist())
    assert top5 == set(chosen)
    others = np.array([t for i, t in t_of.items() if i not in chosen])
    assert np.sum(others > crit) <= stats.poisson.ppf(0.9999, W_TEST_ALPHA * others.size)


def test_variance_component_recovers_a_wrong_weight(clean):
    """Telling the solver the image points are twice as precise as they are (sigma halved): the
    observations' variance component comes out near 2 (within 10 %). The other classes' one-step
    estimates are coupled to it (the DEM's comes out about 1.24 here, its redundancy being ~120
    rows), so only the dominant class is checked; iterated variance components would separate
    them."""
    sc, p, blunder, *_ = clean
    o = p.observations
    half = _with(p, Observations(o.landmark, o.camera, o.band, o.line, o.sample, o.exposure, o.sigma_px / 2))
    *_, rel = _solve(sc, half, blunder)
    vc = rel.summary()["variance_components"]
    assert vc["observations"]["sigma0"] == pytest.approx(2.0, rel=0.1)
    assert vc["observations"]["redundancy"] > 10 * vc["dem"]["redundancy"]
