"""Pushbroom collinearity factors (eqs. 14 and 30), vectorised over observations.

Model for one observation of landmark ``G`` (ECEF m) by camera ``c`` at exposure time ``t``:

    u   = T_go^T (E^T G - P_meas) + D theta            orbital frame, m (eq. 19: P = P_meas - T_go e)
    A   = A_meas - W . knots                           roll, pitch, yaw, rad (eqs. 22-27)
    v   = M^T T_os(A)^T u,   M = T_si(omega) Ry(beta) Rx(delta) Rz(eps)     detector frame
    xi  = f v_x / v_z,  eta = f v_y / v_z              focal-plane projection, m
    r   = [ (xi - x_obs) / a_s,  (eta - y_obs) / c_s ]  image lines and samples (pixels)

with ``x_obs = -(k + (l - L) dx)`` and ``y_obs = f sum_i alpha_i (s - c_y)^i`` (eq. 2), ``E`` the
ECI->ECEF matrix at ``t``, ``P_meas, T_go, A_meas`` the supplied navigation at ``t``, ``D`` the
ephemeris design ``[(t - t_s) I, I]`` and ``W`` the Hermite weights of the bracketing knots.
``c_s`` is the supplied model's cross-track pitch ``dy/ds`` at the observed sample and ``a_s =
dx * rate`` the along-track focal-plane motion per image line (``rate`` ~1 for An, ~1.1 for the A
cameras, ~0.4 for the D cameras, from the supplied geometry): constant scales, so the residual is
in the image lines and samples a matcher measures and is exactly zero where the prediction matches.
A matched observation has ``l = L`` (a continuous exposure index, focal-plane fraction 0).

Camera parameters per observation are the 10-vector :data:`CAMERA_PARAMS`
``(delta, beta, eps, f, alpha_0..alpha_5)`` plus the common ``omega = (wx, wy, wz)``.

:func:`collinearity_residual` is the pure function (arrays in, residual and Jacobians out).
:class:`CollinearityBatch` evaluates it for all observations at once, caches the result, and
provides thin ``gtsam.CustomFactor`` adapters (one per group of observations, e.g. per landmark)
that read the cache while the solver core linearises, or compute live from the ``Values`` when
called by GTSAM's own optimisers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.geometry import attitude_matrix, attitude_matrix_derivatives, drot_x, drot_y, drot_z, rot_x, rot_y, rot_z
from factors.layout import BlockLayout

__all__ = [
    "CAMERA_PARAMS",
    "CAMERA_PARAM_SCALE",
    "camera_param_scale",
    "CollinearityConstants",
    "collinearity_residual",
    "CollinearityBatch",
    "FactorShapeError",
    "cached_at",
]

Array = NDArray[np.float64]
CAMERA_PARAMS = ("delta", "beta", "epsilon", "f", "alpha0", "alpha1", "alpha2", "alpha3", "alpha4", "alpha5")
#: Unit of each camera-correction variable in SI: angles in rad, f in mm, alpha_i in units of
#: the field-angle term at the swath edge (|s - c_y| = 752 px), so all columns are well scaled
#: (alpha_5 in SI is ~1e-18 and made GTSAM's elimination report an indeterminate system).
CAMERA_PARAM_SCALE = np.array([1.0, 1.0, 1.0, 1e-3] + [752.0**-i for i in range(6)])


def camera_param_scale(params: "tuple[str, ...] | list[str]") -> Array:
    """:data:`CAMERA_PARAM_SCALE` of ``params`` (names from :data:`CAMERA_PARAMS`), in their order:
    a variable's value times this is its correction in SI."""
    return CAMERA_PARAM_SCALE[[CAMERA_PARAMS.index(p) for p in params]]


class FactorShapeError(ValueError):
    """A factor produced a residual or Jacobian of the wrong shape (caught before GTSAM sees it)."""


