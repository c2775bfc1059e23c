"""How good a run is: ``metrics`` (relation errors of Kuemmerle et al. 2009 and the absolute trajectory
error against ground truth), ``halo`` (free space drawn beyond a building's walls), and
``memory_estimate`` (a job's peak memory, predicted from its configuration and log)."""

from typing import TYPE_CHECKING

from slam_engine._exports import lazy_exports

if TYPE_CHECKING:
    from slam_engine.evaluation.metrics import (
        absolute_trajectory_error,
        read_ground_truth,
        read_relations,
        relation_errors,
    )

__all__ = ["absolute_trajectory_error", "read_ground_truth", "read_relations", "relation_errors"]
__getattr__, __dir__ = lazy_exports({name: "slam_engine.evaluation.metrics" for name in __all__})
