"""Optional numba kernel for the normal-equation accumulation of :mod:`misrgraph.estimate.problem`.

Why: the vectorised numpy accumulation (batched matmul + ``np.bincount`` scatter of millions of
Hessian contributions on a standard pass) is a large share of each iteration; this fused loop
does the same sums in one pass over the observations (``misrgraph bench sba`` times both).
:func:`accumulate` returns ``None`` when numba is not installed, and the caller falls back to
the numpy path (both are tested to agree).
"""

from __future__ import annotations

import numpy as np

__all__ = ["accumulate", "HAVE_NUMBA"]

try:  # pragma: no cover - exercised when numba is installed
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False


if HAVE_NUMBA:

    @njit(cache=True)
    def _accumulate(bl, bc, r, lm, cc, nl3, n_c):  # pragma: no cover - compiled
        blk = np.zeros((nl3, 3, 3))
        hlc = np.zeros((nl3, 3, n_c))
        hcc = np.zeros((n_c, n_c))
        gl = np.zeros((nl3, 3))
        gc = np.zeros(n_c)
        n_obs, rows, d_nav = bc.shape
        for n in range(n_obs):
            l = lm[n]  # noqa: E741 - the landmark index, as in the equations
            for k in range(rows):
                rk = r[n, k]
                for i in range(3):
                    a = bl[n, k, i]
                    gl[l, i] += a * rk
                    for j in range(3):
                        blk[l, i, j] += a * bl[n, k, j]
                    for d in range(d_nav):
                        c = cc[n, d]
                        if c >= 0:
                            hlc[l, i, c] += a * bc[n, k, d]
                for d in range(d_nav):
                    c = cc[n, d]
                    if c < 0:
                        continue
                    b = bc[n, k, d]
                    gc[c] += b * rk
                    for e in range(d_nav):
                        c2 = cc[n, e]
                        if c2 >= 0:
                            hcc[c, c2] += b * bc[n, k, e]
        return blk, hlc, hcc, gl, gc


def accumulate(bl, bc, r, lm, cc, nl3: int, n_c: int):
    """``(H_ll, H_lc, H_cc, g_l, g_c)`` from whitened per-observation blocks, or None without numba."""
    if not HAVE_NUMBA:
        return None
    return _accumulate(
        np.ascontiguousarray(bl),
        np.ascontiguousarray(bc),
        np.ascontiguousarray(r),
        np.ascontiguousarray(lm, dtype=np.int64),
        np.ascontiguousarray(cc, dtype=np.int64),
        nl3,
        n_c,
    )
