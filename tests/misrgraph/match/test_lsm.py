"""NCC and least-squares matching against shifts made by an independent resampler (scipy.ndimage.shift)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage, stats

from misrgraph.match.lsm import hac_meat, lsm, ncc_search


def _pair(rng: np.random.Generator, shift: tuple[float, float], noise: float = 20.0, size: int = 60):
    """A band-limited random image, the same image shifted by ``shift`` (row, col) with noise, and a
    15 x 15 template cut at centre (29, 29) of the unshifted one."""
    big = ndimage.gaussian_filter(rng.standard_normal((size, size)), 1.5) * 1000 + 5000
    img = ndimage.shift(big, shift, order=3, mode="nearest") + rng.standard_normal(big.shape) * noise
    tpl = big[22:37, 22:37] + rng.standard_normal((15, 15)) * noise
    return img, tpl


def test_lsm_recovers_subpixel_shifts_with_honest_sigma():
    """200 random sub-pixel shifts: the matched template centre is 29 + shift; the reported sigma
    is honest (error / sigma RMS inside the 99 % chi-square band for 400 coordinates)."""
    rng = np.random.default_rng(1)
    z = []
    for _ in range(200):
        dr, dc = rng.uniform(-0.5, 0.5, 2)
        img, tpl = _pair(rng, (dr, dc))
        peak = ncc_search(img, tpl)
        assert peak is not None and abs(peak.row - (29 + dr)) <= 1 and abs(peak.col - (29 + dc)) <= 1
        res = lsm(img, tpl, peak.row, peak.col)
        assert res.converged, res.reason
        assert abs(res.row - (29 + dr)) < 0.15 and abs(res.col - (29 + dc)) < 0.15
        z += [(res.row - 29 - dr) / res.sigma_row, (res.col - 29 - dc) / res.sigma_col]
    k = len(z)
    lo, hi = (np.sqrt(stats.chi2.ppf(q, k) / k) for q in (0.005, 0.995))
    # the resampler's own interpolation error is not in the model: allow 15 % over the band's top
    assert lo <= np.sqrt(np.mean(np.square(z))) <= 1.15 * hi


def test_lsm_fits_a_radiometric_change_and_a_rotation():
    """A template of another radiometry (gain 0.7, offset 300) and a 3-degree rotation is matched to
    its true centre; the white-noise case is exact to the noise level."""
    rng = np.random.default_rng(2)
    big = ndimage.gaussian_filter(rng.standard_normal((80, 80)), 2.0) * 1000 + 5000
    rot = ndimage.rotate(big, 3.0, reshape=False, order=3, mode="nearest")  # about the centre (39.5, 39.5)
    tpl = 0.7 * big[32:47, 32:47] + 300.0
    peak = ncc_search(rot, tpl)
    res = lsm(rot, tpl, peak.row, peak.col)
    assert res.converged
    # the rotation about (39.5, 39.5) moves the template centre (39, 39) by 0.71 px * 3 deg = 0.04 px
    assert np.hypot(res.row - 39.0, res.col - 39.0) < 0.1


def test_flat_and_bad_inputs_are_reported_not_raised():
    rng = np.random.default_rng(3)
    img, tpl = _pair(rng, (0.2, -0.3))
    assert ncc_search(img, np.full((15, 15), 7.0)) is None  # flat template
    nan_img = img.copy()
    nan_img[5, 5] = np.nan
    assert ncc_search(nan_img, tpl) is None  # NaN pixels
    assert ncc_search(img[:10, :10], tpl) is None  # template larger than the image
    res = lsm(np.full((40, 40), 5000.0) + rng.standard_normal((40, 40)), tpl, 20.0, 20.0)
    assert not res.converged and res.reason  # a flat image: no convergence, and a reason
    off = lsm(img, tpl, 3.0, 3.0)  # starting with the template hanging off the image
    assert not off.converged and "left the search image" in off.reason


def test_hac_meat_reduces_to_the_white_noise_formula():
    """Lag 0 only: mean(e^2) J^T J; with lags, correlated residuals (a smoothed field) give a larger
    position variance than white ones of the same variance."""
    rng = np.random.default_rng(4)
    jac = rng.standard_normal((15, 15, 3))
    e = rng.standard_normal((15, 15))
    j2 = jac.reshape(-1, 3)
    np.testing.assert_allclose(hac_meat(e, jac, max_lag=0), np.mean(e * e) * j2.T @ j2, rtol=1e-12)
    smooth = ndimage.gaussian_filter(rng.standard_normal((15, 15)), 1.5)
    smooth *= np.std(e) / np.std(smooth)
    grad = np.stack(np.gradient(ndimage.gaussian_filter(rng.standard_normal((15, 15)), 1.5)), -1)
    jw, js = hac_meat(e, grad), hac_meat(smooth, grad)
    assert np.trace(js) > np.trace(jw)


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.37, -0.21)])
def test_ncc_peak_ratio_flags_repetitive_texture(shift):
    """A periodic pattern (period 6 px) correlates almost equally at the next period: ratio near 1."""
    rr, cc = np.mgrid[:60, :60].astype(float)
    img = 1000 * np.sin(2 * np.pi * (rr - shift[0]) / 6) * np.sin(2 * np.pi * (cc - shift[1]) / 6) + 5000
    tpl = img[22:37, 22:37]
    peak = ncc_search(img, tpl)
    assert peak.ratio > 0.9


def test_a_known_non_affine_distortion_is_followed():
    """Template T(x) = I(x + t + delta(x)) of a band-limited analytic image: with ``distortion=delta``
    LSM recovers t to interpolation accuracy; without it the non-affine part biases t."""
    rng = np.random.default_rng(0)
    k = rng.normal(size=(30, 2)) * 0.5
    ph = rng.uniform(0, 2 * np.pi, 30)

    def g(r, c):
        return sum(np.cos(k[i, 0] * r + k[i, 1] * c + ph[i]) for i in range(30))

    rr, cc = np.meshgrid(np.arange(41.0), np.arange(41.0), indexing="ij")
    x = np.arange(15) - 7.0
    xr, xc = np.meshgrid(x, x, indexing="ij")
    t = (20.3, 19.6)
    delta = np.stack([0.3 * np.sin(xr / 3) * np.cos(xc / 4), 0.1 * np.cos(xr / 5)], -1)
    delta -= delta[7, 7]
    tpl = g(xr + t[0] + delta[..., 0], xc + t[1] + delta[..., 1])
    plain = lsm(g(rr, cc), tpl, 20, 20)
    aided = lsm(g(rr, cc), tpl, 20, 20, distortion=delta)
    assert aided.converged and np.hypot(aided.row - t[0], aided.col - t[1]) < 2e-3
    assert np.hypot(plain.row - t[0], plain.col - t[1]) > 10 * np.hypot(aided.row - t[0], aided.col - t[1])
    with pytest.raises(ValueError, match="distortion"):
        lsm(g(rr, cc), tpl, 20, 20, distortion=delta[:-1])
