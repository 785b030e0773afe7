"""Navigation error models of seed section 4.2: ephemeris drift (eq. 19) and attitude spline (eqs. 23-29).

* :class:`EphemerisErrorModel`: per segment ``s`` between navigation fixes, in the orbital frame
  (x along track, y cross track to the right, z toward nadir), ``e(t) = a_s (t - t_s) + b_s``
  (eq. 19) with ``t_s`` the segment start. Parameters per segment are the ``Vector6``
  ``[a_x, a_y, a_z, b_x, b_y, b_z]`` (m/s, m). The supplied position is ``P_meas = P_true + T_go e``.
* :class:`AttitudeErrorModel`: per angle (roll, pitch, yaw) a cubic Hermite spline through knots
  ``(value, rate)`` (rad, rad/s), eqs. 23-27; ``A_meas = A_true + E(t)`` (eq. 22). Knots are
  equally spaced with a spacing per angle; :func:`knots_to_remove` applies eqs. 28-29, after
  which the spline spans the neighbours of a removed knot.

All evaluation is vectorised and returns the derivatives with respect to the parameters that the
factors need: :meth:`EphemerisErrorModel.design` and :meth:`AttitudeErrorModel.bracket`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import hermite_weights
from misrgraph.errors import InputError
from misrgraph.model.constants import ANGLES, ARCSEC, CAMERAS, NODAL_PERIOD_S

__all__ = [
    "ATTITUDE_RATE_FACTOR",
    "ATTITUDE_DAMPING",
    "JITTER_PERIODS_S",
    "band_correlation",
    "spline_design",
    "projected_band_covariance",
    "unresolved_band_sigma",
    "unresolved_process_sigma",
    "unresolved_attitude",
    "ephemeris_prior_covariance",
    "process_correlation",
    "fit_damping",
    "EphemerisErrorModel",
    "AttitudeErrorModel",
    "knots_to_remove",
    "interval_counts",
    "uniform_knots",
]

Array = NDArray[np.float64]

#: The attitude error rate's 1 sigma per unit of the value's 1 sigma (1/s): for a smooth process
#: with periods log-uniform in 200-2000 s (the GN&C's slow errors) it is
#: ``sqrt(E[(2 pi / P)^2]) = 0.0146`` per second. The estimator's knot priors use it, and the
#: process prior's Matern-3/2 rate ``lam`` equals it.
ATTITUDE_RATE_FACTOR = 2 * np.pi * np.sqrt((1 / (2 * 200.0**2) - 1 / (2 * 2000.0**2)) / np.log(10.0))

#: The damping ratio of the attitude process prior (:mod:`factors.priors`): the value whose
#: correlation function (:func:`process_correlation`) is closest, in least squares over lags
#: 0-600 s (a 10-minute pass), to that of the same periods log-uniform in 200-2000 s
#: (:func:`band_correlation`): :func:`fit_damping` gives 0.58 (0.54 over 0-300 s, 0.58 over
#: 0-1200 s). The critically damped Matern-3/2 (1) has the same value and rate variance but keeps
#: too much power at periods beyond the band (an offset over a pass) and correlates 0.78 over
#: 60 s where the band correlates 0.67; under the independent truth it made the knots
#: conservative (NEES 0.83 on 10-minute passes).
ATTITUDE_DAMPING = 0.58

#: Periods (s) of the attitude error faster than the slow 200-2000 s band: the GN&C's jitter
#: (10 s Kalman updates, gyro noise), with equal power per log-period. A spline with knots every
#: 60 s takes up the part near its longest periods (:func:`projected_band_covariance`); the rest
#: (:func:`unresolved_band_sigma`) no knot can follow.
JITTER_PERIODS_S = (8.0, 120.0)


def band_correlation(tau: ArrayLike, periods_s: tuple[float, float] = (200.0, 2000.0)) -> Array:
    """Correlation at lags ``tau`` (s) of a sum of sinusoids with periods log-uniform in
    ``periods_s`` (equal expected power per log-period): ``(Ci(2 pi tau / P0) - Ci(2 pi tau / P1)) / ln(P1 / P0)``,
    1 at lag 0."""
    from scipy.special import sici

    t = np.abs(np.asarray(tau, dtype=float))
    p0, p1 = periods_s
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (sici(2 * np.pi * t / p0)[1] - sici(2 * np.pi * t / p1)[1]) / np.log(p1 / p0)
    return np.where(t == 0, 1.0, r)


def process_correlation(tau: ArrayLike, lam: float, zeta: float) -> Array:
    """Correlation at lags ``tau`` (s) of the damped-oscillator process (:mod:`factors.priors`)
    with natural frequency ``lam`` (1/s) and damping ratio ``zeta``."""
    t = np.abs(np.asarray(tau, dtype=float))
    a = zeta * lam * t
    if zeta < 1:
        wd = lam * np.sqrt(1 - zeta * zeta)
        return np.exp(-a) * (np.cos(wd * t) + zeta * lam / wd * np.sin(wd * t))
    if zeta == 1:
        return np.exp(-a) * (1 + lam * t)
    wd = lam * np.sqrt(zeta * zeta - 1)
    return np.exp(-a) * (np.cosh(wd * t) + zeta * lam / wd * np.sinh(wd * t))


def fit_damping(
    max_lag_s: float = 600.0, lam: float = ATTITUDE_RATE_FACTOR, periods_s: tuple[float, float] = (200.0, 2000.0)
) -> float:
    """The damping ratio whose process correlation is closest in least squares (lags every 1 s
    up to ``max_lag_s``) to the band's (:func:`band_correlation`), rounded to 0.01."""
    from scipy.optimize import minimize_scalar

    tau = np.arange(0.0, max_lag_s + 0.5, 1.0)
    target = band_correlation(tau, periods_s)
    res = minimize_scalar(
        lambda z: float(np.sum((process_correlation(tau, lam, z) - target) ** 2)),
        bounds=(0.05, 2.0),
        method="bounded",
        options={"xatol": 1e-5},
    )
    return round(float(res.x), 2)


