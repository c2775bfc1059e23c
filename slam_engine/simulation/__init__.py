"""A drive simulator with exact ground truth: a 2-D world of rooms or streets, a vehicle driving a loop
through it, and sensors with realistic errors, written out in any supported log format.

``simulate(scenario="office", seed=0, rig="robot")`` returns a :class:`SimulatedDrive` whose ``log``
is what the rig's sensors recorded and whose ``ground_truth`` is the true pose at every scan.
``write_simulated(drive, format, out_dir)`` writes the log in a format, ``ground_truth.txt``
(``t x y theta`` per scan), ``<scenario>.relations`` (Kuemmerle et al. 2009:
``t1 t2 x y z roll pitch yaw``, consecutive scans and loop closures) and, when the rig has a camera
(the car's stereo pair, THOR's Kinect, rendered from the world's floor texture),
``ground_texture.json`` naming the scenario whose floor the frames show
(:func:`floor_beside_log` gives its colour function back, for the texture's accuracy).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from slam_engine.errors import ConfigError, LogFormatError
from slam_engine.formats import write_log
from slam_engine.model.drive_log import DriveLog, ScanStream
from slam_engine.model.poses import relative, wrap_angle
from slam_engine.model.result import Trajectory
from slam_engine.simulation.buildings import scenario_world as building_world
from slam_engine.simulation.motion import Motion, drive_route
from slam_engine.simulation.rigs import FORMAT_RIGS, RIGS, Rig
from slam_engine.simulation.sensors import (
    encoder_stream,
    gyro_stream,
    odometry_stream,
    sample_times,
    scan_stream,
)
from slam_engine.simulation.world import SCENARIOS, World

if TYPE_CHECKING:  # the camera renderer (OpenCV, ~15 MB) is imported only to simulate cameras
    from slam_engine.simulation.camera_render import FloorRgb

# Loop-closure relations join scans at least this far apart in time whose poses are this close.
LOOP_MIN_DT_S = 20.0
LOOP_MAX_DISTANCE_M = 1.5
LOOP_MAX_ANGLE_RAD = np.radians(45.0)
GROUND_TEXTURE_FILE = "ground_texture.json"
CHANGED_LATER_S = 3 * 86400.0  # a changed world is driven this long after the world it changed from [s]
CHANGES_FILE = "changes.json"  # a changed world's walls taken away and put up (the change map's truth)


@dataclass(frozen=True)
class SimulatedDrive:
    """A simulated drive: the recorded ``log``, the true pose per scan, and how it was made."""

    log: DriveLog
    ground_truth: Trajectory
    world: World
    rig: Rig
    motion: Motion
    scenario: str
    seed: int

    def pose_at(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 3) true vehicle poses [x_m, y_m, theta_rad] at log stamps ``t_s``."""
        x, y, theta, _ = self.motion.at(np.asarray(t_s, dtype=np.float64) - self.rig.t0_s)
        return np.column_stack([x, y, wrap_angle(theta)])


SCENARIO_NAMES = ", ".join([*SCENARIOS, "building-N", "building-N-back (N 1-99)"])


def scenario_world(name: str) -> World | None:
    """The world of scenario ``name`` (:data:`SCENARIOS`, or a made-up office floor ``building-N`` /
    ``building-N-back``: :mod:`slam_engine.simulation.buildings`); None for an unknown name."""
    return SCENARIOS[name]() if name in SCENARIOS else building_world(name)


def rig_for_format(format: str) -> str:
    """Name of the rig whose sensors ``format`` can hold."""
    if format not in FORMAT_RIGS:
        raise ConfigError(f"no simulated rig for format {format!r}; formats: {', '.join(FORMAT_RIGS)}")
    return FORMAT_RIGS[format]


