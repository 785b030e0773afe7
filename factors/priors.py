"""Prior factors: GCP position (eq. 32), alone or sharing a source scene's error; a-priori values
of knots, ephemeris and camera; and the attitude error process's prior between consecutive knots.

These are GTSAM's own C++ factors (no Python callback): ``PriorFactorVector`` and, for the
process prior, a ``LinearContainerFactor`` holding a whitened ``JacobianFactor``. The GCP prior's
noise is 30 m per ENU axis rotated to ECEF as a full covariance: ``C = R diag(s^2) R^T`` with
``R`` the ENU basis at the GCP (:func:`factors.geometry.enu_covariance`).

GCPs from one source scene share the scene's registration error ``o`` (ECEF m, a variable per
scene, prior ``N(0, C_s)`` with ``C_s`` the shared sigma per ENU axis): each GCP's prior is then
``P - (P_GCP + o) ~ N(0, C_own)``, ``C_own = C - C_s``. Marginalising ``o`` gives back ``C`` for
each GCP and ``C_s`` between any two GCPs of the scene, the catalogue's joint distribution. It is
linear in ``(P, o)``, a ``LinearContainerFactor``.

The attitude process prior. Each angle's error ``e(t)`` (rad) is modelled as a stationary
second-order Gauss-Markov process (a damped oscillator driven by white noise): its state
``x = (value, rate)`` obeys ``dx = F x dt + L dw`` with ``F = [[0, 1], [-lam^2, -2 zeta lam]]``.
Its value has variance ``sigma^2`` and its rate ``(lam sigma)^2`` whatever the damping ratio
``zeta`` -- the two moments the navigation accuracy gives; ``zeta`` shapes the spectrum: 1 is the
critically damped Matern-3/2 process, covariance ``C(tau) = sigma^2 (1 + lam |tau|) exp(-lam |tau|)``;
below 1 the power concentrates near ``lam`` and the low frequencies carry less (the spectral density
at zero is proportional to ``zeta``), as for an error that varies on the scale of hundreds of
seconds with no long-term offset. Over a knot spacing ``T``

    x_{k+1} = Phi(T) x_k + w_k,   Phi(T) = expm(F T),
    w_k ~ N(0, Q(T)),            Q(T) = P - Phi P Phi^T,   P = diag(sigma^2, lam^2 sigma^2),

exactly (P is the stationary covariance). A prior ``N(0, P)`` on the first knot and one factor
``x_{k+1} - Phi x_k ~ N(0, Q)`` per pair give the knots their exact joint distribution under the
process: every knot's marginal is ``P`` however long the data gap, and the a-posteriori sigma can
never exceed it.
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import expm

__all__ = [
    "gcp_prior",
    "gcp_scene_prior",
    "scene_offset_prior",
    "vector_prior",
    "process_transition",
    "process_prior_factors",
    "process_covariance",
    "linear_factor",
    "joint_prior_factor",
]


def gcp_prior(key: int, position_ecef: ArrayLike, covariance: ArrayLike) -> gtsam.PriorFactorVector:
    """Eq. 32: ``P_GCP - P = 0`` with a full ECEF covariance (m^2)."""
    return gtsam.PriorFactorVector(
        key,
        np.asarray(position_ecef, dtype=float),
        gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, dtype=float)),
    )


def gcp_scene_prior(
    key: int, scene_key: int, position_ecef: ArrayLike, own_covariance: ArrayLike
) -> gtsam.LinearContainerFactor:
    """A GCP of a source scene (module docstring): ``P - o - P_GCP ~ N(0, C_own)`` on the GCP's
    position ``P`` and its scene's offset ``o`` (both ECEF m); ``own_covariance`` (3, 3) m^2."""
    eye = np.eye(3)
    return linear_factor([key, scene_key], [eye, -eye], np.asarray(position_ecef, dtype=float), own_covariance)


