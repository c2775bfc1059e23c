"""Which alternatives a run tries when its map contradicts itself, and which map it keeps
(``backend/flagged_retry.py``; a whole run that keeps the better map: test_slam_real_odometry.py)."""

from __future__ import annotations

import numpy as np

from slam_engine.backend.flagged_retry import KEEP_AT_MOST, FlaggedRetry, kept_alternative, retry_alternatives
from slam_engine.backend.loop_closer import LoopClosingResult
from slam_engine.backend.step_rematch import StepRematch
from slam_engine.backend.submap_choice import CheckedLoopClosing
from slam_engine.config import LoopClosingConfig


def _checked(replaced: int, tried: list[tuple[float, float]] | None = None) -> CheckedLoopClosing:
    rematched = StepRematch(path=np.zeros((3, 3)), replaced=[(1, 0.1, 0.9)] * replaced)
    return CheckedLoopClosing(rematched, LoopClosingResult(poses=np.zeros((3, 3))), 8.0, tried or [])


def test_a_step_check_that_replaced_steps_is_tried_off_then_longer_submaps() -> None:
    config = LoopClosingConfig()
    names = [(name, c.rematch_steps, c.submap_length_m) for name, c in retry_alternatives(config, _checked(3))]
    assert names == [("step check off", False, 8.0), ("16 m submaps", True, 16.0)]
    # a step check that replaced nothing would give the same map again
    assert [name for name, _ in retry_alternatives(config, _checked(0))] == ["16 m submaps"]


def test_no_alternative_where_the_submap_lengths_were_tried_or_loops_are_not_closed() -> None:
    """On open ground both submap lengths are tried on every run: that choice is the retry there."""
    assert retry_alternatives(LoopClosingConfig(), _checked(5, [(8.0, 0.4), (16.0, 0.38)])) == []
    assert retry_alternatives(LoopClosingConfig(enabled=False), _checked(5)) == []


def test_an_alternative_is_kept_only_when_it_contradicts_clearly_less() -> None:
    assert kept_alternative(0.20, [0.017, 0.20]) == 0  # real intel paired at its stamps
    assert kept_alternative(0.20, [0.30, 0.09]) == 1
    assert kept_alternative(0.50, [0.46, 0.52]) is None  # outdoors: 30-55 % for sound and broken maps alike
    assert kept_alternative(0.20, [KEEP_AT_MOST * 0.20]) == 0
    assert kept_alternative(0.20, []) is None
    summary = FlaggedRetry(0.2, [("step check off", 0.017)], kept="step check off").summary()
    assert summary == {"first_key_frames_contradicted_share": 0.2, "kept": "step check off",
                       "alternatives": [{"alternative": "step check off", "key_frames_contradicted_share": 0.017}]}
