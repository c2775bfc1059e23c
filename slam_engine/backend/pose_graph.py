"""A sparse 2-D pose graph (GTSAM): key-frame poses tied by the front end's relative motions and by
loop closures, the closures under a robust (Cauchy) loss so that a wrong one cannot drag the map.

Nodes are key-frame poses ``[x_m, y_m, theta_rad]`` in the world frame; an edge ``i -> j`` says
``T_i_from_j`` (the pose of j in i's frame) with standard deviations ``[sd_x_m, sd_y_m, sd_theta_rad]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Edge:
    """``T_i_from_j`` measured with standard deviations ``sigmas`` (3,); ``loss``: "cauchy" (robust,
    scale in standard deviations ``loss_scale``) or "" (least squares)."""

    i: int
    j: int
    T_i_from_j: np.ndarray
    sigmas: np.ndarray
    loss: str = ""
    loss_scale: float = 1.0

    @property
    def robust(self) -> bool:
        return self.loss == "cauchy"


class PoseGraph:
    """Key frames 0..K-1 with an initial guess; node 0 is held where it is."""

    def __init__(self, initial_poses: np.ndarray, cauchy_scale: float = 1.0):
        self.initial = np.asarray(initial_poses, np.float64).copy()
        self.cauchy_scale = float(cauchy_scale)
        self.edges: list[Edge] = []
        # each edge's GTSAM factor, built once (by edge number and whether its robust loss applies):
        # the back end optimises the same graph, grown by a few closures, many times
        self._factors: dict[tuple[int, bool], Any] = {}

    def add_edge(self, i: int, j: int, T_i_from_j: np.ndarray, sigmas: np.ndarray, robust: bool = False) -> None:
        """An edge; ``robust``: under the Cauchy loss (scale ``cauchy_scale`` standard deviations)."""
        self.edges.append(Edge(int(i), int(j), np.asarray(T_i_from_j, np.float64), np.asarray(sigmas, np.float64),
                               "cauchy" if robust else "", self.cauchy_scale if robust else 1.0))

    def optimize(self, estimate: np.ndarray | None = None, nodes: int | None = None,
                 max_iterations: int = 100, robust: bool = True) -> np.ndarray:
        """Optimised poses of nodes ``0..nodes-1`` (default all; edges reaching beyond are left out),
        starting from ``estimate`` (default the initial guess); ``robust`` False treats every edge by
        least squares (a verified closure far from the guess then pulls instead of being ignored)."""
        import gtsam  # imported when first needed: ~40 MB that a run closing no loop never uses

        start = self.initial if estimate is None else np.asarray(estimate, np.float64)
        n = len(start) if nodes is None else int(nodes)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        anchor_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-4, 1e-4, 1e-5]))
        graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*start[0]), anchor_noise))
        for k in range(n):
            values.insert(k, gtsam.Pose2(*start[k]))
        for number, e in enumerate(self.edges):
            if e.i < n and e.j < n:
                graph.add(self._factor(number, robust and e.robust))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        return poses_of(gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize(), n)

    def _factor(self, number: int, robust: bool) -> Any:
        """The GTSAM factor of edge ``number`` (under its Cauchy loss when ``robust``), built once."""
        import gtsam

        factor = self._factors.get((number, robust))
        if factor is None:
            e = self.edges[number]
            noise: Any = gtsam.noiseModel.Diagonal.Sigmas(e.sigmas)
            if robust:
                noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(e.loss_scale), noise)
            factor = self._factors[(number, robust)] = gtsam.BetweenFactorPose2(e.i, e.j, gtsam.Pose2(*e.T_i_from_j),
                                                                                noise)
        return factor


def poses_of(values: Any, n: int) -> np.ndarray:
    """(n, 3) ``[x_m, y_m, theta_rad]`` of the Pose2 values 0..n-1 of a GTSAM result (which holds
    exactly those: GTSAM lists them in key order)."""
    import gtsam

    out = np.asarray(gtsam.utilities.extractPose2(values), np.float64).reshape(-1, 3)
    if len(out) != n:
        raise ValueError(f"poses_of: the result holds {len(out)} poses, expected {n}")
    return out