def scene_offset_prior(scene_key: int, covariance: ArrayLike) -> gtsam.PriorFactorVector:
    """A source scene's shared GCP error ``o ~ N(0, C_s)`` (ECEF m; ``covariance`` (3, 3) m^2)."""
    return gtsam.PriorFactorVector(
        scene_key, np.zeros(3), gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, dtype=float))
    )


def vector_prior(key: int, mean: ArrayLike, sigmas: ArrayLike) -> gtsam.PriorFactorVector:
    """Independent Gaussian prior on a vector variable (knot, ephemeris segment, camera)."""
    m = np.asarray(mean, dtype=float)
    return gtsam.PriorFactorVector(
        key, m, gtsam.noiseModel.Diagonal.Sigmas(np.broadcast_to(np.asarray(sigmas, float), m.shape).copy())
    )


def process_transition(dt: float, sigma: float, lam: float, zeta: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(Phi, Q)`` (2x2 each) of the process state ``(value, rate)`` over ``dt`` s (module
    docstring): ``x(t + dt) = Phi x(t) + w``, ``w ~ N(0, Q)``; ``sigma`` in the value's unit,
    ``lam`` in 1/s (the rate's sigma is ``lam sigma`` per s), ``zeta`` the damping ratio (1:
    Matern-3/2, in closed form; otherwise the matrix exponential)."""
    if not (dt > 0 and sigma > 0 and lam > 0 and zeta > 0):
        raise ValueError(f"process_transition needs dt, sigma, lam, zeta > 0, got {dt}, {sigma}, {lam}, {zeta}")
    if zeta == 1.0:
        e = np.exp(-lam * dt)
        phi = e * np.array([[1.0 + lam * dt, dt], [-lam * lam * dt, 1.0 - lam * dt]])
    else:
        phi = expm(np.array([[0.0, 1.0], [-lam * lam, -2.0 * zeta * lam]]) * dt)
    p = np.diag([sigma**2, (lam * sigma) ** 2])
    q = p - phi @ p @ phi.T
    return phi, 0.5 * (q + q.T)


def process_covariance(times: ArrayLike, sigma: float, lam: float, zeta: float = 1.0) -> np.ndarray:
    """Joint covariance ``(2n, 2n)`` (knot-major ``(value, rate)``) of the process's state at
    increasing ``times`` (s): ``Cov(x_j, x_i) = Phi(t_j - t_i) P`` for ``t_j >= t_i`` (module
    docstring), the distribution :func:`process_prior_factors` encode, in covariance form."""
    t = np.asarray(times, dtype=float)
    if t.size == 0 or np.any(np.diff(t) <= 0):
        raise ValueError(f"process_covariance needs increasing times, got {t.size} times")
    n = t.size
    p = np.diag([sigma**2, (lam * sigma) ** 2])
    cache: dict[float, np.ndarray] = {}  # one transition per distinct spacing (knots are mostly uniform)
    phis = []
    for dt in np.diff(t):
        key = round(float(dt), 9)
        if key not in cache:
            cache[key] = process_transition(float(dt), sigma, lam, zeta)[0]
        phis.append(cache[key])
    out = np.zeros((2 * n, 2 * n))
    for i in range(n):
        m = p
        out[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = p
        for j in range(i + 1, n):
            m = phis[j - 1] @ m
            out[2 * j : 2 * j + 2, 2 * i : 2 * i + 2] = m
            out[2 * i : 2 * i + 2, 2 * j : 2 * j + 2] = m.T
    return out


def linear_factor(
    keys: list[int], blocks: list[np.ndarray], rhs: ArrayLike, covariance: ArrayLike
) -> gtsam.LinearContainerFactor:
    """The linear Gaussian factor ``sum_k A_k x_k - b ~ N(0, C)`` on vector variables, as GTSAM's
    C++ ``LinearContainerFactor`` (linearisation point zero, so its error is exactly this)."""
    c = np.asarray(covariance, dtype=float)
    d = np.sqrt(np.diag(c))  # in correlation form first: the blocks may mix units (m, m/s)
    r = np.linalg.cholesky(np.linalg.inv(c / np.outer(d, d))).T / d  # R^T R = C^-1
    args: list = []
    zero = gtsam.Values()
    for k, a in zip(keys, blocks):
        a = np.asarray(a, dtype=float)
        args += [int(k), r @ a]
        zero.insert(int(k), np.zeros(a.shape[1]))
    jf = gtsam.JacobianFactor(*args, r @ np.asarray(rhs, dtype=float), gtsam.noiseModel.Unit.Create(r.shape[0]))
    return gtsam.LinearContainerFactor(jf, zero)


def joint_prior_factor(keys: list[int], dims: list[int], covariance: ArrayLike) -> gtsam.LinearContainerFactor:
    """``x ~ N(0, C)`` for the stacked vector variables ``keys`` (``dims`` each, ``C`` ``(sum dims,)``
    square, in the variables' units), as one GTSAM linear factor on any number of keys (the wrapped
    ``JacobianFactor`` constructors take at most three): the information ``C^-1`` split into one
    ``HessianFactor`` per block on and above the diagonal, summed into one dense
    ``HessianFactor`` (the parts need not be positive definite, their sum is), in a
    ``LinearContainerFactor`` linearised at zero. Its error is ``0.5 x^T C^-1 x``."""
    c = np.asarray(covariance, dtype=float)
    n = int(sum(dims))
    if c.shape != (n, n) or len(keys) != len(dims):
        raise ValueError(f"joint_prior_factor: covariance {c.shape} for {len(keys)} keys of total dimension {n}")
    d = np.sqrt(np.diag(c))
    info = np.linalg.inv(c / np.outer(d, d)) / np.outer(d, d)  # in correlation form first: units may differ
    off = np.concatenate([[0], np.cumsum(dims)]).astype(int)
    parts = gtsam.GaussianFactorGraph()
    zero = gtsam.Values()
    for i, (ki, di) in enumerate(zip(keys, dims)):
        zero.insert(int(ki), np.zeros(di))
        bi = slice(off[i], off[i + 1])
        parts.push_back(gtsam.HessianFactor(int(ki), info[bi, bi], np.zeros(di), 0.0))
        for j in range(i + 1, len(keys)):
            bj = slice(off[j], off[j + 1])
            parts.push_back(
                gtsam.HessianFactor(
                    int(ki),
                    int(keys[j]),
                    np.zeros((di, di)),
                    info[bi, bj],
                    np.zeros(di),
                    np.zeros((dims[j], dims[j])),
                    np.zeros(dims[j]),
                    0.0,
                )
            )
    return gtsam.LinearContainerFactor(gtsam.HessianFactor(parts), zero)


def process_prior_factors(keys: list[int], times: ArrayLike, sigma: float, lam: float, zeta: float = 1.0) -> list:
    """The process prior of one angle's knots ``(value, rate)`` at increasing ``times`` (s), damping
    ratio ``zeta``: ``N(0, diag(sigma^2, (lam sigma)^2))`` on the first knot and
    ``x_{k+1} - Phi x_k ~ N(0, Q)`` between consecutive knots (module docstring)."""
    t = np.asarray(times, dtype=float)
    if t.size != len(keys) or t.size == 0 or np.any(np.diff(t) <= 0):
        raise ValueError(
            f"process_prior_factors needs one increasing time per key, got {t.size} times for {len(keys)} keys"
        )
    out: list = [vector_prior(keys[0], np.zeros(2), [sigma, lam * sigma])]
    for k0, k1, dt in zip(keys[:-1], keys[1:], np.diff(t)):
        phi, q = process_transition(float(dt), sigma, lam, zeta)
        out.append(linear_factor([k0, k1], [-phi, np.eye(2)], np.zeros(2), q))
    return out
