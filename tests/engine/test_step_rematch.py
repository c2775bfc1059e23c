"""Front-end steps checked against the key frames before them (``backend/step_rematch.py``), and the
second loop-closing pass keeping the front end's motions."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.backend.loop_closer import close_loops
from slam_engine.backend.step_rematch import REMATCH_MIN_POINTS, rematch_steps
from slam_engine.config import LoopClosingConfig
from slam_engine.model.poses import compose, relative, wrap_angle
from tests.engine.test_loop_closing import NARROW, _office_key_frames, _office_turning_too_far

# steps whose heading the front end got wrong, and kept wrong afterwards [key frame: rad]
TURNED = {30: 0.2, 60: -0.25, 90: 0.15}


@pytest.fixture(scope="module")
def office() -> tuple[np.ndarray, list[np.ndarray]]:
    return _office_key_frames()


def _step_heading_errors(path: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(K-1,) each step's heading error against the truth's step [rad]."""
    return np.abs(wrap_angle(relative(path[:-1], path[1:])[:, 2] - relative(truth[:-1], truth[1:])[:, 2]))


def _thin(points: np.ndarray, count: int) -> np.ndarray:
    """``count`` of ``points`` (N, 2), spread evenly over the scan."""
    return points[np.linspace(0, len(points) - 1, count).astype(np.int64)]


def _with_turned_steps(truth: np.ndarray) -> np.ndarray:
    path = [truth[0]]
    for k, m in enumerate(relative(truth[:-1], truth[1:]), start=1):
        path.append(compose(path[-1], m + np.array([0.0, 0.0, TURNED.get(k, 0.0)])))
    return np.array(path)


def test_turned_steps_are_replaced_by_the_fit_to_the_key_frames_before(office) -> None:
    """Three steps turned 0.15-0.25 rad (as the campus's front end turns tens of them): each is found
    (its scan scores below 0.3 where the step puts it) and replaced by a fit within 0.02 rad of the
    truth's step; no other step is touched, and the path comes back to the truth's shape."""
    truth, points = office
    path = _with_turned_steps(truth)
    result = rematch_steps(path, points, LoopClosingConfig(), 0.05)
    replaced = {k for k, _, _ in result.replaced}
    assert replaced == set(TURNED), result.replaced
    assert all(step < 0.3 <= fit for _, step, fit in result.replaced)
    errors = _step_heading_errors(result.path, truth)
    assert errors.max() < 0.02, errors.max()
    # untouched steps are the front end's, to the bit
    for k in set(range(1, len(path))) - replaced:
        np.testing.assert_allclose(relative(result.path[k - 1], result.path[k]), relative(path[k - 1], path[k]),
                                   atol=1e-9)
    end_off = relative(truth[0], truth[-1]) - relative(result.path[0], result.path[-1])
    assert np.hypot(end_off[0], end_off[1]) < 0.3 and abs(float(wrap_angle(end_off[2]))) < 0.03
    assert result.summary() == {"steps_replaced": 3, "unverified_steps_replaced": 0}


def test_a_turned_step_with_few_returns_is_replaced(office) -> None:
    """The turned steps' scans keep 20 of their ~520 returns (outdoors, where the campus's front end
    turns its steps most, 82 of 1995 key frames have fewer than 30 returns within match_range_m):
    still found and replaced within 0.01 rad of the truth's step."""
    truth, points = office
    path = _with_turned_steps(truth)
    sparse = [_thin(p, 20) if k in TURNED else p for k, p in enumerate(points)]
    result = rematch_steps(path, sparse, LoopClosingConfig(), 0.05)
    assert {k for k, _, _ in result.replaced} == set(TURNED), result.replaced
    errors = _step_heading_errors(result.path, truth)
    assert max(errors[k - 1] for k in TURNED) < 0.01


