"""Localising a drive scan by scan while it drives (``LiveLocalizer``): the simulated office driven again
in its own map, and the same drive carried off part-way (a kidnap the odometry does not feel)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.kidnap import stream
from slam_engine.config import SlamConfig
from slam_engine.evaluation.metrics import align_rigid_2d
from slam_engine.frontend.odometry import dead_reckoning
from slam_engine.frontend.particle_filter import make_projector
from slam_engine.multisession.live_localization import FOUND, LOST, SEARCHING, LiveLocalizer
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate

CONFIG = SlamConfig(seed=0)


@pytest.fixture(scope="module")
def office_map():
    """The office mapped (seed 0), with the rotation and translation that carry its frame onto the world."""
    drive = simulate("office", seed=0, cameras=False)
    result = run_slam(drive.log, CONFIG)
    rotation, translation = align_rigid_2d(result.trajectory.poses[:, :2], drive.pose_at(result.trajectory.t_s)[:, :2])
    return result.bundle, rotation, translation


def _stream(bundle, drive):
    """The drive's scans fed one by one, each search waited for: the localiser and (scan, report) per scan."""
    return stream(bundle, drive, CONFIG)


def _errors(reports, drive, rotation, translation):
    truth = drive.pose_at(drive.log.scans.t_s)
    return {i: float(np.hypot(*(report.pose[:2] @ rotation.T + translation - truth[i, :2])))
            for i, report in reports if report.pose is not None}


@pytest.mark.slow
def test_the_office_driven_again_is_found_within_two_stretches_and_tracked(office_map) -> None:
    bundle, rotation, translation = office_map
    again = simulate("office", seed=1, cameras=False)
    live, reports = _stream(bundle, again)
    states = [report.state for _, report in reports]
    first = states.index(FOUND)
    # searching (no pose) until a stretch and its confirmation were driven: 6.2 m measured (2 m stretches, grown
    # once while ambiguous; 8.2 m with 4 m stretches), then found throughout
    assert all(state == SEARCHING for state in states[:first]) and set(states[first:]) == {FOUND}
    assert reports[first][1].pose is not None and live.summary()["first_found_travel_m"] < 7.0
    errors = _errors(reports, again, rotation, translation)
    assert max(errors.values()) < 0.05  # measured 0.016 m
    assert live.summary()["states"]["found"] == len(states) - first and live.events[0]["event"] == "found"


@pytest.mark.slow
def test_a_real_drive_streamed_into_its_buildings_map_is_found_and_never_lost(dataset) -> None:
    """intel-b fed scan by scan into intel-a's map (the shared sessions): found after 7.9 m, then 298 scans found
    and 140 outside the map (rooms intel-a never entered), never lost. Counting the travel outside the map after
    a held drop (as a finished drive's localisation does) lost it for 98 scans."""
    from types import SimpleNamespace

    from slam_engine.formats import load_log

    saved = run_slam(load_log(dataset("sessions/intel-a.clf")), CONFIG).bundle
    live, reports = _stream(saved, SimpleNamespace(log=load_log(dataset("sessions/intel-b.clf"))))
    summary = live.summary()
    assert summary["states"]["lost"] == 0 and [event["event"] for event in live.events] == ["found"]
    assert summary["states"]["found"] >= 280 and summary["first_found_travel_m"] < 10.0
    assert summary["states"]["outside"] >= 100


@pytest.mark.slow
def test_a_placement_the_last_search_delivers_is_reported_when_the_stream_ends(office_map) -> None:
    """The drive streamed until the first search that places it is running, then the stream ends: waiting
    for that search reports the last scan again, found where the robot is, and the summary counts it."""
    bundle, rotation, translation = office_map
    again = simulate("office", seed=1, cameras=False)
    log = again.log
    odometry = dead_reckoning(log).poses
    projector = make_projector(log.lidar, CONFIG, no_return_bounded=False)
    live = LiveLocalizer(bundle, CONFIG)
    for i in range(len(log.scans)):
        first = live.add(log.scans.t_s[i], odometry[i], projector.project(log.scans.ranges_m[i]).hits_v)
        again_reported = live.wait()  # as at the stream's end: the search this scan started waited for
        if live.state == FOUND:
            break
    live.close()
    last = len(live.reports) - 1
    assert first.scan == last and first.state == SEARCHING and first.pose is None
    assert again_reported is not None and again_reported.scan == last and again_reported.t_s == first.t_s
    assert again_reported.state == FOUND and again_reported.confidence >= CONFIG.localization.track_min_score
    error = _errors([(last, again_reported)], again, rotation, translation)[last]
    assert error < 0.05  # measured 0.003 m (scan 81, confidence 0.999)
    summary = live.summary()
    assert live.reports[last] is again_reported and summary["scans"] == last + 1
    assert summary["states"]["found"] == 1 and summary["states"]["searching"] == last
    assert summary["first_found_t_s"] == round(first.t_s, 3) and summary["mean_confidence"] > 0
    assert live.wait() is None  # nothing more to report