def simulate(scenario: str | None = "office", seed: int = 0, rig: str = "robot",
             max_duration_s: float | None = None, scan_hz: float | None = None,
             rng: np.random.Generator | None = None, cameras: bool = True, scan_lag_s: float = 0.0,
             kidnap: tuple[float, float] | None = None) -> SimulatedDrive:
    """Simulate one drive along the scenario's route (a loop with a closure).

    ``scenario`` None picks the rig's own (``office`` for robots, ``campus`` for the car);
    ``max_duration_s`` cuts the drive short (tests); ``scan_hz`` overrides the LiDAR rate;
    ``cameras`` False leaves the rig's cameras out (rendering costs about a second a frame);
    ``scan_lag_s``: the scans are stamped this long after they were measured (a LiDAR whose stamps lag
    the odometry's clock, like BreezySLAM's exp2 by about 0.15 s: the engine's time offset is then
    ``-scan_lag_s``); the ground truth is the pose when each scan was measured, at its stamp. A rig
    whose LiDAR model has a ``time_increment_s`` sweeps its beams while it moves (skewed scans).
    ``kidnap`` (at [s], skip [s]): the vehicle is carried off ``at`` seconds into the drive to where it
    would have been ``skip`` seconds later, and drives on from there; its wheels, gyro and odometry feel
    nothing (they go on from where it was taken), its LiDAR and the ground truth see the jump.
    Same seed, same drive (the camera frames are drawn last: with or without them, the other
    streams are the same).
    """
    if rig not in RIGS:
        raise ConfigError(f"unknown rig {rig!r}; rigs: {', '.join(RIGS)}")
    the_rig = RIGS[rig]
    scenario = scenario or the_rig.default_scenario
    world = scenario_world(scenario)
    if world is None:
        raise ConfigError(f"unknown scenario {scenario!r}; scenarios: {SCENARIO_NAMES}")
    if max_duration_s is not None and max_duration_s <= 2.0:
        raise ConfigError(f"max_duration_s must be above 2 s, got {max_duration_s}")
    rng = rng or np.random.default_rng(seed)
    if world.changed_from is not None:  # a later state of a world: driven later, as its clock says
        the_rig = dataclasses.replace(the_rig, t0_s=the_rig.t0_s + CHANGED_LATER_S)
    speed = min(world.cruise_speed_m_s, 12.0)
    step = 0.01 if speed < 2 else 0.05
    motion = drive_route(world.route, speed, the_rig.turn_radius_m, the_rig.lateral_accel_m_s2,
                         the_rig.accel_m_s2, step)
    if max_duration_s is not None:
        motion = motion.truncated(max_duration_s)
    felt = motion  # what the wheels, gyro and odometry sense
    if kidnap is not None:
        if not (0.0 < kidnap[0] < motion.duration_s and 0.0 < kidnap[1] < motion.duration_s - kidnap[0]):
            raise ConfigError(f"kidnap {kidnap}: (at, skip) [s] must both be positive and within the "
                              f"{motion.duration_s:.0f} s drive")
        motion, felt = motion.kidnapped(*kidnap)

    t_measured = sample_times(motion, scan_hz or the_rig.scan_hz, the_rig.t0_s, rng)
    scans = scan_stream(world, motion, t_measured, the_rig, rng)
    t_scan = np.round(t_measured + scan_lag_s, 6) if scan_lag_s else t_measured
    scans = ScanStream(t_s=t_scan, ranges_m=scans.ranges_m, angle_offset_rad=scans.angle_offset_rad)
    encoders = gyro = odometry = None
    if the_rig.encoders_at_scan_times:  # read on each scan's line, at its stamp
        encoders = encoder_stream(felt, t_scan, the_rig, rng)
    elif the_rig.encoder_hz:
        encoders = encoder_stream(felt, sample_times(motion, the_rig.encoder_hz, the_rig.t0_s, rng),
                                  the_rig, rng)
    if the_rig.gyro_hz:
        gyro = gyro_stream(felt, sample_times(motion, the_rig.gyro_hz, the_rig.t0_s, rng), the_rig, rng)
    if the_rig.log_odometry_hz:
        odometry = odometry_stream(felt, sample_times(motion, the_rig.log_odometry_hz, the_rig.t0_s, rng),
                                   the_rig, rng)
    stereo = rgbd = None
    if cameras and the_rig.camera_hz and (the_rig.stereo is not None or the_rig.rgbd is not None):
        t_camera = sample_times(motion, the_rig.camera_hz, the_rig.t0_s, rng)
        x, y, theta, _ = motion.at(t_camera - the_rig.t0_s)
        at_frames = Trajectory(t_s=t_camera, poses=np.column_stack([x, y, wrap_angle(theta)]))
        from slam_engine.simulation.camera_render import render_rgbd_stream, render_stereo_stream
        if the_rig.stereo is not None:
            stereo = render_stereo_stream(world.floor_rgb, at_frames, the_rig.stereo)
        if the_rig.rgbd is not None:
            rgbd = render_rgbd_stream(world.floor_rgb, at_frames, the_rig.rgbd)
    log = DriveLog(vehicle=the_rig.vehicle, lidar=the_rig.lidar, scans=scans, encoders=encoders, gyro=gyro,
                   odometry=odometry, stereo=stereo, rgbd=rgbd, source_format="simulated", source_path=None)
    x, y, theta, _ = motion.at(t_measured - the_rig.t0_s)
    truth = Trajectory(t_s=t_scan.copy(), poses=np.column_stack([x, y, wrap_angle(theta)]))
    return SimulatedDrive(log=log, ground_truth=truth, world=world, rig=the_rig, motion=motion,
                          scenario=scenario, seed=seed)


