"""Noise levels learned from adjusted passes: marginal likelihood of the priors, variance
components of the observation classes.

**Priors** (the attitude process per angle, the ephemeris offset and drifts). A pass's adjusted
values ``x_hat`` of a block of variables (one angle's knots, knot-major ``(value rad, rate
rad/s)``; one ephemeris segment's ``(a m/s x y z, b m x y z)``) and their joint marginal
covariance ``P`` hold, in information form, what the data say about the block once everything
else is marginalised: ``D = P^-1 - L0`` and ``d = P^-1 x_hat``, with ``L0`` the precision of the
prior the pass was adjusted with (zero mean). For another prior precision ``L`` the block's
marginal likelihood is, up to a constant,

    log p(data | L) = 1/2 log|L| - 1/2 log|D + L| + 1/2 d^T (D + L)^-1 d,                   (1)

exact for a linear-Gaussian model whatever prior the pass used. The levels maximise (1) summed
over the passes (type-II maximum likelihood, the empirical-Bayes estimate): per angle the
process's sigma and natural frequency ``lam`` (the rate's sigma is ``lam sigma``; the damping
ratio stays as used), and the ephemeris offset sigma (the three axes pooled) and the drift sigma
per axis. The fitted ``lam`` replaces the base's only where the passes reject the base's for a
faster process (for the attitude as a whole at :data:`SHAPE_Z`, then per angle at
:data:`SHAPE_FOLLOW_Z`), which then gets knots dense enough that the spline misses no more of it
than of the jitter (:func:`knot_spacing_for`). Each level's 1 sigma is from the
curvature of the summed (1) at its maximum, in the logarithm of the level (the Laplace
approximation). A level enters the fitted model only when the passes determine it
(:data:`MAX_LOG_SD`) and reject the base model's level (:data:`LEVEL_Z`); otherwise the base
model's stays, and the fit says which and why (``applied``, ``reason``, ``z``). The blocks are
taken one at a time, each with the others' priors as they were (a pass stores each angle's and
each segment's joint covariance, not their cross-covariance).

**Observation classes** (tie points, GCP measurements, GCP positions, DEM heights): a pass's
variance components give each class's sigma0 after any rescaling (:mod:`misrgraph.estimate.adjust`;
the GCP positions' is their priors' rows, a GCP's own and its scene's); the
level is ``k_used * scale * sigma0`` pooled over the passes' classes with their redundancies
``r`` as weights,

    k^2 = sum r (k_used scale sigma0)^2 / sum r,                                            (2)

with 1 sigma the standard error over passes, and never less than ``k / sqrt(2 sum r)`` (all a
single pass gives; two passes' scatter can be small by chance). The DEM's scale is on its stated
sigma only, while its factors' sigma also holds the surface fit's residual: its class gives
``k`` by :func:`~misrgraph.estimate.reliability.class_scale` from the stated sigma's share of the
factors' variance and the scale its pass weighted them with (the pass's own variance components may have moved
it), in place of ``k_used scale sigma0``. As for the priors, a scale
replaces the base's only when the passes reject the base's (:data:`LEVEL_Z`).

What adjusted passes do not carry is not fitted and keeps its level from the base model: the
jitter, the attitude damping ratio, the camera prior and the once-per-revolution term.
:class:`NoiseFit` says which levels were learned and from how many passes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy import optimize

from factors.priors import process_covariance, process_transition
from misrgraph.errors import InputError
from misrgraph.estimate.reliability import class_scale
from misrgraph.model.constants import ANGLES, ARCSEC
from misrgraph.model.errormodels import (
    ATTITUDE_RATE_FACTOR,
    ephemeris_prior_covariance,
    projected_band_covariance,
    unresolved_process_sigma,
)
from misrgraph.model.noise import NoiseModel

__all__ = [
    "PassLevels",
    "NoiseFit",
    "fit_noise_model",
    "knot_prior_precision",
    "log_marginal_likelihood",
    "relative_log_marginal_likelihood",
    "pooled_scale",
    "MAX_LOG_SD",
    "LEVEL_Z",
    "SHAPE_Z",
    "SHAPE_FOLLOW_Z",
    "SPACING_FRACTIONS",
    "knot_spacing_for",
    "spacing_tolerance",
]


@dataclass
class PassLevels:
    """What one adjusted pass tells about the noise levels (read from its RESULT.h5).

    Per angle ``a`` (roll, pitch, yaw): ``knot_times[a]`` ``(n,)`` s, ``knots[a]`` ``(n, 2)``
    value (rad) and rate (rad/s), ``knot_cov[a]`` ``(2n, 2n)`` their joint covariance
    (knot-major). ``ephemeris_boundaries`` ``(S+1,)`` s, ``ephemeris`` ``(S, 6)`` drift (m/s, x y
    z) and offset (m, x y z) per segment, ``ephemeris_cov`` ``(S, 6, 6)``. ``classes``: per
    observation class ``{"kind": "tie"|"gcp"|"gcp_position"|"dem", "factor": scale * sigma0,
    "redundancy": r}``.
    ``used``: the levels the pass was adjusted with (:meth:`NoiseModel.graph_fields` names, and
    ``knot_prior``)."""

    name: str
    knot_times: list[np.ndarray]
    knots: list[np.ndarray]
    knot_cov: list[np.ndarray]
    ephemeris_boundaries: np.ndarray
    ephemeris: np.ndarray
    ephemeris_cov: np.ndarray
    classes: dict[str, dict[str, Any]]
    used: dict[str, Any]


@dataclass
class NoiseFit:
    """A fitted noise model and, per learned level, its estimate, 1 sigma and the passes behind it."""

    model: NoiseModel
    #: "section.field[.axis]" -> {"value", "sigma" (None when not determined), "previous", "passes", "unit"}
    levels: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the sections holding a learned level (the file's ``source``)
    learned_sections: tuple[str, ...] = ()
    passes: list[str] = field(default_factory=list)


def knot_prior_precision(
    times: np.ndarray,
    sigma: float,
    lam: float,
    zeta: float,
    kind: str = "process",
    jitter_cov: np.ndarray | None = None,
) -> np.ndarray:
    """Precision ``(2n, 2n)`` (knot-major ``(value, rate)``) of one angle's knot prior: the damped
    process (:func:`factors.priors.process_prior_factors`); ``kind="process+jitter"``, the
    process's covariance plus ``jitter_cov`` (the jitter projected onto the knots, in ``sigma``'s
    unit squared; :func:`~misrgraph.model.errormodels.projected_band_covariance`); or,
    ``kind="independent"``, each knot ``N(0, diag(sigma^2, (lam sigma)^2))``."""
    t = np.asarray(times, float)
    n = t.size
    first = np.diag([1.0 / sigma**2, 1.0 / (lam * sigma) ** 2])
    if kind == "independent":
        return np.kron(np.eye(n), first)
    if kind == "process+jitter" and jitter_cov is not None:
        return np.linalg.inv(process_covariance(t, sigma, lam, zeta) + jitter_cov)
    out = np.zeros((2 * n, 2 * n))
    out[:2, :2] = first
    blocks: dict[float, np.ndarray] = {}  # one transition per distinct spacing (knots are mostly uniform)
    for k, dt in enumerate(np.diff(t)):
        key = round(float(dt), 9)
        if key not in blocks:
            phi, q = process_transition(float(dt), sigma, lam, zeta)
            a = np.hstack([-phi, np.eye(2)])
            blocks[key] = a.T @ np.linalg.solve(q, a)
        out[2 * k : 2 * k + 4, 2 * k : 2 * k + 4] += blocks[key]
    return out


def _logdet(m: np.ndarray) -> float:
    sign, val = np.linalg.slogdet(m)
    return float(val) if sign > 0 else -np.inf


def log_marginal_likelihood(data_info: np.ndarray, data_vec: np.ndarray, prior_precision: np.ndarray) -> float:
    """Eq. (1): the block's log marginal likelihood under a zero-mean prior of the given precision,
    from the data's information ``D`` and vector ``d`` (up to a constant)."""
    a = data_info + prior_precision
    ld = _logdet(a)
    if not np.isfinite(ld):
        return -np.inf
    return 0.5 * _logdet(prior_precision) - 0.5 * ld + 0.5 * float(data_vec @ np.linalg.solve(a, data_vec))


