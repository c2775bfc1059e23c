"""The back end on its own: branch-and-bound matching, loop closures on a simulated drive whose
front-end path drifts, and the checks that keep a symmetric corridor from closing a false loop."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.backend import map_alignment
from slam_engine.backend.correlative import (
    NO_ORIGINS,
    MatchGrid,
    branch_and_bound,
    fit_pose,
    max_pyramid,
    refine_pose,
    refine_poses,
    search,
)
from slam_engine.backend.loop_closer import (
    HEADING_TURN_TOO_FAR,
    OUTSCORED,
    LoopCloser,
    close_loops,
    overlap_score,
    overlapping_points,
)
from slam_engine.backend.map_alignment import align_to_map
from slam_engine.backend.pose_graph import PoseGraph
from slam_engine.backend.submaps import match_grid_from_points, observed_mask
from slam_engine.config import LoopClosingConfig, SlamConfig
from slam_engine.evaluation.metrics import absolute_trajectory_error
from slam_engine.frontend.lidar_points import ScanProjector
from slam_engine.model.poses import compose, place_points, relative, wrap_angle
from slam_engine.model.result import Trajectory
from slam_engine.simulation import simulate


def _ate(poses: np.ndarray, truth: np.ndarray) -> float:
    t = np.arange(len(poses), dtype=float)
    return absolute_trajectory_error(Trajectory(t, poses), Trajectory(t, truth))


@pytest.mark.parametrize("near_low_edges", [False, True])
@pytest.mark.parametrize("with_origins", [False, True])
def test_branch_and_bound_finds_the_exhaustive_maximum(near_low_edges: bool, with_origins: bool) -> None:
    """Also where the best shift puts points left of and below the grid, with most of the map's weight
    on its low edges: blocks that start off the grid must still bound what they cover of it. With
    ``origins``, the best of the translations that put the scan's origin on an allowed cell."""
    rng = np.random.default_rng(3)
    for trial in range(5):
        values = (rng.random((40, 48)) ** 4 * 255).astype(np.uint8)
        if near_low_edges:
            values[6:, 6:] //= 8
        grid = MatchGrid.from_values(values, np.zeros(2), 0.1, n_levels=5)
        # 7 headings, 25 points, some near or beyond the map's edges
        low, high = (-4, 20) if near_low_edges else (-12, 52)
        cells = rng.integers(low, high, size=(7, 25, 2)).astype(np.int32)
        window = 9 + trial
        allowed = rng.random(values.shape) < 0.2 if with_origins else np.ones(values.shape, bool)
        origins = max_pyramid(allowed.astype(np.uint8), 5) if with_origins else NO_ORIGINS
        ox, oy = 20, 21  # the scan's origin, untranslated [cells]
        best = -1
        for a in range(7):
            for dx in range(-window, window + 1):
                for dy in range(-window, window + 1):
                    if not allowed[oy + dy, ox + dx]:
                        continue
                    x, y = cells[a, :, 0] + dx, cells[a, :, 1] + dy
                    inside = (x >= 0) & (x < grid.values.shape[1]) & (y >= 0) & (y < grid.values.shape[0])
                    best = max(best, int(grid.values[y[inside], x[inside]].astype(np.int64).sum()))
        a, dx, dy, total = branch_and_bound(grid.pyramid, cells, window, 0, 0, 0, 0, -1, 0, 0.0, 0.0, 1, origins, ox,
                                            oy)
        assert total == best and a >= 0 and allowed[oy + dy, ox + dx]
        for shards in (2, 3):  # searched in parallel: the same pose
            in_shards = branch_and_bound(grid.pyramid, cells, window, 0, 0, 0, 0, -1, 0, 0.0, 0.0, shards, origins,
                                         ox, oy)
            assert in_shards == (a, dx, dy, total)


def test_branch_and_bound_first_only_answers_whether_a_pose_beats_the_floor() -> None:
    """``first_only`` stops at the first leaf above ``min_total``: there is one exactly when the full
    search finds one, and it does beat the floor, whatever the number of threads."""
    rng = np.random.default_rng(11)
    for trial in range(20):
        values = (rng.random((40, 48)) ** 3 * 255).astype(np.uint8)
        grid = MatchGrid.from_values(values, np.zeros(2), 0.1, n_levels=5)
        cells = rng.integers(0, 40, size=(5, 20, 2)).astype(np.int32)
        best = branch_and_bound(grid.pyramid, cells, 8, 0, 0, 0, 0, -1, 0, 0.0, 0.0, 1, NO_ORIGINS, 0, 0)[3]
        floor = int(best * (0.9 + 0.01 * trial))  # some floors below the best, some above it
        for shards in (1, 2, 3):
            a, _, _, total = branch_and_bound(grid.pyramid, cells, 8, floor, 0, 0, 0, -1, 0, 0.0, 0.0, shards,
                                              NO_ORIGINS, 0, 0, True)
            assert (a >= 0) == (best > floor)
            assert a < 0 or floor < total <= best


