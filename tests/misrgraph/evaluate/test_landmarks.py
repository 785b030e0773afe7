"""The landmark NEES split into common (group-mean) and within-group parts, checked against the
dense inverse of a Schur-structured information matrix, a Monte Carlo of its own covariance, and
the per-landmark NEES it must reduce to when every landmark is a group of its own."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.evaluate.landmarks import landmark_nees_split, time_groups


def _schur_system(rng: np.random.Generator, n_l: int = 12, n_c: int = 7):
    """A random least-squares problem in Schur form: every row touches one landmark and a few other
    variables. Returns the dense covariance ``(3 n_l + n_c)^2`` and the Schur pieces."""
    rows = []
    for i in range(n_l):
        for _ in range(4):  # four 2-row observations per landmark
            a = np.zeros((2, 3 * n_l + n_c))
            a[:, 3 * i : 3 * i + 3] = rng.normal(size=(2, 3))
            cols = 3 * n_l + rng.choice(n_c, 3, replace=False)
            a[:, cols] = rng.normal(size=(2, 3))
            rows.append(a)
    j = np.vstack(rows + [0.3 * np.eye(3 * n_l + n_c)])  # a weak prior on everything
    h = j.T @ j
    cov = np.linalg.inv(h)
    n3 = 3 * n_l
    h_ll = np.array([h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n_l)])
    g = np.array([np.linalg.solve(h_ll[i], h[3 * i : 3 * i + 3, n3:]) for i in range(n_l)])  # G_i
    p = np.array([cov[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n_l)])
    return cov[:n3, :n3], p, g, cov[n3:, n3:]


def _dense_split(e: np.ndarray, cov_ll: np.ndarray, group: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The same statistics from the landmarks' dense joint covariance by linear maps."""
    n = e.shape[0]
    common, within, axes = [], [], []
    for label in np.unique(group):
        idx = np.flatnonzero(group == label)
        avg = np.zeros((3, 3 * n))
        for i in idx:
            avg[:, 3 * i : 3 * i + 3] = np.eye(3) / idx.size
        mean = avg @ e.ravel()
        common.append(mean @ np.linalg.solve(avg @ cov_ll @ avg.T, mean))
        if idx.size < 2:
            continue
        for i in idx:
            sel = np.zeros((3, 3 * n))
            sel[:, 3 * i : 3 * i + 3] = np.eye(3)
            dev_map = sel - avg
            c = dev_map @ cov_ll @ dev_map.T
            d = dev_map @ e.ravel()
            within.append(d @ np.linalg.solve(c, d))
            axes.append(d**2 / np.diag(c))
    return float(np.mean(common) / 3), float(np.mean(within) / 3), np.mean(axes, axis=0)


def test_the_split_equals_the_dense_joint_covariance_s():
    rng = np.random.default_rng(7)
    cov_ll, p, g, s = _schur_system(rng)
    group = np.array([0, 0, 0, 1, 1, 1, 1, 2, 3, 3, 3, 3])  # group 2 has one landmark: common only
    e = rng.multivariate_normal(np.zeros(cov_ll.shape[0]), cov_ll).reshape(-1, 3)
    got = landmark_nees_split(e, p, g, s, group)
    common, within, axes = _dense_split(e, cov_ll, group)
    assert got["groups"] == 4 and got["common_dim"] == 12 and got["within_dim"] == 3 * 11
    assert got["common"] == pytest.approx(common, rel=1e-9)
    assert got["within"] == pytest.approx(within, rel=1e-9)
    np.testing.assert_allclose(got["within_enu"], axes, rtol=1e-9)


