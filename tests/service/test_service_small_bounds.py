"""Smaller bounds of issue 18 (item 7): chunks checked against the session's calibration, an
over-limit JSON body without a Content-Length is 413."""

from __future__ import annotations

from service_helpers import CALIBRATION, assert_error, new_session, service_client


def test_a_scan_with_the_wrong_beam_count_is_refused(tmp_path) -> None:
    with service_client(tmp_path) as client:
        sid = new_session(client, calibration=CALIBRATION)  # 2 beams
        scan = {"type": "scan", "t_s": 0.0, "ranges_m": [1.0, 2.0, 3.0]}
        err = assert_error(client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [scan]}), 422)
        assert "3 ranges" in err["message"] and err["detail"]["num_beams"] == 2
        scan["ranges_m"] = [1.0, 2.0]
        assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [scan]}).status_code == 201


def test_an_over_limit_body_without_a_length_is_413(tmp_path) -> None:
    with service_client(tmp_path, max_chunk_bytes=20_000) as client:
        sid = new_session(client, calibration=CALIBRATION)
        message = b'{"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0},'

        def body():  # sent chunked: no Content-Length to refuse it by
            yield b'{"seq": 0, "messages": ['
            for _ in range(1000):
                yield message
            yield b'{"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}]}'

        response = client.post(f"/v1/sessions/{sid}/chunks", content=body(),
                               headers={"content-type": "application/json"})
        assert "content-length" not in response.request.headers
        err = assert_error(response, 413, "payload_too_large")
        assert "20000 bytes" in err["message"]


def test_a_stalled_body_is_answered_408_and_closed(tmp_path) -> None:
    import socket
    import threading
    import time

    import uvicorn

    from service.api.app import create_app
    from service.settings import Settings

    app = create_app(Settings(data_dir=tmp_path, workers=1, body_stall_timeout_s=1.0))
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started and time.monotonic() < deadline:
            time.sleep(0.05)
        with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
            conn.sendall(b"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                         b"Content-Length: 100\r\n\r\n{\"name\": ")  # and then nothing
            started = time.monotonic()
            answer = b""
            while chunk := conn.recv(4096):
                answer += chunk
            waited = time.monotonic() - started
        assert answer.startswith(b"HTTP/1.1 408") and b"request_timeout" in answer, answer
        assert 0.9 < waited < 8  # answered after the 1 s stall, and the connection closed
    finally:
        server.should_exit = True
        thread.join(timeout=10)