def relations(ground_truth: Trajectory, rng: np.random.Generator, max_loop: int | None = None) -> np.ndarray:
    """(R, 5) [t1, t2, dx, dy, dyaw]: consecutive-scan relations plus as many loop-closure relations
    (scans > LOOP_MIN_DT_S apart, poses within LOOP_MAX_DISTANCE_M and LOOP_MAX_ANGLE_RAD)."""
    t, poses = ground_truth.t_s, ground_truth.poses
    pairs = [(i, i + 1) for i in range(len(t) - 1)]
    dt = t[None, :] - t[:, None]
    distance = np.hypot(poses[None, :, 0] - poses[:, None, 0], poses[None, :, 1] - poses[:, None, 1])
    angle = np.abs(wrap_angle(poses[None, :, 2] - poses[:, None, 2]))
    i, j = np.nonzero((dt > LOOP_MIN_DT_S) & (distance < LOOP_MAX_DISTANCE_M) & (angle < LOOP_MAX_ANGLE_RAD))
    wanted = len(pairs) if max_loop is None else max_loop
    if i.size > wanted:
        pick = np.sort(rng.choice(i.size, size=wanted, replace=False))
        i, j = i[pick], j[pick]
    pairs += list(zip(i.tolist(), j.tolist(), strict=True))
    first = np.array([p[0] for p in pairs])
    second = np.array([p[1] for p in pairs])
    motion = relative(poses[first], poses[second])
    return np.column_stack([t[first], t[second], motion])


def write_simulated(drive: SimulatedDrive, format: str, out_dir: str | Path) -> Path:
    """Write the drive's log in ``format`` into ``out_dir`` with ``ground_truth.txt`` and
    ``<scenario>.relations``; returns the log's path. ``load_log(out_dir)`` reads it back.

    The format's writer refuses a drive whose sensors it cannot hold (``rig_for_format`` names a
    rig that fits); rigs with encoders can also be written as CARMEN or ROS bags (dead-reckoned).
    """
    out_dir = Path(out_dir)
    path = write_log(drive.log, format, out_dir)
    truth = drive.ground_truth
    np.savetxt(out_dir / "ground_truth.txt", np.column_stack([truth.t_s, truth.poses]), fmt="%.6f %.6f %.6f %.6f",
               header="t x y theta  (s, m, m, rad) true vehicle pose at every scan")
    rel = relations(truth, np.random.default_rng(drive.seed))
    zeros = np.zeros(len(rel))
    np.savetxt(out_dir / f"{drive.scenario}.relations",
               np.column_stack([rel[:, 0], rel[:, 1], rel[:, 2], rel[:, 3], zeros, zeros, zeros, rel[:, 4]]),
               fmt="%.6f")
    if drive.world.changed_from is not None:
        (out_dir / CHANGES_FILE).write_text(json.dumps({
            "scenario": drive.scenario, "changed_from": drive.world.changed_from,
            "frame": "world frame of ground_truth.txt; walls as [x0, y0, x1, y1] m",
            "removed": drive.world.removed.round(6).tolist(), "added": drive.world.added.round(6).tolist()}) + "\n")
    if drive.log.stereo is not None or drive.log.rgbd is not None:
        (out_dir / GROUND_TEXTURE_FILE).write_text(json.dumps({
            "scenario": drive.scenario,
            "frame": "world frame of ground_truth.txt; the floor colour is World.floor_rgb of the scenario"}) + "\n")
    return path


def changes_beside_log(log_path: str | Path) -> dict[str, np.ndarray] | None:
    """The walls (S, 4) [x0, y0, x1, y1] m, world frame, ``removed`` and ``added`` since the world a
    simulated log's world changed from, from the ``changes.json`` in its folder; None when there is none.
    A damaged file raises :class:`LogFormatError`."""
    log_path = Path(log_path)
    path = (log_path if log_path.is_dir() else log_path.parent) / CHANGES_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        walls = {kind: np.asarray(doc[kind], np.float64).reshape(-1, 4) for kind in ("removed", "added")}
    except (ValueError, KeyError, TypeError) as error:
        raise LogFormatError(f"not a changes file ({type(error).__name__}: {error})", path) from None
    if not all(np.isfinite(w).all() for w in walls.values()):
        raise LogFormatError("not a changes file (a wall's coordinates are not finite numbers)", path)
    return walls


def floor_beside_log(log_path: str | Path) -> FloorRgb | None:
    """The floor colour function (x_m, y_m in the ground truth's frame -> (N, 3) uint8) of a
    simulated log, from the ``ground_texture.json`` in its folder; None when there is none.
    A damaged file raises :class:`LogFormatError`."""
    log_path = Path(log_path)
    path = (log_path if log_path.is_dir() else log_path.parent) / GROUND_TEXTURE_FILE
    if not path.is_file():
        return None
    try:
        scenario = json.loads(path.read_text(encoding="utf-8"))["scenario"]
    except (ValueError, KeyError, TypeError) as error:
        raise LogFormatError(f"not a ground-texture file ({type(error).__name__}: {error})", path) from None
    world = scenario_world(scenario) if isinstance(scenario, str) else None
    if world is None:
        raise LogFormatError(f"unknown scenario {scenario!r}; scenarios: {SCENARIO_NAMES}", path, "scenario")
    return world.floor_rgb


__all__ = ["CHANGES_FILE", "GROUND_TEXTURE_FILE", "SimulatedDrive", "changes_beside_log", "floor_beside_log",
           "rig_for_format", "relations", "scenario_world", "simulate", "write_simulated", "RIGS", "SCENARIOS",
           "SCENARIO_NAMES"]
