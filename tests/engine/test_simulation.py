"""The simulator: determinism, scans consistent with the world and the ground truth, sensor errors
of a realistic size, a loop closure in the relations, the floor texture, the CLI."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from slam_engine.errors import ConfigError
from slam_engine.formats import load_log
from slam_engine.frontend.odometry import odometry_track
from slam_engine.model.poses import relative
from slam_engine.simulation import relations, simulate, write_simulated
from slam_engine.simulation.world import office


@pytest.fixture(scope="module")
def office_drive():
    return simulate(scenario="office", seed=0, rig="robot")


def point_to_segments_m(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest wall segment."""
    p, e = segments[:, :2], segments[:, 2:] - segments[:, :2]
    w = points[:, None, :] - p[None]
    u = np.clip((w * e[None]).sum(-1) / (e * e).sum(-1)[None], 0, 1)
    return np.hypot(*(w - u[..., None] * e[None]).transpose(2, 0, 1)).min(axis=1)


def test_same_seed_same_drive_other_seed_other_noise() -> None:
    a = simulate(seed=5, rig="robot", max_duration_s=5.0)
    b = simulate(seed=5, rig="robot", max_duration_s=5.0)
    c = simulate(seed=6, rig="robot", max_duration_s=5.0)
    np.testing.assert_array_equal(a.log.scans.ranges_m, b.log.scans.ranges_m)
    np.testing.assert_array_equal(a.log.encoders.ticks, b.log.encoders.ticks)
    assert not np.array_equal(a.log.scans.ranges_m, c.log.scans.ranges_m)


def test_full_office_drive_is_a_loop_of_known_size(office_drive) -> None:
    log, truth = office_drive.log, office_drive.ground_truth
    assert 90.0 < office_drive.motion.duration_s < 110.0
    assert office_drive.motion.s_m[-1] == pytest.approx(56.7, abs=0.5)
    assert 450 < len(log.scans) < 550 and len(truth) == len(log.scans)
    np.testing.assert_array_equal(truth.t_s, log.scans.t_s)
    rel = relations(truth, np.random.default_rng(0))
    loops = rel[rel[:, 1] - rel[:, 0] > 20.0]
    assert len(loops) > 50  # the robot re-enters the first room on the same heading


def test_scans_hit_the_walls_where_ground_truth_says(office_drive) -> None:
    log, truth = office_drive.log, office_drive.ground_truth
    lidar = log.lidar
    T = lidar.T_vehicle_from_lidar
    angles = lidar.beam_angles_rad
    distances = []
    for k in range(0, len(log.scans), 25):
        r = log.scans.ranges_m[k]
        ok = np.isfinite(r)
        local = np.column_stack([r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])]) + T[:2, 3]
        x, y, th = truth.poses[k]
        c, s = np.cos(th), np.sin(th)
        world = np.column_stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1]])
        distances.append(point_to_segments_m(world, office_drive.world.segments))
    distances = np.concatenate(distances)
    assert np.quantile(distances, 0.99) < 0.04  # 1 cm range noise
    share_inf = np.isinf(log.scans.ranges_m).mean()
    assert 0.005 < share_inf < 0.05  # 1 % dropouts plus beams out of range


def test_wheel_and_gyro_errors_are_realistic(office_drive) -> None:
    log, truth = office_drive.log, office_drive.ground_truth
    odometry = odometry_track(log)  # encoders + gyro
    length = np.hypot(*np.diff(odometry.poses[:, :2], axis=0).T).sum()
    assert length == pytest.approx(office_drive.motion.s_m[-1], rel=0.02)  # ~0.2 % scale error
    at_scans = np.column_stack([np.interp(truth.t_s, odometry.t_s, odometry.poses[:, i]) for i in range(2)])
    start_offset = truth.poses[0, :2]
    error = np.hypot(*(at_scans[-1] + start_offset - truth.poses[-1, :2]))
    assert 0.05 < error < 3.0  # drifts, but not absurdly
    wheels_only = odometry_track(replace(log, gyro=None))
    heading_error = abs(np.unwrap(wheels_only.poses[:, 2])[-1] - (office_drive.motion.theta_rad[-1]
                                                                    - office_drive.motion.theta_rad[0]))
    assert heading_error > np.radians(2.0)  # wheel scale error and slip bend the heading