@dataclass
class CollinearityConstants:
    """Per-observation constants (leading dimension N).

    ``eci_to_ecef (N,3,3)``, ``p_meas (N,3)`` m ECI, ``t_go (N,3,3)``, ``eph_design (N,3,6)``,
    ``angles_meas (N,3)`` rad, ``hermite (N,3,4)``, ``k (N,)`` m, ``frac (N,)`` line fraction,
    ``sample_offset (N,)`` = s - c_y (pixels), ``cross_scale (N,)`` m per pixel, ``dx`` m,
    ``along_scale (N,)`` m of focal-plane x per image line (default ``dx``: residual in pitches).
    """

    eci_to_ecef: Array
    p_meas: Array
    t_go: Array
    eph_design: Array
    angles_meas: Array
    hermite: Array
    k: Array
    frac: Array
    sample_offset: Array
    cross_scale: Array
    dx: float
    along_scale: Array | None = None

    def __post_init__(self) -> None:
        if self.along_scale is None:
            self.along_scale = np.full(len(self), float(self.dx))
        self.along_scale = np.asarray(self.along_scale, dtype=float)

    def __len__(self) -> int:
        return int(self.p_meas.shape[0])

    def take(self, idx: Any) -> "CollinearityConstants":
        return CollinearityConstants(
            self.eci_to_ecef[idx],
            self.p_meas[idx],
            self.t_go[idx],
            self.eph_design[idx],
            self.angles_meas[idx],
            self.hermite[idx],
            self.k[idx],
            self.frac[idx],
            self.sample_offset[idx],
            self.cross_scale[idx],
            self.dx,
            self.along_scale[idx],
        )


def _t(m: Array) -> Array:
    return np.swapaxes(m, -1, -2)


