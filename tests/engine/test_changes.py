"""The change map: what a drive placed in a saved map sees added and removed, scored against the simulated
office's known changes (a desk moved, a pillar taken away, a door closed, a partition put up)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slam_engine.config import ChangesConfig, SlamConfig
from slam_engine.evaluation.changes import change_accuracy
from slam_engine.evaluation.metrics import align_rigid_2d
from slam_engine.model.result import OccupancyGrid
from slam_engine.multisession.changes import ChangeMap, detect_changes, localization_changes
from slam_engine.multisession.localization import localize_log
from slam_engine.pipeline import run_slam
from slam_engine.products.changes import changes_geojson, changes_image, write_changes
from slam_engine.products.georeference import GeoOrigin, Georeference
from slam_engine.products.multisession import saved_map_grid
from slam_engine.simulation import changes_beside_log, simulate, write_simulated
from slam_engine.texture.accuracy import match_times

RESOLUTION_M = 0.05


def _room() -> OccupancyGrid:
    """A saved map 10 m x 6 m (cells of 5 cm, origin at (0, -1)): free, with a wall at x = 8 m and a
    0.15 m box at (6.0, 1.0) that the new drive will find gone; beyond the wall unknown."""
    log_odds = np.full((120, 200), -2.0, np.float32)
    log_odds[:, 161:] = 0.0  # beyond the wall: never observed
    log_odds[:, 160] = 3.0  # the wall, x in [8.0, 8.05)
    log_odds[38:41, 119:122] = 3.0  # the box, around (6.0, 1.0)
    return OccupancyGrid(log_odds, RESOLUTION_M, 0.0, -1.0)


def _drive(person_at: list[int], standing: bool = True) -> tuple[list[np.ndarray], np.ndarray]:
    """Scans from poses along x = 2 m (y = 0 .. 4 m, heading +x): beams to the wall, a 0.3 m object
    standing at x = 5 m, y = 3 m (``standing``), and a person at x = 5 m, y = 1.5 m in the scans
    ``person_at`` only. Beams that the object or the person would stop end on them."""
    poses = np.column_stack([np.full(17, 2.0), np.linspace(0.0, 4.0, 17), np.zeros(17)])
    scans = []
    for k, (x, y, _) in enumerate(poses):
        blockers = ([(2.85, 3.15)] if standing else []) + ([(1.4, 1.6)] if k in person_at else [])
        wall_y = np.linspace(y - 2.5, y + 2.5, 201)
        at_five = y + (wall_y - y) * (5.0 - x) / (8.0 - x)  # where each wall beam crosses x = 5 m
        blocked = np.zeros(len(wall_y), bool)
        ends = []
        for low, high in blockers:
            blocked |= (at_five >= low) & (at_five <= high)
            ends.append(np.column_stack([np.full(7, 5.0 - x), np.linspace(low, high, 7) - y]))
        ends.append(np.column_stack([np.full(int((~blocked).sum()), 8.0 - x + 0.02), wall_y[~blocked] - y]))
        scans.append(np.concatenate(ends))
    return scans, poses


def _cells(changes: ChangeMap, mask: np.ndarray) -> np.ndarray:
    iy, ix = np.nonzero(mask)
    return changes.origin_m + (np.column_stack([ix, iy]) + 0.5) * changes.resolution_m


def test_an_object_seen_from_many_poses_is_added_a_passer_by_is_not_and_a_box_seen_through_is_removed() -> None:
    scans, poses = _drive(person_at=[3, 4])
    changes = detect_changes(_room(), scans, poses, np.zeros(2), ChangesConfig(key_spacing_m=0.2))

    added = _cells(changes, changes.added)
    assert len(added) > 0
    assert np.all(np.abs(added[:, 0] - 5.0) <= 0.15) and np.all(np.abs(added[:, 1] - 3.0) <= 0.25)  # the object
    removed = _cells(changes, changes.removed)
    assert len(removed) > 0 and np.all(np.hypot(removed[:, 0] - 6.0, removed[:, 1] - 1.0) <= 0.2)  # the box
    # the wall still stands (hit beside where it was, whatever the cell edges), beyond it nothing is judged
    assert not changes.removed[:, 79:].any() and not changes.added[:, 79:].any()
    summary = changes.summary()
    assert summary["added_regions"] == 1 and summary["removed_regions"] == 1
    assert summary["added_m2"] == pytest.approx(changes.added.sum() * 0.01)


def test_nothing_is_a_change_for_fewer_scans_than_min_scans() -> None:
    scans, poses = _drive(person_at=list(range(17)), standing=False)  # the person stands still all drive
    strict = detect_changes(_room(), scans, poses, np.zeros(2), ChangesConfig(key_spacing_m=0.2, min_scans=100))
    assert not strict.added.any() and not strict.removed.any()
    seen_by_all = detect_changes(_room(), scans, poses, np.zeros(2), ChangesConfig(key_spacing_m=0.2))
    assert seen_by_all.added.any()  # ... which the default calls a change: 17 scans from 17 poses hit it


def test_the_geojson_outlines_each_region_and_is_placed_on_earth_when_the_map_is() -> None:
    scans, poses = _drive(person_at=[])
    changes = detect_changes(_room(), scans, poses, np.zeros(2), ChangesConfig(key_spacing_m=0.2))
    local = changes_geojson(changes)
    kinds = sorted(f["properties"]["kind"] for f in local["features"])
    assert kinds == ["added", "removed"]
    for feature in local["features"]:
        ring = np.array(feature["geometry"]["coordinates"][0])
        mask = changes.added if feature["properties"]["kind"] == "added" else changes.removed
        cells = _cells(changes, mask)
        # the outline runs along the cells' edges: their centres half a cell inside it
        assert ring[:, 0].min() == pytest.approx(cells[:, 0].min() - 0.05)
        assert ring[:, 1].max() == pytest.approx(cells[:, 1].max() + 0.05)
        assert feature["properties"]["area_m2"] == pytest.approx(mask.sum() * 0.01)

    georef = Georeference.utm(GeoOrigin(latitude_deg=48.0, longitude_deg=7.8, heading_deg=90.0), [0.0, 0.0, 0.0])
    on_earth = changes_geojson(changes, georef)
    assert "coordinates" not in on_earth  # RFC 7946: WGS 84, no note
    for here, there in zip(local["features"], on_earth["features"], strict=True):
        assert there["properties"]["map_frame_geometry"] == here["geometry"]
        lon, lat = np.array(there["geometry"]["coordinates"][0]).T
        # heading east: map x points east; 5-6 m east of the start is about 7e-5 degrees of longitude at 48 N
        assert np.all(np.abs(lat - 48.0) < 3e-5) and np.all((lon > 7.8 + 5e-5) & (lon < 7.8 + 1e-4))


@pytest.fixture(scope="module")
def office_changed(tmp_path_factory):
    """The office mapped (seed 0), and a drive there days later (office-changed, seed 1) localised in it."""
    config = SlamConfig()
    bundle = run_slam(simulate("office", seed=0, cameras=False).log, config).bundle
    later = simulate("office-changed", seed=1, cameras=False)
    drive, result = localize_log(bundle, later.log, config)
    assert result.localised
    return bundle, later, drive, result, config


@pytest.mark.slow
def test_the_simulated_changes_are_found_cell_by_cell(office_changed, tmp_path) -> None:
    bundle, later, drive, result, config = office_changed
    grid = saved_map_grid(bundle, config)
    changes = localization_changes(grid, drive, result, config.changes)
    assert changes is not None
    # the truth, as the simulator writes it beside its log, read back
    write_simulated(later, "carmen", tmp_path)
    truth = changes_beside_log(tmp_path)
    assert truth is not None and len(truth["removed"]) == 8 and len(truth["added"]) == 6
    index = match_times(later.ground_truth.t_s, result.trajectory.t_s)
    rotation, translation = align_rigid_2d(later.ground_truth.poses[index, :2], result.trajectory.poses[:, :2])
    T_map_from_world = np.array([*translation, np.arctan2(rotation[1, 0], rotation[0, 0])])
    accuracy = change_accuracy(changes, truth["removed"], truth["added"], T_map_from_world)
    assert accuracy["precision"] >= 0.9 and accuracy["recall"] >= 0.8, accuracy  # the targets
    assert accuracy["added"]["recall"] >= 0.75 and accuracy["removed"]["recall"] >= 0.9, accuracy
    summary = changes.summary()
    # added: the moved desk, the door, the partition; removed: the desk where it was, the pillar
    assert summary["added_regions"] >= 3 and summary["removed_regions"] == 2
    assert summary["changed_share"] < 0.02

    written = write_changes(tmp_path / "out", changes, grid)
    doc = json.loads(written["changes.geojson"].read_text())
    assert sum(f["properties"]["area_m2"] for f in doc["features"]) == pytest.approx(
        summary["added_m2"] + summary["removed_m2"], abs=0.01)
    pixels = np.asarray(changes_image(grid, changes))
    assert (pixels == (224, 49, 49)).all(axis=2).sum() >= changes.added.sum() * 4  # 2 x 2 map cells a change cell
    assert (pixels == (28, 126, 214)).all(axis=2).sum() >= changes.removed.sum() * 4


@pytest.mark.slow
def test_the_same_office_again_shows_no_change(office_changed) -> None:
    bundle, _, _, _, config = office_changed
    again = simulate("office", seed=2, cameras=False)
    drive, result = localize_log(bundle, again.log, config)
    changes = localization_changes(saved_map_grid(bundle, config), drive, result, config.changes)
    assert changes is not None and changes.summary()["observed_m2"] > 200
    assert changes.summary()["changed_share"] <= 0.001
    off = localization_changes(saved_map_grid(bundle, config), drive, result,
                               config.changes.model_copy(update={"enabled": False}))
    assert off is None
