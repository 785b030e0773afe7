"""Scatter per-observation Jacobian blocks into per-factor dense matrices, vectorised.

A factor groups the observations that share a group id (e.g. all views of one landmark). Each
observation has ``rows`` residual rows and a set of *slots* (landmark, ephemeris, knots, ...), each
slot naming a key per observation and a block of ``dim`` columns. :class:`BlockLayout` works out,
once, each factor's ordered key list and column offsets and the flat positions of every
(observation, slot) block in one buffer, so that assembling all factors' Jacobians is a handful
of numpy assignments instead of Python loops.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["BlockLayout"]


@dataclass
class BlockLayout:
    """Layout of factors over observations sorted by ``group``.

    Parameters
    ----------
    group: (N,) int, non-decreasing factor index of each observation.
    slot_keys: list of (N,) int arrays, the key of each slot for each observation (-1: unused).
    slot_dims: dimension of each slot's variable.
    rows: residual rows per observation.
    """

    group: NDArray[np.int64]
    slot_keys: list[NDArray[np.int64]]
    slot_dims: list[int]
    rows: int

    def __post_init__(self) -> None:
        g = np.asarray(self.group, dtype=np.int64)
        if g.size and np.any(np.diff(g) < 0):
            raise ValueError("BlockLayout.group must be sorted (non-decreasing)")
        n = g.size
        self.n_factors = int(g.max()) + 1 if n else 0
        starts = np.searchsorted(g, np.arange(self.n_factors + 1))
        self.obs_start = starts[:-1]
        self.obs_stop = starts[1:]
        self.factor_keys: list[list[int]] = []
        self.factor_dims: list[list[int]] = []
        self.col_start: list[NDArray[np.int64]] = []
        self.buf_offset = np.zeros(self.n_factors + 1, np.int64)
        self.n_cols = np.zeros(self.n_factors, np.int64)
        slot_col = [np.zeros(n, np.int64) for _ in self.slot_keys]
        for f in range(self.n_factors):
            a, b = self.obs_start[f], self.obs_stop[f]
            keys: list[int] = []
            dims: list[int] = []
            where: dict[int, int] = {}
            col = 0
            for s, (sk, d) in enumerate(zip(self.slot_keys, self.slot_dims)):
                for i in range(a, b):
                    k = int(sk[i])
                    if k < 0:
                        continue
                    if k not in where:
                        where[k] = col
                        keys.append(k)
                        dims.append(d)
                        col += d
                    slot_col[s][i] = where[k]
            self.factor_keys.append(keys)
            self.factor_dims.append(dims)
            self.col_start.append(np.cumsum([0] + dims[:-1]).astype(np.int64))
            self.n_cols[f] = col
            self.buf_offset[f + 1] = self.buf_offset[f] + (b - a) * self.rows * col
        # flat buffer positions of every (observation, slot) block
        obs_local = np.arange(n) - self.obs_start[g] if n else np.zeros(0, np.int64)
        ncol_obs = self.n_cols[g] if n else np.zeros(0, np.int64)
        base = self.buf_offset[g] + obs_local * self.rows * ncol_obs if n else np.zeros(0, np.int64)
        self.slot_index: list[NDArray[np.int64]] = []
        self.slot_used: list[NDArray[np.bool_]] = []
        rr = np.arange(self.rows)
        for s, d in enumerate(self.slot_dims):
            used = np.asarray(self.slot_keys[s]) >= 0
            cc = np.arange(d)
            idx = (
                base[:, None, None]
                + rr[None, :, None] * ncol_obs[:, None, None]
                + slot_col[s][:, None, None]
                + cc[None, None, :]
            )
            self.slot_index.append(idx[used])
            self.slot_used.append(used)
        self.size = int(self.buf_offset[-1])

    def assemble(
        self, blocks: list[NDArray[np.float64]], select: NDArray[np.int64] | None = None
    ) -> NDArray[np.float64]:
        """Flat buffer of all factors' Jacobians from per-slot blocks ``(N, rows, dim)``."""
        buf = np.zeros(self.size)
        for s, blk in enumerate(blocks):
            used = self.slot_used[s]
            buf[self.slot_index[s]] = blk[used]
        return buf

    def factor_matrix(self, buf: NDArray[np.float64], f: int) -> NDArray[np.float64]:
        """The dense (rows * n_obs, n_cols) Jacobian of factor ``f`` (a view into ``buf``)."""
        m = (self.obs_stop[f] - self.obs_start[f]) * self.rows
        return buf[self.buf_offset[f] : self.buf_offset[f + 1]].reshape(m, self.n_cols[f])

    def split(self, a: NDArray[np.float64], f: int) -> list[NDArray[np.float64]]:
        """Per-key column blocks of a factor matrix, in ``factor_keys[f]`` order."""
        return [a[:, c : c + d] for c, d in zip(self.col_start[f], self.factor_dims[f])]
