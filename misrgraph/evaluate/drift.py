"""Watching a camera parameter over the years: a state-space model of its calibrations and a
sequential change test on the model's innovations.

One camera parameter (an angle correction, in pixels of the camera's footprint or arcseconds: any
unit, the same for the estimates and their sigmas) is calibrated again and again: at times
``t_k`` (days) the calibration gives ``y_k`` with 1-sigma ``s_k`` (from its covariance). The
model of the series:

    y_k = level(t_k) + a cos(2 pi t_k / P) + b sin(2 pi t_k / P) + e_k,      e_k ~ N(0, s_k^2)
    level(t + dt) = level(t) + dt slope(t) + w_level,   w_level ~ N(0, q_level dt)
    slope(t + dt) = slope(t) + w_slope,                 w_slope ~ N(0, q_slope dt)

(a local linear trend with an annual term of period ``P`` = 365.25 d when ``seasonal``; the
random-walk intensities ``q_level`` [unit^2/d] and ``q_slope`` [unit^2/d^3] are the levels of the
process). The Kalman filter gives the innovations ``v_k`` and their variances ``S_k``. The level
starts diffuse (the camera's first correction is whatever it is); the slope starts at zero with
variance ``slope_var`` [unit^2/d^2] and each seasonal coefficient with variance ``season_var``
[unit^2], or diffuse when those are infinite. The first ``n_diffuse`` innovations (as many as the
diffuse states) are left out of the likelihood and the test.

* :func:`fit_process_levels` learns ``q_level``, ``q_slope``, ``slope_var`` and ``season_var``
  from the series by maximising the innovations' Gaussian likelihood, pooled over the series
  given (the levels are not the simulator's: they come from the data, as the project's rule for
  every level the estimator uses). Learning the slope's and the seasonal term's spread across the
  series, rather than starting each series with them unknown, is what lets a series predict its
  next calibration to about its own 1-sigma after a few calibrations: with a diffuse slope and
  seasonal term, four of the first calibrations go to fixing them and the prediction of the next
  stays uncertain by a multiple of the calibration's sigma, which hides a step.
* :func:`cusum` runs a two-sided CUSUM on the standardised innovations ``z_k = v_k / sqrt(S_k)``
  (reference ``k`` in sigmas): a change of the parameter that the model did not predict (a step,
  or a drift faster than the learned process) makes ``z`` lean to one side and the sum cross the
  threshold ``h``. ``k`` is half the shift (in innovation sigmas) the test is made to see
  soonest, CUSUM's classical choice; the default 1.5 suits the steps a camera model must not
  miss, a tenth of a pixel against calibrations of a few hundredths.
* :func:`cusum_threshold` sets ``h`` for a false-alarm probability ``alpha`` over a series of
  ``n`` tests (the probability that a series without any change raises an alarm), by simulating
  sequences of independent N(0, 1) innovations: under the model without change that is what the
  standardised innovations are.
* :func:`monitor_series` puts the three together and says when, in which direction and with what
  evidence (the CUSUM statistic against ``h``) the series asks for a new camera model;
  :func:`monitor_cameras` does so for every camera and parameter at once, the false-alarm
  probability shared among them.
* :func:`conditional_series` turns the cameras' series of one parameter into each camera's series
  *given the other cameras'* at each calibration. A calibration's errors are correlated across
  cameras (the GCP passes' navigation errors move every camera's angles alike: the calibration's
  covariance says by how much), while a camera that moves moves alone. With ``S`` the cameras'
  joint covariance at a calibration, camera ``c``'s value given the others ``o``:

      y'_c = y_c - b^T y_o,    b = S_oo^-1 S_oc,    s'_c^2 = S_cc - S_co b,

  has the error of ``y_c`` that the others do not predict (``s'_c`` the smaller, the more the
  cameras' errors are shared), and moves by the whole change when camera ``c`` alone changes.
  Its true series is ``x_c - b^T x_o``: when the cameras wander independently with the same
  process, one with levels ``1 + |b|^2`` times theirs (its ``gain``): :func:`fit_process_levels`
  learns the cameras' levels from such series divided by the gain's square root, and
  :func:`monitor_cameras` tests each with the levels times its gain.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from misrgraph.errors import InputError

__all__ = [
    "SEASON_DAYS",
    "TrendLevels",
    "FilterResult",
    "ChangeAlarm",
    "kalman_filter",
    "fit_process_levels",
    "cusum",
    "cusum_threshold",
    "monitor_series",
    "monitor_cameras",
    "conditional_series",
]

Array = NDArray[np.float64]

#: The period of the seasonal term (days).
SEASON_DAYS = 365.25
_DIFFUSE = 1e8


@dataclass(frozen=True)
class TrendLevels:
    """The process levels: ``q_level`` (unit^2/day) and ``q_slope`` (unit^2/day^3), and the spread
    of a series' starting slope ``slope_var`` (unit^2/day^2) and of each seasonal coefficient
    ``season_var`` (unit^2); ``inf``: unknown (diffuse)."""

    q_level: float
    q_slope: float
    slope_var: float = math.inf
    season_var: float = math.inf


@dataclass(frozen=True)
class FilterResult:
    """Innovations ``v (n,)`` and their variances ``S (n,)``, the filtered level and its 1-sigma
    ``(n,)``, the log-likelihood of the innovations after the diffuse start and ``n_diffuse``."""

    v: Array
    S: Array
    level: Array
    level_sigma: Array
    slope: Array
    log_likelihood: float
    n_diffuse: int

    @property
    def z(self) -> Array:
        """Standardised innovations (NaN for the diffuse start)."""
        z = self.v / np.sqrt(self.S)
        z[: self.n_diffuse] = np.nan
        return z


@dataclass(frozen=True)
class ChangeAlarm:
    """The first alarm of a series: its index and time, the direction (+1 up, -1 down), the
    test's statistic at the alarm against its threshold, the filtered level before it, which
    test raised it (``"step"``: the CUSUM, ``"departure"``: the level's departure), and the
    estimated onset: for a step, the first calibration of the CUSUM's run that crossed (the one
    after its last zero); for a departure, the alarm's own index."""

    index: int
    t: float
    direction: int
    statistic: float
    threshold: float
    level_before: float
    level_sigma_before: float
    kind: str = "step"
    onset: int = -1