def test_the_split_is_one_in_expectation_under_its_own_covariance():
    """Errors drawn from the joint covariance the split is given: both means are 1 within four
    standard errors of the draws' own scatter."""
    rng = np.random.default_rng(11)
    cov_ll, p, g, s = _schur_system(rng)
    group = np.repeat([0, 1, 2], 4)
    draws = rng.multivariate_normal(np.zeros(cov_ll.shape[0]), cov_ll, size=600).reshape(600, -1, 3)
    res = [landmark_nees_split(e, p, g, s, group) for e in draws]
    for part in ("common", "within"):
        v = np.array([r[part] for r in res])
        assert abs(v.mean() - 1.0) < 4 * v.std(ddof=1) / np.sqrt(v.size), (part, v.mean())


def test_errors_too_large_in_common_show_in_the_common_part_only():
    """A shared offset added to a group's errors (as an unmodelled pointing error would) raises the
    common part and leaves the deviations about the group mean unchanged."""
    rng = np.random.default_rng(5)
    cov_ll, p, g, s = _schur_system(rng)
    group = np.repeat([0, 1], 6)
    e = rng.multivariate_normal(np.zeros(cov_ll.shape[0]), cov_ll).reshape(-1, 3)
    shifted = e + np.where(group[:, None] == 0, 50.0 * np.sqrt(np.max(np.diag(cov_ll))), 0.0)
    a, b = landmark_nees_split(e, p, g, s, group), landmark_nees_split(shifted, p, g, s, group)
    assert b["within"] == pytest.approx(a["within"], rel=1e-9)
    assert b["common"] > 100 * a["common"]


def test_bad_input_is_named():
    rng = np.random.default_rng(1)
    _, p, g, s = _schur_system(rng, n_l=3, n_c=4)
    e = np.zeros((3, 3))
    with pytest.raises(InputError, match="joint"):
        landmark_nees_split(e, p, g, s[:2, :2], np.zeros(3, int))
    with pytest.raises(InputError, match="error, cov"):
        landmark_nees_split(e[:2], p, g, s, np.zeros(3, int))
    with pytest.raises(InputError, match="window_s"):
        time_groups([0.0, 1.0], 0.0)
    with pytest.raises(InputError, match="time_s"):
        time_groups([0.0, np.nan])
    np.testing.assert_array_equal(time_groups([10.0, 250.0, 320.0, 900.0], 300.0), [0, 0, 1, 2])


def test_an_adjusted_pass_s_split_reduces_to_its_landmark_nees(small_pass_dir):
    """On an adjusted pass, with every landmark in a group of its own (a window shorter than any
    two landmarks' time difference) the common part is the per-landmark NEES of ``score_pass`` and
    nothing is left within; the default window gives both parts, over every landmark with an
    adjusted observation."""
    from misrgraph.estimate.adjust import AdjustConfig, adjust_pass
    from misrgraph.evaluate.score import _true_deltas, landmark_split, score_pass
    from misrgraph.sim.simulate import load_scenario

    sc = load_scenario(small_pass_dir)
    op, truth = sc.load_pass(0), sc.load_truth(0)
    cam = sc.camera_model.at_temperature(op.temperature_c)
    res = adjust_pass(op, cam, sc.dem, sc.gcps, AdjustConfig())
    scored = score_pass(op, truth, res, cam)
    delta = _true_deltas(truth, res, cam, False)
    t = op.observation_times()[res.pass_graph.obs_index]
    tiny = 0.5 * np.min(np.diff(np.unique(t)))
    alone = landmark_split(op, truth, res, delta, window_s=tiny)
    assert alone["groups"] == alone["landmarks"] == len(res.pass_graph.landmark_keys)
    assert alone["within_dim"] == 0 and np.isnan(alone["within"])
    assert alone["common"] == pytest.approx(scored["nees"]["landmarks"], rel=1e-9)
    split = scored["landmark_split"]
    assert 2 <= split["groups"] <= 3 and split["window_s"] == 300.0  # a 15-minute pass, in 300 s windows
    assert (
        scored["nees"]["landmarks_common"] == split["common"] and scored["nees"]["landmarks_within"] == split["within"]
    )
    assert np.isfinite(split["common"]) and np.isfinite(split["within"])
