"""ROS bags through the ``rosbags`` library (no ROS install): ROS 2 bag folders (sqlite3 or MCAP
storage), bare ``.mcap`` / ``.db3`` files and ROS 1 ``.bag`` files.

Read: ``sensor_msgs/LaserScan`` (the topic with most messages; stamps from the header), LiDAR
geometry from the first scan, ``nav_msgs/Odometry`` poses, ``sensor_msgs/Imu`` yaw rate (the
angular velocity rotated into the base frame when tf knows the IMU frame), and ``/tf_static`` for
``T_vehicle_from_lidar`` (chained from the scan's frame up to the odometry's child frame, else
``base_link`` / ``base_footprint``). Range values outside [range_min, range_max], NaN and
+-inf are "no return" (REP 117). Written: a ROS 2 bag folder with MCAP storage and topics /scan,
/odom, /imu, /tf_static.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats._checks import time_order
from slam_engine.frontend.odometry import odometry_poses
from slam_engine.model.drive_log import (
    DriveLog,
    GyroStream,
    LidarModel,
    MotionModelKind,
    OdometryStream,
    ScanStream,
    VehicleModel,
)

SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
TF = "tf2_msgs/msg/TFMessage"
BASE_FRAMES = ("base_link", "base_footprint")


def sniff(path: Path) -> bool:
    """A ROS 2 bag folder (metadata.yaml), an MCAP or rosbag2 sqlite file, or a ROS 1 bag."""
    path = Path(path)
    try:
        if path.is_dir():
            meta = path / "metadata.yaml"
            return meta.is_file() and "rosbag2_bagfile_information" in meta.read_text(errors="replace")[:4096]
        if not path.is_file():
            return False
        with open(path, "rb") as handle:
            head = handle.read(16)
        if head.startswith(b"\x89MCAP0\r\n") or head.startswith(b"#ROSBAG V2.0"):
            return True
        if head.startswith(b"SQLite format 3\x00"):
            with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
                tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            return {"messages", "topics"} <= tables
    except (OSError, sqlite3.Error):
        return False
    return False


def _quaternion_matrix(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    n = np.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _stamp(header, bag_ns: int) -> float:
    t = header.stamp.sec + header.stamp.nanosec * 1e-9
    return t if t > 0 else bag_ns * 1e-9


def _pick(connections, msgtype: str, preferred: str, warnings: list[str], path: Path):
    """The connections of the topic of ``msgtype`` with most messages (``preferred`` wins ties)."""
    by_topic: dict[str, list] = {}
    for conn in connections:
        if conn.msgtype == msgtype:
            by_topic.setdefault(conn.topic, []).append(conn)
    if not by_topic:
        return None, []
    topic = max(by_topic, key=lambda t: (sum(c.msgcount for c in by_topic[t]), t == preferred))
    for other in by_topic:
        if other != topic:
            warnings.append(f"{path}: ignored {msgtype} topic {other} (using {topic})")
    return topic, by_topic[topic]


def load(path: Path) -> DriveLog:
    """Read scans, odometry, IMU yaw rate and the static LiDAR mounting from a bag."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    warnings: list[str] = []
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            scan_topic, scan_conns = _pick(reader.connections, SCAN, "/scan", warnings, path)
            odom_topic, odom_conns = _pick(reader.connections, ODOMETRY, "/odom", warnings, path)
            imu_topic, imu_conns = _pick(reader.connections, IMU, "/imu", warnings, path)
            tf_conns = [c for c in reader.connections if c.msgtype == TF and c.topic == "/tf_static"]
            wanted = scan_conns + odom_conns + imu_conns + tf_conns
            if not wanted:
                raise LogFormatError("bag has no LaserScan, Odometry, Imu or tf_static messages", path=str(path))
            scans_t: list[float] = []
            ranges: list[np.ndarray] = []
            starts: list[float] = []  # each scan's angle_min [rad]
            first_scan: Any = None  # a deserialized sensor_msgs/LaserScan
            scan_frame: str | None = None
            odom_t: list[float] = []
            poses: list[tuple[float, float, float]] = []
            base_frame: str | None = None
            imu_t: list[float] = []
            rates: list[tuple[float, float, float]] = []
            imu_frame: str | None = None
            tree: dict[str, tuple[str, np.ndarray]] = {}
            for conn, bag_ns, raw in reader.messages(connections=wanted):
                where = f"topic {conn.topic} message at {bag_ns} ns"
                try:
                    # rosbags types it `object`: the message class is the one conn.msgtype names
                    msg: Any = reader.deserialize(raw, conn.msgtype)
                except Exception as error:  # noqa: BLE001 - rosbags raises several types for corrupt data
                    raise LogFormatError(f"cannot decode {conn.msgtype}: {error}", path=str(path),
                                         location=where) from None
                if conn.msgtype == SCAN:
                    first_scan = first_scan or msg
                    scan_frame = scan_frame or msg.header.frame_id
                    if abs(float(msg.angle_increment) - float(first_scan.angle_increment)) > 1e-9:
                        raise LogFormatError(f"scan angle_increment {msg.angle_increment:g} rad, the first had "
                                             f"{first_scan.angle_increment:g} rad", path=str(path), location=where)
                    if not abs(float(msg.angle_min)) <= 2 * np.pi or len(msg.ranges) == 0:
                        raise LogFormatError(f"scan angle_min {msg.angle_min:g} rad with {len(msg.ranges)} beams: "
                                             "not a real scan", path=str(path), location=where)
                    scans_t.append(_stamp(msg.header, bag_ns))
                    ranges.append(np.asarray(msg.ranges, dtype=np.float32))
                    starts.append(float(msg.angle_min))
                elif conn.msgtype == ODOMETRY:
                    base_frame = base_frame or msg.child_frame_id
                    q = msg.pose.pose.orientation
                    yaw = np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
                    odom_t.append(_stamp(msg.header, bag_ns))
                    poses.append((msg.pose.pose.position.x, msg.pose.pose.position.y, yaw))
                elif conn.msgtype == IMU:
                    imu_frame = imu_frame or msg.header.frame_id
                    imu_t.append(_stamp(msg.header, bag_ns))
                    w = msg.angular_velocity
                    rates.append((w.x, w.y, w.z))
                else:
                    for tf in msg.transforms:
                        T = np.eye(4)
                        T[:3, :3] = _quaternion_matrix(tf.transform.rotation)
                        v = tf.transform.translation
                        T[:3, 3] = (v.x, v.y, v.z)
                        tree[tf.child_frame_id.lstrip("/")] = (tf.header.frame_id.lstrip("/"), T)
    except (AnyReaderError, FileNotFoundError, OSError) as error:
        raise LogFormatError(f"cannot read bag: {error}", path=str(path)) from None
    except LogFormatError:
        raise
    except Exception as error:  # noqa: BLE001 - a damaged bag makes rosbags raise many kinds of errors
        raise LogFormatError(f"cannot read bag ({type(error).__name__}: {error})", path=str(path)) from None

    base = (base_frame or "").lstrip("/") or next((f for f in BASE_FRAMES if _chain(tree, f, f) is not None),
                                                   BASE_FRAMES[0])
    lidar, scans = None, None
    if first_scan is not None:
        T_base_from_lidar = _chain(tree, (scan_frame or "").lstrip("/"), base)
        if T_base_from_lidar is None:
            warnings.append(f"{path}: no tf_static from {scan_frame!r} to {base!r}; LiDAR assumed at the base origin")
            T_base_from_lidar = np.eye(4)
        beams = max(len(r) for r in ranges)  # a scan with fewer beams is padded with no-return
        lidar = LidarModel(num_beams=beams, angle_min_rad=float(first_scan.angle_min),
                           angle_increment_rad=float(first_scan.angle_increment),
                           range_min_m=float(first_scan.range_min), range_max_m=float(first_scan.range_max),
                           T_vehicle_from_lidar=T_base_from_lidar, name=f"ROS {scan_topic}",
                           time_increment_s=float(first_scan.time_increment) or None)
        values = np.full((len(ranges), beams), np.inf, dtype=np.float32)
        for k, r in enumerate(ranges):
            values[k, :r.size] = r
        offsets = np.array(starts) - lidar.angle_min_rad
        changing = bool(np.any(offsets != 0.0))
        if changing or any(r.size != beams for r in ranges):
            warnings.append(f"{path}: {scan_topic}: beam geometry changes from scan to scan "
                            f"({len(np.unique(offsets))} start angles, {min(r.size for r in ranges)}-{beams} beams); "
                            "carried per scan")
        values[~np.isfinite(values) | (values < lidar.range_min_m) | (values > lidar.range_max_m)] = np.inf
        order = time_order(np.array(scans_t), path, scan_topic, warnings, lambda i: f"{scan_topic} message {i}")
        scans = ScanStream(t_s=np.array(scans_t)[order], ranges_m=values[order],
                           angle_offset_rad=offsets[order] if changing else None)
    odometry = None
    if odom_t:
        order = time_order(np.array(odom_t), path, odom_topic, warnings, lambda i: f"{odom_topic} message {i}")
        odometry = OdometryStream(t_s=np.array(odom_t)[order], poses=np.array(poses, dtype=np.float64)[order])
        bad = np.flatnonzero(~np.isfinite(odometry.poses).all(axis=1))
        if bad.size:
            raise LogFormatError("odometry pose is not finite", path=str(path),
                                 location=f"{odom_topic} message {bad[0]}")
    else:
        warnings.append(f"{path}: no nav_msgs/Odometry topic; the log has no odometry")
    gyro = None
    if imu_t:
        R = np.eye(3)
        T_base_from_imu = _chain(tree, (imu_frame or "").lstrip("/"), base)
        if T_base_from_imu is not None:
            R = T_base_from_imu[:3, :3]
        yaw_rate = (np.array(rates) @ R.T)[:, 2]
        order = time_order(np.array(imu_t), path, imu_topic, warnings, lambda i: f"{imu_topic} message {i}")
        gyro = GyroStream(t_s=np.array(imu_t)[order], yaw_rate_rad_s=yaw_rate[order])
    return DriveLog(vehicle=VehicleModel(kind=MotionModelKind.ODOMETRY, name="ROS robot"), lidar=lidar,
                    scans=scans, odometry=odometry, gyro=gyro, source_format="rosbag", source_path=str(path),
                    warnings=warnings)


