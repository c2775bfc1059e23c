"""Pooling an occupancy grid's log-odds into larger cells (animation frames, previews, products):
a numba kernel, without engine imports (``result`` uses it)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def pool_known_max(log_odds: np.ndarray, factor: int) -> np.ndarray:
    """(ceil(H / factor), ceil(W / factor)) float32: each block of ``factor`` x ``factor`` cells of
    ``log_odds`` (H, W) float32 as the largest of its known (non-zero) values, 0 where none is known."""
    h, w = log_odds.shape
    out = np.zeros(((h + factor - 1) // factor, (w + factor - 1) // factor), np.float32)
    known = np.zeros(out.shape, np.bool_)
    for i in range(h):
        oi = i // factor
        for j in range(w):
            v = log_odds[i, j]
            if v != 0.0:
                oj = j // factor
                if not known[oi, oj] or v > out[oi, oj]:
                    out[oi, oj] = v
                    known[oi, oj] = True
    return out
