"""The HTTP surface's small bounds (issue 41, items 2 and 10): a request head past the limit is 431 and
does not stall /healthz; booleans are not numbers; OPTIONS and wrong methods carry ``Allow``; HEAD of a
session and a job; which paths need a key is a setting whose default opens only /healthz."""

from __future__ import annotations

import base64
import socket
import threading
import time

import httpx
import pytest
from service_helpers import CALIBRATION, assert_error, new_session, service_client

from bench.api_attacks import lidarmap_serve


def _raw_request_with_header(url: str, header_bytes: int) -> tuple[bytes, float]:
    """Send a GET whose one header is ``header_bytes`` long; the first bytes of the answer and seconds taken."""
    host, port = url.removeprefix("http://").split(":")
    start = time.monotonic()
    with socket.create_connection((host, int(port)), timeout=60) as conn:
        conn.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: ")
        block = b"a" * 65536
        try:
            for _ in range(header_bytes // len(block)):
                conn.sendall(block)
            conn.sendall(b"\r\n\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed before the whole header was sent
        answer = conn.recv(4096)
    return answer, time.monotonic() - start


def test_an_oversized_request_head_is_431_and_healthz_keeps_answering(tmp_path) -> None:
    """Before: a 16 MB header was read whole (no status line for seconds, /healthz stalled behind it)."""
    with lidarmap_serve(tmp_path / "data", max_header_bytes=65536) as (url, _):
        latencies: list[float] = []
        stop = threading.Event()

        def poll_healthz() -> None:
            while not stop.is_set():
                start = time.monotonic()
                httpx.get(f"{url}/healthz", timeout=60).raise_for_status()
                latencies.append(time.monotonic() - start)
                time.sleep(0.05)

        poller = threading.Thread(target=poll_healthz, daemon=True)
        poller.start()
        try:
            answer, seconds = _raw_request_with_header(url, 16 * 1024**2)
        finally:
            stop.set()
            poller.join()
        assert answer.startswith(b"HTTP/1.1 431"), answer[:200]
        assert b'"request_header_fields_too_large"' in answer
        assert seconds < 10.0, seconds
        assert latencies and max(latencies) < 2.0, latencies
        ok = httpx.get(f"{url}/healthz", headers={"X-Small": "b" * 8000})  # a large but legal header
        assert ok.status_code == 200


@pytest.mark.parametrize("path,body", [
    ("chunks", {"seq": 0, "messages": [{"type": "scan", "t_s": 0.0, "ranges_m": [False, 1.0]}]}),
    ("chunks", {"seq": 0, "messages": [{"type": "odometry", "t_s": False, "x_m": 0, "y_m": 0, "theta_rad": 0}]}),
    ("chunks", {"seq": True, "messages": [{"type": "odometry", "t_s": 0, "x_m": 0, "y_m": 0, "theta_rad": 0}]}),
    ("chunks/finish", {"last_seq": False}),
])
def test_booleans_are_not_numbers(tmp_path, path: str, body: dict) -> None:
    """Before: each was accepted (201 / 200), the boolean read as 0 or 1."""
    with service_client(tmp_path) as client:
        sid = new_session(client, calibration=CALIBRATION)
        assert_error(client.post(f"/v1/sessions/{sid}/{path}", json=body), 422, "validation_error")
        odometry = {"type": "odometry", "t_s": 0, "x_m": 1, "y_m": 0.5, "theta_rad": 0}  # integers stay numbers
        assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [odometry]}).status_code == 201
        assert_error(client.post("/v1/sessions", json={"name": "g", "geo": {"lat_deg": True, "lon_deg": 0}}), 422)


def test_options_head_and_wrong_methods_say_what_is_allowed(tmp_path) -> None:
    """Before: OPTIONS was 405 without Allow, HEAD of a session or a job 405."""
    with service_client(tmp_path) as client:
        sid = new_session(client)
        session = client.get(f"/v1/sessions/{sid}")
        head = client.head(f"/v1/sessions/{sid}")
        assert head.status_code == 200 and head.content == b""
        assert head.headers["content-length"] == session.headers["content-length"]
        options = client.options(f"/v1/sessions/{sid}")
        assert options.status_code == 204 and options.headers["allow"] == "DELETE, GET, HEAD, OPTIONS"
        wrong = client.put(f"/v1/sessions/{sid}")
        err = assert_error(wrong, 405, "method_not_allowed")
        assert wrong.headers["allow"] == "DELETE, GET, HEAD, OPTIONS" and "PUT" in err["message"]
        assert client.options("/v1/sessions").headers["allow"] == "GET, HEAD, OPTIONS, POST"
        listed, head = client.get("/v1/sessions"), client.head("/v1/sessions")  # HEAD of every GET
        assert head.status_code == 200 and head.content == b""
        assert head.headers["content-length"] == listed.headers["content-length"]
        assert client.head("/v1/jobs/no-such-job").status_code == 404
        finish = client.get("/openapi.json").json()["paths"]["/v1/sessions/{session_id}/chunks/finish"]["post"]
        assert {"400", "507"} <= set(finish["responses"])  # the table above did not hide the documented errors
        job = client.post(f"/v1/sessions/{sid}/jobs", json={})
        if job.status_code == 202:
            assert client.head(f"/v1/jobs/{job.json()['id']}").status_code == 200


def test_only_healthz_is_open_by_default_and_browsers_get_a_login_prompt(tmp_path) -> None:
    """Before: /docs, /openapi.json, /redoc and /viewer/ were served without a key although keys were set."""
    with service_client(tmp_path, api_keys="k-one") as client:
        assert client.get("/healthz").status_code == 200
        for path in ("/docs", "/openapi.json", "/redoc", "/viewer/", "/"):
            response = client.get(path, follow_redirects=False)
            assert_error(response, 401, "unauthorized")
            assert response.headers["www-authenticate"].startswith("Basic"), path  # the browser asks
        assert client.get("/v1/sessions").headers["www-authenticate"] == "Bearer"  # no prompt for API calls
        basic = {"Authorization": "Basic " + base64.b64encode(b"anyone:k-one").decode()}
        assert client.get("/viewer/", headers=basic).status_code == 200
        assert client.get("/openapi.json", headers={"X-API-Key": "k-one"}).status_code == 200
        assert_error(client.get("/v1/sessions", headers=basic), 401)  # the API takes X-API-Key or Bearer
        assert_error(client.get("/docs", headers={"X-API-Key": "wrong"}), 401)
    with service_client(tmp_path / "open", api_keys="k-one", open_paths="/healthz,/viewer,/docs,/openapi.json") \
            as client:
        assert client.get("/viewer/").status_code == 200 and client.get("/openapi.json").status_code == 200
        assert_error(client.get("/redoc"), 401)
        assert_error(client.get("/v1/sessions"), 401)