def _check(t: ArrayLike, y: ArrayLike, s: ArrayLike) -> tuple[Array, Array, Array]:
    tt, yy, ss = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (t, y, s))
    if not (tt.shape == yy.shape == ss.shape) or tt.ndim != 1:
        raise InputError("t, y, sigma", (tt.shape, yy.shape, ss.shape), "three 1-D arrays of one length")
    if not (np.all(np.isfinite(tt)) and np.all(np.diff(tt) > 0)):
        raise InputError("t", tt[:3].tolist(), "finite, strictly increasing times (days)")
    if not np.all(np.isfinite(yy)):
        raise InputError("y", yy[~np.isfinite(yy)][:1].tolist(), "finite estimates")
    if not (np.all(np.isfinite(ss)) and np.all(ss > 0)):
        raise InputError("sigma", ss[~(ss > 0)][:1].tolist(), "positive 1-sigmas")
    return tt, yy, ss


def kalman_filter(
    t: ArrayLike,
    y: ArrayLike,
    sigma: ArrayLike,
    levels: TrendLevels,
    seasonal: bool = True,
    prior_variance: float = _DIFFUSE,
) -> FilterResult:
    """Run the filter of the module docstring over the series (times in days); the states start at
    zero, the level with variance ``prior_variance`` (diffuse by default), the slope and the
    seasonal coefficients with ``levels.slope_var`` and ``levels.season_var`` (``prior_variance``
    where those are infinite)."""
    tt, yy, ss = _check(t, y, sigma)
    v, S, level, level_sig, slope, m = _filter(tt, yy[None, :], ss[None, :], levels, seasonal, prior_variance)
    return FilterResult(v[0], S[0], level[0], level_sig[0], slope[0], _log_likelihood(v, S, m), m)