def relative_log_marginal_likelihood(
    data_info: np.ndarray, data_vec: np.ndarray, x0: np.ndarray, prior0: np.ndarray, prior_precision: np.ndarray
) -> float:
    """Eq. (1) less its value at the prior ``prior0`` the block was adjusted with (``x0`` its
    estimate then), in a form that keeps its precision when the data's information is large:
    ``d^T (D + L)^-1 d - d^T (D + L0)^-1 d = -x(L)^T (L - L0) x0`` with ``x(L) = (D + L)^-1 d``."""
    a = data_info + prior_precision
    ld = _logdet(a)
    if not np.isfinite(ld):
        return -np.inf
    x = np.linalg.solve(a, data_vec)
    quad = -float(x @ (prior_precision - prior0) @ x0)
    at0 = 0.5 * _logdet(prior0) - 0.5 * _logdet(data_info + prior0)
    return 0.5 * _logdet(prior_precision) - 0.5 * ld + 0.5 * quad - at0


def _data_terms(x: np.ndarray, cov: np.ndarray, prior0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``D = P^-1 - L0`` and ``d = P^-1 x`` of a block (in units scaled to order 1)."""
    p_inv = np.linalg.inv(0.5 * (cov + cov.T))
    return p_inv - prior0, p_inv @ x


def _maximise(
    objective: Callable[[np.ndarray], float], start: np.ndarray, bounds: list[tuple[float, float]]
) -> tuple[np.ndarray, np.ndarray | None]:
    """Maximise ``objective`` over log-levels; the maximum and the covariance of the log-levels
    from the curvature there: an infinite variance for a level that ended at its bound (e.g. a
    sigma driven to zero) or whose curvature alone leaves it undetermined, the inverse curvature
    of the others; None when that is not negative definite."""
    res = optimize.minimize(lambda th: -objective(th), start, method="L-BFGS-B", bounds=bounds)
    th = res.x
    lo, hi = np.array(bounds).T
    at_bound = (th - lo < 1e-3) | (hi - th < 1e-3)
    n, h = th.size, 1e-3
    hess = np.zeros((n, n))
    f0 = objective(th)
    for i in range(n):
        for j in range(i, n):
            ei, ej = np.eye(n)[i] * h, np.eye(n)[j] * h
            if i == j:
                v = (objective(th + ei) - 2 * f0 + objective(th - ei)) / h**2
            else:
                v = (
                    objective(th + ei + ej)
                    - objective(th + ei - ej)
                    - objective(th - ei + ej)
                    + objective(th - ei - ej)
                ) / (4 * h * h)
            hess[i, j] = hess[j, i] = v
    # a level at its bound, or one whose own curvature is too flat to determine it (its log's
    # sd above MAX_LOG_SD even with the others held), is left out: infinite variance. The others'
    # covariance is the inverse of their block of the curvature (the Laplace approximation with
    # the left-out levels held at the maximum).
    flat = at_bound | ~(-np.diag(hess) > 1.0 / MAX_LOG_SD**2)
    keep = np.flatnonzero(~flat)
    cov = np.full((n, n), 0.0)
    cov[flat, flat] = np.inf
    if keep.size:
        try:
            sub = np.linalg.inv(-hess[np.ix_(keep, keep)])
        except np.linalg.LinAlgError:
            return th, None
        if not np.all(np.linalg.eigvalsh(0.5 * (sub + sub.T)) > 0):
            return th, None
        cov[np.ix_(keep, keep)] = sub
    return th, cov


def _mean_and_se(per_pass: list[float]) -> tuple[float, float]:
    x = np.asarray(per_pass, float)
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(x.size))


def pooled_scale(factors: list[float], redundancies: list[float]) -> tuple[float, float]:
    """Eq. (2) for one pass's classes: the pooled factor and its 1 sigma ``k / sqrt(2 sum r)``."""
    f = np.asarray(factors, float)
    r = np.asarray(redundancies, float)
    k = float(np.sqrt(np.sum(r * f**2) / np.sum(r)))
    return k, float(k / np.sqrt(2.0 * np.sum(r)))


#: a prior level enters the fitted model only when the passes determine it: the standard deviation
#: of its logarithm (from the likelihood's curvature) below this, i.e. known to better than a factor
#: of ~1.65; otherwise the base model's level stays (a level at a bound, or one pass's single
#: ephemeris segment, cannot say how wide a prior should be)
MAX_LOG_SD = 0.5


def _determined(cov: np.ndarray | None, i: int) -> bool:
    return cov is not None and bool(np.isfinite(cov[i, i]) and np.sqrt(cov[i, i]) < MAX_LOG_SD)


#: a determined level replaces the base model's only when the passes reject the base's: its log
#: more than this many standard deviations from the base's (two-sided 5 %). Within that the
#: documented pre-flight level (or the file's stated sigma, scale 1) stays: a loosely determined
#: maximum-likelihood sigma from a few passes scatters, and low more often than high (the
#: ephemeris offset from two passes: 27 +- 11 m where the truth is 50 m), and an under-stated
#: prior makes every covariance of the pass over-confident
LEVEL_Z = 1.96


def _z(value: float, base: float, log_sd: float | None) -> float | None:
    """``log(value / base)`` in standard deviations of the log (None without a finite sd)."""
    if log_sd is None or not (np.isfinite(log_sd) and log_sd > 0) or not (value > 0 and base > 0):
        return None
    return float(np.log(value / base) / log_sd)


def _level(
    levels: dict[str, dict[str, Any]],
    name: str,
    value: float,
    sigma: float | None,
    previous: Any,
    n: int,
    unit: str,
    determined: bool = True,
    base: float | None = None,
) -> bool:
    """Record a learned level; with ``base`` (the base model's level) it is applied only when
    ``determined`` and its z against ``base`` (:data:`LEVEL_Z`) rejects the base. Returns whether it
    is applied."""
    z = _z(value, base, (sigma / value) if sigma is not None and value > 0 else None) if base is not None else None
    if not determined:
        applied, reason = False, "not determined"
    elif base is not None and (z is None or abs(z) <= LEVEL_Z):
        applied, reason = False, "agrees with the base"
    else:
        applied, reason = True, "learned"
    levels[name] = {
        "value": float(value),
        "sigma": sigma,
        "previous": previous,
        "passes": n,
        "unit": unit,
        "applied": applied,
        "reason": reason,
        "z": z,
    }
    return applied


def _sd(cov: np.ndarray | None, i: int, value: float) -> float | None:
    """1 sigma of a level from its log's variance (None when not determined)."""
    return None if cov is None or not np.isfinite(cov[i, i]) else float(value * np.sqrt(cov[i, i]))


#: the attitude process's fitted shape replaces the base's (``learn_attitude_shape`` None) when
#: the passes reject the base's natural frequency for a higher one: the fitted log more than this
#: many standard deviations above the base's (0.05 % one-sided). A few passes' fitted shape within
#: that makes the knots over-confident (``misrgraph bench worlds``); a slower process than the
#: base's is not applied: its prior would hold the knots' rates tighter than the jitter's share in
#: them (:func:`~misrgraph.model.errormodels.projected_band_covariance`)
SHAPE_Z = 3.29

#: once some angle's shape rejects the base's (:data:`SHAPE_Z`), the base's shape no longer holds
#: for the attitude process, and each other angle's fitted shape replaces the base's when its own
#: z is above this (2.5 % one-sided): a gatekeeping test, the strict level guarding the family
#: (``misrgraph bench worlds``, the attitude band 30-300 s world: yaw's z near 2.3 while roll's and
#: pitch's are above 5; yaw on the base's shape leaves the passes' knots over-confident)
SHAPE_FOLLOW_Z = 1.96

#: the knot spacings (as fractions of the base's) tried, longest first, for a process faster than
#: the base's (:func:`knot_spacing_for`)
SPACING_FRACTIONS = (1.0, 0.75, 0.5, 1.0 / 3.0, 0.25, 1.0 / 6.0)


def _missed(spacing_s: float, span_s: float, sigma_arcsec: float, lam: float, zeta: float) -> float:
    """What knots every ``spacing_s`` over ``span_s`` (s) miss of an attitude process (arcsec,
    :func:`~misrgraph.model.errormodels.unresolved_process_sigma`)."""
    return unresolved_process_sigma(np.arange(0.0, span_s + 0.5 * spacing_s, spacing_s), sigma_arcsec, lam, zeta)


def knot_spacing_for(
    sigma_arcsec: float, lam: float, zeta: float, base_spacing_s: float, tolerance_arcsec: float
) -> float:
    """The longest of :data:`SPACING_FRACTIONS` of ``base_spacing_s`` (s) on which the spline misses
    no more than ``tolerance_arcsec`` of an attitude process (1 sigma ``sigma_arcsec``, natural
    frequency ``lam`` 1/s, damping ``zeta``; :func:`~misrgraph.model.errormodels.unresolved_process_sigma`
    over twenty base spacings), else the shortest."""
    span = 20.0 * base_spacing_s
    for f in SPACING_FRACTIONS:
        h = base_spacing_s * f
        if _missed(h, span, sigma_arcsec, lam, zeta) <= tolerance_arcsec:
            return float(h)
    return float(base_spacing_s * SPACING_FRACTIONS[-1])


def spacing_tolerance(model: NoiseModel) -> float:
    """What knots for a faster process may miss of it (arcsec, :func:`knot_spacing_for`): the
    larger of the model's jitter sigma and what the model's own knots miss of its own process (the
    worst angle, over twenty of its spacings)."""
    a = model.attitude
    own = max(
        _missed(h, 20.0 * h, v, r / v, float(a.damping))
        for h, v, r in zip(a.knot_spacing_s, a.value_sigma_arcsec, a.rate_sigmas())
    )
    return max(float(model.jitter.sigma_arcsec), own)


def _attitude_blocks(passes: list[PassLevels], base: NoiseModel, a: int) -> list[tuple]:
    """One angle's knot blocks of the passes for eq. (1), in arcsec and arcsec/s (entries of order
    1): ``(times, D, d, damping, (prior kind, the jitter's covariance or None), x_hat, L0)`` per pass
    with at least two knots."""
    blocks = []
    for p in passes:
        if p.knots[a].shape[0] < 2:
            continue
        u = p.used
        s0 = float(u.get("attitude_sigma_arcsec", base.attitude.value_sigma_arcsec)[a]) * ARCSEC
        rates = u.get("attitude_rate_sigma_arcsec_per_s") or ()
        lam0 = float(rates[a]) * ARCSEC / s0 if len(rates) else ATTITUDE_RATE_FACTOR
        zeta = float(u.get("knot_prior_damping", base.attitude.damping))
        kind = str(u.get("knot_prior", "process"))
        jitter = None
        if kind == "process+jitter":  # the jitter's share of the knots, as the pass's graph held it
            jit = float(u.get("attitude_jitter_arcsec", base.jitter.sigma_arcsec))
            periods = tuple(u.get("attitude_jitter_periods_s", base.jitter.periods_s))
            jitter = projected_band_covariance(p.knot_times[a], jit, periods) if jit > 0 else None
        x = p.knots[a].reshape(-1) / ARCSEC
        cov = p.knot_cov[a] / ARCSEC**2
        prior0 = knot_prior_precision(p.knot_times[a], s0 / ARCSEC, lam0, zeta, kind, jitter)
        d_info, d_vec = _data_terms(x, cov, prior0)
        blocks.append((p.knot_times[a], d_info, d_vec, zeta, (kind, jitter), x, prior0))
    return blocks


def _shape_applied(shape_z: list[float | None], learn_shape: bool | None, determined: list[bool]) -> list[bool]:
    """Per angle, whether the fitted natural frequency replaces the base's (module docstring):
    ``learn_shape`` True applies every determined one and False none; None (the default) applies an
    angle's when the passes reject the base's for a faster process, for the attitude as a whole at
    :data:`SHAPE_Z` (some angle's z above it) and then for each angle at :data:`SHAPE_FOLLOW_Z`."""
    if learn_shape is not None:
        return [bool(learn_shape) and d for d in determined]
    z = [v if v is not None else -np.inf for v in shape_z]
    if max(z) <= SHAPE_Z:
        return [False] * len(z)
    return [v > SHAPE_FOLLOW_Z for v in z]


def _fit_attitude(passes: list[PassLevels], base: NoiseModel, levels: dict, learn_shape: bool | None = None) -> Any:
    value_sig = list(base.attitude.value_sigma_arcsec)
    rate_sig = list(base.attitude.rate_sigmas())
    spacing = [float(x) for x in base.attitude.knot_spacing_s]
    base_spacing = list(spacing)
    zeta_base = float(base.attitude.damping)
    tolerance = spacing_tolerance(base)
    fits: dict[int, tuple] = {}  # angle -> (sigma, lam, log-levels' covariance, passes, base lam, shape z)
    for a in range(len(ANGLES)):
        blocks = _attitude_blocks(passes, base, a)
        if not blocks:
            continue

        def objective(th: np.ndarray, blocks=blocks) -> float:
            sig, lam = np.exp(th)
            return sum(
                relative_log_marginal_likelihood(d, v, x0, l0, knot_prior_precision(t, sig, lam, z, *k))
                for t, d, v, z, k, x0, l0 in blocks
            )

        start = np.log([value_sig[a], rate_sig[a] / value_sig[a]])
        th, cov = _maximise(objective, start, [(np.log(0.01), np.log(1e4)), (np.log(1e-5), np.log(1.0))])
        base_lam = rate_sig[a] / value_sig[a]
        # the fitted natural frequency against the base's, in standard deviations of its log
        shape_z = (
            float((th[1] - np.log(base_lam)) / np.sqrt(cov[1, 1]))
            if cov is not None and np.isfinite(cov[1, 1]) and cov[1, 1] > 0
            else None
        )
        fits[a] = (*np.exp(th), cov, len(blocks), base_lam, shape_z)
    fitted = sorted(fits)
    applied = dict(
        zip(
            fitted,
            _shape_applied([fits[a][5] for a in fitted], learn_shape, [_determined(fits[a][2], 1) for a in fitted]),
        )
    )
    for a in fitted:
        ang = ANGLES[a]
        sig, lam, cov, n_passes, base_lam, shape_z = fits[a]
        if _level(
            levels,
            f"attitude.value_sigma_arcsec.{ang}",
            sig,
            _sd(cov, 0, sig),
            float(passes[0].used.get("attitude_sigma_arcsec", base.attitude.value_sigma_arcsec)[a]),
            n_passes,
            "arcsec",
            _determined(cov, 0),
            value_sig[a],
        ):
            value_sig[a] = float(sig)
        shape = applied[a]
        rate_sig[a] = float(value_sig[a] * (lam if shape else base_lam))
        if shape and lam > base_lam:
            spacing[a] = min(
                base_spacing[a], knot_spacing_for(value_sig[a], float(lam), zeta_base, base_spacing[a], tolerance)
            )
        rate_sd = (
            None
            if cov is None or not np.all(np.isfinite(cov))
            else float(sig * lam * np.sqrt(cov[0, 0] + cov[1, 1] + 2 * cov[0, 1]))
        )
        _level(
            levels,
            f"attitude.rate_sigma_arcsec_per_s.{ang}",
            sig * lam,
            rate_sd,
            None,
            n_passes,
            "arcsec/s",
            shape,
        )
        levels[f"attitude.rate_sigma_arcsec_per_s.{ang}"]["shape_z"] = shape_z
        if not shape:
            levels[f"attitude.rate_sigma_arcsec_per_s.{ang}"]["reason"] = "the base's shape"
        if spacing[a] != base_spacing[a]:
            _level(levels, f"attitude.knot_spacing_s.{ang}", spacing[a], None, base_spacing[a], n_passes, "s")
    return base.attitude.replace(
        value_sigma_arcsec=tuple(value_sig), rate_sigma_arcsec_per_s=tuple(rate_sig), knot_spacing_s=tuple(spacing)
    )


def _fit_ephemeris(passes: list[PassLevels], base: NoiseModel, levels: dict) -> Any:
    e = base.ephemeris
    blocks = []
    for p in passes:
        u = p.used
        a0 = np.broadcast_to(np.asarray(u.get("ephemeris_a_sigma_mps", e.drift_sigma_mps), float), (3,))
        b0 = float(u.get("ephemeris_b_sigma_m", e.offset_sigma_m))
        amp = float(u.get("ephemeris_once_per_rev_m", e.once_per_rev_m))
        edges = np.asarray(p.ephemeris_boundaries, float)
        for s in range(p.ephemeris.shape[0]):
            seg = edges[s : s + 2] if amp > 0 else np.array([0.0, 1.0])
            prior0 = np.linalg.inv(ephemeris_prior_covariance(seg, a0, b0, amp))
            d_info, d_vec = _data_terms(p.ephemeris[s], p.ephemeris_cov[s], prior0)
            blocks.append((seg, amp, d_info, d_vec, p.ephemeris[s], prior0))

    def objective(th: np.ndarray) -> float:
        b, a = np.exp(th[0]), np.exp(th[1:])
        return sum(
            relative_log_marginal_likelihood(d, v, x0, l0, np.linalg.inv(ephemeris_prior_covariance(seg, a, b, amp)))
            for seg, amp, d, v, x0, l0 in blocks
        )

    start = np.log([e.offset_sigma_m, *np.broadcast_to(np.asarray(e.drift_sigma_mps, float), (3,))])
    th, cov = _maximise(objective, start, [(np.log(0.01), np.log(1e5))] + [(np.log(1e-6), np.log(10.0))] * 3)
    b, a = float(np.exp(th[0])), np.exp(th[1:])
    n = len(passes)
    prev_b = float(passes[0].used.get("ephemeris_b_sigma_m", e.offset_sigma_m))
    offset_ok = _level(
        levels, "ephemeris.offset_sigma_m", b, _sd(cov, 0, b), prev_b, n, "m", _determined(cov, 0), e.offset_sigma_m
    )
    base_a = np.broadcast_to(np.asarray(e.drift_sigma_mps, float), (3,))
    drift = []
    for i, axis in enumerate(("along", "cross", "radial")):
        ok = _level(
            levels,
            f"ephemeris.drift_sigma_mps.{axis}",
            a[i],
            _sd(cov, 1 + i, float(a[i])),
            None,
            n,
            "m/s",
            _determined(cov, 1 + i),
            float(base_a[i]),
        )
        drift.append(float(a[i]) if ok else float(base_a[i]))
    return e.replace(offset_sigma_m=b if offset_ok else e.offset_sigma_m, drift_sigma_mps=tuple(drift))


def fit_noise_model(
    passes: list[PassLevels], base: NoiseModel | None = None, learn_attitude_shape: bool | None = None
) -> NoiseFit:
    """The noise model learned from adjusted passes (module docstring); levels the passes do not
    carry keep ``base``'s (default: the pre-flight model).

    The attitude process's shape (its natural frequency, i.e. the rate's sigma over the value's)
    is estimated and reported; per angle it replaces the base's only when the passes reject the
    base's for a faster one (``learn_attitude_shape`` None, the default: :data:`SHAPE_Z` for some
    angle, then :data:`SHAPE_FOLLOW_Z` for each), always (True) or never (False). Otherwise the
    rate follows the learned value sigma with the base's shape: a few passes' fitted shape, close
    to the base's, makes the knots over-confident (``misrgraph bench worlds`` measures it). A
    learned process faster than the base's also gets denser knots (:func:`knot_spacing_for`: the
    spline misses no more of it than of the jitter).

    Raises
    ------
    InputError
        With no pass.
    """
    if not passes:
        raise InputError("RESULTS", 0, "at least one adjusted pass (RESULT.h5 of 'misrgraph adjust --out')")
    base = base or NoiseModel()
    levels: dict[str, dict[str, Any]] = {}
    attitude = _fit_attitude(passes, base, levels, learn_attitude_shape)
    ephemeris = _fit_ephemeris(passes, base, levels)

    # observation classes and the DEM: eq. (2)
    scales: dict[str, float] = {}
    for kind, section, fname, used_key in (
        ("tie", "observations", "tie_sigma_scale", "tie_sigma_scale"),
        ("gcp", "observations", "gcp_pixel_sigma_scale", "gcp_pixel_sigma_scale"),
        ("gcp_position", "observations", "gcp_sigma_scale", "gcp_sigma_scale"),
        ("dem", "dem", "sigma_scale", "dem_sigma_scale"),
    ):
        per_pass, r_all, f_all, amp_all = [], [], [], []
        for p in passes:
            cls = [c for c in p.classes.values() if c["kind"] == kind and c["redundancy"] > 0]
            if not cls:
                continue
            used = float(p.used.get(used_key, 1.0))
            f, amp = zip(
                *(class_scale(used * c.get("scale", 1.0), c["factor"], c.get("stated_share", 1.0)) for c in cls)
            )
            r = [c["redundancy"] for c in cls]
            k, _ = pooled_scale(list(f), r)
            per_pass.append(k**2)
            r_all += r
            f_all += f
            amp_all += amp
        if not per_pass:
            continue
        k, sk = pooled_scale(f_all, r_all)
        sk *= float(np.average(amp_all, weights=r_all))  # the share the scale moves
        if len(per_pass) >= 2:  # the passes' scatter, unless smaller than the redundancy allows (few passes)
            m2, se2 = _mean_and_se(per_pass)
            k, sk = float(np.sqrt(m2)), max(float(se2 / (2 * np.sqrt(m2))), sk)
        base_k = float(getattr(base.dem if section == "dem" else base.observations, fname))
        if _level(
            levels,
            f"{section}.{fname}",
            k,
            sk,
            float(passes[0].used.get(used_key, 1.0)),
            len(per_pass),
            "1",
            True,
            base_k,
        ):
            scales[fname] = k
    observations = base.observations.replace(
        **{k: v for k, v in scales.items() if k in ("tie_sigma_scale", "gcp_pixel_sigma_scale", "gcp_sigma_scale")}
    )
    dem = base.dem.replace(sigma_scale=scales["sigma_scale"]) if "sigma_scale" in scales else base.dem
    model = base.replace(attitude=attitude, ephemeris=ephemeris, observations=observations, dem=dem)
    sections = {name.split(".")[0] for name, v in levels.items() if v["applied"]}
    return NoiseFit(
        model=model, levels=levels, learned_sections=tuple(sorted(sections)), passes=[p.name for p in passes]
    )
