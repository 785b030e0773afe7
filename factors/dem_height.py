"""DEM height factor (eq. 31): ``h_DEM(lat(P), lon(P)) + N - H(P) = 0``.

A surface that returns NaN (a landmark off the DEM) gives a non-finite error, which the solver
treats as a rejected step; linearising there is an error.

``h_DEM`` is the local surface fitted to the DEM postings around the landmark (eq. 8; height
above MSL, gradient in m per degree), ``N`` the geoid undulation (m) and ``H`` the ellipsoidal
height of the landmark ``P`` (ECEF m, eq. 9). Residual in metres; noise is the surface's 1 sigma.

The surface is supplied as a callable ``surface(lat_deg, lon_deg) -> (h, dh_dlat, dh_dlon)``
(numpy arrays) so this module stays independent of how the DEM is stored; the landmark's
latitude/longitude follow it, so the fit is re-evaluated at every linearisation.
"""

from __future__ import annotations

from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.collinearity import FactorShapeError, cached_at
from factors.geometry import geodetic_from_ecef, geodetic_jacobians

__all__ = ["dem_residual", "dem_residual_hessian", "DemBatch", "Surface"]

Array = NDArray[np.float64]
Surface = Callable[[Array, Array], tuple[Array, Array, Array]]
_DEG = 180.0 / np.pi


def dem_residual(landmark: Array, surface: Surface, jacobians: bool = True) -> tuple[Array, Array | None]:
    """Residual ``(N,)`` m and Jacobian ``(N, 1, 3)`` w.r.t. the ECEF landmark ``(N, 3)``.

    ``surface`` returns the ellipsoidal surface height (MSL height + geoid) and its gradient.
    """
    lat, lon, h = geodetic_from_ecef(landmark)
    hs, dlat, dlon = surface(np.degrees(lat), np.degrees(lon))
    r = np.asarray(hs, dtype=float) - h
    if not jacobians:
        return r, None
    glat, glon, gh = geodetic_jacobians(lat, lon, h)
    j = (np.asarray(dlat)[:, None] * _DEG) * glat + (np.asarray(dlon)[:, None] * _DEG) * glon - gh
    return r, j[:, None, :]


def dem_residual_hessian(landmark: Array, surface: Surface, step_m: float = 1.0) -> Array:
    """Hessian ``d^2 r / dP^2`` ``(N, 3, 3)`` in m^-1 of the residual of :func:`dem_residual`.

    Central differences of the analytic gradient with a ``step_m`` (m) step along each ECEF axis,
    symmetrised. The local surface is piecewise cubic between DEM postings (~90 m apart), so a 1 m
    step is exact inside a cell up to rounding. Used for the second-order term ``r * d^2 r`` that
    Gauss-Newton neglects (the DEM curvature the solver core adds near convergence).
    """
    p = np.asarray(landmark, dtype=float)
    out = np.empty((p.shape[0], 3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = step_m
        _, jp = dem_residual(p + e, surface, True)
        _, jm = dem_residual(p - e, surface, True)
        assert jp is not None and jm is not None
        out[:, a, :] = (jp[:, 0, :] - jm[:, 0, :]) / (2.0 * step_m)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


class DemBatch:
    """One DEM factor per landmark, evaluated together (same cache protocol as CollinearityBatch).

    ``sigma_m`` ``(N,)`` m: each factor's 1 sigma; ``stated_m`` ``(N,)`` m (optional): the part of
    it that is the DEM's own stated sigma (as weighted), the rest being the local surface fit's
    residual; it says how much of the factors' variance a misstated DEM sigma would move."""

    def __init__(
        self, keys: NDArray[np.int64], sigma_m: Array, surface: Surface, stated_m: Array | None = None
    ) -> None:
        self.keys = np.asarray(keys, np.int64)
        self.sigma_m = np.asarray(sigma_m, float)
        self.stated_m = None if stated_m is None else np.asarray(stated_m, float)
        self.surface = surface
        self._cache: tuple[gtsam.Values, Array, Array | None] | None = None  # (at, residuals, Jacobians)

    def __len__(self) -> int:
        return int(self.keys.size)

    @classmethod
    def concatenate(cls, batches: "list[DemBatch]") -> "DemBatch":
        """One batch with every factor of ``batches`` (in their order), evaluated on the first
        batch's surface (the batches must have been built on the same DEM, geoid and fit)."""
        if not batches:
            raise ValueError("DemBatch.concatenate needs at least one batch")
        stated = np.concatenate([b.stated_m for b in batches]) if all(b.stated_m is not None for b in batches) else None
        return cls(
            np.concatenate([b.keys for b in batches]),
            np.concatenate([b.sigma_m for b in batches]),
            batches[0].surface,
            stated,
        )

    def _landmarks(self, values: gtsam.Values) -> Array:
        return np.stack([values.atVector(int(k)) for k in self.keys]) if len(self) else np.zeros((0, 3))

    def residuals(self, values: gtsam.Values, jacobians: bool = False) -> tuple[Array, Array | None]:
        return dem_residual(self._landmarks(values), self.surface, jacobians)

    def evaluate(self, values: gtsam.Values, jacobians: bool = True) -> None:
        self.cache(*self.residuals(values, jacobians), values=values)

    def cache(self, r: Array, j: Array | None, values: gtsam.Values) -> None:
        """Cache an evaluation already made at ``values`` (:func:`dem_residual`'s output for every
        landmark); used only by factors called with that same ``Values`` object."""
        self._cache = (values, r, j)

    def clear(self) -> None:
        self._cache = None

    def factors(self) -> list[gtsam.CustomFactor]:
        return [
            gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, float(s)), [int(k)], self._callback(i))
            for i, (k, s) in enumerate(zip(self.keys, self.sigma_m))
        ]

    def _callback(self, i: int):
        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> Array:
            hit = cached_at(self._cache, values, H is not None)
            if hit is not None:
                r, j = hit[0][i : i + 1], (hit[1][i] if hit[1] is not None else None)
            else:
                rr, jj = dem_residual(
                    np.asarray(values.atVector(int(self.keys[i])))[None, :], self.surface, H is not None
                )
                r, j = rr, (jj[0] if jj is not None else None)
            if r.shape != (1,):
                raise FactorShapeError(f"DEM factor {i}: residual shape {r.shape}, expected (1,)")
            if H is not None and not np.all(np.isfinite(r)):
                raise FactorShapeError(f"DEM factor {i}: the landmark is off the DEM tiles at the linearisation point")
            if H is not None:
                H[0] = np.asarray(j).reshape(1, 3)
            return r

        return error