def _increasing_times(
    times: ArrayLike, field: str = "knot_times", expected: str = "at least 2 increasing times (s)"
) -> Array:
    """``times`` (s) as a float array, refused (naming ``field``, expecting ``expected``) unless
    they are at least 2 strictly increasing values."""
    t = np.asarray(times, dtype=float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise InputError(field, t, expected)
    return t


@dataclass
class EphemerisErrorModel:
    """Piecewise-linear ephemeris error (eq. 19). ``boundaries (S+1,)`` s; ``params (S, 6)``."""

    boundaries: Array
    params: Array

    def __post_init__(self) -> None:
        self.boundaries = _increasing_times(
            self.boundaries, "ephemeris_error.boundaries", "increasing segment boundaries (at least 2)"
        )
        self.params = np.asarray(self.params, dtype=float)
        if self.params.shape != (self.boundaries.size - 1, 6):
            raise InputError("ephemeris_error.params", self.params.shape, f"shape ({self.boundaries.size - 1}, 6)")

    @classmethod
    def zeros(cls, t_start: float, t_end: float, segments: int = 1) -> "EphemerisErrorModel":
        """A zero model with ``segments`` equal segments over [t_start, t_end]."""
        if segments < 1:
            raise InputError("segments", segments, "an integer >= 1")
        return cls(np.linspace(t_start, t_end, segments + 1), np.zeros((segments, 6)))

    @property
    def n_segments(self) -> int:
        return self.params.shape[0]

    def segment_of(self, t: ArrayLike) -> NDArray[np.int64]:
        """Index of the segment containing each time (times outside clamp to the end segments)."""
        return np.clip(
            np.searchsorted(self.boundaries, np.asarray(t, dtype=float), side="right") - 1, 0, self.n_segments - 1
        )

    def design(self, t: ArrayLike) -> tuple[NDArray[np.int64], Array]:
        """Segment index and ``de/dparams`` (``(N, 3, 6)``) at times ``t``: ``[(t - t_s) I, I]``."""
        tt = np.ravel(np.asarray(t, dtype=float))
        seg = self.segment_of(tt)
        dt = tt - self.boundaries[seg]
        d = np.zeros((tt.size, 3, 6))
        d[:, [0, 1, 2], [0, 1, 2]] = dt[:, None]
        d[:, [0, 1, 2], [3, 4, 5]] = 1.0
        return seg, d

    def evaluate(self, t: ArrayLike) -> Array:
        """``e(t)`` in the orbital frame (m), ``(N, 3)``."""
        seg, d = self.design(t)
        return np.einsum("nij,nj->ni", d, self.params[seg])


def uniform_knots(t_start: float, t_end: float, spacing: float) -> Array:
    """Equally spaced knot times covering [t_start, t_end] (the last knot at or after t_end)."""
    if spacing <= 0:
        raise InputError("knot spacing", spacing, "a positive number of seconds")
    n = int(np.ceil((t_end - t_start) / spacing - 1e-9))
    return t_start + spacing * np.arange(max(n, 1) + 1)


@dataclass
class AttitudeErrorModel:
    """Cubic Hermite attitude error per angle. ``knot_times[a] (M_a,)``, ``knots[a] (M_a, 2)``
    as (value rad, rate rad/s) for ``a`` in roll, pitch, yaw."""

    knot_times: list[Array]
    knots: list[Array]

    def __post_init__(self) -> None:
        if len(self.knot_times) != 3 or len(self.knots) != 3:
            raise InputError("attitude_error", len(self.knot_times), "three angles (roll, pitch, yaw)")
        for a in range(3):
            kt = _increasing_times(
                self.knot_times[a], f"attitude_error.knot_times[{ANGLES[a]}]", "at least 2 increasing times"
            )
            kv = np.asarray(self.knots[a], dtype=float)
            if kv.shape != (kt.size, 2):
                raise InputError(f"attitude_error.knots[{ANGLES[a]}]", kv.shape, f"shape ({kt.size}, 2)")
            self.knot_times[a] = kt
            self.knots[a] = kv

    @classmethod
    def zeros(cls, t_start: float, t_end: float, spacing: tuple[float, float, float]) -> "AttitudeErrorModel":
        """Zero error, knots every ``spacing`` s per angle (roll, pitch, yaw)."""
        kt = [uniform_knots(t_start, t_end, s) for s in spacing]
        return cls(kt, [np.zeros((k.size, 2)) for k in kt])

    def bracket(self, angle: int, t: ArrayLike) -> tuple[NDArray[np.int64], Array]:
        """Index ``i`` of the left knot bracketing each time and the Hermite weights ``(N, 4)`` of
        ``(a_i, a'_i, a_{i+1}, a'_{i+1})``; times outside the knots extrapolate the end segments."""
        kt = self.knot_times[angle]
        tt = np.ravel(np.asarray(t, dtype=float))
        i = np.clip(np.searchsorted(kt, tt, side="right") - 1, 0, kt.size - 2)
        dt = kt[i + 1] - kt[i]
        return i, hermite_weights((tt - kt[i]) / dt, dt)

    def evaluate(self, t: ArrayLike) -> Array:
        """``E(t)`` (rad), ``(N, 3)`` in order roll, pitch, yaw."""
        tt = np.ravel(np.asarray(t, dtype=float))
        out = np.empty((tt.size, 3))
        for a in range(3):
            i, w = self.bracket(a, tt)
            k = self.knots[a]
            out[:, a] = w[:, 0] * k[i, 0] + w[:, 1] * k[i, 1] + w[:, 2] * k[i + 1, 0] + w[:, 3] * k[i + 1, 1]
        return out

    def rate(self, t: ArrayLike) -> Array:
        """``dE/dt`` (rad/s), ``(N, 3)``: the derivative of the same piecewise cubic Hermite
        (``scipy.interpolate.CubicHermiteSpline``; end segments extended as in :meth:`evaluate`)."""
        from scipy.interpolate import CubicHermiteSpline

        tt = np.ravel(np.asarray(t, dtype=float))
        return np.stack(
            [CubicHermiteSpline(self.knot_times[a], self.knots[a][:, 0], self.knots[a][:, 1])(tt, 1) for a in range(3)],
            -1,
        )

    def without(self, removed: list[NDArray[np.int64]]) -> "AttitudeErrorModel":
        """A copy with knots removed per angle (indices into the current knots)."""
        kt, kv = [], []
        for a in range(3):
            keep = np.ones(self.knot_times[a].size, bool)
            keep[np.asarray(removed[a], dtype=int)] = False
            kt.append(self.knot_times[a][keep].copy())
            kv.append(self.knots[a][keep].copy())
        return AttitudeErrorModel(kt, kv)


def spline_design(knot_times: ArrayLike, t: ArrayLike) -> Array:
    """The design matrix ``(N, 2K)`` of one angle's cubic Hermite spline on ``knot_times`` (``K``
    increasing times, s) at times ``t`` (``N``, s): ``E(t_n) = B[n] @ knots.ravel()`` with the knots
    ordered ``(a_0, a'_0, a_1, a'_1, ...)`` (rad, rad/s), end segments extrapolated as in
    :meth:`AttitudeErrorModel.evaluate`."""
    kt = np.asarray(knot_times, dtype=float)
    i, w = AttitudeErrorModel([kt] * 3, [np.zeros((kt.size, 2))] * 3).bracket(0, t)
    design = np.zeros((i.size, 2 * kt.size))
    np.put_along_axis(design, np.stack([2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3], -1), w, axis=1)
    return design


def _projection(knot_times: Array, step_s: float) -> tuple[Array, Array, Array]:
    """Samples every ``step_s`` over the knots' span, the spline's design ``B`` at them and the
    least-squares projection ``M = (B^T B)^-1 B^T``."""
    t = np.arange(knot_times[0], knot_times[-1] + 0.5 * step_s, step_s)
    design = spline_design(knot_times, t)
    return t, design, np.linalg.solve(design.T @ design, design.T)


def _projected_covariance(m: Array, r: Array) -> Array:
    """``M R M^T`` for the Toeplitz correlation ``R`` of the samples (first column ``r``)."""
    from scipy.linalg import matmul_toeplitz

    cov = m @ matmul_toeplitz(r, m.T)
    return 0.5 * (cov + cov.T)


def projected_band_covariance(
    knot_times: ArrayLike, sigma: float, periods_s: tuple[float, float] = JITTER_PERIODS_S, step_s: float = 1.0
) -> Array:
    """Covariance ``(2K, 2K)`` of the spline's share of a stationary error: the least-squares
    projection onto the Hermite spline on ``knot_times`` of an error ``e(t)`` with 1 sigma
    ``sigma`` (rad) and periods log-uniform in ``periods_s`` (s; correlation :func:`band_correlation`),
    sampled every ``step_s`` s over the knots' span::

        k = M e,   M = (B^T B)^-1 B^T,   Cov(k) = sigma^2 M R M^T

    with ``B`` the :func:`spline_design` at the samples and ``R`` their (Toeplitz) correlation.
    Knot order ``(a_0, a'_0, a_1, ...)``: rad^2, rad^2/s, rad^2/s^2. This is how an error faster
    than the slow process (jitter) enters the knots' truth (``misrgraph.evaluate.score.true_knots``
    projects the same way): for knots every 60 s and the default :data:`JITTER_PERIODS_S`, an
    interior knot takes up 0.44 sigma of value and 0.074 sigma/s of rate, an end knot 1.2 sigma
    and 0.16 sigma/s. Cost: one Toeplitz product by FFT, ~0.05 s for a 45-minute pass.
    """
    kt = _increasing_times(knot_times)
    if not (sigma >= 0 and step_s > 0 and 0 < periods_s[0] < periods_s[1]):
        raise InputError(
            "(sigma, periods_s, step_s)",
            (sigma, periods_s, step_s),
            "sigma >= 0, 0 < period_min < period_max, step > 0",
        )
    t, _, m = _projection(kt, step_s)
    return sigma**2 * _projected_covariance(m, band_correlation(t - t[0], periods_s))


def unresolved_band_sigma(
    knot_times: ArrayLike, sigma: float, periods_s: tuple[float, float] = JITTER_PERIODS_S, step_s: float = 1.0
) -> float:
    """RMS over the knots' span (rad) of the part of a stationary error (1 sigma ``sigma`` rad,
    periods log-uniform in ``periods_s`` s) that the spline on ``knot_times`` cannot take up: the
    residual of its least-squares projection (:func:`projected_band_covariance`, ``Cov(k)``),
    sampled every ``step_s`` s (``N`` samples, design ``B``)::

        sigma_u^2 = sigma^2 - tr(B Cov(k) B^T) / N

    (the projection is orthogonal in the samples' inner product, so the residual's mean variance
    is the error's minus the projection's). For knots every 60 s and the default
    :data:`JITTER_PERIODS_S` it is 0.86 ``sigma`` (26 % of the variance is the knots'), 0.99 ``sigma`` for
    knots every 120 s."""
    if not sigma >= 0:
        raise InputError("sigma", sigma, "a 1 sigma >= 0 (rad)")
    if not (step_s > 0 and len(periods_s) == 2 and 0 < periods_s[0] < periods_s[1]):
        raise InputError("(periods_s, step_s)", (periods_s, step_s), "0 < period_min < period_max, step > 0")
    share = _unresolved_share(_spacings(knot_times), ("band", *(float(x) for x in periods_s)), float(step_s))
    return float(sigma * np.sqrt(share))


def unresolved_process_sigma(
    knot_times: ArrayLike, sigma: float, lam: float, zeta: float, step_s: float = 1.0
) -> float:
    """As :func:`unresolved_band_sigma` for the slow attitude process itself (1 sigma ``sigma``
    rad, natural frequency ``lam`` 1/s, damping ratio ``zeta``; correlation
    :func:`process_correlation`): what of it the spline on ``knot_times`` cannot take up. For the
    pre-flight process (``lam`` = :data:`ATTITUDE_RATE_FACTOR`, ``zeta`` = 0.58) on knots every
    60 s it is 0.027 ``sigma``; for ``lam`` = 0.1/s (errors with periods of tens of seconds) it is
    0.46 ``sigma`` on the same knots and 0.06 ``sigma`` on knots every 15 s."""
    if not (sigma >= 0 and lam > 0 and zeta > 0 and step_s > 0):
        raise InputError(
            "(sigma, lam, zeta, step_s)",
            (sigma, lam, zeta, step_s),
            "sigma >= 0 (rad), lam > 0 (1/s), zeta > 0, step > 0",
        )
    share = _unresolved_share(_spacings(knot_times), ("process", float(lam), float(zeta)), float(step_s))
    return float(sigma * np.sqrt(share))


def unresolved_attitude(
    knot_times: list[Array],
    jitter_arcsec: float,
    periods_s: tuple[float, float] = JITTER_PERIODS_S,
    process: tuple[Any, Any, float] | None = None,
) -> float:
    """1 sigma (rad) of the attitude error the knots cannot follow: per angle
    :func:`~misrgraph.model.errormodels.unresolved_band_sigma` of a jitter of ``jitter_arcsec``
    (1 sigma, arcsec) with periods log-uniform in ``periods_s`` (s) on that angle's knots and, with
    ``process = (value_sigma_arcsec (3,), rate_sigma_arcsec_per_s (3,), damping)``, in quadrature
    :func:`unresolved_process_sigma` of the slow process (natural frequency rate over value); then
    the RMS over the three angles (one figure: equal knot grids, the default, give equal values)."""
    var = np.zeros(len(knot_times))
    if jitter_arcsec > 0:
        var += [unresolved_band_sigma(kt, jitter_arcsec * ARCSEC, tuple(periods_s)) ** 2 for kt in knot_times]
    if process is not None:
        value, rate, zeta = process
        var += [
            unresolved_process_sigma(kt, float(v) * ARCSEC, float(r) / float(v), float(zeta)) ** 2
            for kt, v, r in zip(knot_times, value, rate)
        ]
    return float(np.sqrt(np.mean(var))) if var.size else 0.0


def _spacings(knot_times: ArrayLike) -> tuple[float, ...]:
    # the unresolved share depends on the knots' spacings only (the samples start at the first
    # knot); to the microsecond they repeat from pass to pass, so it is computed once per grid
    return tuple(float(x) for x in np.round(np.diff(_increasing_times(knot_times)), 6))


@lru_cache(maxsize=128)
def _unresolved_share(spacings: tuple[float, ...], correlation: tuple, step_s: float) -> float:
    """``1 - tr(B Cov(k) B^T) / N`` for unit sigma (:func:`unresolved_band_sigma`), knots at
    ``cumsum((0,) + spacings)``; ``correlation``: ``("band", P0, P1)`` or ``("process", lam, zeta)``."""
    kt = np.concatenate([[0.0], np.cumsum(spacings)])
    t, design, m = _projection(kt, step_s)
    kind, *par = correlation
    r = band_correlation(t - t[0], tuple(par)) if kind == "band" else process_correlation(t - t[0], *par)
    share = float(np.einsum("ni,ij,nj->", design, _projected_covariance(m, r), design)) / design.shape[0]
    return max(1.0 - share, 0.0)


def ephemeris_prior_covariance(
    boundaries: ArrayLike,
    a_sigma_mps: ArrayLike,
    b_sigma_m: float,
    amplitude_m: float,
    period_s: float | None = None,
    step_s: float = 5.0,
) -> Array:
    """Covariance ``(6 S, 6 S)`` of the eq. 19 parameters of ``S`` segments (``boundaries (S+1,)``
    s; per segment ``[a_x, a_y, a_z, b_x, b_y, b_z]`` as :class:`EphemerisErrorModel` orders them,
    segment after segment) when the ephemeris error of each orbital axis ``k`` is the process

        e_k(t) = b_k + a_k (t - t_0) + c_k sin(w t) + d_k cos(w t),
        b_k ~ N(0, b_sigma^2), a_k ~ N(0, a_sigma_k^2), c_k, d_k ~ N(0, amplitude^2 / 2),

    (an offset and a drift over the pass, and a once-per-revolution term ``A_k sin(w t + phi)``
    with ``A_k ~ N(0, amplitude^2)``, ``w = 2 pi / period_s``, default the nodal period) and each
    segment's parameters are the least-squares line through the process over the segment
    (samples every ``step_s``). Axes are independent. Per axis the parameters are linear in the
    four variables ``(b, a, c, d)``, so the covariance is regular for one or two segments and
    :class:`~misrgraph.errors.InputError` names ``ephemeris_segments`` for more while
    ``amplitude_m > 0``. Two segments follow the term's curvature over a long pass (over 45
    minutes one line leaves ~0.19 of its amplitude, RMS, that no offset and drift can take). With ``amplitude_m =
    0`` and one segment it is ``diag(a_sigma^2, b_sigma^2)``, the plain eq. 19 prior."""
    edges = _increasing_times(boundaries, "ephemeris boundaries", "increasing segment boundaries (at least 2)")
    if not (np.isfinite(amplitude_m) and amplitude_m >= 0):
        raise InputError("ephemeris_once_per_rev_m", amplitude_m, "a 1 sigma amplitude >= 0 (m)")
    n_seg = edges.size - 1
    if amplitude_m > 0 and n_seg > 2:
        raise InputError(
            "ephemeris_segments",
            n_seg,
            "1 or 2 with a once-per-revolution term (an offset, a drift and "
            "the term are 4 variables per axis: more segments are not determined)",
        )
    w = 2 * np.pi / (NODAL_PERIOD_S if period_s is None else period_s)
    a_sig = np.broadcast_to(np.asarray(a_sigma_mps, dtype=float), (3,))
    # per segment: the least-squares line's (slope, value at the segment start) per unit of each variable
    fit = np.zeros((n_seg, 2, 4))
    for s in range(n_seg):
        t = np.linspace(edges[s], edges[s + 1], max(int(np.ceil((edges[s + 1] - edges[s]) / step_s)), 1) + 1)
        design = np.stack([t - edges[s], np.ones_like(t)], axis=1)
        basis = np.stack([np.ones_like(t), t - edges[0], np.sin(w * t), np.cos(w * t)], axis=1)
        fit[s] = np.linalg.lstsq(design, basis, rcond=None)[0]
    cov = np.zeros((n_seg, 6, n_seg, 6))
    m = fit.reshape(2 * n_seg, 4)  # rows: segment 0 slope, value, segment 1 slope, value, ...
    for k in range(3):
        lam = np.diag([b_sigma_m**2, a_sig[k] ** 2, amplitude_m**2 / 2, amplitude_m**2 / 2])
        ck = (m @ lam @ m.T).reshape(n_seg, 2, n_seg, 2)
        for i, pi in enumerate((k, 3 + k)):
            for j, pj in enumerate((k, 3 + k)):
                cov[:, pi, :, pj] = ck[:, i, :, j]
    return cov.reshape(6 * n_seg, 6 * n_seg)


def interval_counts(knot_times: ArrayLike, obs_times: ArrayLike, obs_camera: ArrayLike) -> NDArray[np.int64]:
    """``N_tie_point_seen(t_i, t_{i+1}, camera)``: observations per knot interval and camera,
    shape ``(M - 1, 9)`` (an observation at exactly ``t_{i+1}`` counts in the next interval)."""
    kt = np.asarray(knot_times, dtype=float)
    t = np.asarray(obs_times, dtype=float)
    cam = np.asarray(obs_camera, dtype=int)
    idx = np.searchsorted(kt, t, side="right") - 1
    ok = (idx >= 0) & (idx < kt.size - 1)
    counts = np.zeros((kt.size - 1, len(CAMERAS)), dtype=np.int64)
    np.add.at(counts, (idx[ok], cam[ok]), 1)
    return counts


def knots_to_remove(counts: ArrayLike, threshold1: int, threshold2: int, rule: str = "interval") -> NDArray[np.int64]:
    """Knots to remove by eqs. 28-29 from the per-interval, per-camera counts ``(M - 1, 9)``.

    ``rule="interval"`` is the seed's literal rule: knot ``i`` is judged on ``[t_i, t_{i+1})``.
    ``rule="support"`` judges it on its whole support ``[t_{i-1}, t_{i+1})`` -- the two segments
    its value and rate shape. A knot is removed when the tie-point observations counted there,
    summed over cameras, are fewer than ``threshold1`` (eq. 28) or when fewer than ``threshold2``
    cameras see any (eq. 29). The first and last knots are always kept so the spline still spans
    the pass (their values are held by their priors).

    With ``rule="support"`` and ``threshold1 = threshold2 = 1`` only knots with no data at all
    in their support go, so every merged segment is free of data and no observation is fitted by
    a spline coarser than its own (see docs/explanation/conventions.md for the measured consequence).
    """
    c = np.asarray(counts)
    if c.ndim != 2:
        raise InputError("counts", c.shape, "an (intervals, cameras) array")
    if rule not in ("interval", "support"):
        raise InputError("knot removal rule", rule, ("interval", "support"))
    m = c.shape[0] + 1
    judged = c.copy()
    if rule == "support":
        judged = np.zeros_like(c)
        judged[1:] = c[1:] + c[:-1]  # knot i (1..M-2) sees intervals i-1 and i
    fail = (judged.sum(axis=1) < threshold1) | ((judged > 0).sum(axis=1) < threshold2)
    fail[0] = False
    idx = np.flatnonzero(fail)
    return idx[(idx > 0) & (idx < m - 1)]
