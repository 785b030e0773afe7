"""A calibration's errors given the other cameras': standardised as the covariance says, against a
Monte Carlo of correlated errors."""

from __future__ import annotations

import numpy as np

from misrgraph.evaluate.calibration import given_others_z
from misrgraph.model.constants import CAMERAS


def test_given_others_z_is_standard_normal_under_its_covariance(rng) -> None:
    """Errors drawn from a covariance with strong sharing between cameras (and an extra parameter
    in between): each camera's z given the others has mean square 1 (4000 draws, within 4 standard
    errors), and the same errors standardised with a covariance that halves the sharing do not."""
    labels = [f"{c}.{p}" for c in CAMERAS for p in ("delta", "beta", "epsilon", "alpha2")]
    n = len(labels)
    same = np.array([[a.split(".")[1] == b.split(".")[1] for b in labels] for a in labels], float)

    def covariance(share: float) -> np.ndarray:
        corr = share * same
        np.fill_diagonal(corr, 1.0)
        return corr * np.outer(sd, sd)

    sd = rng.uniform(0.5, 2.0, n)
    cov = covariance(0.85)
    chol = np.linalg.cholesky(cov)
    z = np.array([given_others_z(labels, chol @ rng.standard_normal(n), cov) for _ in range(4000)])
    assert z.shape == (4000, 27)
    m = np.mean(z**2, axis=0)
    se = np.std(z**2, axis=0, ddof=1) / np.sqrt(z.shape[0])
    assert np.all(np.abs(m - 1.0) < 4 * se), m
    wrong = np.array([given_others_z(labels, chol @ rng.standard_normal(n), covariance(0.425)) for _ in range(1000)])
    assert abs(np.mean(wrong**2) - 1.0) > 0.2, np.mean(wrong**2)
    assert given_others_z(labels[:-4], np.zeros(n - 4), np.eye(n - 4)).size == 0
