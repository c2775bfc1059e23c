"""Security: with API keys set, every route (enumerated from the app, so a new one cannot slip
through) refuses callers without a valid key, except /healthz, and a key never reaches another
key's sessions, jobs, logs or artifacts. Uploaded zips: no path traversal, links, special files,
duplicate members, too many entries or too many bytes."""

from __future__ import annotations

import io
import re
import stat
import sys
import zipfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))

from service_helpers import assert_error, service_client, wait_for  # noqa: E402

from service.api.openapi_errors import api_routes  # noqa: E402
from service.http_errors import InvalidInput, PayloadTooLarge  # noqa: E402
from service.storage.uploads import extract_zip  # noqa: E402

OPEN_ROUTES = {("GET", "/healthz")}  # LIDARMAP_OPEN_PATHS' default
CALIBRATION = {"vehicle": {"kind": "odometry"},
               "lidar": {"num_beams": 2, "angle_min_rad": 0.0, "angle_increment_rad": 0.5,
                         "range_min_m": 0.1, "range_max_m": 20.0}}
CHUNK = {"seq": 1, "messages": [{"type": "odometry", "t_s": 1.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}]}
PARAMETERS = {"layer": "occupancy", "z": "0", "x": "0", "y": "0"}
ALPHA, BETA = {"X-API-Key": "alpha-key"}, {"Authorization": "Bearer beta-key"}


def body_for(method: str, path: str) -> dict:
    """A valid request body for each route that takes one (a new POST route must be added here)."""
    bodies = {
        ("POST", "/v1/sessions"): {"json": {"name": "probe"}},
        ("POST", "/v1/sessions/{session_id}/logs"): {"files": {"file": ("log.clf", b"ODOM 0 0 0 0 0 0 1 h 1\n")}},
        ("POST", "/v1/sessions/{session_id}/chunks"): {"json": CHUNK},
        ("POST", "/v1/sessions/{session_id}/chunks/finish"): {"json": {"last_seq": 5}},
        ("POST", "/v1/sessions/{session_id}/jobs"): {"json": {"particles": 1, "seed": 1}},
        ("POST", "/v1/sessions/{session_id}/maps"): {"files": {"file": ("map_bundle.npz", b"PK\x05\x06" + bytes(18))}},
    }
    if method in ("POST", "PUT", "PATCH"):
        assert (method, path) in bodies, f"new route {method} {path}: add a request body to this test"
    return bodies.get((method, path), {})


def fill(path: str, ids: dict[str, str]) -> str:
    return re.sub(r"\{(\w+)\}", lambda m: {**PARAMETERS, **ids}[m.group(1)], path)


def test_every_route_needs_a_key_and_keys_see_only_their_own(tmp_path) -> None:
    with service_client(tmp_path, job_function="stress_jobs:instant", api_keys="alpha-key,beta-key") as client:
        session = client.post("/v1/sessions", json={"name": "alpha", "calibration": CALIBRATION}, headers=ALPHA)
        sid = session.json()["id"]
        client.post(f"/v1/sessions/{sid}/chunks", json={**CHUNK, "seq": 0}, headers=ALPHA)
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 1, "seed": 1}, headers=ALPHA).json()
        assert wait_for_alpha(client, job["id"])["status"] == "succeeded"
        alpha_ids = {sid, job["id"]}
        routes = [(method, route.path_format) for route in api_routes(client.app) for method in route.methods]
        assert len(routes) >= 26

        for method, path in routes:
            url = fill(path, {"session_id": sid, "job_id": job["id"]})
            body = body_for(method, path)
            name = f"{method} {path}"
            if (method, path) in OPEN_ROUTES:
                assert client.request(method, url).status_code == 200, name
                continue
            for headers in ({}, {"X-API-Key": "wrong"}, {"Authorization": "Bearer wrong"}, {"X-API-Key": ""}):
                response = client.request(method, url, headers=headers, **body)
                expect_error(method, response, 401, "unauthorized")
                challenge = "bearer" if path.startswith(("/v1/", "/readyz")) else "basic"  # pages: the browser asks
                assert challenge in response.headers.get("www-authenticate", "").lower(), name
            # beta: alpha's resources do not exist; nothing of alpha's appears in any answer
            response = client.request(method, url, headers=BETA, **body)
            if "{session_id}" in path or "{job_id}" in path:
                expect_error(method, response, 404, "not_found")
            else:
                assert response.status_code < 400, f"{name}: {response.status_code} {response.text}"
            others = {i for i in alpha_ids if i not in url}  # the 404 may echo the id beta sent, nothing else
            assert not any(i in response.text for i in others), f"{name} shows alpha's ids to beta"

        # alpha's things survived beta's deletes and are still alpha's
        assert client.get(f"/v1/sessions/{sid}", headers=ALPHA).status_code == 200
        assert client.get(f"/v1/jobs/{job['id']}", headers=ALPHA).json()["status"] == "succeeded"
        assert client.get(f"/v1/jobs/{job['id']}/run", headers=ALPHA).status_code == 200
        assert {s["name"] for s in client.get("/v1/sessions", headers=BETA).json()["data"]} <= {"probe"}