def collinearity_residual(
    landmark: Array,
    theta: Array,
    knots: Array,
    camera: Array,
    omega: Array,
    c: CollinearityConstants,
    jacobians: bool = True,
) -> tuple[Array, dict[str, Array] | None]:
    """Residual (N, 2) in pixels and, optionally, its Jacobians.

    Inputs: ``landmark (N,3)`` ECEF m; ``theta (N,6)`` ephemeris parameters of the observation's
    segment; ``knots (N,3,4)`` per angle ``(a_i, a'_i, a_{i+1}, a'_{i+1})``; ``camera (N,10)`` the
    :data:`CAMERA_PARAMS`; ``omega (N,3)`` or ``(3,)``.

    Jacobians (when asked): ``landmark (N,2,3)``, ``theta (N,2,6)``, ``knots (N,2,3,4)``,
    ``camera (N,2,10)``, ``omega (N,2,3)``.
    """
    n = len(c)
    om = np.broadcast_to(np.asarray(omega, dtype=float), (n, 3))
    g_eci = np.einsum("nji,nj->ni", c.eci_to_ecef, landmark)
    u = np.einsum("nji,nj->ni", c.t_go, g_eci - c.p_meas) + np.einsum("nij,nj->ni", c.eph_design, theta)
    ang = c.angles_meas - np.sum(c.hermite * knots, axis=-1)
    if jacobians:
        r_os, d_roll, d_pitch, d_yaw = attitude_matrix_derivatives(ang[:, 0], ang[:, 1], ang[:, 2])
    else:
        r_os = attitude_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
    v_s = np.einsum("nji,nj->ni", r_os, u)
    f = camera[:, 3]
    alpha = camera[:, 4:10]
    # the rotation chain depends only on (delta, beta, eps, omega): a handful of distinct cameras
    angles6 = np.concatenate([camera[:, :3], om], axis=1)
    # rows hashed to one float (irrational weights), verified exactly below
    h = angles6 @ np.array([1.0, 1.6180339887, 2.7182818284, 3.1415926535, 1.4142135623, 1.7320508075])
    _, first, inv = np.unique(h, return_index=True, return_inverse=True)
    inv = inv.ravel()
    uniq = angles6[first]
    if not np.array_equal(uniq[inv], angles6):  # pragma: no cover - a hash collision
        uniq, inv = angles6, np.arange(n)
    u_delta, u_beta, u_eps = uniq[:, 0], uniq[:, 1], uniq[:, 2]
    u_rx, u_ry, u_rz = rot_x(uniq[:, 3]), rot_y(uniq[:, 4]), rot_z(uniq[:, 5])
    u_tsi = u_rz @ u_ry @ u_rx
    u_rxd, u_ryb, u_rze = rot_x(u_delta), rot_y(u_beta), rot_z(u_eps)
    u_tic = u_ryb @ u_rxd  # T_ic = Ry(beta) Rx(delta): delta rolls about the line axis, then beta tilts
    m = (u_tsi @ u_tic @ u_rze)[inv]
    v = np.einsum("nji,nj->ni", m, v_s)
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    so = c.sample_offset
    powers = so[:, None] ** np.arange(6)
    poly = np.sum(alpha * powers, axis=-1)
    x_obs = -(c.k + c.frac * c.dx)
    y_obs = f * poly
    a_s = c.along_scale
    r = np.stack([(f * vx / vz - x_obs) / a_s, (f * vy / vz - y_obs) / c.cross_scale], axis=-1)
    if not jacobians:
        return r, None
    jv = np.zeros((n, 2, 3))
    jv[:, 0, 0] = f / (a_s * vz)
    jv[:, 0, 2] = -f * vx / (a_s * vz * vz)
    jv[:, 1, 1] = f / (c.cross_scale * vz)
    jv[:, 1, 2] = -f * vy / (c.cross_scale * vz * vz)
    jm = jv @ _t(m)  # dr/dv_s
    jms = jm @ _t(r_os)  # dr/du
    j_land = jms @ _t(c.t_go) @ _t(c.eci_to_ecef)
    j_theta = jms @ c.eph_design
    j_knots = np.empty((n, 2, 3, 4))
    for a, d in enumerate((d_roll, d_pitch, d_yaw)):
        dr_da = np.einsum("nij,nj->ni", jm, np.einsum("nji,nj->ni", d, u))
        j_knots[:, :, a, :] = -dr_da[:, :, None] * c.hermite[:, a, None, :]
    j_cam = np.zeros((n, 2, 10))
    dms = (
        u_tsi @ u_ryb @ drot_x(u_delta) @ u_rze,
        u_tsi @ drot_y(u_beta) @ u_rxd @ u_rze,
        u_tsi @ u_tic @ drot_z(u_eps),
    )
    for i, dm in enumerate(dms):
        j_cam[:, :, i] = np.einsum("nij,nj->ni", jv, np.einsum("nji,nj->ni", dm[inv], v_s))
    j_cam[:, 0, 3] = vx / (vz * a_s)
    j_cam[:, 1, 3] = (vy / vz - poly) / c.cross_scale
    j_cam[:, 1, 4:10] = -(f / c.cross_scale)[:, None] * powers
    rest = u_tic @ u_rze
    dws = (
        u_rz @ u_ry @ drot_x(uniq[:, 3]) @ rest,
        u_rz @ drot_y(uniq[:, 4]) @ u_rx @ rest,
        drot_z(uniq[:, 5]) @ u_ry @ u_rx @ rest,
    )
    j_om = np.zeros((n, 2, 3))
    for i, dm in enumerate(dws):
        j_om[:, :, i] = np.einsum("nij,nj->ni", jv, np.einsum("nji,nj->ni", dm[inv], v_s))
    return r, {"landmark": j_land, "theta": j_theta, "knots": j_knots, "camera": j_cam, "omega": j_om}


# slots of the block layout, in column order within a factor
_SLOTS = ("landmark", "ephemeris", "roll0", "roll1", "pitch0", "pitch1", "yaw0", "yaw1", "camera", "omega")


def _robust(noise: gtsam.noiseModel.Base, robust: tuple[str, float] | None) -> gtsam.noiseModel.Base:
    if robust is None:
        return noise
    kind, k = robust
    est = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[kind].Create(k)
    return gtsam.noiseModel.Robust.Create(est, noise)


