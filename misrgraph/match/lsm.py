"""Area-based image matching: normalised cross-correlation and least-squares matching (LSM).

Pure functions on arrays (pixels in, positions and covariances out); the MISR-specific prediction
and bookkeeping are in :mod:`misrgraph.match.pipeline`.

* :func:`ncc_search` -- normalised cross-correlation of a template over a search image
  (``skimage.feature.match_template``), the integer peak, its value and the peak ratio (the best
  correlation more than 2 px away over the peak: near 1 means an ambiguous, repetitive match).
* :func:`lsm` -- Gauss-Newton least-squares matching with an affine geometry and a linear
  radiometry. Model, for template pixel ``x`` (row, col relative to the template centre):

      I(A x + t + delta(x)) = r0 + r1 T(x) + e(x),   A = [[1 + a00, a01], [a10, 1 + a11]]

  with ``I`` the search image, interpolated by cubic splines (``scipy.ndimage.map_coordinates``),
  and its gradient by central differences, interpolated the same way; ``delta(x)`` is an optional
  known non-affine distortion (zero at the centre: terrain relief predicted from a DEM). The
  matched position of the template centre is ``t`` (row, col of the search image). Its covariance is the sandwich
  ``(J^T J)^-1 (J^T Sigma_e J) (J^T J)^-1`` restricted to ``t``, with ``J^T Sigma_e J`` from the
  residuals' own autocovariance (:func:`hac_meat`): residuals of a band-limited image (blur,
  BRDF and surface change between the two images) are not white, and ``s0^2 (J^T J)^-1`` -- the
  white-noise formula -- is then optimistic by up to 3x (measured on the simulator's chips).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from misrgraph.errors import InputError

__all__ = ["NccPeak", "LsmResult", "ncc_search", "lsm", "hac_meat"]

Array = NDArray[np.float64]


@dataclass
class NccPeak:
    """Integer NCC peak: ``row, col`` of the template centre in the search image (continuous
    coordinates: the centre of a template of even size falls between pixels), the correlation
    ``value`` and the ``ratio`` second-best / best (2 px exclusion)."""

    row: float
    col: float
    value: float
    ratio: float


@dataclass
class LsmResult:
    """Least-squares match: template-centre position ``row, col`` in the search image, its 1 sigma
    ``sigma_row, sigma_col`` (px), the residual RMS ``s0`` (counts), the correlation of the fitted
    template with the image, iterations used and whether it ``converged``; ``reason`` says why not."""

    row: float
    col: float
    sigma_row: float
    sigma_col: float
    s0: float
    correlation: float
    iterations: int
    converged: bool
    reason: str = ""


def _centre(n: int) -> float:
    return (n - 1) / 2.0


def ncc_search(
    image: Array,
    template: Array,
    row_range: tuple[float, float] | None = None,
    col_range: tuple[float, float] | None = None,
) -> NccPeak | None:
    """Best NCC position of ``template`` in ``image`` (template-centre coordinates), optionally
    restricted to centres within ``row_range``/``col_range``; None when nothing can be searched
    (the template does not fit, or the template or image is flat)."""
    from skimage.feature import match_template

    image = np.asarray(image, dtype=float)
    template = np.asarray(template, dtype=float)
    th, tw = template.shape
    if image.shape[0] < th or image.shape[1] < tw or not np.all(np.isfinite(image)) or np.std(template) <= 0:
        return None
    cc = match_template(image, template)  # (H - th + 1, W - tw + 1): top-left positions
    cr, ccn = _centre(th), _centre(tw)
    rows = np.arange(cc.shape[0]) + cr
    cols = np.arange(cc.shape[1]) + ccn
    mask = np.ones(cc.shape, bool)
    if row_range is not None:
        mask &= ((rows >= row_range[0]) & (rows <= row_range[1]))[:, None]
    if col_range is not None:
        mask &= ((cols >= col_range[0]) & (cols <= col_range[1]))[None, :]
    cc = np.where(mask & np.isfinite(cc), cc, -np.inf)
    if not np.isfinite(cc).any():
        return None
    i, j = np.unravel_index(int(np.argmax(cc)), cc.shape)
    best = float(cc[i, j])
    rr, qq = np.ogrid[: cc.shape[0], : cc.shape[1]]
    far = (np.abs(rr - i) > 2) | (np.abs(qq - j) > 2)
    others = cc[far & mask]
    second = float(np.max(others)) if others.size and np.isfinite(others).any() else -1.0
    ratio = max(second, 0.0) / best if best > 0 else 1.0
    return NccPeak(float(rows[i]), float(cols[j]), best, ratio)


def hac_meat(e: Array, jac: Array, max_lag: int = 4) -> Array:
    """``J^T Sigma_e J`` for residuals ``e (h, w)`` correlated between neighbouring pixels, with
    ``jac (h, w, p)``: the Newey-West (Bartlett-weighted) sum over lags ``|dr|, |dc| <= max_lag`` of
    the residuals' empirical autocovariance ``c(d)`` times ``sum_x J(x) J(x + d)^T`` -- a
    covariance that stays positive semi-definite and reduces to ``c(0) J^T J`` for white residuals."""
    h, w = e.shape
    p = jac.shape[-1]
    meat = np.zeros((p, p))
    for dr in range(-max_lag, max_lag + 1):
        for dc in range(-max_lag, max_lag + 1):
            a = (slice(max(dr, 0), h + min(dr, 0)), slice(max(dc, 0), w + min(dc, 0)))
            b = (slice(max(-dr, 0), h + min(-dr, 0)), slice(max(-dc, 0), w + min(-dc, 0)))
            c = float(np.sum(e[a] * e[b])) / e.size
            wgt = (1 - abs(dr) / (max_lag + 1)) * (1 - abs(dc) / (max_lag + 1))
            meat += wgt * c * np.einsum("ijk,ijl->kl", jac[a], jac[b])
    return 0.5 * (meat + meat.T)


def lsm(
    image: Array,
    template: Array,
    row0: float,
    col0: float,
    max_iter: int = 30,
    tol_px: float = 2e-3,
    max_shift_px: float = 3.0,
    distortion: Array | None = None,
) -> LsmResult:
    """Least-squares matching of ``template`` in ``image`` from the template-centre position
    ``(row0, col0)`` (see the module docstring). Not converged when it leaves the image, moves more
    than ``max_shift_px`` from the start, the normal matrix is singular or ``max_iter`` is reached.

    ``distortion (th, tw, 2)`` px (rows, cols), optional: a known non-affine part of the mapping,
    ``I(A x + t + delta(x))`` -- e.g. terrain relief predicted from a DEM. It must vanish at the
    template centre (``delta(0) = 0``), so ``t`` stays the centre's match."""
    image = np.asarray(image, dtype=float)
    tpl = np.asarray(template, dtype=float)
    th, tw = tpl.shape
    xr, xc = np.meshgrid(np.arange(th) - _centre(th), np.arange(tw) - _centre(tw), indexing="ij")
    xr, xc, tv = xr.ravel(), xc.ravel(), tpl.ravel()
    dr = dc = 0.0
    if distortion is not None:
        dist = np.asarray(distortion, dtype=float)
        if dist.shape != (th, tw, 2) or not np.all(np.isfinite(dist)):
            raise InputError("distortion", dist.shape, f"finite values of shape ({th}, {tw}, 2)")
        dr, dc = dist[..., 0].ravel(), dist[..., 1].ravel()
    n = tv.size
    coeff = ndimage.spline_filter(image, order=3)
    gr, gc = np.gradient(image)
    coeff_r, coeff_c = ndimage.spline_filter(gr, order=3), ndimage.spline_filter(gc, order=3)
    # geometry p = (a00, a01, a10, a11, t_r, t_c); radiometry (r0, r1) from a linear fit first
    p = np.array([0.0, 0.0, 0.0, 0.0, row0, col0])
    h_img, w_img = image.shape
    it = 0
    reason = "iteration limit"
    converged = False
    jtj = np.eye(8)
    e = np.zeros(n)
    r0, r1 = 0.0, 1.0
    for it in range(1, max_iter + 1):
        r = (1 + p[0]) * xr + p[1] * xc + p[4] + dr
        c = p[2] * xr + (1 + p[3]) * xc + p[5] + dc
        if r.min() < 1 or c.min() < 1 or r.max() > h_img - 2 or c.max() > w_img - 2:
            reason = "left the search image"
            break
        coords = np.vstack([r, c])
        iv = ndimage.map_coordinates(coeff, coords, order=3, prefilter=False)
        ir = ndimage.map_coordinates(coeff_r, coords, order=3, prefilter=False)
        ic = ndimage.map_coordinates(coeff_c, coords, order=3, prefilter=False)
        if it == 1:
            r1, r0 = np.polyfit(tv, iv, 1)
        e = iv - (r0 + r1 * tv)
        jac = np.column_stack([ir * xr, ir * xc, ic * xr, ic * xc, ir, ic, -np.ones(n), -tv])
        jtj = jac.T @ jac
        try:
            step = -np.linalg.solve(jtj, jac.T @ e)
        except np.linalg.LinAlgError:
            reason = "singular normal matrix (a flat or one-dimensional pattern)"
            break
        p += step[:6]
        r0 += step[6]
        r1 += step[7]
        if np.hypot(p[4] - row0, p[5] - col0) > max_shift_px:
            reason = f"moved more than {max_shift_px} px from the start"
            break
        if np.hypot(step[4], step[5]) < tol_px and np.max(np.abs(step[:4])) < tol_px / 5:
            converged = True
            reason = ""
            break
    dof = max(n - 8, 1)
    s0 = float(np.sqrt(np.sum(e * e) / dof))
    sig_r = sig_c = float("inf")
    if converged:
        try:
            bread = np.linalg.inv(jtj)
            cov = bread @ hac_meat(e.reshape(th, tw), jac.reshape(th, tw, 8)) @ bread * (n / dof)
            sig_r = float(np.sqrt(max(cov[4, 4], 0.0)))
            sig_c = float(np.sqrt(max(cov[5, 5], 0.0)))
        except np.linalg.LinAlgError:
            converged, reason = False, "singular normal matrix (a flat or one-dimensional pattern)"
    fitted = r0 + r1 * tv
    corr = float(np.corrcoef(fitted + e, tv)[0, 1]) if np.std(tv) > 0 else 0.0
    return LsmResult(float(p[4]), float(p[5]), sig_r, sig_c, s0, corr, it, converged, reason)