def _log_likelihood(v: Array, S: Array, m: int) -> float:
    """The innovations' Gaussian log-likelihood after the ``m`` diffuse ones, summed over rows."""
    if v.shape[1] <= m:
        return 0.0
    return -0.5 * float(np.sum(np.log(2 * math.pi * S[:, m:]) + v[:, m:] ** 2 / S[:, m:]))


def _filter(
    tt: Array, Y: Array, Ss: Array, levels: TrendLevels, seasonal: bool, prior_variance: float
) -> tuple[Array, Array, Array, Array, Array, int]:
    """The filter of :func:`kalman_filter` over ``B`` series sharing the times ``tt (n,)``: values
    and 1-sigmas ``(B, n)``; innovations, their variances, level, its 1-sigma and slope ``(B, n)``
    and the number of diffuse states."""
    n_state = 4 if seasonal else 2
    B, n = Y.shape
    x = np.zeros((B, n_state))
    p0 = float(prior_variance)
    start = [p0, levels.slope_var, levels.season_var, levels.season_var][:n_state]
    P = np.broadcast_to(
        np.diag([p0 if not math.isfinite(v) else float(v) for v in start]), (B, n_state, n_state)
    ).copy()
    m = sum(1 for i, v in enumerate(start) if i == 0 or not math.isfinite(v))
    v, S = np.zeros((B, n)), np.zeros((B, n))
    level, level_sig, slope = np.zeros((B, n)), np.zeros((B, n)), np.zeros((B, n))
    ql, qs = float(levels.q_level), float(levels.q_slope)
    for k in range(n):
        if k:
            dt = tt[k] - tt[k - 1]
            F = np.eye(n_state)
            F[0, 1] = dt
            Q = np.zeros((n_state, n_state))
            Q[0, 0] = ql * dt + qs * dt**3 / 3.0
            Q[0, 1] = Q[1, 0] = qs * dt**2 / 2.0
            Q[1, 1] = qs * dt
            x = x @ F.T
            P = F @ P @ F.T + Q
        h = np.zeros(n_state)
        h[0] = 1.0
        if seasonal:
            w = 2.0 * math.pi * tt[k] / SEASON_DAYS
            h[2], h[3] = math.cos(w), math.sin(w)
        Ph = P @ h  # (B, n_state)
        v[:, k] = Y[:, k] - x @ h
        S[:, k] = Ph @ h + Ss[:, k] ** 2
        K = Ph / S[:, k, None]
        x = x + K * v[:, k, None]
        P = P - K[:, :, None] * Ph[:, None, :]
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
        level[:, k], level_sig[:, k], slope[:, k] = x[:, 0], np.sqrt(np.maximum(P[:, 0, 0], 0.0)), x[:, 1]
    return v, S, level, level_sig, slope, m


