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


def test_values_an_upload_refuses_are_refused_in_a_chunk_and_the_stream_goes_on(tmp_path) -> None:
    """1e308 as a position or range, 1e300 as a time: an uploaded log with them is refused, and so is a
    chunk (it was taken with 201 and the job then failed with an OverflowError; a chunk stamped 1e300
    also blocked every later chunk of its session)."""
    import api_schemas.drivelog as schema
    import slam_engine.model.drive_log as engine

    for name in ("MAX_TIME_S", "MAX_COORDINATE_M", "MAX_ANGLE_RAD", "MAX_RANGE_M", "MAX_YAW_RATE_RAD_S"):
        assert getattr(schema, name) == getattr(engine, name), name  # the same bounds as a log's
    with service_client(tmp_path) as client:
        sid = new_session(client, calibration=CALIBRATION)
        url = f"/v1/sessions/{sid}/chunks"
        bad_messages = [
            {"type": "odometry", "t_s": 0.0, "x_m": 1e308, "y_m": 0.0, "theta_rad": 0.0},
            {"type": "odometry", "t_s": 1e300, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0},
            {"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 1e7},
            {"type": "scan", "t_s": 0.0, "ranges_m": [1e308, 1.0, 1.0, 1.0]},
            {"type": "gyro", "t_s": 0.0, "yaw_rate_rad_s": 1e9},
            {"type": "encoder", "t_s": 0.0, "ticks": [10**30, 0]},
        ]
        for message in bad_messages:
            answer = client.post(url, json={"seq": 0, "messages": [message]})
            err = assert_error(answer, 422, "validation_error")
            assert "less than or equal" in str(err) or "greater than or equal" in str(err), (message, err)
        # nothing was taken: chunk 0 is still free and the stream carries on
        assert client.post(url, json=chunk(0, 0.0)).status_code == 201
        assert client.post(url, json=chunk(1, 0.3)).status_code == 201
