"""The place index (:mod:`slam_engine.backend.place_index`) on the simulated office, with exact ground truth:
a place found again from a turned copy of its surroundings with the heading it was turned by, the revisit
at the end of the office loop retrieved from the map of its start, look-alike places both proposed; and
the search at the proposed places answering as the whole-map search or refusing; and which of several
saved maps a drive is in (:mod:`slam_engine.multisession.which_map`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from slam_engine.backend.correlative import search
from slam_engine.backend.loop_closer import thin
from slam_engine.backend.place_index import PlaceIndex, search_at_places
from slam_engine.backend.submaps import match_grid_from_points
from slam_engine.config import SlamConfig
from slam_engine.model.poses import inverse, place_each, place_points, wrap_angle
from slam_engine.multisession.localization import DriveScans, localize
from slam_engine.multisession.which_map import localize_in_maps
from slam_engine.pipeline import run_slam
from slam_engine.simulation import SimulatedDrive, simulate

CONFIG = SlamConfig(particles=10, seed=0)
RADIUS_M, SPACING_M = CONFIG.place_index.radius_m, CONFIG.place_index.spacing_m


@pytest.fixture(scope="module")
def office() -> SimulatedDrive:
    return simulate("office", seed=0, cameras=False)


@pytest.fixture(scope="module")
def scans(office: SimulatedDrive) -> DriveScans:
    return DriveScans.from_log(office.log, CONFIG)


def world_points(office: SimulatedDrive, scans: DriveScans, last: int | None = None) -> np.ndarray:
    """The end points of scans ``0..last`` at their true poses (world frame) [m]."""
    last = len(scans) - 1 if last is None else last
    hits = scans.hits[: last + 1]
    return place_each(office.ground_truth.poses[: last + 1], np.concatenate(hits),
                      np.repeat(np.arange(len(hits)), [len(h) for h in hits]))


def test_a_turned_copy_of_a_place_is_found_with_the_heading_it_was_turned_by(office, scans) -> None:
    world = world_points(office, scans)
    index = PlaceIndex.along(world, office.ground_truth.poses[:, :2], SPACING_M, RADIUS_M)
    assert len(index) > 10
    for place, heading in ((3, 1.0), (len(index) // 2, -2.5), (len(index) - 4, 3.0)):
        pose = np.array([*index.centres[place], heading])
        copy_v = place_points(inverse(pose), world)  # the map as a vehicle there, turned, sees it
        best = index.query(copy_v, 5)[0]
        assert best.place == place
        # measured: within 0.01 rad (5-degree sectors, refined by a parabola through the peak)
        assert abs(float(wrap_angle(best.heading_rad - heading))) < 0.05


def _square_walls(half_m: float, step_m: float = 0.05) -> np.ndarray:
    """(N, 2) points on the walls of a square of half-width ``half_m`` about the origin [m]."""
    side = np.arange(-half_m, half_m, step_m)
    edge = np.full_like(side, half_m)
    return np.concatenate([np.stack(xy, axis=1) for xy in ((side, edge), (side, -edge), (edge, side), (-edge, side))])


def test_the_map_beyond_what_a_query_saw_is_not_held_against_a_place() -> None:
    # a room, with a notch on one wall so that its heading is unique, seen from its centre; its place in
    # the map, and a second place like it whose map also holds an outer wall that the query's walls hide
    # (the map saw it from elsewhere). Both are the query's place: only the bins the query saw count
    # (counting every bin of the sectors it saw: 0.99 and 0.68).
    notch = np.stack([np.full(20, 4.0 + 0.05 * np.arange(20)), np.full(20, 1.0)], axis=1)
    room = np.concatenate([_square_walls(4.0), notch])
    outer = _square_walls(0.75 * RADIUS_M)
    heading = 0.7
    query = place_points(inverse(np.array([0.0, 0.0, heading])), room)
    bare = PlaceIndex.build(room, np.zeros((1, 2)), RADIUS_M)
    walled = PlaceIndex.build(np.concatenate([room, outer]), np.zeros((1, 2)), RADIUS_M)
    found_bare, found_walled = bare.query(query, 1)[0], walled.query(query, 1)[0]
    assert found_bare.similarity > 0.95  # measured 1.0
    assert found_walled.similarity == pytest.approx(found_bare.similarity, abs=1e-6)
    assert abs(float(wrap_angle(found_walled.heading_rad - heading))) < 0.05


def test_the_revisit_at_the_end_of_the_office_loop_is_retrieved_from_the_map_of_its_start(office, scans) -> None:
    truth = office.ground_truth.poses
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    last = len(truth) - 1
    behind = int(np.searchsorted(travel, travel[last] - 30.0))  # the map: the drive until 30 m before
    index = PlaceIndex.along(world_points(office, scans, behind), truth[:behind, :2], SPACING_M, RADIUS_M)
    first = int(np.searchsorted(scans.travel_m, scans.travel_m[last] - 8.0))
    found = index.query(scans.cloud(first, last, 3000), 5)  # 8 m of the drive, in its own frame
    best = found[0]
    assert math.hypot(*(best.centre_m - truth[last, :2])) < SPACING_M
    assert abs(float(wrap_angle(best.heading_rad - truth[last, 2]))) < 0.1


def test_look_alike_places_are_both_proposed(office, scans) -> None:
    room = world_points(office, scans)
    room = room[np.hypot(*(room - office.ground_truth.poses[0, :2]).T) < 8.0]
    twin = room + np.array([60.0, 0.0])  # the same room again, 60 m east
    centres = np.array([office.ground_truth.poses[0, :2], office.ground_truth.poses[0, :2] + [60.0, 0.0]])
    index = PlaceIndex.build(np.concatenate([room, twin]), centres, RADIUS_M)
    found = index.query(place_points(inverse(np.array([*centres[1], 0.4])), twin), 2)
    assert sorted(c.place for c in found) == [0, 1]  # the search that follows must tell them apart, or refuse
    assert abs(found[0].similarity - found[1].similarity) < 0.05


def test_a_query_that_describes_too_little_proposes_nothing(office, scans) -> None:
    index = PlaceIndex.along(world_points(office, scans), office.ground_truth.poses[:, :2], SPACING_M, RADIUS_M)
    assert index.query(np.array([[1.0, 0.0], [1.0, 0.1]]), 5) == []
    assert PlaceIndex.along(np.zeros((0, 2)), np.zeros((0, 2)), SPACING_M, RADIUS_M).query(scans.hits[0], 5) == []


def test_a_drive_is_localised_in_the_map_it_is_in_and_refused_where_it_is_in_none(office) -> None:
    start, end = office.log.time_span_s() or (0.0, 0.0)
    middle = (start + end) / 2
    office_map = run_slam(office.log.between(start, middle), CONFIG).bundle
    elsewhere = simulate("campus", seed=1, rig="robot", cameras=False, max_duration_s=40.0).log
    other_map = run_slam(elsewhere, CONFIG).bundle
    second = office.log.between(middle, end + 1.0)
    which = localize_in_maps([("other", other_map), ("office", office_map)], second, CONFIG)
    assert [t.name for t in which.tries] == ["office", "other"]  # the index ranks the office first ...
    assert which.tries[0].likeness > which.tries[1].likeness
    assert which.chosen == 0 and which.result is not None and which.result.localised
    assert which.tries[1].localised is None  # ... and the other map is never searched
    alone = localize(office_map, which.drive, CONFIG)  # the same answer as the office map alone
    assert alone.trajectory is not None and which.result.trajectory is not None
    assert np.array_equal(alone.trajectory.poses, which.result.trajectory.poses)
    assert which.summary()["chosen"] == "office"
    refused = localize_in_maps([("office", office_map)], elsewhere, CONFIG)
    assert refused.chosen is None and refused.result is None and refused.tries[0].localised is False
    # the index proposes where each stretch is searched for: the same placement and refusal as searching
    # the whole map for every one, without a whole-map search for the best
    whole_map = CONFIG.model_copy(update={"localization": CONFIG.localization.model_copy(
        update={"from_places": False})})
    searched = localize(office_map, which.drive, whole_map)
    assert searched.trajectory is not None
    assert np.allclose(searched.trajectory.poses, alone.trajectory.poses, atol=1e-9)
    assert alone.whole_map_searches == 0 < alone.global_searches
    assert searched.whole_map_searches > 0 and searched.summary()["whole_map_searches"] == searched.whole_map_searches
    refused_whole = localize_in_maps([("office", office_map)], elsewhere, whole_map)
    assert refused_whole.chosen is None and refused_whole.tries[0].localised is False
    # below the bar the best score is what the proposed places held (measured 0.598 against 0.599)
    assert refused.tries[0].best_score <= refused_whole.tries[0].best_score


def test_a_query_scores_every_place_as_the_spectra_say_and_takes_them_best_first(office, scans) -> None:
    """The one pass over the places' spectra gives the sums of their products ring by ring (float32 spectra:
    to their precision), and the candidates are taken in the order a stable sort of every peak gives
    (equal scores in index order), sorted a block at a time."""
    from slam_engine.backend.place_index import _ring_sums, best_first, describe_query, seen_bins

    world = world_points(office, scans)
    index = PlaceIndex.along(world, office.ground_truth.poses[:, :2], SPACING_M, RADIUS_M)
    C, C_squared = index._spectra
    described = describe_query(scans.cloud(100, 180, 3000), RADIUS_M).descriptors
    seen = np.stack([seen_bins(q == 1.0) for q in described])
    Q, S = np.conj(np.fft.rfft(described * seen, axis=-1)), np.conj(np.fft.rfft(seen, axis=-1))
    numerator, masked = _ring_sums(C, C_squared, Q, S)
    assert numerator.shape == (len(described), len(index), C.shape[-1])
    np.testing.assert_allclose(numerator, (Q[:, None] * C[None]).sum(axis=2), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(masked, (S[:, None] * C_squared[None]).sum(axis=2), rtol=1e-5, atol=1e-4)
    rng = np.random.default_rng(3)
    for scores in (rng.random(1000), rng.integers(0, 9, 1000) / 9.0, np.zeros(3)):
        expected = np.argsort(-scores, kind="stable").tolist()
        assert list(best_first(scores)) == expected and list(best_first(scores, block=7)) == expected


def test_a_search_at_the_proposed_places_answers_as_the_whole_map_or_refuses(office, scans) -> None:
    """search_at_places finds the whole-map search's own match where the index proposes its place, and
    where the index proposes only elsewhere, never a unique match there (the runner-up search over the
    whole map finds the better pose it missed)."""
    world = world_points(office, scans)
    grid = match_grid_from_points(world, 0.2, 1.0, n_levels=10)
    truth = office.ground_truth.poses
    last = len(truth) // 3
    first = int(np.searchsorted(scans.travel_m, scans.travel_m[last] - 8.0))
    cloud = thin(place_points(inverse(truth[last]), world[np.hypot(*(world - truth[last, :2]).T) < 15.0]), 400)
    centre, reach = grid.centre_and_reach()
    c = CONFIG.localization
    args = (c.ambiguity_m, c.ambiguity_rad, c.runner_up_ratio, 0.5)
    whole = search(grid, cloud, centre, reach, math.pi, 0.5, ambiguity_m=c.ambiguity_m, ambiguity_rad=c.ambiguity_rad,
                   runner_up_share=c.runner_up_ratio, runner_up_min_score=0.5, any_runner_up=True)
    assert whole is not None and whole.runner_up_score < c.runner_up_ratio * whole.score  # unique
    assert math.hypot(*(whole.pose[:2] - truth[last, :2])) < 0.3
    index = PlaceIndex.along(world, truth[:, :2], SPACING_M, RADIUS_M)
    proposed = index.query(scans.cloud(first, last, 3000), 5)
    assert any(math.hypot(*(p.centre_m - truth[last, :2])) < 2.0 for p in proposed)
    at_places = search_at_places(grid, cloud, centre, reach, math.pi, proposed, 2.5, 0.25, 0.5, *args)
    assert at_places is not None
    assert np.allclose(at_places.pose, whole.pose) and at_places.score == whole.score  # the same lattice
    assert at_places.runner_up_score < c.runner_up_ratio * at_places.score
    # only places elsewhere proposed: what it finds there is never unique (measured: 0.83 at a look-alike
    # 6 m off, judged ambiguous by the whole map's runner-up)
    elsewhere = [p for p in index.query(scans.cloud(first, last, 3000), 40)
                 if math.hypot(*(p.centre_m - truth[last, :2])) > 6.0][:5]
    missed = search_at_places(grid, cloud, centre, reach, math.pi, elsewhere, 2.5, 0.25, 0.5, *args)
    assert missed is not None and missed.score < whole.score
    assert missed.runner_up_score >= c.runner_up_ratio * missed.score


def test_a_runner_up_among_the_proposed_places_spares_the_whole_map_search(office, scans, monkeypatch) -> None:
    """The office and a copy of it 60 m east: a stretch fits both alike. The copy's proposed place already
    makes the best ambiguous (:func:`runner_up_among`, as the runner-up search over the whole map judges it)
    and search_at_places says so without that search; a pose that search would not count (in the
    ambiguity box around the best, off its lattice, out of its window, below the share) is not taken for one."""
    import slam_engine.backend.place_index as place_index
    from slam_engine.backend.correlative import lattice_pose, runner_up_among, runner_up_score

    office_points = world_points(office, scans)
    shift = np.array([60.0, 0.0])
    world = np.concatenate([office_points, office_points + shift])
    grid = match_grid_from_points(world, 0.2, 1.0, n_levels=10)
    truth = office.ground_truth.poses
    last = len(truth) // 3
    first = int(np.searchsorted(scans.travel_m, scans.travel_m[last] - 8.0))
    cloud = thin(place_points(inverse(truth[last]), office_points[np.hypot(*(office_points - truth[last, :2]).T)
                                                                  < 15.0]), 400)
    centre, reach = grid.centre_and_reach()
    c = CONFIG.localization
    index = PlaceIndex.along(world, np.concatenate([truth[:, :2], truth[:, :2] + shift]), SPACING_M, RADIUS_M)
    proposed = index.query(scans.cloud(first, last, 3000), 5)
    for copy in (np.zeros(2), shift):  # both copies proposed
        assert any(math.hypot(*(p.centre_m - truth[last, :2] - copy)) < 2.0 for p in proposed)
    searched = [search(grid, cloud, lattice_pose(cloud, 0.2, centre, np.array([*p.centre_m, p.heading_rad])), 2.5,
                       0.25, 0.5) for p in proposed]
    matches = [m for m in searched if m is not None]
    best = max(matches, key=lambda m: m.score)
    floor = c.runner_up_ratio * best.score
    args = (grid, cloud, centre, reach, math.pi, best.pose, floor, c.ambiguity_m, c.ambiguity_rad)
    found = runner_up_among(*args, [m for m in matches if m is not best])
    assert found is not None and found >= floor
    assert runner_up_score(*args) >= floor  # the whole map's search agrees: ambiguous
    twin = next(m for m in matches if m is not best and m.score >= floor)
    assert math.hypot(*(twin.pose[:2] - best.pose[:2])) == pytest.approx(60.0, abs=0.3)
    # poses its search would not count
    near_best = replace(twin, pose=best.pose + np.array([0.2, 0.0, 0.0]))
    off_lattice = replace(twin, pose=twin.pose + np.array([0.07, 0.0, 0.0]))
    weak = replace(twin, score=0.99 * floor)
    assert runner_up_among(*args, [near_best, off_lattice, weak]) is None
    small = (grid, cloud, best.pose, 10.0, math.pi, best.pose, floor, c.ambiguity_m, c.ambiguity_rad)
    assert runner_up_among(*small, [replace(twin, pose=lattice_pose(cloud, 0.2, best.pose, twin.pose))]) is None
    # search_at_places takes it from there: no whole-map search
    monkeypatch.setattr(place_index, "runner_up_score", lambda *a, **k: pytest.fail("searched the whole map"))
    at_places = search_at_places(grid, cloud, centre, reach, math.pi, proposed, 2.5, 0.25, 0.5, c.ambiguity_m,
                                 c.ambiguity_rad, c.runner_up_ratio, 0.5)
    assert at_places is not None and at_places.runner_up_score >= c.runner_up_ratio * at_places.score


def test_a_drive_is_placed_in_its_own_building_among_made_up_ones_with_the_places_its_bundle_keeps(tmp_path) -> None:
    """Three made-up office floors mapped; each one's places kept in its bundle (read back from the file,
    and made again from a bundle of the first format version, which kept none: the same ranking); a drive
    of the second floor driven the other way round is placed in its map, ranked first; a fourth floor's
    drive is refused by all three."""
    from slam_engine.products.map_bundle import read_bundle, write_bundle

    maps = []
    for number in (1, 2, 3):
        bundle = run_slam(simulate(f"building-{number}", seed=0, cameras=False).log, CONFIG).bundle
        assert bundle is not None and bundle.places is not None and len(bundle.places.centres) > 50
        maps.append((f"building-{number}", read_bundle(write_bundle(bundle, tmp_path / f"{number}.npz"))))
        assert np.array_equal(maps[-1][1].places.bins, bundle.places.bins)
    back = simulate("building-2-back", seed=1, cameras=False).log
    which = localize_in_maps(maps, back, CONFIG)
    assert which.summary()["chosen"] == "building-2" and which.tries[0].name == "building-2"
    assert [t.localised for t in which.tries] == [True, None, None]
    assert which.tries[0].likeness > max(t.likeness for t in which.tries[1:]) + 0.05
    unkept = [(name, replace(bundle, places=None)) for name, bundle in maps]  # as version 1 bundles read
    again = localize_in_maps(unkept, back, CONFIG)
    assert [t.name for t in again.tries] == [t.name for t in which.tries]
    assert [t.likeness for t in again.tries] == pytest.approx([t.likeness for t in which.tries], abs=1e-6)
    foreign = localize_in_maps(maps, simulate("building-4", seed=1, cameras=False).log, CONFIG)
    assert foreign.chosen is None and all(t.localised is False for t in foreign.tries)