def _chain(tree: dict[str, tuple[str, np.ndarray]], frame: str, base: str) -> np.ndarray | None:
    """T_base_from_frame by walking tf_static parents from ``frame`` up to ``base`` (None if unlinked)."""
    T = np.eye(4)
    seen = set()
    while frame != base:
        if frame in seen or frame not in tree:
            return None
        seen.add(frame)
        parent, T_parent_from_frame = tree[frame]
        T = T_parent_from_frame @ T
        frame = parent
    return T


# ---------------------------------------------------------------------------------------------- writing

def _rotation_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return float(x), float(y), float(z), float(w)


def write(log: DriveLog, out_dir: Path, name: str = "log") -> Path:
    """Write a ROS 2 bag folder ``out_dir/<name>`` (MCAP storage); returns its path. Odometry is
    dead-reckoned from the encoders when the log has none."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    path = Path(out_dir) / name
    if path.exists():
        raise LogFormatError("bag folder exists already", path=str(path))
    for stream_name in ("scans", "encoders", "gyro", "odometry"):
        stream = getattr(log, stream_name)
        if stream is not None and len(stream.t_s) and float(np.min(stream.t_s)) < 0:
            raise LogFormatError(f"ROS stamps cannot be negative ({stream_name} start at {np.min(stream.t_s)} s)",
                                 location=stream_name)
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    odometry = odometry_poses(log) if (log.odometry is not None or log.encoders is not None) else None

    def header(t: float, frame: str):
        sec = int(np.floor(t))
        return types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000),
            frame_id=frame)

    vector = types["geometry_msgs/msg/Vector3"]
    quaternion = types["geometry_msgs/msg/Quaternion"]
    records: list[tuple[int, str, object]] = []
    if log.scans is not None and log.lidar is not None:
        lidar = log.lidar
        T = np.asarray(lidar.T_vehicle_from_lidar)
        tf = types["geometry_msgs/msg/TransformStamped"](
            header=header(float(log.scans.t_s[0]), "base_link"), child_frame_id="laser",
            transform=types["geometry_msgs/msg/Transform"](translation=vector(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                                            rotation=quaternion(*_rotation_quaternion(T[:3, :3]))))
        records.append((int(round(log.scans.t_s[0] * 1e9)), "/tf_static", types[TF](transforms=[tf])))
        offsets = np.zeros(len(log.scans)) if log.scans.angle_offset_rad is None else log.scans.angle_offset_rad
        for t, r, offset in zip(log.scans.t_s, log.scans.ranges_m, offsets, strict=True):
            msg = types[SCAN](header=header(float(t), "laser"), angle_min=lidar.angle_min_rad + float(offset),
                              angle_max=float(lidar.beam_angles_rad[-1] + offset),
                              angle_increment=lidar.angle_increment_rad,
                              time_increment=float(lidar.time_increment_s or 0.0), scan_time=0.0,
                              range_min=lidar.range_min_m,
                              range_max=lidar.range_max_m, ranges=np.asarray(r, dtype=np.float32),
                              intensities=np.zeros(0, dtype=np.float32))
            records.append((int(round(t * 1e9)), "/scan", msg))
    zeros9 = np.zeros(9)
    if odometry is not None:
        for t, (x, y, yaw) in zip(odometry.t_s, odometry.poses, strict=True):
            pose = types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                orientation=quaternion(x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)))
            msg = types[ODOMETRY](
                header=header(float(t), "odom"), child_frame_id="base_link",
                pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=types["geometry_msgs/msg/Twist"](linear=vector(x=0.0, y=0.0, z=0.0),
                                                           angular=vector(x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36)))
            records.append((int(round(t * 1e9)), "/odom", msg))
    if log.gyro is not None:
        for t, rate in zip(log.gyro.t_s, log.gyro.yaw_rate_rad_s, strict=True):
            msg = types[IMU](header=header(float(t), "base_link"),
                             orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                             orientation_covariance=np.concatenate([[-1.0], zeros9[1:]]),
                             angular_velocity=vector(x=0.0, y=0.0, z=float(rate)), angular_velocity_covariance=zeros9,
                             linear_acceleration=vector(x=0.0, y=0.0, z=9.81), linear_acceleration_covariance=zeros9)
            records.append((int(round(t * 1e9)), "/imu", msg))
    msgtypes = {"/scan": SCAN, "/odom": ODOMETRY, "/imu": IMU, "/tf_static": TF}
    records.sort(key=lambda r: r[0])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=store)
                       for topic, msgtype in msgtypes.items() if any(r[1] == topic for r in records)}
        for stamp, topic, record in records:
            writer.write(connections[topic], stamp, store.serialize_cdr(record, msgtypes[topic]))
    return path
