"""Log uploads: streamed, hashed, validated by the loader; 413/415/422 with the reason; safe zips."""

from __future__ import annotations

import hashlib
import io
import stat
import zipfile

from service_helpers import assert_error, new_session, service_client

from service.storage.uploads import extract_zip


def upload(client, sid: str, name: str, content: bytes, **params):
    return client.post(f"/v1/sessions/{sid}/logs", files={"file": (name, content)}, params=params)


def zip_bytes(entries: dict[str, bytes], symlink: str | None = None) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
        if symlink is not None:
            info = zipfile.ZipInfo(symlink)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            archive.writestr(info, "/etc/passwd")
    return buffer.getvalue()


def test_upload_validates_with_the_loader(tmp_path, dataset) -> None:
    intel = dataset("benchmark/intel.clf").read_bytes()
    with service_client(tmp_path, max_upload_bytes=2 * 1024**2) as client:
        sid = new_session(client)
        response = upload(client, sid, "intel.clf", intel)
        assert response.status_code == 201, response.text
        log = response.json()
        assert log["sha256"] == hashlib.sha256(intel).hexdigest() and log["size_bytes"] == len(intel)
        assert log["archive"] is False and log["filename"] == "intel.clf"
        summary = log["summary"]
        assert summary["format"] == "carmen" and summary["lidar_beams"] == 180
        assert summary["streams"]["scans"] == 910 and summary["streams"]["odometry"] > 0
        assert summary["duration_s"] > 2000

        # explicit format, and as a zipped folder
        assert upload(client, sid, "intel.clf", intel, format="carmen").status_code == 201
        zipped = upload(client, sid, "intel-folder.zip", zip_bytes({"intel/intel.clf": intel}))
        assert zipped.status_code == 201, zipped.text
        assert zipped.json()["archive"] is True and zipped.json()["summary"]["streams"]["scans"] == 910
        listed = client.get(f"/v1/sessions/{sid}/logs").json()
        assert listed["count"] == 3 and listed["data"][0]["id"] == zipped.json()["id"]

        # 415: no format matches; 422: corrupt, with the loader's location
        err = assert_error(upload(client, sid, "notes.txt", b"hello world\n" * 10), 415, "unsupported_format")
        assert "none of the supported formats" in err["message"]
        lines = intel.decode().splitlines()
        flaser = next(i for i, line in enumerate(lines) if line.startswith("FLASER"))
        lines[flaser] = lines[flaser].replace("FLASER 180", "FLASER 181", 1)
        err = assert_error(upload(client, sid, "broken.clf", "\n".join(lines).encode()), 422, "log_format")
        assert f"line {flaser + 1}" in (err["detail"]["location"] or "") + err["message"]
        err = assert_error(upload(client, sid, "intel.clf", intel, format="rosbag"), 422, "log_format")
        assert_error(upload(client, sid, "intel.clf", intel, format="pdf"), 422, "invalid_input")

        # 413: too big (declared or streamed), 415: not multipart, 422: no file field
        assert_error(upload(client, sid, "big.clf", b"x" * (3 * 1024**2)), 413, "payload_too_large")
        assert_error(client.post(f"/v1/sessions/{sid}/logs", content=intel[:1000],
                                 headers={"content-type": "application/octet-stream"}), 415)
        assert_error(client.post(f"/v1/sessions/{sid}/logs", data={"format": "carmen"},
                                 files={"other": ("x.clf", b"1")}), 422, "invalid_input")
        truncated = b'--xx\r\nContent-Disposition: form-data; name="file"; filename="a.clf"\r\n\r\nODOM 1 2'
        err = assert_error(client.post(f"/v1/sessions/{sid}/logs", content=truncated,
                                       headers={"content-type": "multipart/form-data; boundary=xx"}), 400)
        assert "truncated" in err["message"]

        # unsafe zips are refused
        for bad in (zip_bytes({"../escape.clf": intel}), zip_bytes({"/abs/intel.clf": intel}),
                    zip_bytes({"ok.clf": intel}, symlink="link.clf"), b"PK\x03\x04 not really a zip"):
            assert_error(upload(client, sid, "bad.zip", bad), 422)
        assert client.get(f"/v1/sessions/{sid}").json()["logs"] == 3
        assert not any((tmp_path / "tmp").iterdir())  # partial uploads cleaned
        assert_error(upload(client, "00000000-0000-0000-0000-000000000000", "intel.clf", intel[:100]), 404)


def test_zip_limits(tmp_path) -> None:
    path = tmp_path / "many.zip"
    path.write_bytes(zip_bytes({f"f{i}.txt": b"x" for i in range(5)}))
    from service.http_errors import PayloadTooLarge

    try:
        extract_zip(path, tmp_path / "out1", max_entries=4, max_total_bytes=10**6)
        raise AssertionError("entry limit not enforced")
    except PayloadTooLarge as exc:
        assert "5 entries" in exc.message
    bomb = tmp_path / "bomb.zip"
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("zeros.bin", b"\0" * 5_000_000)
    assert bomb.stat().st_size < 100_000
    try:
        extract_zip(bomb, tmp_path / "out2", max_entries=10, max_total_bytes=1_000_000)
        raise AssertionError("size limit not enforced")
    except PayloadTooLarge:
        pass
    root = extract_zip(path, tmp_path / "out3", max_entries=10, max_total_bytes=10**6)
    assert sorted(p.name for p in root.iterdir()) == [f"f{i}.txt" for i in range(5)]