def test_relations_are_true_relative_motions(office_drive) -> None:
    truth = office_drive.ground_truth
    rel = relations(truth, np.random.default_rng(1), max_loop=10)
    index = {t: i for i, t in enumerate(truth.t_s)}
    i, j = index[rel[-1, 0]], index[rel[-1, 1]]
    np.testing.assert_allclose(rel[-1, 2:], relative(truth.poses[[i]], truth.poses[[j]])[0])


def test_written_folder_has_truth_relations_and_loads(tmp_path) -> None:
    drive = simulate(seed=0, rig="carmen-robot", max_duration_s=6.0)
    write_simulated(drive, "carmen", tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ground_truth.txt", "log.clf", "office.relations"]
    rows = np.loadtxt(tmp_path / "office.relations")
    assert rows.shape[1] == 8 and np.all(rows[:, 4:7] == 0)
    assert len(load_log(tmp_path).scans) == len(drive.ground_truth)


def test_floor_texture_is_deterministic_and_varied() -> None:
    world = office()
    x, y = np.meshgrid(np.linspace(0, 3, 150), np.linspace(0, 3, 150))
    rgb = world.floor_rgb(x.ravel(), y.ravel())
    assert rgb.shape == (150 * 150, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb, world.floor_rgb(x.ravel(), y.ravel()))
    assert rgb.astype(float).std(axis=0).min() > 15
    assert (rgb == 45).all(axis=1).mean() > 0.01  # grout lines between tiles


def test_car_on_campus_uses_the_tilted_lidar() -> None:
    drive = simulate(seed=0, rig="car", scenario=None, max_duration_s=5.0, cameras=False)
    assert drive.scenario == "campus"
    assert drive.log.lidar.num_beams == 286
    assert np.isfinite(drive.log.scans.ranges_m).mean() > 0.5


def test_bad_simulation_requests() -> None:
    with pytest.raises(ConfigError, match="unknown rig"):
        simulate(rig="tank")
    with pytest.raises(ConfigError, match="unknown scenario"):
        simulate(scenario="moon")


def test_cli_simulate_and_formats(tmp_path) -> None:
    from lidarmap.cli import app

    runner = CliRunner()
    out = tmp_path / "sim"
    result = runner.invoke(app, ["simulate", "--format", "breezyslam", "--out", str(out), "--seed", "3",
                                 "--duration", "4"])
    assert result.exit_code == 0, result.output
    assert len(load_log(out).scans) == len(np.loadtxt(out / "ground_truth.txt"))
    result = runner.invoke(app, ["simulate", "--format", "breezyslam", "--out", str(out)])
    assert result.exit_code == 2 and "not empty" in result.output
    result = runner.invoke(app, ["formats"])
    assert result.exit_code == 0 and "ece276a-car" in result.output
    result = runner.invoke(app, ["formats", "--schema"])
    assert result.exit_code == 0 and '"DriveLogManifest"' in result.output


def test_interlaced_rig_is_the_same_drive_with_each_scan_at_its_own_start_angle(tmp_path) -> None:
    plain = simulate("office", seed=0, rig="carmen-robot", max_duration_s=10.0, cameras=False)
    interlaced = simulate("office", seed=0, rig="carmen-interlaced", max_duration_s=10.0, cameras=False)
    offsets = interlaced.log.scans.angle_offset_rad
    assert plain.log.scans.angle_offset_rad is None
    assert np.degrees(offsets[:8]) == pytest.approx([0.0, 0.25, 0.5, 0.75] * 2)
    np.testing.assert_array_equal(interlaced.ground_truth.poses, plain.ground_truth.poses)
    np.testing.assert_array_equal(interlaced.log.odometry.poses, plain.log.odometry.poses)
    first_phase = offsets == 0.0
    np.testing.assert_array_equal(interlaced.log.scans.ranges_m[first_phase], plain.log.scans.ranges_m[first_phase])
    assert not np.array_equal(interlaced.log.scans.ranges_m[~first_phase], plain.log.scans.ranges_m[~first_phase])
    # each scan's end points, at its true pose with its own start angle, lie on the world's walls
    walls = interlaced.world.segments
    lidar = interlaced.log.lidar
    for k in (1, 2, 3):
        ranges = interlaced.log.scans.ranges_m[k].astype(np.float64)
        angles = lidar.beam_angles_rad + offsets[k]
        x, y, theta = interlaced.ground_truth.poses[k]
        mount = lidar.T_vehicle_from_lidar[:2, 3]
        origin = np.array([x, y]) + np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]]) @ mount
        hit = np.isfinite(ranges)
        ends = origin + ranges[hit, None] * np.column_stack([np.cos(theta + angles[hit]), np.sin(theta + angles[hit])])
        assert np.median(point_to_segments_m(ends, walls)) < 0.008  # measured 0.004-0.005 (0.011-0.018 unturned)
    # CARMEN, drivelog and ROS bags store a start angle per scan: the other formats refuse rather than lose it
    from slam_engine.errors import LogFormatError
    with pytest.raises(LogFormatError, match="cannot store a start angle that changes"):
        write_simulated(interlaced, "breezyslam", tmp_path / "dat")
    bag = load_log(write_simulated(interlaced, "rosbag", tmp_path / "bag"))
    np.testing.assert_allclose(bag.scans.angle_offset_rad, offsets, atol=1e-6)  # float32 angle_min in the bag
    np.testing.assert_array_equal(bag.scans.ranges_m, interlaced.log.scans.ranges_m)
    assert any("carried per scan" in w for w in bag.warnings)