def test_a_scan_with_too_few_returns_keeps_its_step(office) -> None:
    """Below REMATCH_MIN_POINTS returns a scan is not searched for: its turned step stays."""
    truth, points = office
    path = _with_turned_steps(truth)
    sparse = [_thin(p, REMATCH_MIN_POINTS - 1) if k in TURNED else p for k, p in enumerate(points)]
    result = rematch_steps(path, sparse, LoopClosingConfig(), 0.05)
    assert not {k for k, _, _ in result.replaced} & set(TURNED)
    errors = _step_heading_errors(result.path, truth)
    np.testing.assert_allclose([errors[k - 1] for k in TURNED], [abs(t) for t in TURNED.values()], atol=1e-9)


def test_an_unverified_step_is_searched_even_where_its_scan_fits(office) -> None:
    """Freiburg 079's real odometry drives forward where the robot backs up: key frames 0.3-0.65 m
    off whose scans still fit the key frames before them at 0.3 and more along the corridors. Step
    50 here runs 0.6 m too far (its scan scores 0.47 where the step puts it): a step the front end
    matched is left as it is; one whose match it rejected is searched and replaced by the fit within
    2 cm and 0.01 rad of the truth's step."""
    truth, points = office
    path = [truth[0]]
    for k, m in enumerate(relative(truth[:-1], truth[1:]), start=1):
        path.append(compose(path[-1], m + np.array([0.6 if k == 50 else 0.0, 0.0, 0.0])))
    path = np.array(path)
    assert rematch_steps(path, points, LoopClosingConfig(), 0.05).replaced == []
    unverified = np.zeros(len(path), bool)
    unverified[50] = True
    result = rematch_steps(path, points, LoopClosingConfig(), 0.05, unverified=unverified)
    assert [k for k, _, _ in result.replaced] == [50]
    assert 0.3 <= result.replaced[0][1] < 0.6 < result.replaced[0][2]  # measured 0.47 -> 0.93
    off = relative(result.path[49], result.path[50]) - relative(truth[49], truth[50])
    assert np.hypot(off[0], off[1]) < 0.02 and abs(off[2]) < 0.01
    assert result.summary() == {"steps_replaced": 1, "unverified_steps_replaced": 1}
    # on open ground (rematch_unverified off) it is left, as a step the front end matched
    outdoors = rematch_steps(path, points, LoopClosingConfig(rematch_unverified=False), 0.05, unverified=unverified)
    assert outdoors.replaced == []


def test_a_right_path_is_left_as_it_is(office) -> None:
    truth, points = office
    result = rematch_steps(truth, points, LoopClosingConfig(), 0.05)
    assert result.replaced == []
    np.testing.assert_allclose(result.path, truth, atol=1e-9)


@pytest.mark.parametrize("settings", [{"rematch_steps": False}, {"enabled": False}])
def test_off_keeps_the_front_ends_steps(office, settings: dict) -> None:
    truth, points = office
    path = _with_turned_steps(truth)
    result = rematch_steps(path, points, LoopClosingConfig(**settings), 0.05)
    assert result.replaced == []
    np.testing.assert_array_equal(result.path, path)


def test_the_second_pass_ties_the_key_frames_by_the_front_ends_motions() -> None:
    """The second pass starts its searches from the first pass's corrected poses, but its graph keeps the
    front end's motions (those of the first pass's result would carry whatever it bent: on the campus's
    seed 4 replayed, 1.52 m with them against 0.17 m for the same closures on the front end's motions)."""
    truth, path, points = _office_turning_too_far()
    twice = close_loops(path, points, LoopClosingConfig(**NARROW, far_second_pass_m=5.0), 0.05)
    assert twice.far_search is not None and "second_pass" in twice.far_search
    motions = [e for e in twice.edges if not e.robust]
    assert len(motions) == len(path) - 1
    for e in motions:
        np.testing.assert_allclose(e.T_i_from_j, relative(path[e.i], path[e.j]), atol=1e-9)
