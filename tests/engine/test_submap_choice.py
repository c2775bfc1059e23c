"""Loops closed with each submap length tried, keeping the map its key frames contradict least
(``backend/submap_choice.py``)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from slam_engine.backend import submap_choice
from slam_engine.backend.loop_closer import close_loops
from slam_engine.backend.step_rematch import rematch_steps
from slam_engine.backend.submap_choice import close_loops_checked, key_frames_contradicted, submap_lengths
from slam_engine.config import GridConfig, LoopClosingConfig, SlamConfig
from slam_engine.model.poses import compose, relative
from tests.engine.test_loop_closing import _office_key_frames


@pytest.fixture(scope="module")
def office() -> tuple[np.ndarray, list[np.ndarray]]:
    return _office_key_frames()


def test_the_configured_length_comes_first_and_each_length_once() -> None:
    config = LoopClosingConfig(alternative_submap_lengths_m=[16.0, 8.0, 16.0, 4.0])
    assert submap_lengths(config) == [8.0, 16.0, 4.0]
    assert submap_lengths(LoopClosingConfig()) == [8.0]


@pytest.mark.parametrize("lengths", [[0.0], [1001.0], [4.0, 8.0, 12.0, 16.0, 20.0]])
def test_alternative_lengths_are_bounded(lengths: list[float]) -> None:
    with pytest.raises(ValidationError):
        SlamConfig.model_validate({"loop_closing": {"alternative_submap_lengths_m": lengths}})


def test_a_map_whose_parts_overlap_offset_contradicts_more_key_frames(office) -> None:
    """The office's key frames at their true poses hold together; with the second half of the drive
    shifted 0.5 m and turned 0.05 rad against the first, where the two halves overlap the returns of one
    fall where the other's rays crossed."""
    truth, points = office
    grid = GridConfig()
    right = key_frames_contradicted(truth, points, grid)
    half = len(truth) // 2
    broken = truth.copy()
    broken[half:] = compose(np.array([0.5, 0.0, 0.05]), truth[half:])
    offset = key_frames_contradicted(broken, points, grid)
    assert right < 0.02, right
    assert offset > right + 0.1, (right, offset)


def test_each_length_is_tried_and_equal_maps_keep_the_configured_length(office) -> None:
    """A front end that drifts 0.004 rad and 1 % per metre (ATE 1.05 m): loops closed with 8, 16 and 4 m
    submaps all give maps that no key frame contradicts (ATE 0.18 m), and the configured 8 m is kept, as
    loop closing with it alone gives it after the front end's steps were checked."""
    truth, points = office
    path = [truth[0]]
    for m in relative(truth[:-1], truth[1:]):
        d = float(np.hypot(m[0], m[1]))
        path.append(compose(path[-1], np.array([1.01 * m[0], 1.01 * m[1], m[2] + 0.004 * d])))
    path_arr = np.array(path)
    config = LoopClosingConfig(alternative_submap_lengths_m=[16.0, 4.0])
    grid = GridConfig()
    checked = close_loops_checked(path_arr, points, config, grid)
    assert [length for length, _ in checked.tried] == [8.0, 16.0, 4.0]
    assert checked.submap_length_m == 8.0 and [share for _, share in checked.tried] == [0.0, 0.0, 0.0]
    rematched = rematch_steps(path_arr, points, config, grid.resolution_m)
    alone = close_loops(rematched.path, points, config.model_copy(update={"submap_length_m": checked.submap_length_m}),
                        grid.resolution_m)
    np.testing.assert_array_equal(checked.backend.poses, alone.poses)
    for length, share in checked.tried:
        again = close_loops(rematched.path, points, config.model_copy(update={"submap_length_m": length}),
                            grid.resolution_m)
        assert key_frames_contradicted(again.poses, points, grid) == pytest.approx(share)
    summary = checked.summary()
    assert summary["submap_length_m"] == checked.submap_length_m
    assert [row["submap_length_m"] for row in summary["submap_lengths_tried"]] == [8.0, 16.0, 4.0]


@pytest.mark.parametrize("broken", [8.0, 16.0])
def test_the_map_that_holds_together_is_kept(office, monkeypatch, broken: float) -> None:
    """Of two loop closings, the one whose result has its second half shifted 0.5 m and turned 0.05 rad
    against the first (as a wrong or missing closure leaves it) is dropped, whichever length gave it."""
    truth, points = office
    real = submap_choice.close_loops

    def closing(path, points_v, config, *args, **kwargs):
        result = real(path, points_v, config, *args, **kwargs)
        if config.submap_length_m == broken:
            half = len(result.poses) // 2
            result.poses[half:] = compose(np.array([0.5, 0.0, 0.05]), result.poses[half:])
        return result

    monkeypatch.setattr(submap_choice, "close_loops", closing)
    checked = close_loops_checked(truth, points, LoopClosingConfig(alternative_submap_lengths_m=[16.0]), GridConfig())
    kept = 16.0 if broken == 8.0 else 8.0
    assert checked.submap_length_m == kept
    shares = dict(checked.tried)
    assert shares[kept] < 0.02 < 0.1 < shares[broken], shares
    np.testing.assert_allclose(checked.backend.poses[:, :2], truth[:, :2], atol=0.05)


def test_without_alternatives_loop_closing_is_as_before(office) -> None:
    truth, points = office
    path = truth
    checked = close_loops_checked(path, points, LoopClosingConfig(), GridConfig())
    plain = close_loops(rematch_steps(path, points, LoopClosingConfig(), 0.05).path, points, LoopClosingConfig(), 0.05)
    np.testing.assert_array_equal(checked.backend.poses, plain.poses)
    assert checked.tried == [] and checked.submap_length_m == 8.0
    assert checked.summary() == {"steps_replaced": 0, "unverified_steps_replaced": 0}

