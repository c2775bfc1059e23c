"""Streamed chunks: idempotent retries, 409 on a changed retry, gaps and time order reported."""

from __future__ import annotations

from service_helpers import assert_error, new_session, service_client

CALIBRATION = {"vehicle": {"kind": "odometry"},
               "lidar": {"num_beams": 4, "angle_min_rad": -1.5, "angle_increment_rad": 1.0,
                         "range_min_m": 0.1, "range_max_m": 20.0}}


def chunk(seq: int, t0: float, n: int = 3) -> dict:
    messages = []
    for i in range(n):
        t = t0 + 0.1 * i
        messages.append({"type": "odometry", "t_s": t, "x_m": t, "y_m": 0.0, "theta_rad": 0.0})
        messages.append({"type": "scan", "t_s": t, "ranges_m": [1.0, None, 2.5, 3.0]})
    return {"seq": seq, "messages": messages}


def test_chunks_idempotent_gaps_and_order(tmp_path) -> None:
    with service_client(tmp_path, max_chunk_bytes=20_000) as client:
        sid = new_session(client, calibration=CALIBRATION)
        url = f"/v1/sessions/{sid}/chunks"

        first = client.post(url, json=chunk(0, 0.0))
        assert first.status_code == 201
        body = first.json()
        assert body["duplicate"] is False and body["messages"] == 6
        assert (body["t_first_s"], body["t_last_s"]) == (0.0, 0.2)
        assert body["stream"] == {"received": 1, "contiguous_through": 0, "next_expected_seq": 1,
                                  "missing_seqs": [], "messages": 6, "finished": False, "last_seq": None}

        retry = client.post(url, json=chunk(0, 0.0))
        assert retry.status_code == 200 and retry.json()["duplicate"] is True
        assert retry.json()["sha256"] == body["sha256"] and retry.json()["stream"]["received"] == 1

        changed = chunk(0, 0.0)
        changed["messages"][1]["ranges_m"][0] = 1.5
        err = assert_error(client.post(url, json=changed), 409, "conflict")
        assert err["detail"]["seq"] == 0 and err["detail"]["stored_sha256"] == body["sha256"]

        ahead = client.post(url, json=chunk(3, 3.0))  # 1 and 2 not yet sent
        assert ahead.status_code == 201
        assert ahead.json()["stream"] == {"received": 2, "contiguous_through": 0, "next_expected_seq": 1,
                                          "missing_seqs": [1, 2], "messages": 6, "finished": False,
                                          "last_seq": None}
        # chunk 2 must end before chunk 3 starts
        err = assert_error(client.post(url, json=chunk(2, 2.95)), 422, "invalid_input")
        assert "before" in err["message"] or "after" in err["message"]
        # chunk 1 must start after chunk 0 ends
        assert_error(client.post(url, json=chunk(1, 0.1)), 422, "invalid_input")
        assert client.post(url, json=chunk(1, 1.0)).status_code == 201
        assert client.post(url, json=chunk(2, 2.0)).status_code == 201
        state = client.get(url).json()
        assert state == {"received": 4, "contiguous_through": 3, "next_expected_seq": 4,
                         "missing_seqs": [], "messages": 24, "finished": False, "last_seq": None}

        backwards = chunk(4, 5.0)
        backwards["messages"][2]["t_s"] = 4.0
        err = assert_error(client.post(url, json=backwards), 422, "invalid_input")
        assert err["detail"] == {"seq": 4, "message_index": 2}

        bad = chunk(5, 6.0)
        bad["messages"][0] = {"type": "sonar", "t_s": 6.0}
        assert_error(client.post(url, json=bad), 422, "validation_error")
        assert_error(client.post(url, json={"seq": -1, "messages": chunk(0, 0)["messages"]}), 422)
        assert_error(client.post(url, json={"seq": 9, "messages": []}), 422)
        huge = chunk(6, 7.0, n=200)
        assert_error(client.post(url, json=huge), 413, "payload_too_large")
        assert_error(client.post("/v1/sessions/00000000-0000-0000-0000-000000000000/chunks", json=chunk(0, 0.0)), 404)
        assert client.get(f"/v1/sessions/{sid}").json()["chunks"] == 4
