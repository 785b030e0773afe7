"""Prior factors: GCP position (eq. 32) and a-priori values of knots, ephemeris and camera.

These are GTSAM's own C++ ``PriorFactorVector`` (no Python callback). The GCP prior's noise is
30 m per ENU axis rotated to ECEF as a full covariance: ``C = R diag(s^2) R^T`` with ``R`` the
ENU basis at the GCP (:func:`factors.geometry.enu_covariance`).
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import ArrayLike

__all__ = ["gcp_prior", "vector_prior"]


def gcp_prior(key: int, position_ecef: ArrayLike, covariance: ArrayLike) -> gtsam.PriorFactorVector:
    """Eq. 32: ``P_GCP - P = 0`` with a full ECEF covariance (m^2)."""
    return gtsam.PriorFactorVector(key, np.asarray(position_ecef, dtype=float),
                                   gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, dtype=float)))


def vector_prior(key: int, mean: ArrayLike, sigmas: ArrayLike) -> gtsam.PriorFactorVector:
    """Independent Gaussian prior on a vector variable (knot, ephemeris segment, camera)."""
    m = np.asarray(mean, dtype=float)
    return gtsam.PriorFactorVector(key, m, gtsam.noiseModel.Diagonal.Sigmas(np.broadcast_to(np.asarray(sigmas, float), m.shape).copy()))