def fit_process_levels(
    series: Sequence[tuple[ArrayLike, ArrayLike, ArrayLike]],
    seasonal: bool = True,
    learn_start: bool = True,
    gains: Sequence[float] | None = None,
) -> TrendLevels:
    """The levels that maximise the innovations' likelihood (module docstring) summed over
    ``series`` (``(t, y, sigma)`` each: e.g. the years before the ones watched, or the series of
    other cameras that share the process). Each is searched in log space, in units of the median
    calibration variance ``s2``: ``q_level`` between 1e-10 and 1e2 ``s2`` per day, ``q_slope``
    between 1e-18 and 1e2 ``s2`` per day^3; with ``learn_start``, ``slope_var`` between 1e-14 and
    1e-2 ``s2`` per day^2 and ``season_var`` between 1e-8 and 1e4 ``s2`` (otherwise those two stay
    diffuse). ``gains``: per series, the factor its levels have over the common ones (a camera
    given the others, :func:`conditional_series`): the series and its sigma are divided by the
    factor's square root, so the levels returned are the cameras' own."""
    if gains is not None:
        if len(gains) != len(series) or not all(np.isfinite(g) and g > 0 for g in gains):
            raise InputError("gains", list(gains), f"{len(series)} positive factors, one per series")
        series = [
            (t, np.asarray(y, float) / math.sqrt(g), np.asarray(s, float) / math.sqrt(g))
            for (t, y, s), g in zip(series, gains)
        ]
    checked = [_check(*one) for one in series]
    if not checked:
        raise InputError("series", [], "at least one (t, y, sigma) series")
    need = (4 if seasonal else 2) + 3
    if sum(c[0].size for c in checked) < need:
        raise InputError("series length", sum(c[0].size for c in checked), f"at least {need} calibrations")
    scale = float(np.median(np.concatenate([c[2] for c in checked]))) ** 2
    lo = np.log([scale * 1e-10, scale * 1e-18, scale * 1e-14, scale * 1e-8])
    hi = np.log([scale * 1e2, scale * 1e2, scale * 1e-2, scale * 1e4])
    n_par = 2 + (1 + int(seasonal)) * int(learn_start)

    def levels_of(p: Array) -> TrendLevels:
        e = np.exp(np.clip(p, lo[:n_par], hi[:n_par]))
        extra = list(e[2:]) + [math.inf] * (4 - n_par)
        return TrendLevels(float(e[0]), float(e[1]), float(extra[0]), float(extra[1]))

    groups: dict[bytes, list[tuple[Array, Array, Array]]] = {}
    for c in checked:  # series that share their times are filtered together
        groups.setdefault(c[0].tobytes(), []).append(c)
    batches = [(g[0][0], np.stack([c[1] for c in g]), np.stack([c[2] for c in g])) for g in groups.values()]

    def nll(p: Array) -> float:
        lv = levels_of(p)
        total = 0.0
        for tt, Y, Ss in batches:
            v, S, _, _, _, m = _filter(tt, Y, Ss, lv, seasonal, _DIFFUSE)
            total += _log_likelihood(v, S, m)
        return -total

    starts = [
        np.log([scale / 100.0, scale / 1e6, scale * 1e-6, scale * 0.1])[:n_par],
        np.log([scale / 1e4, scale / 1e8, scale * 1e-9, scale * 0.01])[:n_par],
    ]
    opts = {"xatol": 1e-3, "fatol": 1e-4, "maxfev": 400 * n_par}
    fits = [minimize(nll, s0, method="Nelder-Mead", options=opts) for s0 in starts]
    return levels_of(min(fits, key=lambda r: r.fun).x)


def cusum(z: ArrayLike, k: float = 1.5) -> tuple[Array, Array]:
    """The upper and lower CUSUM of the standardised innovations ``z`` (NaN entries are skipped):
    ``C+_i = max(0, C+_{i-1} + z_i - k)``, ``C-_i = max(0, C-_{i-1} - z_i - k)``."""
    zz = np.asarray(z, dtype=float)
    up, dn = np.zeros(zz.size), np.zeros(zz.size)
    cu = cd = 0.0
    for i, zi in enumerate(zz):
        if np.isfinite(zi):
            cu = max(0.0, cu + zi - k)
            cd = max(0.0, cd - zi - k)
        up[i], dn[i] = cu, cd
    return up, dn


@functools.lru_cache(maxsize=256)
def cusum_threshold(n: int, alpha: float = 0.05, k: float = 1.5, draws: int | None = None, seed: int = 0) -> float:
    """The threshold ``h`` at which a two-sided CUSUM over ``n`` independent N(0, 1) values alarms
    with probability ``alpha`` (the (1 - alpha) quantile of its maximum, from ``draws`` simulated
    sequences; default enough for 200 in the tail, at least 20 000)."""
    if draws is None:
        draws = int(max(20000, math.ceil(200.0 / max(float(alpha), 1e-9))))
    if not (0.0 < alpha < 1.0):
        raise InputError("alpha", alpha, "a false-alarm probability in (0, 1)")
    if n < 1:
        raise InputError("n", n, "at least one test")
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((draws, n))
    cu = np.zeros(draws)
    cd = np.zeros(draws)
    best = np.zeros(draws)
    for i in range(n):
        cu = np.maximum(0.0, cu + z[:, i] - k)
        cd = np.maximum(0.0, cd - z[:, i] - k)
        best = np.maximum(best, np.maximum(cu, cd))
    return float(np.quantile(best, 1.0 - alpha))


