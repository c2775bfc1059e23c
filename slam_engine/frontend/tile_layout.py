"""The layout of the particles' tiled maps (:mod:`slam_engine.frontend.grid`), in a module of its own so
that what only needs the sizes - the memory estimate a service runs before a job - does not load the
kernels (numba)."""

from __future__ import annotations

import numpy as np

TILE_SHIFT = 6
TILE = 1 << TILE_SHIFT  # cells per tile side at level 0
N_LEVELS = 4  # level k: cells of 2**k * resolution_m, tiles of TILE >> k cells
POOL_DTYPE = np.int16
POOL_GROWTH_DIVISOR = 32  # the pool grows by 1 / this of its size (at least; 8 kept intel 7 MB higher)