@pytest.mark.slow
def test_a_robot_carried_off_is_lost_within_metres_and_never_found_somewhere_else(office_map) -> None:
    bundle, rotation, translation = office_map
    # 24 s in, carried from the north-west room to where it would have been 20 s (6 m as the crow flies) later
    drive = simulate("office", seed=1, cameras=False, kidnap=(24.0, 20.0))
    truth = drive.pose_at(drive.log.scans.t_s)
    steps = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    kidnap = int(np.argmax(steps))  # the scan before the jump
    assert steps[kidnap] > 5.0 and np.hypot(*np.diff(dead_reckoning(drive.log).poses[:, :2], axis=0).T).max() < 0.2
    live, reports = _stream(bundle, drive)
    after = [(i, report) for i, report in reports if i > kidnap]
    lost_at = next(i for i, report in after if report.state == LOST)
    travel = np.concatenate([[0.0], np.cumsum(np.where(steps > 1.0, 0.0, steps))])  # driven, not carried
    assert travel[lost_at] - travel[kidnap + 1] < 3.0  # noticed: 2 m of scans the map refuses
    # where it was carried the map fits nowhere near its motion: no pose after the kidnap is called found
    # unless it is right
    errors = _errors(reports, drive, rotation, translation)
    assert all(errors[i] < 0.3 for i, report in after if report.state == FOUND)
    assert [event["event"] for event in live.events][:2] == ["found", "lost"]


@pytest.mark.slow
def test_a_robot_carried_off_to_a_look_alike_place_is_lost_there_and_found_again(office_map) -> None:
    """20 s in, carried to where it would have been 10 s later (6.1 m): a place of the office that looks like
    where it was, whose scans go on fitting near there (0.4-0.8 after 1.00; walls fit, furniture and doors
    stand in the map's free space). Measured before the drop and free-space checks: never lost, 211 scans
    found 5.5 m off; now lost after 1.4 m, found again by a search after 5.5 m."""
    bundle, rotation, translation = office_map
    drive = simulate("office", seed=1, cameras=False, kidnap=(20.0, 10.0))
    truth = drive.pose_at(drive.log.scans.t_s)
    steps = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    kidnap = int(np.argmax(steps))
    assert steps[kidnap] > 5.0
    live, reports = _stream(bundle, drive)
    after = [(i, report) for i, report in reports if i > kidnap]
    errors = _errors(reports, drive, rotation, translation)
    assert all(errors[i] < 0.3 for i, report in after if report.state == FOUND)
    travel = np.concatenate([[0.0], np.cumsum(np.where(steps > 1.0, 0.0, steps))])  # driven, not carried
    lost_at = next(i for i, report in after if report.state == LOST)
    found_at = next(i for i, report in after if report.state == FOUND)
    assert travel[lost_at] - travel[kidnap + 1] < 3.0 and lost_at < found_at
    assert travel[found_at] - travel[kidnap + 1] < 10.0  # the target
    assert any(event.get("search") for event in live.events if event["event"] == "found")


@pytest.mark.slow
def test_a_drive_that_leaves_the_map_and_comes_back_is_carried_then_found_again() -> None:
    """A map of the office's north rooms and corridor only (``office-north``), and the office's own drive
    through the south rooms too: out there it is carried (outside), back in it is found, never lost; the
    whole drive localised afterwards stays within centimetres of the truth throughout."""
    from slam_engine.multisession.localization import localize_log

    north = simulate("office-north", seed=0, cameras=False)
    mapped = run_slam(north.log, CONFIG)
    rotation, translation = align_rigid_2d(mapped.trajectory.poses[:, :2], north.pose_at(mapped.trajectory.t_s)[:, :2])
    drive = simulate("office", seed=1, cameras=False)
    live, reports = _stream(mapped.bundle, drive)
    states = [report.state for _, report in reports]
    runs = [state for k, state in enumerate(states) if k == 0 or state != states[k - 1]]
    assert runs == [SEARCHING, FOUND, "outside", FOUND] and LOST not in states  # measured: 36 scans outside
    truth = drive.pose_at(drive.log.scans.t_s)
    out_there = [i for i, report in reports if report.state == "outside"]
    assert min(truth[i, 1] for i in out_there) < -2.5  # in the south rooms, which the map never drove
    assert max(_errors([(i, r) for i, r in reports if r.state == FOUND], drive, rotation, translation).values()) < 0.05
    _, whole = localize_log(mapped.bundle, drive.log, CONFIG)
    errors = np.hypot(*(whole.trajectory.poses[:, :2] @ rotation.T + translation - truth[:, :2]).T)
    assert whole.outside_map.sum() >= 20 and errors.max() < 0.1  # measured 0.038 m


@pytest.mark.slow
def test_a_robot_carried_off_in_a_made_up_floor_is_not_found_where_it_was() -> None:
    """A made-up office floor (no look-alike twin, unlike the office): carried off 30 s in to where it would
    have been 20 s later (5.6 m away), its first scan there still fits, weakly (0.55 after 1.00), near where
    it was: a drop that sharp is not found, and no pose after the kidnap is found unless it is right."""
    mapped = simulate("building-2", seed=0, cameras=False)
    result = run_slam(mapped.log, CONFIG)
    rotation, translation = align_rigid_2d(result.trajectory.poses[:, :2],
                                           mapped.pose_at(result.trajectory.t_s)[:, :2])
    drive = simulate("building-2", seed=1, cameras=False, kidnap=(30.0, 20.0))
    steps = np.hypot(*np.diff(drive.pose_at(drive.log.scans.t_s)[:, :2], axis=0).T)
    kidnap = int(np.argmax(steps))
    assert steps[kidnap] > 5.0
    live, reports = _stream(result.bundle, drive)
    after = [(i, report) for i, report in reports if i > kidnap]
    assert after[0][1].state != FOUND and reports[kidnap][1].state == FOUND  # tracked up to the jump
    errors = _errors(reports, drive, rotation, translation)
    assert all(errors[i] < 0.3 for i, report in after if report.state == FOUND)
    travel = np.concatenate([[0.0], np.cumsum(np.where(steps > 1.0, 0.0, steps))])
    lost_at = next(i for i, report in after if report.state == LOST)
    assert travel[lost_at] - travel[kidnap + 1] < 3.0
