"""Shortest paths over an undirected graph with positive edge lengths: how much drive separates two
key frames, over the front end's motions and accepted closures (:class:`~slam_engine.backend.loop_closer.
LoopCloser` sizes its search windows by it).

A numba Dijkstra on the graph in compressed sparse rows (both directions of every edge stored), so
that the back end needs neither scipy.sparse (about 20 MB resident and 0.25 s to import) nor a
conversion per search.
"""

from __future__ import annotations

import heapq

import numba as nb
import numpy as np


def adjacency(n_nodes: int, i: np.ndarray, j: np.ndarray, length: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indptr (n+1,), neighbours, lengths) of the undirected edges ``i[k] - j[k]`` of ``length[k]``:
    node u's neighbours are ``neighbours[indptr[u]:indptr[u + 1]]``."""
    i = np.asarray(i, np.int64)
    j = np.asarray(j, np.int64)
    length = np.asarray(length, np.float64)
    if not (len(i) == len(j) == len(length)):
        raise ValueError(f"adjacency: {len(i)} start nodes, {len(j)} end nodes, {len(length)} lengths")
    if len(i) and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n_nodes):
        raise ValueError(f"adjacency: an edge names a node outside 0..{n_nodes - 1}")
    if np.any(~(length > 0)):
        raise ValueError("adjacency: edge lengths must be positive")
    source = np.concatenate([i, j])
    order = np.argsort(source, kind="stable")
    indptr = np.zeros(n_nodes + 1, np.int64)
    np.cumsum(np.bincount(source, minlength=n_nodes), out=indptr[1:])
    return indptr, np.concatenate([j, i])[order], np.concatenate([length, length])[order]


@nb.njit(cache=True, nogil=True)
def shortest_distances(indptr, neighbours, lengths, source, limit):
    """(n,) length of the shortest path from ``source`` to every node (:func:`adjacency`'s arrays);
    inf where it is longer than ``limit`` or there is none."""
    n = indptr.shape[0] - 1
    dist = np.full(n, np.inf)
    dist[source] = 0.0
    heap = [(0.0, source)]
    while len(heap):
        d, u = heapq.heappop(heap)
        if d > dist[u]:  # a stale entry: u was reached by a shorter path since
            continue
        for e in range(indptr[u], indptr[u + 1]):
            v = neighbours[e]
            candidate = d + lengths[e]
            if candidate < dist[v] and candidate <= limit:
                dist[v] = candidate
                heapq.heappush(heap, (candidate, v))
    return dist