def test_branch_and_bound_breaks_ties_alike_in_any_number_of_shards() -> None:
    """A map of a few equal values gives many equally good poses: the one picked is the first the
    search reaches, whichever shard reaches it and however fast."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        values = ((rng.random((40, 48)) < 0.15) * 255).astype(np.uint8)
        grid = MatchGrid.from_values(values, np.zeros(2), 0.1, n_levels=5)
        cells = rng.integers(0, 40, size=(5, 6, 2)).astype(np.int32)
        found = {branch_and_bound(grid.pyramid, cells, 8, 0, 0, 0, 0, -1, 0, 0.0, 0.0, shards, NO_ORIGINS, 0,
                                  0) for shards in (1, 2, 3, 4)}
        assert len(found) == 1, found
        # the runner-up search (an exclusion zone around the best) as well
        a, dx, dy, total = found.pop()
        runner_up = {branch_and_bound(grid.pyramid, cells, 8, total // 2, a, dx, dy, 1, 3, 0.0, 0.0, shards,
                                     NO_ORIGINS, 0, 0)
                     for shards in (1, 2, 3, 4)}
        assert len(runner_up) == 1, runner_up


def _room_points(rng: np.random.Generator) -> np.ndarray:
    """End points on the walls of an irregular 8 x 6 m room with a pillar [m]."""
    walls = [((0, 0), (8, 0)), ((8, 0), (8, 6)), ((8, 6), (3, 6)), ((3, 6), (3, 4)), ((3, 4), (0, 4)),
             ((0, 4), (0, 0)), ((5, 2), (5.6, 2)), ((5.6, 2), (5.6, 2.6)), ((5.6, 2.6), (5, 2.6)), ((5, 2.6), (5, 2))]
    pts = []
    for (x0, y0), (x1, y1) in walls:
        n = int(np.hypot(x1 - x0, y1 - y0) / 0.05)
        f = rng.random(n)
        pts.append(np.stack([x0 + f * (x1 - x0), y0 + f * (y1 - y0)], axis=1))
    return np.concatenate(pts)


def test_max_pyramid_holds_the_largest_value_of_each_block() -> None:
    values = np.random.default_rng(3).integers(0, 256, size=(37, 53)).astype(np.uint8)
    pyramid = max_pyramid(values, 5)
    for level in range(5):
        size = 1 << level
        for y in range(37):
            for x in range(53):
                assert pyramid[level, y, x] == values[y: y + size, x: x + size].max(), (level, y, x)


def test_a_point_marks_its_cells_and_blurs_onto_their_neighbours() -> None:
    """A point on the corner of four cells (the grid's lattice starts a whole number of cells from it)
    marks each with twice its bilinear weight (0.25 -> 0.5: 128 of 255); the cells around them get 0.45
    of that beside and 0.2 diagonally; nothing farther."""
    point = np.array([[1.0, 2.0]])
    grid = match_grid_from_points(point, 0.05, margin_m=0.2)
    i, j = np.floor((point[0] - grid.origin_m) / 0.05 + 1e-9).astype(int)  # the cell above and right of it
    block = grid.values[j - 3: j + 3, i - 3: i + 3].astype(int)
    expected = np.zeros((6, 6), int)
    expected[1:5, 1:5] = [[26, 57, 57, 26], [57, 128, 128, 57], [57, 128, 128, 57], [26, 57, 57, 26]]
    assert np.array_equal(block, expected)


def test_search_recovers_a_pose_metres_and_degrees_away() -> None:
    rng = np.random.default_rng(0)
    room = _room_points(rng)
    grid = match_grid_from_points(room, 0.05, margin_m=1.0)
    truth = np.array([2.0, 1.5, 0.3])
    scan = relative(truth, np.column_stack([room[::4], np.zeros(len(room[::4]))]))[:, :2]  # room in the scan frame
    guess = truth + np.array([1.2, -0.9, -0.25])
    match = search(grid, scan, guess, window_m=2.0, window_rad=0.4, min_score=0.5, ambiguity_m=0.5,
                   ambiguity_rad=0.1, runner_up_share=0.5)
    assert match is not None
    assert np.hypot(*(match.pose[:2] - truth[:2])) < 0.08  # on the lattice: within a cell or two
    assert abs(match.pose[2] - truth[2]) < 0.01
    assert match.score > 0.6 and match.runner_up_score < 0.8 * match.score
    refined = refine_pose(grid, scan, match.pose)
    assert np.hypot(*(refined[:2] - truth[:2])) < 0.02
    assert abs(refined[2] - truth[2]) < 0.004


def test_a_local_fit_reaches_the_pose_from_a_close_prediction_and_refine_does_not() -> None:
    rng = np.random.default_rng(0)
    room = _room_points(rng)
    grid = match_grid_from_points(room, 0.05, margin_m=1.0)
    truth = np.array([2.0, 1.5, 0.3])
    scan = relative(truth, np.column_stack([room[::4], np.zeros(len(room[::4]))]))[:, :2]
    guess = truth + np.array([0.09, -0.07, 0.03])  # two cells and 1.7 degrees off
    fitted = fit_pose(grid, scan, guess)
    assert np.hypot(*(fitted[:2] - truth[:2])) < 0.02 and abs(fitted[2] - truth[2]) < 0.004
    np.testing.assert_array_equal(refine_pose(grid, scan, guess), guess)  # bounded to a cell: it keeps the start


def test_unobserved_cells_are_neutral() -> None:
    """A scan from the middle of a 4 m round room sees its inside: those cells are seen (free space
    0, the walls hits); outside the room, where the scan never looked, the grid holds the neutral
    value, so a point there is neither a hit nor a miss."""
    bearings = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    wall = np.column_stack([2.0 * np.cos(bearings), 2.0 * np.sin(bearings)])
    scans = [(np.zeros(2), wall[np.random.default_rng(1).permutation(len(wall))])]  # any order of points
    lo = np.array([-3.0, -3.0])
    seen = observed_mask(scans, lo, (120, 120), 0.05)
    cell = ((np.array([[0.0, 0.0], [1.0, -1.2], [2.6, 0.0], [-2.5, 2.5]]) - lo) / 0.05).astype(int)
    assert seen[cell[:, 1], cell[:, 0]].tolist() == [True, True, False, False]
    assert 0.2 < seen.mean() * (6.0 * 6.0) / (np.pi * 4.0) < 1.1  # about the room's area
    grid = match_grid_from_points(wall, 0.05, margin_m=1.0, scans=scans, unobserved=0.3)
    plain = match_grid_from_points(wall, 0.05, margin_m=1.0)

    def value(g, xy: tuple[float, float]) -> int:
        i, j = ((np.asarray(xy) - g.origin_m) / g.resolution_m).astype(int)
        return int(g.values[j, i])

    assert value(grid, (0.0, 0.0)) == 0 and value(plain, (2.7, 0.0)) == 0
    assert value(grid, (2.7, 0.0)) == round(0.3 * 255)  # beyond the wall: never looked at
    assert value(grid, (2.0, 0.0)) == value(plain, (2.0, 0.0)) > 150  # the wall itself: a hit in both


def _corridor_points(x_from: float, x_to: float) -> np.ndarray:
    """Two walls 2 m apart with a 0.8 m doorway every 4 m: the corridor looks the same 4 m on."""
    xs = np.arange(x_from, x_to, 0.03)
    in_door = np.abs(((xs + 2.0) % 4.0) - 2.0) < 0.4
    wall = xs[~in_door]
    return np.concatenate([np.stack([wall, np.full_like(wall, -1.0)], 1), np.stack([wall, np.full_like(wall, 1.0)], 1)])


def test_a_symmetric_corridor_match_is_ambiguous() -> None:
    grid = match_grid_from_points(_corridor_points(0.0, 40.0), 0.05, margin_m=1.0)
    scan = _corridor_points(-6.0, 6.0)  # seen from x = 20 m, in the vehicle frame
    match = search(grid, scan, np.array([19.0, 0.0, 0.0]), window_m=6.0, window_rad=0.1, min_score=0.3,
                   ambiguity_m=1.0, ambiguity_rad=0.15, runner_up_share=0.9)
    assert match is not None
    assert match.runner_up_score >= 0.9 * match.score  # 4 m on (or back) fits as well


def _walls(x_from: float, x_to: float, doors: list[float], half_width_m: float = 1.0) -> np.ndarray:
    """Two walls ``2 * half_width_m`` apart along x with a 0.8 m doorway centred at each of ``doors`` [m]."""
    xs = np.arange(x_from, x_to, 0.03)
    if doors:
        xs = xs[np.all(np.abs(xs[:, None] - np.asarray(doors)[None, :]) > 0.4, axis=1)]
    return np.concatenate([np.stack([xs, np.full_like(xs, -half_width_m)], 1),
                           np.stack([xs, np.full_like(xs, half_width_m)], 1)])


def test_a_higher_min_score_only_prunes_the_search() -> None:
    """The loop closer searches a wide window with min_score_wide: the best pose and the runner-up are
    those of a search with the lower min_score, as long as the runner-up counts from that lower score."""
    grid = match_grid_from_points(_walls(0.0, 40.0, [6.0, 10.0, 22.0, 30.0]), 0.05, margin_m=1.0)
    scan = _walls(-6.0, 6.0, [-4.0, 0.0])  # seen from x = 10 m
    kwargs = dict(window_m=6.0, window_rad=0.1, ambiguity_m=1.0, ambiguity_rad=0.15, runner_up_share=0.5)
    low = search(grid, scan, np.array([9.0, 0.0, 0.0]), min_score=0.3, **kwargs)
    assert low is not None and low.runner_up_pose is not None
    np.testing.assert_allclose(low.pose, [10.0, 0.0, 0.0], atol=1e-9)
    between = (low.score + low.runner_up_score) / 2  # above the runner-up (14 m), below the best
    assert low.runner_up_score < between < low.score
    high = search(grid, scan, np.array([9.0, 0.0, 0.0]), min_score=between, runner_up_min_score=0.3, **kwargs)
    assert high is not None and high.runner_up_pose is not None
    np.testing.assert_array_equal(high.pose, low.pose)
    np.testing.assert_array_equal(high.runner_up_pose, low.runner_up_pose)
    assert (high.score, high.runner_up_score) == (low.score, low.runner_up_score)
    alone = search(grid, scan, np.array([9.0, 0.0, 0.0]), min_score=between, **kwargs)
    assert alone is not None and alone.runner_up_score == 0.0  # the runner-up counts from min_score by default
    assert search(grid, scan, np.array([9.0, 0.0, 0.0]), min_score=low.score + 0.001, runner_up_min_score=0.3,
                  **kwargs) is None


def test_a_match_that_fits_only_the_points_picked_at_the_prediction_fails_the_overlap_check() -> None:
    """The search scores the points that overlap the submap at the predicted pose. Here those 4 m of
    corridor fit the submap 4 m back, where the rest of the cloud (a narrow passage) lands on the
    submap too, in its free space: a false closure, told by scoring the points that overlap there."""
    submap = _walls(0.0, 12.0, [5.0, 7.0, 10.0])
    grid = match_grid_from_points(submap, 0.05, margin_m=1.0)
    cloud = np.concatenate([_walls(-6.0, -2.0, [-5.0, -3.0]), _walls(-2.0, 2.0, [], half_width_m=0.5)])
    predicted = np.array([14.0, 0.0, 0.0])
    picked = overlapping_points(grid, cloud, predicted)
    assert picked[:, 0].max() < -1.9  # only the corridor part overlaps the submap at the prediction
    match = search(grid, picked, predicted, window_m=5.0, window_rad=0.05, min_score=0.6,
                   ambiguity_m=1.0, ambiguity_rad=0.1, runner_up_share=0.9)
    assert match is not None and abs(match.pose[0] - 10.0) < 0.06 and match.score > 0.8
    assert (overlap_score(grid, cloud, match.pose) or 1.0) < 0.4 < LoopClosingConfig().overlap_min_score
    assert overlap_score(grid, cloud[:20], match.pose) is None  # too few points to tell either way
    # a true fit keeps its score: the submap seen from x = 6 m
    own = submap - np.array([6.0, 0.0])
    own = own[np.abs(own[:, 0]) < 5.0]
    true_match = search(grid, overlapping_points(grid, own, np.array([7.5, 0.0, 0.0])), np.array([7.5, 0.0, 0.0]),
                        window_m=3.0, window_rad=0.05, min_score=0.6, ambiguity_m=1.0, ambiguity_rad=0.1,
                        runner_up_share=0.9)
    assert true_match is not None and abs(true_match.pose[0] - 6.0) < 0.06
    assert (overlap_score(grid, own, true_match.pose) or 0.0) > 0.8


def _segment(a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    """Points every 3 cm from ``a`` to ``b`` [m]."""
    start, end = np.asarray(a, float), np.asarray(b, float)
    f = np.arange(int(np.hypot(*(end - start)) / 0.03)) / int(np.hypot(*(end - start)) / 0.03)
    return start + f[:, None] * (end - start)


def test_points_where_the_submap_never_looked_count_only_if_seen_through_its_walls() -> None:
    """The submap saw a corridor and, through a door, a wedge of the room beyond. The cloud, taken
    partly from inside the room, sees the whole room: its walls and cabinets outside the wedge lie
    within the submap's bounds but on cells it never saw (neutral 0.3). The overlap check leaves them
    out and the true match keeps its score; counted, they would sink it to about ``min_score`` (on
    exp2's short-range URG that lost nine true closures, half agreement 0.555 -> 0.398). Had the
    same points been seen from the corridor, their rays would cross its walls: misses."""
    corridor = np.concatenate([_segment((0, -1), (6, -1)), _segment((0, 1), (2.6, 1)), _segment((3.4, 1), (6, 1))])
    wedge = np.array([(0, -1), (6, -1), (6, 1), (3.4, 1), (5.3, 6), (0.7, 6), (2.6, 1), (0, 1)], float)
    grid = match_grid_from_points(np.concatenate([corridor, _segment((0.7, 6), (5.3, 6))]), 0.05, margin_m=1.0,
                                  scans=[(np.array([3.0, 0.0]), wedge)], unobserved=0.3)
    room = np.concatenate([_segment((0, 6), (6, 6)), _segment((0, 1), (0, 6)), _segment((6, 1), (6, 6)),
                           _segment((0.5, 2), (0.5, 5.5)), _segment((5.5, 2), (5.5, 5.5))])
    truth = np.array([3.0, 0.0, 0.0])
    cloud = np.concatenate([corridor, room]) - truth[:2]
    from_room = np.concatenate([np.zeros((len(corridor), 2)), np.tile([0.0, 3.5], (len(room), 1))])
    assert (overlap_score(grid, cloud, truth, from_room) or 0.0) > 0.8
    in_bounds = overlapping_points(grid, cloud, truth)
    counted = search(grid, in_bounds, truth, 0.05, 0.01, 0.0)
    assert counted is not None and counted.score < 0.65
    assert (overlap_score(grid, cloud, truth, np.zeros_like(cloud)) or 1.0) < 0.55


def _there_and_back(heading_bias_rad: float) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Down the periodic corridor (30 m) and back, key frames every 0.5 m: truth, a front-end path
    that measures every step 3 % long and turns ``heading_bias_rad`` per step, and each key frame's
    end points (vehicle frame)."""
    out = [np.array([x, 0.0, 0.0]) for x in np.arange(0.0, 30.0, 0.5)]
    back = [np.array([x, 0.0, np.pi]) for x in np.arange(30.0, 0.0, -0.5)]
    truth = np.array(out + back)
    motion = relative(truth[:-1], truth[1:])
    drifted = [truth[0]]
    for m in motion:
        drifted.append(compose(drifted[-1], m * np.array([1.03, 1.0, 1.0]) + np.array([0.0, 0.0, heading_bias_rad])))
    world = _corridor_points(-10.0, 40.0)
    points = []
    for pose in truth:
        near = world[np.abs(world[:, 0] - pose[0]) < 8.0]
        points.append(relative(pose, np.column_stack([near, np.zeros(len(near))]))[:, :2])
    return truth, np.array(drifted), points


def test_loop_closer_rejects_the_symmetric_corridor() -> None:
    """Down a periodic corridor and back with odometry 3 % long: every match is ambiguous along the
    corridor, so no pose closure is accepted and the positions along it stay as the front end gave
    them; the matches only confirm the heading (heading closures), which was right."""
    truth, path, points = _there_and_back(0.0)
    config = LoopClosingConfig(base_window_m=5.0, min_loop_travel_m=8.0)
    result = close_loops(path, points, config, 0.05)
    assert result.closures, "candidates were matched"
    assert not any(c.accepted for c in result.closures if c.kind == "pose")
    assert "ambiguous" in {c.reason for c in result.closures}
    # the heading closures' headings are good to about a milliradian: 3.4 cm sideways after 30 m
    np.testing.assert_allclose(result.poses[:, :2], path[:, :2], atol=0.05)
    assert np.max(np.abs(wrap_angle(result.poses[:, 2] - path[:, 2]))) < 0.005
    assert not any(c.accepted for c in close_loops(path, points, config.model_copy(update={"heading_closures": False}),
                                                   0.05).closures)


def test_a_heading_closure_that_turns_its_key_frame_too_far_is_refused() -> None:
    """The symmetric corridor's heading closures turn their key frames by up to a few milliradians
    (the heading was right). Allowed a turn of half a milliradian, the key frames whose best match is
    such a closure close no loop, and the records say why."""
    truth, path, points = _there_and_back(0.0)
    config = LoopClosingConfig(base_window_m=5.0, min_loop_travel_m=8.0)
    free = close_loops(path, points, config, 0.05)
    turns = [c.correction_rad for c in free.closures if c.accepted and c.kind == "heading"]
    assert turns and max(turns) > 0.0005 and max(turns) < config.heading_closure_max_turn_rad
    capped = close_loops(path, points, config.model_copy(update={"heading_closure_max_turn_rad": 0.0005}), 0.05)
    refused = [c for c in capped.closures if c.reason == HEADING_TURN_TOO_FAR]
    assert refused and all(c.correction_rad > 0.0005 and c.kind == "heading" for c in refused)
    assert all(c.correction_rad <= 0.0005 for c in capped.closures if c.accepted and c.kind == "heading")
    assert sum(c.accepted for c in capped.closures) < sum(c.accepted for c in free.closures)


def test_a_stretch_of_corridor_tells_apart_what_one_scan_cannot() -> None:
    """The periodic corridor with one alcove (2 m wide, 3 m deep, at x = 14 m), key frames every 0.5 m
    from x = 10 m, each seeing 6 m either way. At x = 22 m the scan sees doors only and fits 4 m on as
    well; the key frame's match points (``match_span_m`` = 4: the key frames back to x = 18 m, which
    saw the alcove) fit in one place only, the right one."""
    corridor = _corridor_points(0.0, 40.0)
    corridor = corridor[~((np.abs(corridor[:, 0] - 14.0) < 1.0) & (corridor[:, 1] < 0))]
    xs = np.arange(13.0, 15.0, 0.03)
    ys = np.arange(-4.0, -1.0, 0.03)
    world = np.concatenate([corridor, np.column_stack([xs, np.full_like(xs, -4.0)]),
                            np.column_stack([np.full_like(ys, 13.0), ys]),
                            np.column_stack([np.full_like(ys, 15.0), ys])])
    path = np.array([[x, 0.0, 0.0] for x in np.arange(10.0, 22.01, 0.5)])
    points = [relative(pose, np.column_stack([near, np.zeros(len(near))]))[:, :2]
              for pose in path for near in [world[np.abs(world[:, 0] - pose[0]) < 6.0]]]
    closer = LoopCloser(path, points, LoopClosingConfig(match_span_m=4.0), 0.05)
    k = len(path) - 1
    cloud = closer.match_points(k)
    assert len(cloud) <= closer.config.max_points
    placed = relative(np.array([-22.0, 0.0, 0.0]), np.column_stack([cloud, np.zeros(len(cloud))]))[:, :2]
    gaps = np.min(np.hypot(placed[:, None, 0] - world[None, :, 0], placed[:, None, 1] - world[None, :, 1]), axis=1)
    assert gaps.max() < 0.02  # every point where the world has one
    assert np.any(placed[:, 1] < -3.0)  # the alcove's back wall is among them
    grid = match_grid_from_points(world, 0.05, margin_m=1.0)
    initial = np.array([21.0, 0.1, 0.02])
    kwargs = dict(window_m=6.0, window_rad=0.1, min_score=0.3, ambiguity_m=1.0, ambiguity_rad=0.15,
                  runner_up_share=0.9)
    single = search(grid, closer.points_v[k], initial, **kwargs)
    assert single is not None and single.runner_up_score >= 0.9 * single.score
    stretch = search(grid, cloud, initial, **kwargs)
    assert stretch is not None and stretch.runner_up_score < 0.9 * stretch.score
    np.testing.assert_allclose(stretch.pose, [22.0, 0.0, 0.0], atol=0.06)


def test_heading_closures_take_the_heading_drift_out_of_a_corridor() -> None:
    """The same corridor with a front end whose heading drifts 0.002 rad per step (0.24 rad by the
    end, 3.6 m off sideways): the ambiguous matches still fix the heading, and the path comes back
    to the corridor's axis; along it nothing is claimed."""
    truth, path, points = _there_and_back(0.002)
    result = close_loops(path, points, LoopClosingConfig(base_window_m=5.0, min_loop_travel_m=8.0), 0.05)
    accepted = [c for c in result.closures if c.accepted]
    assert accepted and all(c.kind == "heading" for c in accepted)
    assert np.max(np.abs(wrap_angle(path[:, 2] - truth[:, 2]))) > 0.2
    assert np.max(np.abs(wrap_angle(result.poses[:, 2] - truth[:, 2]))) < 0.06
    assert np.max(np.abs(path[:, 1])) > 3.0
    assert np.max(np.abs(result.poses[:, 1])) < 0.6


def test_search_finds_the_line_of_a_corridor() -> None:
    """A corridor match is ambiguous along the corridor only: the search reports that line; a room's
    match is not ambiguous and has none."""
    grid = match_grid_from_points(_corridor_points(0.0, 40.0), 0.05, margin_m=1.0)
    match = search(grid, _corridor_points(-6.0, 6.0), np.array([19.0, 0.2, 0.02]), window_m=6.0, window_rad=0.1,
                   min_score=0.3, ambiguity_m=1.0, ambiguity_rad=0.15, runner_up_share=0.9, line_half_width_m=0.3,
                   line_half_width_rad=0.03)
    assert match is not None and match.line_direction is not None
    assert abs(match.line_direction[0]) > 0.99  # along x, the corridor's axis
    assert abs(match.pose[1]) < 0.06 and abs(match.pose[2]) < 0.01  # across it and in heading: found
    rng = np.random.default_rng(0)
    room = _room_points(rng)
    room_grid = match_grid_from_points(room, 0.05, margin_m=1.0)
    scan = relative(np.array([2.0, 1.5, 0.3]), np.column_stack([room[::4], np.zeros(len(room[::4]))]))[:, :2]
    unique = search(room_grid, scan, np.array([2.5, 1.0, 0.2]), window_m=2.0, window_rad=0.4, min_score=0.5,
                    ambiguity_m=0.5, ambiguity_rad=0.1, runner_up_share=0.9, line_half_width_m=0.3,
                    line_half_width_rad=0.03)
    assert unique is not None and unique.line_direction is None and unique.runner_up_score == 0.0


def _office_key_frames() -> tuple[np.ndarray, list[np.ndarray]]:
    """The simulated office loop's true poses at key frames every 0.5 m, and each key frame's scan end
    points (vehicle frame)."""
    drive = simulate("office", seed=0, cameras=False)
    truth_all = drive.pose_at(drive.log.scans.t_s)
    keep = [0]
    for k in range(1, len(truth_all)):
        if np.hypot(*(truth_all[k, :2] - truth_all[keep[-1], :2])) >= 0.5:
            keep.append(k)
    projector = ScanProjector(drive.log.lidar, 30.0, 0.2, 20.0, 0.05, 0.0)
    return truth_all[keep], [projector.project(drive.log.scans.ranges_m[k]).hits_v for k in keep]


@pytest.fixture(scope="module")
def drifting_office() -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Key frames every 0.5 m of the simulated office loop (56 m): truth, a front-end path that drifts
    0.004 rad and 1 cm per metre (0.6 m ATE), and each key frame's scan end points."""
    truth, points = _office_key_frames()
    motion = relative(truth[:-1], truth[1:])
    path = [truth[0]]
    for m in motion:
        d = float(np.hypot(m[0], m[1]))
        path.append(compose(path[-1], np.array([1.01 * m[0], 1.01 * m[1], m[2] + 0.004 * d])))
    return truth, np.array(path), points


def test_back_end_closes_the_loop_the_front_end_drifted(drifting_office) -> None:
    truth, path, points = drifting_office
    before = _ate(path, truth)
    result = close_loops(path, points, SlamConfig().loop_closing, 0.05)
    after = _ate(result.poses, truth)
    summary = result.summary()
    # measured: 0.61 m -> 0.066 m with 17 closures accepted
    assert before > 0.4
    assert after < 0.12, summary
    assert summary["closures_accepted"] >= 3 and summary["optimizations"] >= 1
    assert summary["largest_correction_m"] > 0.5  # the first closure moved its key frame metres
    # deterministic: the same input gives the same poses and closures, with the candidate submaps
    # matched in two threads as well
    again = close_loops(path, points, SlamConfig().loop_closing, 0.05, threads=2)
    np.testing.assert_array_equal(again.poses, result.poses)
    assert again.summary() == summary


def test_closures_reported_accepted_are_the_graphs_closure_edges(drifting_office) -> None:
    """run.json's accepted closures are exactly those in the pose graph: a key frame matched to two
    submaps uses the better one, and the other is reported as not used (it once said "accepted")."""
    _, path, points = drifting_office
    closer = LoopCloser(path, points, SlamConfig().loop_closing, 0.05)
    result = closer.run()
    accepted = sorted((c.node, c.submap) for c in result.closures if c.accepted)
    # the final graph ties each closure to a key frame of its submap (the one nearest the node)
    edges = sorted((e.j, int(closer.submap_of[e.i])) for e in closer.graph.edges if e.robust)
    assert accepted == edges and len(edges) >= 3
    assert any(e.i != closer.submaps[closer.submap_of[e.i]].anchor for e in closer.graph.edges if e.robust)
    outscored = [c for c in result.closures if c.reason == OUTSCORED]
    assert outscored  # the office's key frames often see two old submaps
    for c in outscored:
        assert any(o.node == c.node and o.score >= c.score and o.reason != OUTSCORED for o in result.closures)


@pytest.mark.parametrize("glitch_at", [40, 80])
def test_an_unverified_step_is_where_the_graph_bends(glitch_at: int) -> None:
    """A front-end path that is exact but for one step 0.25 rad off, where the particle kept its motion
    sample (freiburg-079's odometry turns 0.2-0.3 rad while the robot stands, and the front end follows
    it on some seeds). Marked unverified, that step bends freely in the pose graph, no submap or match
    cloud spans it, and closures across it are searched wider: the loop closes onto the truth. Unmarked,
    the glitch stays in a submap, in the clouds and in a stiff motion edge."""
    truth, points = _office_key_frames()
    steps = relative(truth[:-1], truth[1:])
    steps[glitch_at - 1, 2] += 0.25
    path = [truth[0]]
    for step in steps:
        path.append(compose(path[-1], step))
    unverified = np.zeros(len(path), bool)
    unverified[glitch_at] = True
    config = SlamConfig().loop_closing
    plain = close_loops(np.array(path), points, config, 0.05)
    marked = close_loops(np.array(path), points, config, 0.05, unverified=unverified)
    # measured: front end 1.40 / 0.48 m ATE; unmarked 0.145 / 0.47 m; marked 0.005 / 0.002 m
    assert _ate(marked.poses, truth) < 0.03
    assert _ate(plain.poses, truth) > 0.1


def test_back_end_off_returns_the_front_end_path(drifting_office) -> None:
    _, path, points = drifting_office
    result = close_loops(path, points, LoopClosingConfig(enabled=False), 0.05)
    np.testing.assert_array_equal(result.poses, path)
    assert result.closures == []


def test_pose_graph_cauchy_loss_resists_a_false_closure() -> None:
    """A square loop of four 5 m sides with a true closure and a wrong one 2 m off: the robust loss
    keeps the square."""
    truth = np.array([[0, 0, 0], [5, 0, np.pi / 2], [5, 5, np.pi], [0, 5, -np.pi / 2], [0, 0, 0]], float)
    graph = PoseGraph(truth + np.array([0.0, 0.0, 0.0]))
    sig = np.array([0.05, 0.05, 0.01])
    for k in range(4):
        graph.add_edge(k, k + 1, relative(truth[k], truth[k + 1]), sig)
    graph.add_edge(0, 4, np.zeros(3), sig, robust=True)
    graph.add_edge(1, 3, relative(truth[1], truth[3]) + np.array([2.0, 0.0, 0.0]), sig, robust=True)
    poses = graph.optimize()
    assert np.abs(poses[:, :2] - truth[:, :2]).max() < 0.15


def _step_error_m(poses: np.ndarray, truth: np.ndarray) -> float:
    """Mean translation error of the motion from each key frame to the next [m]."""
    d = relative(poses[:-1], poses[1:]) - relative(truth[:-1], truth[1:])
    return float(np.mean(np.hypot(d[:, 0], d[:, 1])))


def test_map_alignment_removes_each_key_frames_own_error() -> None:
    """Key frames of the simulated office placed with white noise (2 cm, 5 mrad per pose, as a front
    end's match and proposal draw leave them): fitted onto the map of all of them and combined with the
    input by the noise measured on the fits themselves, the trajectory is far closer to the truth.
    Exact poses stay within millimetres."""
    truth, points = _office_key_frames()
    noisy = truth + np.random.default_rng(1).normal(0.0, 1.0, truth.shape) * [0.02, 0.02, 0.005]
    aligned, summary = align_to_map(noisy, points, 0.05, passes=3, max_range_m=20.0)
    # measured: ATE 0.026 -> 0.009 m, step error 0.031 -> 0.005 m; the fits' sd 1-2 mm
    assert summary["applied"] and summary["fit_sd_m"] < 0.005, summary
    assert _ate(aligned, truth) < 0.5 * _ate(noisy, truth)
    assert _step_error_m(aligned, truth) < 0.3 * _step_error_m(noisy, truth)
    exact, _ = align_to_map(truth, points, 0.05, passes=3, max_range_m=20.0)
    assert _ate(exact, truth) < 0.003
    unchanged, off = align_to_map(noisy, points, 0.05, passes=0, max_range_m=20.0)
    assert not off["applied"] and np.array_equal(unchanged, noisy)


def test_map_alignment_builds_its_map_a_stretch_at_a_time() -> None:
    """The stretches (:func:`map_alignment._chunks`) partition the key frames in order, each box holds
    its key frames' end points and stays within the size unless one key frame alone exceeds it."""
    truth, points = _office_key_frames()
    points[3] = points[3][:0]  # a key frame without end points belongs to the stretch around it
    placed = [place_points(p, q) for p, q in zip(truth, points, strict=True)]
    starts = np.concatenate([[0], np.cumsum([len(p) for p in placed])])
    chunks = map_alignment._chunks(np.concatenate(placed), starts, 15.0)
    assert len(chunks) > 5
    assert [k for nodes, _ in chunks for k in nodes] == list(range(len(truth)))
    for nodes, box in chunks:
        own = [np.ptp(placed[k], axis=0).max() for k in nodes if len(placed[k])]
        assert box[2] - box[0] <= max(15.0, *own) and box[3] - box[1] <= max(15.0, *own)
        for k in nodes:
            assert (placed[k] >= box[:2] - 1e-9).all() and (placed[k] <= box[2:] + 1e-9).all()


def test_refining_many_key_frames_at_once_gives_each_fit_refine_pose_gives() -> None:
    """:func:`correlative.refine_poses` (key frames in threads, all or every second end point) returns
    bit for bit what :func:`refine_pose` returns key frame by key frame, a fit pushed beyond its bound
    (kept at its start) included; key frames not asked for keep their poses."""
    truth, points = _office_key_frames()
    placed = np.concatenate([place_points(p, q) for p, q in zip(truth, points, strict=True)])
    grid = match_grid_from_points(placed, 0.05, 1.0, n_levels=0)
    rng = np.random.default_rng(3)
    start = truth + rng.normal(0.0, 1.0, truth.shape) * [0.02, 0.02, 0.005]
    start[1] = truth[1] + [0.3, 0.0, 0.0]  # six cells off: its fit moves too far and keeps its start
    vehicle = np.concatenate(points)
    starts = np.concatenate([[0], np.cumsum([len(p) for p in points])])
    nodes = np.arange(0, len(truth), 2)
    for first, step in ((0, 1), (0, 2), (1, 2)):
        many = refine_poses(grid, vehicle, starts, start, nodes, first=first, step=step)
        for k in range(len(truth)):
            one = refine_pose(grid, points[k][first::step], start[k]) if k in nodes else start[k]
            assert np.array_equal(many[k], one), (first, step, k)
    assert np.array_equal(many[1], start[1])  # not asked for
    assert np.array_equal(refine_poses(grid, vehicle, starts, start, nodes[:1])[0],
                          refine_pose(grid, points[0], start[0]))
    fitted = refine_poses(grid, vehicle, starts, start, np.array([1]))
    assert np.array_equal(fitted[1], start[1])  # beyond 1.5 cells: the start kept


def test_a_key_frames_match_cloud_is_its_scans_placed_one_by_one() -> None:
    """The cloud a key frame is matched with (:meth:`LoopCloser.match_cloud`): the end points of the key
    frames over the last ``match_span_m`` of travel, each placed by its front-end pose relative to the
    key frame's, thinned to ``max_points``, and each point's scan origin; the same values as placing
    them scan by scan."""
    truth, points = _office_key_frames()
    config = LoopClosingConfig(match_span_m=3.0, max_points=400)
    closer = LoopCloser(truth, points, config, 0.05)
    k = len(truth) - 1
    cloud, origins = closer.match_cloud(k)
    first = int(np.searchsorted(closer.travel_m, closer.travel_m[k] - 3.0, side="left"))
    assert first < k - 1
    parts = [place_points(relative(truth[k], truth[j]), closer.points_v[j]) for j in range(k, first - 1, -1)]
    froms = [np.repeat(relative(truth[k], truth[j])[None, :2], len(closer.points_v[j]), 0)
             for j in range(k, first - 1, -1)]
    every = int(np.ceil(sum(map(len, parts)) / 400))
    assert every > 1 and len(cloud) <= 400
    assert np.array_equal(cloud, np.concatenate(parts)[::every])
    assert np.array_equal(origins, np.concatenate(froms)[::every])


def test_travel_graph_distances_are_the_shortest_paths_within_the_limit() -> None:
    """A chain of 1 m steps 0-1-2-3-4 with a 0.5 m shortcut 0-4: node 4 is 0.5 m away, node 3 1.5 m
    (through 4, not 3 m along the chain); beyond the limit, or unconnected, is inf."""
    from slam_engine.backend.travel_graph import adjacency, shortest_distances

    graph = adjacency(6, np.array([0, 1, 2, 3, 0]), np.array([1, 2, 3, 4, 4]), np.array([1.0, 1.0, 1.0, 1.0, 0.5]))
    np.testing.assert_array_equal(shortest_distances(*graph, 0, 10.0), [0.0, 1.0, 2.0, 1.5, 0.5, np.inf])
    np.testing.assert_array_equal(shortest_distances(*graph, 2, 1.5), [np.inf, 1.0, 0.0, 1.0, np.inf, np.inf])
    with pytest.raises(ValueError, match="positive"):
        adjacency(2, np.array([0]), np.array([1]), np.array([0.0]))
    with pytest.raises(ValueError, match="outside"):
        adjacency(2, np.array([0]), np.array([2]), np.array([1.0]))


def _office_turning_too_far() -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The office's key frames: truth, a front-end path that turns 0.02 rad too far per metre, end points."""
    truth, points = _office_key_frames()
    path = [truth[0]]
    for m in relative(truth[:-1], truth[1:]):
        path.append(compose(path[-1], np.array([m[0], m[1], m[2] + 0.02 * float(np.hypot(m[0], m[1]))])))
    return truth, np.array(path), points


# search windows of at most 2 m, and far searches from 20 m behind, every 2 m
NARROW = {"max_window_m": 2.0, "max_window_rad": 0.2, "far_min_gap_m": 20.0, "far_every_m": 2.0}


def test_a_far_search_closes_the_loop_no_window_reaches() -> None:
    """A front end that turns 0.02 rad too far per metre comes back to the office's start 5 m off; with
    search windows of at most 2 m no windowed search reaches, and the map stays drifted. The far search
    places the returning stretch over the whole map behind it, confirmed by the stretch before it, and
    the closure brings the drive back (measured: ATE 2.84 m -> 0.23 m with one far closure, 8.3 m)."""
    truth, path_arr, points = _office_turning_too_far()
    without = close_loops(path_arr, points, LoopClosingConfig(**NARROW, far_search=False), 0.05)
    result = close_loops(path_arr, points, LoopClosingConfig(**NARROW), 0.05)
    assert _ate(path_arr, truth) > 2.5 and _ate(without.poses, truth) > 2.5
    assert without.far_search is None and not any(c.accepted for c in without.closures)
    far = [c for c in result.closures if c.reason == "accepted (far)"]
    assert len(far) == 1 and far[0].correction_m > 5.0, result.summary()["far_search"]
    # where the drive came back to: the node against the start, front end and back end
    node = far[0].node
    off = [relative(p[0], p[node]) - relative(truth[0], truth[node]) for p in (path_arr, result.poses)]
    # measured: 8.15 m and 1.10 rad off by the front end, 0.35 m and 0.14 rad after the back end
    assert np.hypot(off[0][0], off[0][1]) > 6.0 and abs(float(wrap_angle(off[0][2]))) > 0.9
    assert np.hypot(off[1][0], off[1][1]) < 0.5 and abs(float(wrap_angle(off[1][2]))) < 0.2
    assert _ate(result.poses, truth) < 0.35
    assert result.far_search is not None and result.far_search["accepted"] == 1


def test_far_searches_wait_while_windows_reach_the_map_behind(drifting_office) -> None:
    """The drifting office's loops close within their windows: no far search is made, and the result is
    the windowed back end's to the bit."""
    _, path, points = drifting_office
    with_far = close_loops(path, points, SlamConfig().loop_closing, 0.05)
    without = close_loops(path, points, LoopClosingConfig(far_search=False), 0.05)
    assert with_far.far_search == {"searches": 0, "placed": 0, "confirmed": 0, "accepted": 0}
    np.testing.assert_array_equal(with_far.poses, without.poses)


def test_a_far_correction_beyond_the_second_pass_distance_searches_the_drive_again() -> None:
    """After a far closure that moved its key frame farther than ``far_second_pass_m``, the key frames are
    searched once more from the corrected poses: the office's windows, which could not reach the start
    from the drifted estimate, then close loops along the whole way back (measured: 13 closures against
    4, ATE 0.226 m)."""
    truth, path_arr, points = _office_turning_too_far()
    once = close_loops(path_arr, points, LoopClosingConfig(**NARROW), 0.05)  # the 8.3 m correction: below 30 m
    twice = close_loops(path_arr, points, LoopClosingConfig(**NARROW, far_second_pass_m=5.0), 0.05)
    assert once.far_search is not None and "second_pass" not in once.far_search
    assert twice.far_search is not None and "second_pass" in twice.far_search
    assert sum(c.accepted for c in twice.closures) >= 2 * sum(c.accepted for c in once.closures)
    assert _ate(twice.poses, truth) < 0.35