def test_a_kidnapped_drive_jumps_where_its_wheels_feel_nothing() -> None:
    from slam_engine.frontend.odometry import dead_reckoning

    drive = simulate("office", seed=1, cameras=False, kidnap=(24.0, 20.0))
    plain = simulate("office", seed=1, cameras=False)
    assert drive.motion.duration_s == pytest.approx(plain.motion.duration_s - 20.0, abs=0.02)
    truth = drive.pose_at(drive.log.scans.t_s)
    steps = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    jump = int(np.argmax(steps))
    assert 23.5 < drive.log.scans.t_s[jump] - drive.log.scans.t_s[0] < 24.5
    # carried from where the plain drive is 24 s in to where it is 44 s in (a scan or two across the jump)
    assert np.hypot(*(truth[jump, :2] - plain.pose_at(drive.log.scans.t_s[jump:jump + 1])[0, :2])) < 0.2
    landed = plain.pose_at(drive.log.scans.t_s[jump + 2:jump + 3] + 20.0)[0]
    assert np.hypot(*(truth[jump + 2, :2] - landed[:2])) < 0.2
    odometry = dead_reckoning(drive.log).poses
    assert np.hypot(*np.diff(odometry[:, :2], axis=0).T).max() < 0.2  # its wheels felt nothing
    with pytest.raises(ConfigError, match="kidnap"):
        simulate("office", seed=1, cameras=False, kidnap=(95.0, 20.0))  # beyond the 100 s drive


def test_made_up_buildings_are_their_own_floors_and_their_routes_keep_clear_of_every_wall() -> None:
    from slam_engine.simulation import RIGS, scenario_world
    from slam_engine.simulation.motion import rounded_path

    first, again, other = (scenario_world(name) for name in ("building-3", "building-3", "building-4"))
    assert first is not None and again is not None and other is not None
    np.testing.assert_array_equal(first.segments, again.segments)  # the number is the floor
    assert first.segments.shape != other.segments.shape or not np.allclose(first.segments, other.segments)
    back = scenario_world("building-3-back")
    assert back is not None and np.array_equal(back.segments, first.segments)
    np.testing.assert_array_equal(back.route, first.route[::-1])  # the same floor driven the other way
    for number in range(1, 21):
        world = scenario_world(f"building-{number}")
        assert world is not None
        path, _ = rounded_path(world.route, RIGS["robot"].turn_radius_m, 0.05)
        assert point_to_segments_m(path, world.segments).min() > 0.4, number  # through doors, past furniture
        assert 40.0 < float(np.hypot(*np.diff(path, axis=0).T).sum()) < 90.0
    drive = simulate("building-2", seed=0, rig="robot", max_duration_s=10.0, cameras=False)
    truth = drive.ground_truth.poses
    assert len(truth) >= 40 and drive.scenario == "building-2"
    for name in ("building-0", "building-100", "building-3-forth", "buildings-3"):
        with pytest.raises(ConfigError, match="unknown scenario.*building-N"):
            simulate(scenario=name)
