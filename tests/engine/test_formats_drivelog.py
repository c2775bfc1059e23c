"""The .drivelog archive: safe reading, manifest validation, agreement with api_schemas."""

from __future__ import annotations

import io
import json
import stat
import zipfile

import numpy as np
import pytest
from pydantic import ValidationError

from api_schemas.drivelog import DriveLogChunk, DriveLogManifest, json_schemas
from slam_engine.errors import LogFormatError
from slam_engine.formats import drivelog, load_log, write_log
from slam_engine.simulation import simulate


@pytest.fixture(scope="module")
def log():
    return simulate(seed=2, rig="robot", max_duration_s=5.0).log


def rewrite(src, dst, manifest=None, extra=(), drop=()):
    """Copy an archive, optionally replacing the manifest, adding (name, bytes, attr) entries."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            if info.filename in drop:
                continue
            data = zin.read(info)
            if info.filename == "manifest.json" and manifest is not None:
                data = json.dumps(manifest).encode()
            zout.writestr(info, data)
        for name, data, attr in extra:
            entry = zipfile.ZipInfo(name)
            entry.external_attr = attr
            zout.writestr(entry, data)
    return dst


def manifest_of(path):
    with zipfile.ZipFile(path) as archive:
        return json.loads(archive.read("manifest.json"))


def test_engine_manifest_validates_with_the_api_schema_and_back(log, tmp_path) -> None:
    path = write_log(log, "drivelog", tmp_path)
    manifest = manifest_of(path)
    model = DriveLogManifest.model_validate(manifest)
    assert [s.kind for s in model.streams] == ["scans", "encoders", "gyro"]
    # What the pydantic model serialises, the engine reads (same data back).
    again = rewrite(path, tmp_path / "again.drivelog", manifest=json.loads(model.model_dump_json()))
    loaded = load_log(again)
    np.testing.assert_array_equal(loaded.scans.ranges_m, log.scans.ranges_m)
    assert (loaded.vehicle.kind, loaded.vehicle.wheel_names, loaded.vehicle.track_width_m) == (
        log.vehicle.kind, log.vehicle.wheel_names, log.vehicle.track_width_m)
    np.testing.assert_allclose(loaded.lidar.T_vehicle_from_lidar, log.lidar.T_vehicle_from_lidar)


@pytest.mark.parametrize(("change", "engine_says"), [
    (lambda m: m["vehicle"].update(kind="hovercraft"), "vehicle.kind"),
    (lambda m: m["lidar"].update(num_beams=0), "lidar.num_beams"),
    (lambda m: m["lidar"].update(range_min_m=30.0), "lidar.range_min_m"),
    (lambda m: m["lidar"].update(T_vehicle_from_lidar=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     "lidar.T_vehicle_from_lidar"),
    (lambda m: m["streams"][0]["columns"].update(ranges_m="../../etc/passwd"), "streams[0].columns.ranges_m"),
    (lambda m: m["streams"][1].update(kind="scans"), "streams[1].kind"),
    (lambda m: m.update(format_version=99), "format_version"),
    (lambda m: m.update(lidar=None), "lidar"),
])
def test_engine_and_api_schema_reject_the_same_manifests(log, tmp_path, change, engine_says) -> None:
    path = write_log(log, "drivelog", tmp_path)
    manifest = manifest_of(path)
    change(manifest)
    with pytest.raises(ValidationError):
        DriveLogManifest.model_validate(manifest)
    with pytest.raises(LogFormatError, match=f"manifest.json {engine_says}".replace("[", r"\[").replace("]", r"\]")):
        load_log(rewrite(path, tmp_path / "bad.drivelog", manifest=manifest))


def test_unsafe_archives_are_refused(log, tmp_path) -> None:
    path = write_log(log, "drivelog", tmp_path)
    traversal = rewrite(path, tmp_path / "t.drivelog", extra=[("../evil.npy", b"x", 0)])
    with pytest.raises(LogFormatError, match="unsafe entry name '../evil.npy'"):
        load_log(traversal)
    link = rewrite(path, tmp_path / "l.drivelog", extra=[("scans/link.npy", b"/etc/passwd",
                                                          (stat.S_IFLNK | 0o777) << 16)])
    with pytest.raises(LogFormatError, match="symbolic link"):
        load_log(link)
    many = rewrite(path, tmp_path / "m.drivelog", extra=[(f"pad/x{i}.npy", b"", 0) for i in range(70)])
    with pytest.raises(LogFormatError, match="entries"):
        load_log(many)
    with pytest.raises(LogFormatError, match="expands to"):
        drivelog.load(path, max_total_bytes=1000)
    missing = rewrite(path, tmp_path / "x.drivelog", drop=("gyro/yaw_rate_rad_s.npy",))
    with pytest.raises(LogFormatError, match="gyro/yaw_rate_rad_s.npy: column listed in the manifest is missing"):
        load_log(missing)
    truncated = tmp_path / "cut.drivelog"
    truncated.write_bytes(path.read_bytes()[:3000])
    with pytest.raises(LogFormatError):
        load_log(truncated, format="drivelog")


def test_bad_columns_are_refused(log, tmp_path) -> None:
    path = write_log(log, "drivelog", tmp_path)
    ranges = log.scans.ranges_m.copy()
    ranges[4, 7] = np.nan

    def npy(array):
        buffer = io.BytesIO()
        np.save(buffer, array)
        return buffer.getvalue()

    bad = rewrite(path, tmp_path / "nan.drivelog", drop=("scans/ranges_m.npy",),
                  extra=[("scans/ranges_m.npy", npy(ranges), 0)])
    with pytest.raises(LogFormatError, match="scans row 4: range is NaN"):
        load_log(bad)
    bad = rewrite(path, tmp_path / "shape.drivelog", drop=("encoders/ticks.npy",),
                  extra=[("encoders/ticks.npy", npy(log.encoders.ticks[:, :1]), 0)])
    with pytest.raises(LogFormatError, match=r"encoders/ticks.npy: shape .* expected \(\d+, 2\)"):
        load_log(bad)
    bad = rewrite(path, tmp_path / "pickle.drivelog", drop=("gyro/t_s.npy",),
                  extra=[("gyro/t_s.npy", npy(np.array([object()] * len(log.gyro), dtype=object)), 0)])
    with pytest.raises(LogFormatError, match="gyro/t_s.npy: not a valid .npy array"):
        load_log(bad)


def test_message_chunk_schema_round_trips_engine_messages(log) -> None:
    from slam_engine.model.messages import EncoderMessage, ScanMessage

    messages = []
    for message in list(log.messages())[:30]:
        if isinstance(message, ScanMessage):
            ranges = [None if not np.isfinite(r) else float(r) for r in message.ranges_m]
            messages.append({"type": "scan", "t_s": message.t_s, "ranges_m": ranges})
        elif isinstance(message, EncoderMessage):
            messages.append({"type": "encoder", "t_s": message.t_s, "ticks": message.ticks.tolist()})
        else:
            messages.append({"type": "gyro", "t_s": message.t_s, "yaw_rate_rad_s": message.yaw_rate_rad_s})
    chunk = DriveLogChunk.model_validate({"messages": messages})
    assert len(chunk.messages) == 30
    with pytest.raises(ValidationError):
        DriveLogChunk.model_validate({"messages": [{"type": "scan", "t_s": 1.0, "ranges_m": [-1.0]}]})
    schemas = json_schemas()
    assert schemas["DriveLogManifest"]["properties"]["format"]["const"] == drivelog.FORMAT_NAME
    assert set(schemas["DriveLogChunk"]["$defs"]) >= {"ScanMessageModel", "EncoderMessageModel"}


def test_per_scan_start_angles_round_trip_as_format_version_2(log, tmp_path) -> None:
    interlaced = simulate("office", seed=0, rig="carmen-interlaced", max_duration_s=5.0, cameras=False).log
    path = write_log(interlaced, "drivelog", tmp_path / "interlaced")
    manifest = manifest_of(path)
    assert manifest["format_version"] == 2
    assert manifest["streams"][0]["columns"]["angle_offset_rad"] == "scans/angle_offset_rad.npy"
    DriveLogManifest.model_validate(manifest)
    loaded = load_log(path)
    np.testing.assert_array_equal(loaded.scans.angle_offset_rad, interlaced.scans.angle_offset_rad)
    np.testing.assert_array_equal(loaded.scans.ranges_m, interlaced.scans.ranges_m)
    # a log whose beams never move is written as before: version 1, which older readers take
    assert manifest_of(write_log(log, "drivelog", tmp_path / "plain"))["format_version"] == 1
    # the column claimed by a version-1 manifest is refused by both readers
    manifest["format_version"] = 1
    with pytest.raises(ValidationError, match="needs format_version 2"):
        DriveLogManifest.model_validate(manifest)
    with pytest.raises(LogFormatError, match=r"manifest.json streams\[0\].columns"):
        load_log(rewrite(path, tmp_path / "v1.drivelog", manifest=manifest))


def test_an_absurd_angle_offset_names_its_row(tmp_path) -> None:
    interlaced = simulate("office", seed=0, rig="carmen-interlaced", max_duration_s=5.0, cameras=False).log
    path = write_log(interlaced, "drivelog", tmp_path / "interlaced")
    offsets = np.asarray(interlaced.scans.angle_offset_rad).copy()
    offsets[3] = 40.0
    data = io.BytesIO()
    np.save(data, offsets)
    bad = rewrite(path, tmp_path / "bad.drivelog", drop=("scans/angle_offset_rad.npy",),
                  extra=[("scans/angle_offset_rad.npy", data.getvalue(), 0)])
    with pytest.raises(LogFormatError, match="angle_offset_rad.npy row 3: angle offset 40 rad is not within"):
        load_log(bad)