def expect_error(method: str, response, status: int, code: str) -> None:
    """The JSON error body with this status; a HEAD answer has the status and no body."""
    if method == "HEAD":
        assert response.status_code == status and response.content == b"", (response.status_code, response.text)
    else:
        assert_error(response, status, code)


def wait_for_alpha(client, job_id: str) -> dict:
    client.headers.update(ALPHA)
    try:
        return wait_for(client, job_id)
    finally:
        del client.headers["X-API-Key"]


# ---- zips ---------------------------------------------------------------------------------------


def zip_with(*members: tuple[zipfile.ZipInfo | str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for info, content in members:
            archive.writestr(info, content)
    return buffer.getvalue()


def special(name: str, mode: int) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.external_attr = mode << 16
    return info


UNSAFE = {
    "parent traversal": zip_with(("logs/../../escape.clf", b"x")),
    "absolute path": zip_with(("/tmp/escape.clf", b"x")),
    "backslash traversal": zip_with(("..\\escape.clf", b"x")),
    "drive letter": zip_with(("C:/escape.clf", b"x")),
    "symlink": zip_with((special("link.clf", stat.S_IFLNK | 0o777), b"/etc/passwd")),
    "fifo": zip_with((special("pipe", stat.S_IFIFO | 0o644), b"")),
    "block device": zip_with((special("disk", stat.S_IFBLK | 0o644), b"")),
}


@pytest.mark.parametrize("case", sorted(UNSAFE))
def test_unsafe_zip_members_are_refused(tmp_path, case: str) -> None:
    path = tmp_path / "bad.zip"
    path.write_bytes(UNSAFE[case])
    with pytest.raises(InvalidInput):
        extract_zip(path, tmp_path / "out", max_entries=10, max_total_bytes=10**6)
    assert not (tmp_path / "escape.clf").exists() and not Path("/tmp/escape.clf").exists()


def test_zip_bombs_and_duplicates_are_refused(tmp_path) -> None:
    duplicate = tmp_path / "dup.zip"
    with zipfile.ZipFile(duplicate, "w") as archive, pytest.warns(UserWarning):
        archive.writestr("a.clf", b"one")
        archive.writestr("a.clf", b"two")
    with pytest.raises(InvalidInput, match="appears twice"):
        extract_zip(duplicate, tmp_path / "out1", max_entries=10, max_total_bytes=10**6)
    bomb = tmp_path / "bomb.zip"
    bomb.write_bytes(zip_with(*[(f"z{i}.bin", b"\0" * 2_000_000) for i in range(5)]))  # 10 MB in a few KB
    assert bomb.stat().st_size < 100_000
    with pytest.raises(PayloadTooLarge):
        extract_zip(bomb, tmp_path / "out2", max_entries=10, max_total_bytes=3_000_000)
    written = sum(p.stat().st_size for p in (tmp_path / "out2").rglob("*") if p.is_file())
    assert written <= 3_000_000 + (1 << 20)  # stopped while writing, not after


def test_unsafe_zips_through_http(tmp_path) -> None:
    many = zip_with(*[(f"f{i}.txt", b"x") for i in range(20)])
    with service_client(tmp_path, max_zip_entries=10, max_extracted_bytes=4096) as client:
        sid = client.post("/v1/sessions", json={"name": "zips"}).json()["id"]
        for case, content in UNSAFE.items():
            response = client.post(f"/v1/sessions/{sid}/logs", files={"file": ("bad.zip", content)})
            assert_error(response, 422, "invalid_input"), case
        assert_error(client.post(f"/v1/sessions/{sid}/logs", files={"file": ("many.zip", many)}), 413)
        big = zip_with(("big.bin", b"\0" * 100_000))
        assert_error(client.post(f"/v1/sessions/{sid}/logs", files={"file": ("big.zip", big)}), 413)
        assert client.get(f"/v1/sessions/{sid}/logs").json()["count"] == 0
        assert not any((tmp_path / "uploads").iterdir()) and not any((tmp_path / "tmp").iterdir())
