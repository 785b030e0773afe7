"""Each camera's tie-matching precision from the pass's own redundancy.

The least-squares matcher's covariance (:mod:`misrgraph.match.lsm`) sees only what its residuals
show. The largest error between two views of a patch does not show there: the scene looks
different from another angle (BRDF), so the pattern changes at the texture's own scales.
The fit absorbs most of that change, which then moves the matched position. For the D cameras
(70.5 deg against An's nadir) the LSM sigma is about 2x optimistic on the simulator's scenes.

The data carry the missing information. A tie point is matched from An into up to eight cameras,
each at the position the supplied navigation and the DEM predict. The difference
``d = matched - predicted (line, sample)`` of camera ``c`` is

    d_ic = s_c(t_i, x_i) + h_i e_ic + m_ic

* ``s_c`` is the navigation and camera-model error, smooth in the observation time ``t`` and in
  ``x`` (the sample's offset from the array centre, normalised); its two forms are below.
* ``h_i e_ic`` is the feature's height error along An's ray. An's observation defines the tie
  point, so the point keeps one degree of freedom: its height. ``e_ic`` is the image displacement
  in camera ``c`` per metre of height (the epipolar direction).
* ``m_ic`` is the matching error, with sigma ``k_c sigma_ic``.

These are the unknowns the adjustment itself has (a smooth attitude on its knots, a landmark
position). So ``k_c`` is the scale that makes the sigma honest *for the adjustment*: the scatter
the adjustment cannot absorb. Errors faster than the knots, such as jitter, are counted in the
scale. For the adjustment they are observation noise.

Two forms of ``s_c``:

* **Shared attitude** (when the caller gives each observation's pointing sensitivity, as the
  matching pipeline does). The adjustment's own model: one attitude correction ``a(t)`` (roll,
  pitch, yaw; a cubic B-spline on ``knot_s`` knots) for all cameras, seen twice by each
  difference -- in camera ``c`` at its time ``t_c`` and through An's defining ray at An's time
  ``t_An`` (the prediction starts from where An's supplied ray meets the DEM)::

      s_c = J_c a(t_c) + K_c a(t_An) + P_c(x, tau)

  ``J_c`` ``(2, 3)`` px/rad moves camera ``c``'s prediction of a fixed ground point, ``K_c``
  moves it through An's ground point; ``P_c`` is per camera and static or slow: ``1, x, x^2,
  x^3, tau, tau^2`` per coordinate (``tau`` the pass time, normalised), for the camera model and
  the per-camera share of ephemeris errors. The attitude is shared, so a camera with few matches
  pays 12 parameters, not a spline of its own: the D cameras of a short pass keep a redundancy
  of tens where the per-camera form left them near 0.
* **Per camera** (without pointing sensitivities): a cubic B-spline in ``t`` with the
  adjustment's knot spacing, times ``(1, x)``, plus ``x^2, x^3`` terms constant in time, for each
  camera on its own. It needs ~30 matches per camera of a 10-minute pass before it leaves any
  redundancy.

Method:

* One weighted least-squares fit of the smooth model and all heights together. The heights are
  eliminated by a Schur complement, so the cost grows linearly with the features.
* Each camera's redundancy is ``r_c = n_c - tr(N^-1 N_c)`` (the sum of its rows' ``1 - h_ii``,
  ``h`` the hat matrix's diagonal), exact for the linear model.
* ``k_c^2 = sum_c z^2 / r_c`` (Foerstner's variance components), iterated with the weights
  ``1 / (k_c sigma)^2`` until the scales settle.
* Robust: an observation whose radial ``z^2`` exceeds the chi-square (2 dof) quantile of
  ``+-clip`` sigma is left out of the next fit.
* A camera with a redundancy below ``min_redundancy`` keeps ``k_c = 1``. This is reported,
  not hidden.

**The GCPs' precision** (shared-attitude form, with ``gcp``: :class:`GcpRows`). A GCP chip is
matched with the same least-squares matcher, and its sigma is as optimistic: the chip comes from
another sensor and another date (other sun, other surface), and the change of pattern does not
show in the residuals. The pass's GCP observations join the same fit as a class of their own,
one scale ``k_g`` for all of them::

    d_gc = J_c a(t_c) + P_c(x, tau) + G_gc dg_g + m_gc      (camera c other than An)
    d_gA = J_A a(t_A) + J_A dA + G_gA dg_g + m_gA           (An)

``d`` is matched minus the catalogue position's prediction; ``G`` ``(2, 3)`` px/m moves the
prediction per metre of ground east, north and up, and ``dg_g`` (three per GCP) takes up
everything the GCP's observations share -- the catalogue error, the chip's own misregistration,
the ephemeris at its time. ``dA`` (three angles) is An's static pointing error: the tie
differences see it through An's ray (``K_c dA``; in the tie-only fit the cameras' constants
absorb it), An's GCP observations directly. ``k_g`` is the variance component of the GCP rows,
estimated when their redundancy reaches ``gcp_min_redundancy`` (its relative standard error is
about ``1/sqrt(2 r)``: 22 % at 10), else 1. The GCP rows are clipped like the ties' (left out of
the next fit, never rejected: that is the adjustment's call).

**The offset a feature's conjugates share** (shared-attitude form, ``shared_offset``). All
conjugates of a tie feature match the same An template, so part of their error is common: the
template's own position error. With ``shared_offset`` each feature gets a (line, sample) offset
``o_i`` in every conjugate row, a random effect ``o_i ~ N(0, s_o^2)`` whose variance is a variance
component of its own (the prior's pseudo-observations: ``s_o^2 = sum |o_i|^2 / r_o``, ``r_o`` their
redundancy), iterated with the cameras'. The cameras' scales then count only their conjugates' own
error; ``s_o`` (``PrecisionFit.shared_offset``) is the sigma of the defining (An) observation,
off the conjugates' common point by exactly that error. The features' height and offset are
eliminated together (:func:`_solve_blocks`, ``3 x 3`` blocks).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.interpolate import BSpline

from misrgraph.errors import InputError

__all__ = ["GcpRows", "GcpScale", "PrecisionFit", "Pointing", "SharedOffset", "camera_sigma_scales"]

Array = NDArray[np.float64]


class Pointing(NamedTuple):
    """Each observation's pointing sensitivity, for the shared-attitude form (``n`` rows):
    ``an_time_s (n,)`` the time (s) of its feature's An observation; ``camera_px_per_rad (n, 2, 3)``
    ``J_c``, d(line, sample) of the camera's prediction of a fixed ground point per rad of roll,
    pitch, yaw at the observation's time; ``an_px_per_rad (n, 2, 3)`` ``K_c``, d(line, sample) of
    the prediction per rad of attitude at An's time (through An's ground point on the DEM)."""

    an_time_s: Array
    camera_px_per_rad: Array
    an_px_per_rad: Array


class GcpRows(NamedTuple):
    """The pass's GCP observations for the fit (``g`` rows, one band, the ties'): ``gcp (g,)`` the
    GCP (any integer id; its observations share ``dg``), ``camera (g,)``, ``time_s (g,)`` the
    observation time (s), ``x (g,)`` the normalised sample offset from the array centre, ``d (g, 2)``
    matched minus predicted (line, sample) px, the prediction being the catalogue position's
    through the supplied navigation, ``sigma (g,)`` px the matcher's, ``camera_px_per_rad (g, 2, 3)``
    ``J_c`` as in :class:`Pointing`, ``ground_px_per_m (g, 2, 3)`` d(line, sample) per metre of
    ground east, north and up, and ``defining_camera``."""

    gcp: NDArray[np.int64]
    camera: NDArray[np.int64]
    time_s: Array
    x: Array
    d: Array
    sigma: Array
    camera_px_per_rad: Array
    ground_px_per_m: Array
    #: the camera whose pixels define the tie points (An): no static terms of its own; it sees An's
    #: static pointing error directly
    defining_camera: int


@dataclass
class GcpScale:
    """The GCP observations' sigma scale: ``scale`` (1 where not estimated), the ``redundancy``
    behind it, the observations ``kept`` and ``clipped`` in the fit, ``estimated``."""

    scale: float = 1.0
    redundancy: float = 0.0
    kept: int = 0
    clipped: int = 0
    estimated: bool = False

    def as_dict(self) -> dict[str, float | int | bool]:
        return {
            "scale": self.scale,
            "redundancy": self.redundancy,
            "kept": self.kept,
            "clipped": self.clipped,
            "estimated": self.estimated,
        }


@dataclass
class SharedOffset:
    """The (line, sample) offset all conjugates of a tie feature share (the template's own position
    error): its 1 sigma ``sigma_px`` per coordinate (0 where not estimated), the ``redundancy``
    behind it, ``estimated``."""

    sigma_px: float = 0.0
    redundancy: float = 0.0
    estimated: bool = False
    #: camera -> the conjugates' scale in the fit that models the offset over the scale their
    #: sigmas were given (1 when they were given that fit's scales; below 1 when their sigma also
    #: holds part of the shared variance): ``sigma_own = rho sigma``
    own_scale_ratio: dict[int, float] = field(default_factory=dict)

    def as_dict(self, names: list[str] | tuple[str, ...] | None = None) -> dict[str, Any]:
        out: dict[str, Any] = {"sigma_px": self.sigma_px, "redundancy": self.redundancy, "estimated": self.estimated}
        if self.own_scale_ratio and names is not None:
            out["own_scale_ratio"] = {names[c]: v for c, v in sorted(self.own_scale_ratio.items())}
        return out


@dataclass
class PrecisionFit:
    """Per-camera sigma scales ``scale[c]`` (where not estimated: the twin camera's, ``borrowed[c]``
    naming it, when the twin's is estimated, else 1), the redundancy and the kept and
    clipped observation counts behind each (camera index -> value), and the variance-component
    ``iterations``."""

    scale: dict[int, float] = field(default_factory=dict)
    redundancy: dict[int, float] = field(default_factory=dict)
    kept: dict[int, int] = field(default_factory=dict)
    clipped: dict[int, int] = field(default_factory=dict)
    estimated: dict[int, bool] = field(default_factory=dict)
    #: camera -> the twin whose scale it took (its own redundancy too small)
    borrowed: dict[int, int] = field(default_factory=dict)
    iterations: int = 0
    #: per input row: True where the observation was clipped (inconsistent with the pass)
    outlier: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    #: the smooth model: "shared attitude" or "per camera" (module docstring)
    model: str = "per camera"
    #: the GCP observations' scale, when the fit had them (module docstring)
    gcp: GcpScale | None = None
    #: the offset a feature's conjugates share, when the fit modelled it (``shared_offset``)
    shared_offset: SharedOffset | None = None

    def as_dict(self, names: list[str] | tuple[str, ...]) -> dict[str, dict[str, float | int | bool | str]]:
        out: dict[str, dict[str, float | int | bool | str]] = {}
        for c in sorted(self.scale):
            out[names[c]] = {
                "scale": self.scale[c],
                "redundancy": self.redundancy[c],
                "kept": self.kept[c],
                "clipped": self.clipped[c],
                "estimated": self.estimated[c],
            }
            if c in self.borrowed:
                out[names[c]]["scale_from"] = names[self.borrowed[c]]
        return out


def _bspline(t: Array, lo: float, hi: float, knot_s: float) -> Array:
    """Cubic B-spline basis ``(n, nb)`` on ``[lo, hi]`` with knots about ``knot_s`` s apart."""
    n_int = max(int(np.ceil((hi - lo) / knot_s)), 1)
    inner = np.linspace(lo, hi + 1e-9, n_int + 1)
    knots = np.r_[[inner[0]] * 3, inner, [inner[-1]] * 3]
    return BSpline.design_matrix(np.clip(t, inner[0], inner[-1]), knots, 3).toarray()


def _design(t: Array, x: Array, knot_s: float) -> Array:
    """Smooth-model design ``(n, p)``: cubic B-splines in ``t`` (s) times ``(1, x)``, plus ``x^2, x^3``."""
    b = _bspline(t, float(np.min(t)), float(np.max(t)), knot_s)
    return np.hstack([b, b * x[:, None], (x**2)[:, None], (x**3)[:, None]])


def _solve(
    X: dict[int, Array],
    rows: dict[int, NDArray[np.int64]],
    feat_of: NDArray[np.int64],
    n_feat: int,
    d: Array,
    e: Array,
    w: Array,
    h_prior_m: float,
) -> tuple[Array, dict[int, float]]:
    """Joint weighted least squares of the smooth models and the heights (Schur complement on the
    heights); the residuals ``(n, 2)`` and each camera's redundancy ``n_c - tr(N^-1 N_c)``. Rows
    with ``w = 0`` are out of the fit."""
    # parameter blocks: (camera, coordinate) -> offset into the smooth parameters
    off, o = {}, 0
    for c in rows:
        for q in range(2):
            off[c, q] = o
            o += X[c].shape[1]
    n_s = o
    a_ss = np.zeros((n_s, n_s))
    b = np.zeros((n_s, n_feat))
    rhs_s = np.zeros(n_s)
    dd = np.full(n_feat, 1.0 / h_prior_m**2)
    rhs_h = np.zeros(n_feat)
    for c, r in rows.items():
        xc, wc, fc = X[c], w[r], feat_of[r]
        for q in range(2):
            sl = slice(off[c, q], off[c, q] + xc.shape[1])
            a_ss[sl, sl] = xc.T @ (xc * wc[:, None])
            rhs_s[sl] = xc.T @ (wc * d[r, q])
            we = wc * e[r, q]
            np.add.at(b[sl].T, fc, xc * we[:, None])
            np.add.at(dd, fc, we * e[r, q])
            np.add.at(rhs_h, fc, we * d[r, q])
    bd = b / dd  # B D^-1
    s_mat = a_ss - bd @ b.T
    s_mat += np.eye(n_s) * (1e-10 * max(float(np.max(np.diag(s_mat))), 1e-300))  # cameras without data
    q_mat = np.linalg.pinv(s_mat, hermitian=True)
    x_s = q_mat @ (rhs_s - bd @ rhs_h)
    h = (rhs_h - b.T @ x_s) / dd
    res = d.copy()
    for c, r in rows.items():
        for q in range(2):
            res[r, q] -= X[c] @ x_s[off[c, q] : off[c, q] + X[c].shape[1]]
    res -= h[feat_of][:, None] * e
    # redundancy per camera: n_c - tr(N^-1 N_c), N^-1 = [[Q, R], [R^T, H]], R = -Q B D^-1
    qbd = q_mat @ bd
    h_diag = 1.0 / dd + np.sum(bd * qbd, axis=0)
    red = {}
    for c, r in rows.items():
        xc, wc, fc = X[c], w[r], feat_of[r]
        tr = 0.0
        for q in range(2):
            sl = slice(off[c, q], off[c, q] + xc.shape[1])
            tr += float(np.sum(q_mat[sl, sl] * a_ss[sl, sl]))
            we = wc * e[r, q]
            # 2 tr(R B_c^T): B_c's column f is sum over camera c's rows of feature f of x w e
            tr -= 2.0 * float(np.sum(np.sum(qbd[sl][:, fc] * (xc * we[:, None]).T, axis=0)))
            tr += float(np.sum(h_diag[fc] * we * e[r, q]))
        red[c] = 2.0 * float(np.count_nonzero(wc)) - tr
    return res, red


def _shared_design(
    camera: NDArray[np.int64],
    cams: list[int],
    time_s: Array,
    x: Array,
    pointing: Pointing,
    knot_s: float,
    span: tuple[float, float] | None = None,
) -> Array:
    """Shared-attitude design ``(2n, p)``, rows ``2i`` (line) and ``2i + 1`` (sample) of
    observation ``i``: the attitude spline's coefficients (3 axes, rad; on ``span`` (s), by default
    the observations' own) seen as ``J_c B(t_c) + K_c B(t_An)``, then per camera of ``cams`` and
    coordinate ``1, x, x^2, x^3, tau, tau^2`` (a row whose camera is not in ``cams`` has none)."""
    t_an = np.asarray(pointing.an_time_s, float)
    jc = np.asarray(pointing.camera_px_per_rad, float)
    ka = np.asarray(pointing.an_px_per_rad, float)
    n = time_s.size
    lo, hi = span if span is not None else (float(min(time_s.min(), t_an.min())), float(max(time_s.max(), t_an.max())))
    b_c = _bspline(time_s, lo, hi, knot_s)
    b_a = _bspline(t_an, lo, hi, knot_s)
    nb = b_c.shape[1]
    # (n, 2, 3, nb) -> (2n, 3 nb): axis-major columns
    att = (jc[:, :, :, None] * b_c[:, None, None, :] + ka[:, :, :, None] * b_a[:, None, None, :]).reshape(2 * n, 3 * nb)
    tau = (time_s - 0.5 * (lo + hi)) / max(0.5 * (hi - lo), 1.0)
    poly = np.column_stack([np.ones(n), x, x**2, x**3, tau, tau**2])  # (n, 6)
    static = np.zeros((2 * n, len(cams) * 12))
    mine = np.flatnonzero(np.isin(camera, cams))
    pos = np.searchsorted(cams, camera[mine])
    for q in range(2):
        cols = pos[:, None] * 12 + q * 6 + np.arange(6)[None, :]
        static[2 * mine[:, None] + q, cols] = poly[mine]
    return np.hstack([att, static])


def _joint_design(
    a_tie: Array, pointing: Pointing, gcp: GcpRows, cams: list[int], span: tuple[float, float], knot_s: float
) -> Array:
    """The shared design with the GCP rows below the tie rows (module docstring): the tie rows'
    ``a_tie (2n, p)`` and An's static pointing ``dA`` through ``K_c``; the GCP rows' attitude and
    static terms, ``dA`` through ``J_A`` on An's rows, and three ground columns per GCP."""
    g = gcp.time_s.size
    a_gcp = _shared_design(
        gcp.camera,
        cams,
        gcp.time_s,
        gcp.x,
        Pointing(gcp.time_s, gcp.camera_px_per_rad, np.zeros((g, 2, 3))),
        knot_s,
        span,
    )
    own = (gcp.camera == gcp.defining_camera)[:, None, None]
    d_an = np.vstack(
        [
            np.asarray(pointing.an_px_per_rad, float).reshape(-1, 3),
            np.where(own, gcp.camera_px_per_rad, 0.0).reshape(-1, 3),
        ]
    )
    ids, of = np.unique(gcp.gcp, return_inverse=True)
    ground = np.zeros((2 * g, 3 * ids.size))
    for q in range(2):
        ground[2 * np.arange(g)[:, None] + q, 3 * of[:, None] + np.arange(3)[None, :]] = gcp.ground_px_per_m[:, q, :]
    top = np.hstack([a_tie, np.zeros((a_tie.shape[0], ground.shape[1]))])
    return np.hstack([np.vstack([top, np.hstack([a_gcp, ground])]), d_an])


def _solve_rows(
    a: Array, y: Array, e: Array, feat_of: NDArray[np.int64], n_feat: int, w: Array, h_prior_m: float
) -> tuple[Array, Array]:
    """Weighted least squares of ``y (m,) = a (m, p) s + e (m,) h[feat_of]`` with a weak prior
    ``h ~ N(0, h_prior_m^2)`` on each height, the heights eliminated by a Schur complement; the
    residuals ``(m,)`` and the hat matrix's diagonal ``(m,)`` (0 where ``w = 0``): :func:`_solve_blocks`
    with one unknown per feature. A gauge the rows do not fix -- a constant attitude against the
    cameras' offsets -- leaves the residuals alone."""
    res, hat, _, _ = _solve_blocks(a, y, e[:, None], feat_of, n_feat, w, np.array([1.0 / h_prior_m**2]))
    return res, hat


def _solve_blocks(
    a: Array, y: Array, e: Array, feat_of: NDArray[np.int64], n_feat: int, w: Array, prior: Array
) -> tuple[Array, Array, Array, Array]:
    """Weighted least squares of ``y (m,) = a (m, p) s + sum_j e[:, j] u[feat_of, j]`` with ``q``
    unknowns ``u`` per feature (``e (m, q)``), each with a zero-mean prior of precision ``prior (q,)``,
    the features' unknowns eliminated by a Schur complement on their ``q x q`` blocks. Returns the
    residuals ``(m,)``, the hat matrix's diagonal ``(m,)`` (0 where ``w = 0``), the features'
    unknowns ``(n_feat, q)`` and their covariance blocks ``(n_feat, q, q)`` (of the unit-weight
    system). Columns are equilibrated and the reduced system solved by a pseudo-inverse, as in
    :func:`_solve_rows`."""
    q = e.shape[1]
    col = np.sqrt(np.einsum("mp,m->p", a * a, w))
    col[col == 0] = 1.0
    a = a / col
    aw = a * w[:, None]
    a_ss = a.T @ aw
    b = np.zeros((n_feat, q, a.shape[1]))
    np.add.at(b, feat_of, e[:, :, None] * aw[:, None, :])
    d = np.zeros((n_feat, q, q)) + np.diag(prior)
    np.add.at(d, feat_of, w[:, None, None] * e[:, :, None] * e[:, None, :])
    rhs_h = np.zeros((n_feat, q))
    np.add.at(rhs_h, feat_of, (w * y)[:, None] * e)
    d_inv = np.linalg.inv(d)
    g = d_inv @ b  # (F, q, p)
    q_mat = np.linalg.pinv(a_ss - np.einsum("fqp,fqk->pk", b, g), hermitian=True, rcond=1e-12)
    x_s = q_mat @ (aw.T @ y - np.einsum("fqp,fq->p", b, np.einsum("fqk,fk->fq", d_inv, rhs_h)))
    u = np.einsum("fqk,fk->fq", d_inv, rhs_h - b @ x_s)
    res = y - a @ x_s - np.sum(e * u[feat_of], axis=1)
    aq = a @ q_mat
    cov_u = d_inv + (g @ q_mat) @ g.transpose(0, 2, 1)
    hat = w * (
        np.sum(aq * a, axis=1)
        - 2.0 * np.einsum("rp,rjp,rj->r", aq, g[feat_of], e)
        + np.einsum("rq,rqj,rj->r", e, cov_u[feat_of], e)
    )
    return res, hat, u, cov_u


#: the GCP rows' class in the fit's per-class dictionaries (cameras are >= 0)
_GCP = -1


def camera_sigma_scales(
    feature: NDArray[np.int64],
    camera: NDArray[np.int64],
    time_s: Array,
    x: Array,
    d: Array,
    epipolar: Array,
    sigma: Array,
    knot_s: float = 60.0,
    clip: float = 4.0,
    min_redundancy: float = 30.0,
    max_iter: int = 10,
    tol: float = 0.01,
    height_prior_m: float = 1000.0,
    pointing: Pointing | None = None,
    twin: dict[int, int] | None = None,
    gcp: GcpRows | None = None,
    gcp_min_redundancy: float = 10.0,
    shared_offset: bool = False,
) -> PrecisionFit:
    """Per-camera scales of the matching sigmas (see the module docstring).

    Arguments, one row per matched (non-defining) observation, ``n`` rows:
    ``feature (n,)`` the tie feature, ``camera (n,)``, ``time_s (n,)`` the observation time (s),
    ``x (n,)`` the normalised sample offset from the array centre, ``d (n, 2)`` matched minus
    predicted (line, sample) px, ``epipolar (n, 2)`` px per metre of height along the defining ray,
    ``sigma (n,)`` px the matcher's sigmas; ``knot_s`` the smooth model's knot spacing (s).
    ``height_prior_m`` is a weak prior on each height (it only removes the exact degeneracy
    between a common height change and the smooth models). The scales are iterated as variance
    components (Foerstner) until they change by less than ``tol`` (relative). With ``pointing``
    (:class:`Pointing`) the smooth model is the shared attitude, else each camera's own spline
    (module docstring). ``twin`` maps a camera to the one at the same view angle on the other side
    of nadir (MISR's Df and Da, ...): a camera whose redundancy is below ``min_redundancy`` takes its
    twin's scale when the twin's is estimated (the pattern's change with view angle, the scale's main
    cause, is alike), else keeps its stated sigma (scale 1). ``gcp`` (:class:`GcpRows`, shared-attitude
    form only) adds the pass's GCP observations as a class of their own; their scale
    (``PrecisionFit.gcp``) is estimated when their redundancy reaches ``gcp_min_redundancy``.
    ``shared_offset`` (shared-attitude form only) also models the offset a feature's conjugates
    share; its sigma (``PrecisionFit.shared_offset``) is estimated when the prior's redundancy
    reaches ``min_redundancy`` (module docstring)."""
    feature = np.asarray(feature, np.int64)
    camera = np.asarray(camera, np.int64)
    d = np.asarray(d, float).reshape(-1, 2)
    e = np.asarray(epipolar, float).reshape(-1, 2)
    sigma = np.asarray(sigma, float)
    n = feature.size
    out = PrecisionFit()
    if n == 0:
        return out
    if gcp is not None and pointing is None:
        raise InputError("gcp", "GCP rows without pointing", "pointing sensitivities too (the shared-attitude form)")
    chi2_clip = float(stats.chi2.isf(2.0 * stats.norm.sf(clip), 2))
    rows = {int(c): np.flatnonzero(camera == c) for c in np.unique(camera)}
    cams = sorted(rows)
    feat_ids, feat_of = np.unique(feature, return_inverse=True)
    time_s = np.asarray(time_s, float)
    x = np.asarray(x, float)
    klass = camera
    n_gcp = 0
    offset: dict[str, float] = {}
    if shared_offset and pointing is None:
        raise InputError("shared_offset", True, "pointing sensitivities too (the shared-attitude form)")
    if pointing is not None:
        for name, v, shape in (
            ("an_time_s", pointing.an_time_s, (n,)),
            ("camera_px_per_rad", pointing.camera_px_per_rad, (n, 2, 3)),
            ("an_px_per_rad", pointing.an_px_per_rad, (n, 2, 3)),
        ):
            if np.shape(v) != shape or not np.all(np.isfinite(v)):
                raise InputError(f"pointing.{name}", np.shape(v), f"finite values of shape {shape}")
        if gcp is not None:
            gcp = _checked_gcp(gcp)
            n_gcp = gcp.time_s.size
        t_an = np.asarray(pointing.an_time_s, float)
        times = [time_s, t_an] + ([gcp.time_s] if gcp is not None else [])
        span = (float(min(t.min() for t in times if t.size)), float(max(t.max() for t in times if t.size)))
        # a camera with GCP rows and no tie rows still has static terms (An has none: it sees dA)
        cams_fit = cams if gcp is None else sorted(set(cams) | {int(c) for c in gcp.camera if c != gcp.defining_camera})
        a_rows = _shared_design(camera, cams_fit, time_s, x, pointing, knot_s, span)
        y_rows, e_rows, f_rows = d.reshape(-1), e.reshape(-1), np.repeat(feat_of, 2)
        if n_gcp:
            assert gcp is not None
            a_rows = _joint_design(a_rows, pointing, gcp, cams_fit, span, knot_s)
            y_rows = np.concatenate([y_rows, gcp.d.reshape(-1)])
            e_rows = np.concatenate([e_rows, np.zeros(2 * n_gcp)])  # no height of a tie feature
            f_rows = np.concatenate([f_rows, np.zeros(2 * n_gcp, np.int64)])
            d = np.vstack([d, gcp.d])
            sigma = np.concatenate([sigma, gcp.sigma])
            klass = np.concatenate([camera, np.full(n_gcp, _GCP)])
            rows[_GCP] = np.arange(n, n + n_gcp)
        out.model = "shared attitude"
        n_all = n + n_gcp

        if shared_offset:  # per feature: the height and a (line, sample) offset all its tie rows share
            e_blk = np.zeros((y_rows.size, 3))
            e_blk[:, 0] = e_rows
            e_blk[0 : 2 * n : 2, 1] = 1.0
            e_blk[1 : 2 * n : 2, 2] = 1.0
            offset["var"] = (0.5 * float(np.median(sigma[:n]))) ** 2

        def solve(w: Array) -> tuple[Array, dict[int, float]]:
            if shared_offset:
                prior = np.array([1.0 / height_prior_m**2, 1.0 / offset["var"], 1.0 / offset["var"]])
                res_r, hat, u, cov_u = _solve_blocks(
                    a_rows, y_rows, e_blk, f_rows, feat_ids.size, np.repeat(w, 2), prior
                )
                # two pseudo-observations (the prior) per feature, each with redundancy 1 - p [N^-1]_kk
                r_o = float(np.sum(2.0 - (cov_u[:, 1, 1] + cov_u[:, 2, 2]) / offset["var"]))
                offset["redundancy"] = r_o
                if r_o > 0:
                    # its variance component (Foerstner), kept off zero so that the prior stays finite
                    new = max(float(np.sum(u[:, 1:] ** 2) / r_o), (1e-3 * float(np.median(sigma[:n]))) ** 2)
                    offset["change"] = abs(np.sqrt(new / offset["var"]) - 1.0)
                    offset["var"] = new
            else:
                res_r, hat = _solve_rows(a_rows, y_rows, e_rows, f_rows, feat_ids.size, np.repeat(w, 2), height_prior_m)
            used = np.repeat(w > 0, 2)
            red_row = np.where(used, 1.0 - hat, 0.0).reshape(n_all, 2).sum(axis=1)
            return res_r.reshape(n_all, 2), {c: float(np.sum(red_row[r])) for c, r in rows.items()}
    else:
        X = {c: _design(time_s[r], x[r], knot_s) for c, r in rows.items()}

        def solve(w: Array) -> tuple[Array, dict[int, float]]:
            return _solve(X, rows, feat_of, feat_ids.size, d, e, w, height_prior_m)

    scale = {c: 1.0 for c in rows}
    keep = np.ones(klass.size, bool)
    red: dict[int, float] = {}
    it = 0
    classes = sorted(rows)
    cls_pos = np.searchsorted(classes, klass)  # each row's class, as a position in classes

    def per_row(v: dict[int, float]) -> Array:
        return np.array([v[c] for c in classes])[cls_pos]

    def enough(c: int) -> bool:
        return red[c] >= (gcp_min_redundancy if c == _GCP else min_redundancy)

    def estimated_twin(c: int) -> int | None:
        """``c``'s twin when the fit estimated the twin's scale (``red`` of the latest solve)."""
        t = twin.get(c) if twin is not None and c != _GCP else None
        return t if t in red and enough(t) else None

    for it in range(1, max_iter + 1):
        w = np.where(keep, 1.0 / (sigma * per_row(scale)) ** 2, 0.0)
        res, red = solve(w)
        z2 = np.sum(res**2, axis=1) / sigma**2  # against the stated sigma, both coordinates
        change = 0.0
        for c, r in rows.items():
            k = keep[r]
            if enough(c):
                new = float(np.sqrt(np.sum(z2[r][k]) / red[c]))
                change = max(change, abs(new / scale[c] - 1.0))
                scale[c] = new
        for c in rows:
            if not enough(c):
                t = estimated_twin(c)
                scale[c] = 1.0 if t is None else scale[t]
        new_keep = z2 <= per_row(scale) ** 2 * chi2_clip
        change = max(change, offset.get("change", 0.0))
        if change < tol and np.array_equal(new_keep, keep):
            break
        keep = new_keep
    for c, r in rows.items():
        est = enough(c)
        if c == _GCP:
            out.gcp = GcpScale(scale[c], float(max(red[c], 0.0)), int(keep[r].sum()), int((~keep[r]).sum()), bool(est))
            continue
        out.scale[c] = scale[c]  # the twin's, or 1, where not estimated (set in the loop)
        if not est and (t := estimated_twin(c)) is not None:
            out.borrowed[c] = t
        out.redundancy[c] = float(max(red[c], 0.0))
        out.estimated[c] = bool(est)
        out.kept[c] = int(keep[r].sum())
        out.clipped[c] = int((~keep[r]).sum())
    out.iterations = it
    out.outlier = ~keep[:n]
    if offset:
        est = offset.get("redundancy", 0.0) >= min_redundancy
        out.shared_offset = SharedOffset(
            float(np.sqrt(offset["var"])) if est else 0.0, float(max(offset.get("redundancy", 0.0), 0.0)), bool(est)
        )
    return out


def _checked_gcp(gcp: GcpRows) -> GcpRows:
    """``gcp`` as float/int arrays, every field of the same length and finite (InputError naming the field)."""
    g = np.size(gcp.time_s)
    shapes = {
        "gcp": (g,),
        "camera": (g,),
        "time_s": (g,),
        "x": (g,),
        "d": (g, 2),
        "sigma": (g,),
        "camera_px_per_rad": (g, 2, 3),
        "ground_px_per_m": (g, 2, 3),
    }
    out = {}
    for name, shape in shapes.items():
        v = np.asarray(getattr(gcp, name), np.int64 if name in ("gcp", "camera") else float)
        if v.shape != shape or not np.all(np.isfinite(v)):
            raise InputError(f"gcp.{name}", np.shape(getattr(gcp, name)), f"finite values of shape {shape}")
        out[name] = v
    if not np.all(out["sigma"] > 0):
        raise InputError("gcp.sigma", float(np.min(out["sigma"])), "positive sigmas (px)")
    return GcpRows(**out, defining_camera=int(gcp.defining_camera))
