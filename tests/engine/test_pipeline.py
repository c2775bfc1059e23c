"""run_slam on small synthetic logs: one pose per scan, determinism, progress and cancelling,
logs without scans or without odometry."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from slam_engine.config import SlamConfig
from slam_engine.errors import Cancelled, ConfigError
from slam_engine.model.drive_log import DriveLog, LidarModel, MotionModelKind, OdometryStream, ScanStream, VehicleModel
from slam_engine.model.poses import compose, relative
from slam_engine.pipeline import (
    ALIGNING_TO_MAP,
    CLOSING_LOOPS,
    MAPPING_SCANS,
    RENDERING_MAP,
    STAGES,
    WRITING_PRODUCTS,
    RunProgress,
    run_fraction,
    run_slam,
)

sys.path.insert(0, str(Path(__file__).parent.parent))
from test_scan_matcher import room_scan  # noqa: E402

N_BEAMS = 360


def room_log(n_scans: int = 40, odometry_bias: float = 0.0) -> tuple[DriveLog, np.ndarray]:
    """A robot driving a loop in the synthetic room; odometry over-reports turning by ``odometry_bias``."""
    t = np.arange(n_scans, dtype=float)
    phase = 2 * np.pi * t / n_scans
    truth = np.stack([1.8 * np.cos(phase) - 0.5, 1.2 * np.sin(phase) - 0.5, phase + np.pi / 2], axis=1)
    odom = [truth[0]]
    for k in range(1, n_scans):
        step = relative(truth[k - 1], truth[k])
        step[2] *= 1.0 + odometry_bias
        odom.append(compose(odom[-1], step))
    ranges = np.array([np.hypot(*room_scan(p, N_BEAMS).T) for p in truth], np.float32)
    lidar = LidarModel(num_beams=N_BEAMS, angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / N_BEAMS,
                       range_min_m=0.05, range_max_m=30.0)
    log = DriveLog(vehicle=VehicleModel(kind=MotionModelKind.ODOMETRY), lidar=lidar,
                   scans=ScanStream(t_s=t, ranges_m=ranges), odometry=OdometryStream(t_s=t, poses=np.array(odom)))
    return log, truth


def test_biased_odometry_is_corrected_and_every_scan_gets_a_pose() -> None:
    log, truth = room_log(odometry_bias=0.08)
    result = run_slam(log, SlamConfig(particles=8))
    assert len(result.trajectory) == len(log.scans) == len(result.dead_reckoning)
    np.testing.assert_array_equal(result.trajectory.t_s, log.scans.t_s)
    expected = relative(truth[0], truth)
    slam_err = np.hypot(*(result.trajectory.poses[:, :2] - expected[:, :2]).T).max()
    dr_err = np.hypot(*(result.dead_reckoning.poses[:, :2] - expected[:, :2]).T).max()
    assert dr_err > 0.5
    assert slam_err < 0.06 and slam_err < dr_err / 10


def test_same_seed_same_map_and_progress_is_reported() -> None:
    log, _ = room_log(n_scans=15, odometry_bias=0.05)
    seen: list[RunProgress] = []
    a = run_slam(log, SlamConfig(particles=5, seed=3), progress=seen.append)
    b = run_slam(log, SlamConfig(particles=5, seed=3))
    np.testing.assert_array_equal(a.grid.log_odds, b.grid.log_odds)
    np.testing.assert_array_equal(a.trajectory.poses, b.trajectory.poses)
    assert seen[-1].scans_done == seen[-1].scans_total == 15
    assert [p.scans_done for p in seen[:3]] == [1, 2, 3]


def test_progress_goes_through_the_named_stages_in_order_and_ends_with_the_products() -> None:
    log, _ = room_log(n_scans=40, odometry_bias=0.05)
    seen: list[RunProgress] = []
    run_slam(log, SlamConfig(particles=3), progress=seen.append)
    stages = [p.stage for i, p in enumerate(seen) if i == 0 or p.stage != seen[i - 1].stage]
    assert stages == [MAPPING_SCANS, CLOSING_LOOPS, ALIGNING_TO_MAP, RENDERING_MAP]
    fractions = [p.fraction for p in seen]
    assert fractions == sorted(fractions)  # never backwards
    mapped = max(p.fraction for p in seen if p.stage == MAPPING_SCANS)
    assert mapped == pytest.approx(0.70) and fractions[-1] == pytest.approx(0.97)  # the products are the rest
    assert len({p.fraction for p in seen if p.stage == CLOSING_LOOPS}) > 5  # moves while loops are searched
    assert STAGES[-1] == WRITING_PRODUCTS and run_fraction(WRITING_PRODUCTS, 0.999) < 1.0
    assert run_fraction(WRITING_PRODUCTS, 1.0) == 1.0  # only at the very end


def test_a_cancel_stops_the_back_end_too() -> None:
    log, _ = room_log(n_scans=40)

    def stop_in_the_back_end(p: RunProgress) -> None:
        if p.stage == CLOSING_LOOPS and (p.stage_fraction or 0.0) > 0.3:
            raise Cancelled("stopped by the user")

    with pytest.raises(Cancelled):
        run_slam(log, SlamConfig(particles=3), progress=stop_in_the_back_end)


def test_snapshots_every_n_processed_scans() -> None:
    log, _ = room_log(n_scans=20)
    result = run_slam(log, SlamConfig(particles=3, snapshot_every_scans=5))
    assert len(result.snapshots) == 4
    assert [len(s.trajectory) for s in result.snapshots] == [5, 10, 15, 20]


def test_progress_callback_can_cancel() -> None:
    log, _ = room_log(n_scans=15)

    def stop_after_three(p: RunProgress) -> None:
        if p.scans_done >= 3:
            raise Cancelled("stopped by the user")

    with pytest.raises(Cancelled):
        run_slam(log, SlamConfig(particles=3), progress=stop_after_three)


def test_log_without_scans_gives_dead_reckoning_with_a_warning() -> None:
    log, _ = room_log(n_scans=5)
    log.scans = None
    result = run_slam(log, SlamConfig(particles=3))
    assert any("no LiDAR scans" in w for w in result.warnings)
    np.testing.assert_array_equal(result.trajectory.poses, result.dead_reckoning.poses)
    assert len(result.trajectory) == 5


def test_log_without_odometry_is_a_config_error() -> None:
    log, _ = room_log(n_scans=5)
    log.odometry = None
    with pytest.raises(ConfigError, match="no odometry source"):
        run_slam(log, SlamConfig(particles=3))


def test_clones_after_resampling_share_one_insertion_with_identical_results(monkeypatch) -> None:
    """Inserting the scan once per ancestor after resampling (clones share that map) gives bit-identical
    trajectories and maps to inserting it into every particle."""
    from slam_engine.frontend.particle_filter import SlamFilter

    log, _ = room_log(odometry_bias=0.1)
    config = SlamConfig(particles=12, seed=3, resample_threshold=0.99)
    calls: list[int | None] = []
    original = SlamFilter._insert

    def counting(self, projected, clones_of):
        calls.append(None if clones_of is None else len(np.unique(clones_of)))
        original(self, projected, clones_of)

    monkeypatch.setattr(SlamFilter, "_insert", counting)
    shared = run_slam(log, config)
    assert any(c is not None and c < config.particles for c in calls)  # clones existed and were shared
    monkeypatch.setattr(SlamFilter, "_insert", lambda self, projected, clones_of: original(self, projected, None))
    unshared = run_slam(log, config)
    np.testing.assert_array_equal(shared.trajectory.poses, unshared.trajectory.poses)
    np.testing.assert_array_equal(shared.grid.log_odds, unshared.grid.log_odds)


def test_snapshots_without_live_previews_are_the_same_frames() -> None:
    """Without live previews the filter only marks where each frame goes, and the frames are drawn
    after the back end, at an animation frame's size, in one pass over the key frames' scans. Where
    the final map is the filter's own (no loop closing, unbounded no-return rays), they are the
    snapshots that live previews take during the filter, cell for cell."""
    from slam_engine.model.result import SNAPSHOT_MAX_SIDE_CELLS
    from slam_engine.pipeline import run_filter
    from slam_engine.simulation import simulate

    drive = simulate("office", seed=0, rig="carmen-robot", max_duration_s=80.0, cameras=False)
    config = SlamConfig(particles=4, seed=0, snapshot_every_scans=40, loop_closing={"enabled": False},
                        grid={"no_return_bounded": False})
    offline = run_filter(drive.log, config, np.random.default_rng(config.seed), live_previews=False)
    assert offline.snapshots == [] and len(offline.frame_marks) == offline.steps_processed // 40
    live = run_slam(drive.log, config, progress=lambda p: None)
    frames = run_slam(drive.log, config, live_previews=False)
    assert len(live.snapshots) == len(frames.snapshots) >= 5
    pooled = 0
    for a, b in zip(live.snapshots, frames.snapshots, strict=True):
        assert max(b.grid.shape) <= SNAPSHOT_MAX_SIDE_CELLS
        assert (a.grid.resolution_m, a.grid.origin_x_m, a.grid.origin_y_m) == \
            (b.grid.resolution_m, b.grid.origin_x_m, b.grid.origin_y_m)
        np.testing.assert_array_equal(a.grid.log_odds, b.grid.log_odds)
        pooled += b.grid.resolution_m > config.grid.resolution_m
    assert pooled >= 1  # the later maps are larger than a frame: pooled, the same either way


def test_snapshots_are_the_final_map_being_built() -> None:
    """When the final map is re-rendered (optimised poses, bounded no-return rays), the animation's
    snapshots are drawn the same way in the same pass: each carries the final trajectory up to its
    time and lies inside the final map (not the filter's own map and path)."""
    from slam_engine.products.animation import map_extent
    from slam_engine.simulation import simulate

    drive = simulate("office", seed=0, rig="carmen-robot", max_duration_s=80.0, cameras=False)
    config = SlamConfig(particles=4, seed=0, snapshot_every_scans=40)
    result = run_slam(drive.log, config, live_previews=False)
    assert len(result.snapshots) >= 5
    left, bottom, right, top = map_extent(result.grid)
    for snapshot in result.snapshots:
        so_far = result.trajectory.until(snapshot.t_s)
        np.testing.assert_array_equal(snapshot.trajectory.poses, so_far.poses)
        assert snapshot.trajectory.t_s[-1] == snapshot.t_s
        pad = snapshot.grid.resolution_m  # a pooled snapshot's known blocks may reach one block further
        s_left, s_bottom, s_right, s_top = map_extent(snapshot.grid)
        assert (s_left >= left - pad and s_bottom >= bottom - pad and s_right <= right + pad
                and s_top <= top + pad), (map_extent(snapshot.grid), (left, bottom, right, top))


def test_a_saved_maps_animation_ends_on_the_runs_final_frame(tmp_path: Path) -> None:
    """Drawn later from the map bundle (``lidarmap animate``), the animation is the map being built key
    frame by key frame at the final poses: as many frames as asked, the known area growing, each with its
    drive's trajectory up to the frame's key frame, and the last frame the run's own."""
    from PIL import Image, ImageSequence

    from slam_engine.products.animation import bundle_snapshots, write_animation_gif, write_bundle_animation
    from slam_engine.simulation import simulate

    drive = simulate("office", seed=0, rig="carmen-robot", max_duration_s=80.0, cameras=False)
    result = run_slam(drive.log, SlamConfig(particles=4, seed=0, snapshot_every_scans=40), live_previews=False)
    assert result.bundle is not None and len(result.snapshots) >= 5
    snapshots, grid, trajectory = bundle_snapshots(result.bundle, frames=12)
    assert len(snapshots) == 11
    # re-rendered as the run does, from the bundle's float32 rays: 1 cell of 128 000 differs (a ray's end
    # rounded across a cell boundary)
    assert grid.log_odds.shape == result.grid.log_odds.shape
    assert (grid.log_odds != result.grid.log_odds).sum() <= 1e-4 * (result.grid.log_odds != 0).sum()
    np.testing.assert_array_equal(trajectory.poses, result.trajectory.poses)
    known = [int((s.grid.log_odds != 0).sum() * s.grid.resolution_m ** 2) for s in snapshots]
    assert known == sorted(known) and known[0] < known[-1]
    for snapshot in snapshots:
        assert snapshot.trajectory.t_s[-1] <= snapshot.t_s and len(snapshot.trajectory) > 1
    write_animation_gif(result.snapshots, result.grid, result.trajectory, tmp_path / "run.gif")
    write_bundle_animation(result.bundle, tmp_path / "later.gif", frames=12)
    run_frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(tmp_path / "run.gif"))]
    later = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(tmp_path / "later.gif"))]
    assert len(later) == 12 and later[-1].shape == run_frames[-1].shape
    assert (later[-1] != run_frames[-1]).any(axis=2).sum() <= 2  # measured: 0


def test_loop_closures_are_placed_on_the_final_map() -> None:
    """run.json's closures carry their two key frames' places on the final map (for the viewer)."""
    from slam_engine.simulation import simulate

    office = simulate("office", seed=0, cameras=False)
    result = run_slam(office.log, SlamConfig(particles=10))
    closures = result.input_summary["loop_closing"]["closures"]
    accepted = [c for c in closures if c["accepted"]]
    assert len(accepted) >= 5
    for closure in closures:
        for end in ("node", "anchor"):
            np.testing.assert_allclose(closure[f"{end}_xy_m"], result.bundle.poses[closure[end], :2], atol=1e-4)
