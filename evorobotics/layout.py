"""Where each weight of the chromosome lives in the network (Eqs 4-6, 8).

The chromosome C is every sub-matrix W[m,t,s] flattened row-major (neuron n, then input i,
bias last), the sub-matrices ordered by layer m, then lag t, then source level s: exactly the
paper's order w_{m,t,s,n,i}. A level s that layer m lacks (`spec.source(m, s)` is None: beyond
its recurrence depth) has no block.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from schemas.network import NetworkSpec


@dataclass(frozen=True)
class Block:
    """One sub-matrix W[m,t,s]: `rows` neurons of layer m x (`cols` - 1 source neurons + bias)."""

    m: int
    t: int
    s: int
    src: int
    rows: int
    cols: int
    offset: int

    @property
    def size(self) -> int:
        return self.rows * self.cols


@dataclass(frozen=True)
class Layout:
    """The block table of a spec plus per-weight indices for the GA's Eqs 7, 9 and 10."""

    spec: NetworkSpec
    blocks: tuple[Block, ...]
    n_weights: int
    m: np.ndarray
    """(n_weights,) layer index m of each weight (1..M)."""
    t: np.ndarray
    """(n_weights,) delay lag t of each weight (0..T)."""
    s: np.ndarray
    """(n_weights,) source level s of each weight (0..S, S the largest depth of any layer)."""
    block_size: np.ndarray
    """(n_weights,) N*I of the sub-matrix each weight belongs to (Eq 9)."""

    def view(self, weights: np.ndarray, block: Block) -> np.ndarray:
        """The (..., rows, cols) sub-matrix of `block` in a (..., n_weights) weight array."""
        flat = weights[..., block.offset : block.offset + block.size]
        return flat.reshape(*weights.shape[:-1], block.rows, block.cols)


@cache
def layout(spec: NetworkSpec) -> Layout:
    """The layout of `spec` (cached: specs are frozen and hashable)."""
    sizes = spec.sizes
    blocks: list[Block] = []
    offset = 0
    for m in range(1, spec.layers + 1):
        for t in range(spec.delays + 1):
            for s in range(spec.layers + 1):
                src = spec.source(m, s)
                if src is None:
                    continue
                block = Block(m, t, s, src, sizes[m], sizes[src] + 1, offset)
                blocks.append(block)
                offset += block.size
    m_idx, t_idx, s_idx, bsize = (np.empty(offset, dtype=np.int64) for _ in range(4))
    for b in blocks:
        sl = slice(b.offset, b.offset + b.size)
        m_idx[sl], t_idx[sl], s_idx[sl], bsize[sl] = b.m, b.t, b.s, b.size
    for arr in (m_idx, t_idx, s_idx, bsize):
        arr.flags.writeable = False
    return Layout(spec, tuple(blocks), offset, m_idx, t_idx, s_idx, bsize)