def cached_at(
    cache: tuple[gtsam.Values, Array, Array | None] | None, values: gtsam.Values | None, want_jacobians: bool
) -> tuple[Array, Array | None] | None:
    """A batch cache's (residuals, Jacobians) if it was computed at this very ``Values`` object
    (and holds Jacobians when they are wanted); None means: compute live."""
    if cache is None or cache[0] is not values or (want_jacobians and cache[2] is None):
        return None
    return cache[1], cache[2]


class CollinearityBatch:
    """All collinearity observations of a problem, grouped into CustomFactors.

    Parameters
    ----------
    const: per-observation constants.
    camera_supplied: ``(N, 10)`` supplied camera parameters per observation; the camera variable
        (if any) holds *corrections* to the entries ``camera_select``, in the units of
        :data:`CAMERA_PARAM_SCALE`.
    omega_supplied: ``(3,)`` supplied instrument angles; the omega variable holds corrections.
    sigma_px: ``(N,)`` 1-sigma of both coordinates, or ``(N, 2)`` of (line, sample) apart
        (pixels); held as ``(N, 2)``.
    group: ``(N,)`` factor index of each observation (one factor per landmark, or per observation).
    keys: ``landmark (N,)``, ``ephemeris (N,)``, ``knots (N,3,2)``, optional ``camera (N,)``
        and ``omega (N,)`` (-1 where not estimated).
    robust: ``None`` or ``("huber" | "cauchy", k)`` applied per factor.
    """

    def __init__(
        self,
        const: CollinearityConstants,
        camera_supplied: Array,
        omega_supplied: Array,
        sigma_px: Array,
        group: NDArray[np.int64],
        keys: dict[str, NDArray[np.int64]],
        camera_select: tuple[int, ...] = (0, 1, 2),
        robust: tuple[str, float] | None = None,
    ) -> None:
        order = np.argsort(np.asarray(group), kind="stable")
        self.order = order
        self.const = const.take(order)
        self.camera_supplied = np.asarray(camera_supplied, float)[order]
        self.omega_supplied = np.asarray(omega_supplied, float)
        sig = np.asarray(sigma_px, float)
        if sig.ndim == 1:
            sig = np.stack([sig, sig], axis=1)
        if sig.shape != (len(const), 2):
            raise FactorShapeError(f"sigma_px: shape {sig.shape}, expected ({len(const)},) or ({len(const)}, 2)")
        self.sigma_px = sig[order]
        g = np.asarray(group)[order]
        _, self.group = np.unique(g, return_inverse=True)
        n = self.group.size
        none = -np.ones(n, np.int64)
        kn = np.asarray(keys["knots"], np.int64)[order]
        self.slot_keys = [
            np.asarray(keys["landmark"], np.int64)[order],
            np.asarray(keys["ephemeris"], np.int64)[order],
            kn[:, 0, 0],
            kn[:, 0, 1],
            kn[:, 1, 0],
            kn[:, 1, 1],
            kn[:, 2, 0],
            kn[:, 2, 1],
            np.asarray(keys["camera"], np.int64)[order] if keys.get("camera") is not None else none,
            np.asarray(keys["omega"], np.int64)[order] if keys.get("omega") is not None else none,
        ]
        self.camera_select = tuple(int(i) for i in camera_select)
        self.camera_scale = CAMERA_PARAM_SCALE[list(self.camera_select)]
        self.slot_dims = [3, 6, 2, 2, 2, 2, 2, 2, len(self.camera_select), 3]
        self.layout = BlockLayout(self.group, self.slot_keys, self.slot_dims, rows=2)
        self.robust = robust
        self._cache: tuple[gtsam.Values, Array, Array | None] | None = None  # (at, residuals, Jacobians)

    def __len__(self) -> int:
        return int(self.group.size)

    @classmethod
    def concatenate(cls, batches: "list[CollinearityBatch]") -> "CollinearityBatch":
        """One batch holding every observation of ``batches`` (in their order), each batch's
        factors kept apart (group ids offset per batch). The batches must share the supplied
        instrument angles, the pixel pitch ``dx``, the estimated camera parameters and the loss."""
        if not batches:
            raise ValueError("CollinearityBatch.concatenate needs at least one batch")
        b0 = batches[0]
        for i, b in enumerate(batches[1:], 1):
            same = (
                b.camera_select == b0.camera_select
                and b.robust == b0.robust
                and b.const.dx == b0.const.dx
                and np.array_equal(b.omega_supplied, b0.omega_supplied)
            )
            if not same:
                raise ValueError(
                    f"CollinearityBatch.concatenate: batch {i} differs from batch 0 in its camera "
                    "selection, loss, pixel pitch or supplied instrument angles"
                )
        cat = np.concatenate
        const = CollinearityConstants(
            *(
                cat([getattr(b.const, f) for b in batches])
                for f in (
                    "eci_to_ecef",
                    "p_meas",
                    "t_go",
                    "eph_design",
                    "angles_meas",
                    "hermite",
                    "k",
                    "frac",
                    "sample_offset",
                    "cross_scale",
                )
            ),
            b0.const.dx,
            cat([b.const.along_scale for b in batches]),
        )
        groups, base = [], 0
        for b in batches:
            groups.append(b.group + base)
            base += b.layout.n_factors
        sk = [cat([b.slot_keys[s] for b in batches]) for s in range(len(b0.slot_keys))]
        keys = {
            "landmark": sk[0],
            "ephemeris": sk[1],
            "knots": np.stack([np.stack([sk[2 + 2 * a], sk[3 + 2 * a]], -1) for a in range(3)], 1),
            "camera": sk[8],
            "omega": sk[9],
        }
        return cls(
            const,
            cat([b.camera_supplied for b in batches]),
            b0.omega_supplied,
            cat([b.sigma_px for b in batches]),
            cat(groups),
            keys,
            b0.camera_select,
            b0.robust,
        )

    # ------------------------------------------------------------------ variables
    def _gather(self, values: gtsam.Values, sl: slice) -> tuple[Array, Array, Array, Array, Array]:
        n = sl.stop - sl.start
        fetched: dict[int, Array] = {}

        def col(s: int, dim: int) -> Array:
            keys = self.slot_keys[s][sl]
            out = np.zeros((n, dim))
            uk, inv = np.unique(keys, return_inverse=True)
            rows = []
            for k in uk:
                if k < 0:
                    rows.append(np.zeros(dim))
                    continue
                if k not in fetched:
                    fetched[k] = np.asarray(values.atVector(int(k)), dtype=float)
                rows.append(fetched[k])
            out[:] = np.asarray(rows)[inv.ravel()]
            return out

        land = col(0, 3)
        theta = col(1, 6)
        knots = np.stack([np.concatenate([col(2 + 2 * a, 2), col(3 + 2 * a, 2)], axis=-1) for a in range(3)], axis=1)
        cam = self.camera_supplied[sl].copy()
        if np.any(self.slot_keys[8][sl] >= 0):
            cam[:, list(self.camera_select)] += col(8, len(self.camera_select)) * self.camera_scale
        om = np.broadcast_to(self.omega_supplied, (n, 3)).copy()
        if np.any(self.slot_keys[9][sl] >= 0):
            om += col(9, 3)
        return land, theta, knots, cam, om

    def _blocks(self, j: dict[str, Array]) -> list[Array]:
        jk = j["knots"]
        return [
            j["landmark"],
            j["theta"],
            jk[:, :, 0, :2],
            jk[:, :, 0, 2:],
            jk[:, :, 1, :2],
            jk[:, :, 1, 2:],
            jk[:, :, 2, :2],
            jk[:, :, 2, 2:],
            j["camera"][:, :, list(self.camera_select)] * self.camera_scale,
            j["omega"],
        ]

    def residuals(self, values: gtsam.Values, jacobians: bool = False) -> tuple[Array, dict[str, Array] | None]:
        """Residuals (N, 2) in the batch's (sorted) observation order, and Jacobians if asked."""
        args = self._gather(values, slice(0, len(self)))
        return collinearity_residual(*args, self.const, jacobians=jacobians)

    # ------------------------------------------------------------------ cache for the solver core
    def evaluate(self, values: gtsam.Values, jacobians: bool = True) -> None:
        """Evaluate every observation at ``values`` and cache the result for the factors."""
        self.cache(*self.residuals(values, jacobians), values=values)

    def cache(self, r: Array, j: dict[str, Array] | None, values: gtsam.Values) -> None:
        """Cache an evaluation already made at ``values``: :func:`collinearity_residual`'s output
        for every observation, in the batch's order (as :meth:`residuals` returns it).

        The cache belongs to that ``Values`` object: a factor called with any other ``Values``
        computes live, so a stale cache can never answer for another point. (Do not modify
        ``values`` while the cache is live; :func:`misrgraph.estimate.solver.linearize` never does.)"""
        self._cache = (values, r.ravel(), self.layout.assemble(self._blocks(j)) if j is not None else None)

    def clear(self) -> None:
        """Drop the cache: factors compute live from the Values they are given."""
        self._cache = None

    # ------------------------------------------------------------------ factors
    def factors(self) -> list[gtsam.CustomFactor]:
        """One ``gtsam.CustomFactor`` per group, with a diagonal (optionally robust) noise model."""
        out = []
        for f in range(self.layout.n_factors):
            a, b = int(self.layout.obs_start[f]), int(self.layout.obs_stop[f])
            sig = self.sigma_px[a:b].ravel()
            noise = _robust(gtsam.noiseModel.Diagonal.Sigmas(sig), self.robust)
            out.append(gtsam.CustomFactor(noise, [int(k) for k in self.layout.factor_keys[f]], self._callback(f)))
        return out

    def factor_rows(self, f: int, values: gtsam.Values | None, want_h: bool) -> tuple[Array, list[Array] | None]:
        """Residual (2m,) and per-key Jacobian blocks of factor ``f`` (cached or live)."""
        a, b = int(self.layout.obs_start[f]), int(self.layout.obs_stop[f])
        hit = cached_at(self._cache, values, want_h)
        if hit is not None:
            r_all, buf = hit
            r = r_all[2 * a : 2 * b]
            blocks = self.layout.split(self.layout.factor_matrix(buf, f), f) if want_h and buf is not None else None
            return r, blocks
        assert values is not None
        args = self._gather(values, slice(a, b))
        r, j = collinearity_residual(*args, self.const.take(slice(a, b)), jacobians=want_h)
        if not want_h or j is None:
            return r.ravel(), None
        blocks_obs = self._blocks(j)
        mats = [np.zeros((2 * (b - a), d)) for d in self.layout.factor_dims[f]]
        where = {k: i for i, k in enumerate(self.layout.factor_keys[f])}
        for s, blk in enumerate(blocks_obs):
            keys = self.slot_keys[s][a:b]
            for i in range(b - a):
                if keys[i] >= 0:
                    mats[where[int(keys[i])]][2 * i : 2 * i + 2] = blk[i]
        return r.ravel(), mats

    def _callback(self, f: int):
        dims = self.layout.factor_dims[f]
        m = 2 * int(self.layout.obs_stop[f] - self.layout.obs_start[f])

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> Array:
            r, blocks = self.factor_rows(f, values, H is not None)
            if r.shape != (m,):
                raise FactorShapeError(f"collinearity factor {f}: residual shape {r.shape}, expected ({m},)")
            if H is not None and not np.all(np.isfinite(r)):
                raise FactorShapeError(f"collinearity factor {f}: non-finite residual at the linearisation point")
            if H is not None:
                assert blocks is not None
                for i, (blk, d) in enumerate(zip(blocks, dims)):
                    if blk.shape != (m, d):
                        raise FactorShapeError(
                            f"collinearity factor {f}: Jacobian {i} shape {blk.shape}, expected ({m}, {d})"
                        )
                    H[i] = blk
            return r

        return error