def monitor_series(
    t: ArrayLike,
    y: ArrayLike,
    sigma: ArrayLike,
    levels: TrendLevels,
    alpha: float = 0.05,
    k: float = 1.5,
    seasonal: bool = True,
    reference: int | None = None,
) -> tuple[FilterResult, ChangeAlarm | None]:
    """Filter the series with ``levels`` and test it, the false-alarm probability ``alpha`` split
    between two tests (three quarters to the first, which must see a step at once), and return
    the first alarm (or None):

    * a **step**: either CUSUM of the standardised innovations crosses its threshold
      (:func:`cusum_threshold`);
    * a **departure**: the filtered level leaves the level at calibration ``reference`` (default:
      the first after the diffuse start, the model the series started from) by more than
      ``z sqrt(P_k + P_ref + q_level dt + q_slope dt^3 / 3)`` (the two estimates' variances and
      the wander the learned process allows in the ``dt`` days between them), ``z`` the
      two-sided normal quantile of ``alpha / 4`` shared by the tests after ``reference``
      (Bonferroni: conservative, the levels are correlated). This sees a slow drift that the
      trend model follows and the innovations hardly show.

    ``ChangeAlarm.statistic``/``threshold`` are the crossing test's (CUSUM in sigmas, or the
    departure in sigmas)."""
    from scipy.stats import norm

    res = kalman_filter(t, y, sigma, levels, seasonal)
    tt = np.atleast_1d(np.asarray(t, dtype=float))
    n_test = tt.size - res.n_diffuse
    if n_test < 1:
        return res, None
    ref = res.n_diffuse if reference is None else int(reference)
    if not res.n_diffuse <= ref < tt.size:
        raise InputError("reference", reference, f"a calibration index in {res.n_diffuse}..{tt.size - 1}")
    h = cusum_threshold(n_test, 0.75 * alpha, k)
    up, dn = cusum(res.z, k)
    step = np.flatnonzero((up > h) | (dn > h))
    looks = tt.size - ref - 1
    zdep = float(norm.isf(alpha / 8 / max(looks, 1)))
    dt = np.abs(tt - tt[ref])
    wander = levels.q_level * dt + levels.q_slope * dt**3 / 3.0
    dep = (res.level - res.level[ref]) / np.sqrt(res.level_sigma**2 + res.level_sigma[ref] ** 2 + wander)
    dep[: ref + 1] = 0.0
    drift = np.flatnonzero(np.abs(dep) > zdep)
    i_step = int(step[0]) if step.size else tt.size
    i_drift = int(drift[0]) if drift.size else tt.size
    if min(i_step, i_drift) >= tt.size:
        return res, None
    i = min(i_step, i_drift)
    before = max(i - 1, 0)
    if i == i_step:
        direction, stat, thr = (1 if up[i] > h else -1), float(max(up[i], dn[i])), h
        run = up if direction > 0 else dn
        zeros = np.flatnonzero(run[:i] == 0.0)
        onset = int(zeros[-1]) + 1 if zeros.size else res.n_diffuse
    else:
        direction, stat, thr = int(np.sign(dep[i])), float(abs(dep[i])), zdep
        onset = i
    return res, ChangeAlarm(
        index=i,
        t=float(tt[i]),
        direction=direction,
        statistic=stat,
        threshold=thr,
        level_before=float(res.level[before]),
        level_sigma_before=float(res.level_sigma[before]),
        kind="step" if i == i_step else "departure",
        onset=onset,
    )


def _scaled(levels: TrendLevels, gain: float) -> TrendLevels:
    return TrendLevels(levels.q_level * gain, levels.q_slope * gain, levels.slope_var * gain, levels.season_var * gain)


def monitor_cameras(
    series: dict[tuple[str, str], tuple[ArrayLike, ArrayLike, ArrayLike]],
    levels: TrendLevels,
    alpha: float = 0.05,
    k: float = 1.5,
    seasonal: bool = True,
    gains: dict[tuple[str, str], float] | None = None,
) -> list[dict[str, object]]:
    """Test every ``(camera, parameter)`` series for a change, with the false-alarm probability
    ``alpha`` shared by all of them (Bonferroni: ``alpha / len(series)`` each), and return the
    alarms, earliest first and, at the same calibration, strongest evidence (statistic over
    threshold) first: ``{"camera", "parameter", "index", "t", "direction", "statistic",
    "threshold", "level_before", "level_sigma_before", "kind", "onset"}`` ("a new camera model is
    needed"). ``gains``: per series, the factor on ``levels`` (:func:`conditional_series`; 1 when
    absent)."""
    if not series:
        raise InputError("series", {}, "at least one (camera, parameter) series")
    each = float(alpha) / len(series)
    out = []
    for (cam, param), (t, y, s) in series.items():
        lv = levels if gains is None else _scaled(levels, float(gains.get((cam, param), 1.0)))
        _, alarm = monitor_series(t, y, s, lv, each, k, seasonal)
        if alarm is not None:
            out.append({"camera": cam, "parameter": param, **alarm.__dict__})
    return sorted(out, key=lambda a: (a["t"], -a["statistic"] / a["threshold"], a["camera"], a["parameter"]))


def conditional_series(
    series: dict[tuple[str, str], tuple[ArrayLike, ArrayLike, ArrayLike]],
    covariances: dict[str, ArrayLike],
    cameras: Sequence[str],
) -> tuple[dict[tuple[str, str], tuple[Array, Array, Array]], dict[tuple[str, str], float]]:
    """Each camera's series given the other cameras' (module docstring), and its gain.

    Parameters
    ----------
    series
        ``(camera, parameter) -> (t (n,), y (n,), sigma (n,))`` for every camera of ``cameras``
        and every parameter of ``covariances``, on the same times.
    covariances
        parameter -> ``(n, C, C)``: the cameras' joint covariance of that parameter at each
        calibration, cameras in the order of ``cameras`` (the same unit squared as ``y``).
    cameras
        The ``C`` cameras (at least two).

    Returns
    -------
    (series, gains)
        The conditional series, ``(t, y', s')`` per ``(camera, parameter)``, and per series the
        factor on the process levels, ``1 + |b|^2`` averaged over the calibrations.
    """
    cams = list(cameras)
    if len(cams) < 2:
        raise InputError("cameras", cams, "at least two cameras (a camera given the others)")
    out: dict[tuple[str, str], tuple[Array, Array, Array]] = {}
    gains: dict[tuple[str, str], float] = {}
    for par, cov in covariances.items():
        try:
            t = np.asarray(series[cams[0], par][0], dtype=float)
            y = np.stack([np.asarray(series[c, par][1], dtype=float) for c in cams], axis=1)
        except KeyError as exc:
            raise InputError("series", exc.args[0], f"a series for every camera of {cams} and {par}") from None
        S = np.asarray(cov, dtype=float)
        if S.shape != (t.size, len(cams), len(cams)) or y.shape != (t.size, len(cams)):
            raise InputError(
                f"covariances[{par!r}]", S.shape, f"({t.size}, {len(cams)}, {len(cams)}) beside series of {t.size}"
            )
        for i, c in enumerate(cams):
            o = [j for j in range(len(cams)) if j != i]
            try:
                b = np.linalg.solve(S[:, o][:, :, o], S[:, o, i][..., None])[..., 0]  # (n, C-1)
            except np.linalg.LinAlgError:
                raise InputError(f"covariances[{par!r}]", "singular", "positive definite covariances") from None
            var = S[:, i, i] - np.einsum("nj,nj->n", S[:, i, o], b)
            if np.any(~np.isfinite(var)) or np.any(var <= 0):
                raise InputError(f"covariances[{par!r}]", "not positive definite", "positive definite covariances")
            out[c, par] = (t, y[:, i] - np.einsum("nj,nj->n", b, y[:, o]), np.sqrt(var))
            gains[c, par] = float(np.mean(1.0 + np.sum(b**2, axis=1)))
    return out, gains
