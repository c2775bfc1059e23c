"""Sessions routes, the JSON error body, unknown ids and routes, readiness."""

from __future__ import annotations

import uuid

from service_helpers import assert_error, new_session, service_client


def test_session_crud_and_errors(tmp_path) -> None:
    with service_client(tmp_path) as client:
        created = client.post("/v1/sessions", json={
            "name": "lab loop", "vehicle_preset": "intel_pioneer",
            "geo": {"lat_deg": 45.52, "lon_deg": -122.68, "heading_deg": 90.0}})
        assert created.status_code == 201
        session = created.json()
        uuid.UUID(session["id"])
        assert session["geo"] == {"lat_deg": 45.52, "lon_deg": -122.68, "heading_deg": 90.0}
        assert (session["logs"], session["chunks"], session["jobs"]) == (0, 0, 0)
        other = new_session(client)

        listed = client.get("/v1/sessions").json()
        assert listed["count"] == 2 and {s["id"] for s in listed["data"]} == {session["id"], other}
        assert client.get("/v1/sessions", params={"limit": 1}).json()["count"] == 2
        assert len(client.get("/v1/sessions", params={"limit": 1}).json()["data"]) == 1
        assert client.get(f"/v1/sessions/{session['id']}").json()["name"] == "lab loop"

        deleted = client.delete(f"/v1/sessions/{session['id']}")
        assert deleted.status_code == 200 and deleted.json() == {"id": session["id"], "jobs_cancelled": 0}
        assert_error(client.get(f"/v1/sessions/{session['id']}"), 404, "not_found")
        assert_error(client.delete(f"/v1/sessions/{session['id']}"), 404, "not_found")
        assert_error(client.get("/v1/sessions/not-a-uuid"), 404, "not_found")
        assert_error(client.get("/v1/sessions/" + "x" * 100), 422, "validation_error")

        # bad input is a 422 naming the field, never a 500
        err = assert_error(client.post("/v1/sessions", json={"name": "x", "geo": {"lat_deg": 91, "lon_deg": 0}}),
                           422, "validation_error")
        assert err["message"].startswith("body.geo.lat_deg")
        assert_error(client.post("/v1/sessions", json={}), 422, "validation_error")
        assert_error(client.post("/v1/sessions", json={"name": "x", "surprise": 1}), 422, "validation_error")
        assert_error(client.post("/v1/sessions", content=b"{not json", headers={"content-type": "application/json"}),
                     422, "validation_error")
        assert_error(client.post("/v1/sessions", json={"name": "x", "vehicle_preset": "../etc"}), 422)
        assert_error(client.get("/v1/sessions", params={"limit": 0}), 422)
        assert_error(client.get("/v1/nothing-here"), 404, "not_found")
        assert_error(client.put("/v1/sessions"), 405, "method_not_allowed")


def test_health_and_readiness(tmp_path) -> None:
    with service_client(tmp_path, workers=2) as client:
        assert client.get("/healthz").json()["status"] == "ok"
        ready = client.get("/readyz")
        assert ready.status_code == 200
        body = ready.json()
        assert body["ready"] is True
        assert body["workers"]["workers_total"] == 2 and body["workers"]["workers_alive"] == 2
        assert body["storage"]["database_ok"] and body["storage"]["data_dir_writable"]
        assert "/v1/jobs/{job_id}/tiles/{layer}/{z}/{x}/{y}.png" in client.get("/openapi.json").json()["paths"]


def test_calibration_is_bounded_and_shaped(tmp_path) -> None:
    """A malformed mounting matrix or an absurd number is refused when the session is created (422),
    not when a job runs."""
    lidar = {"num_beams": 180, "angle_min_rad": -1.57, "angle_increment_rad": 0.0175, "range_min_m": 0.0,
             "range_max_m": 50.0}
    bad = [
        {"vehicle": {"kind": "odometry"}, "lidar": {**lidar, "T_vehicle_from_lidar": [[1, 0, 0], [0, 1, 0]]}},
        {"vehicle": {"kind": "differential", "ticks_per_revolution": 1e12}},
        {"vehicle": {"kind": "differential", "wheel_diameters_m": [0.2, -1.0]}},
        {"vehicle": {"kind": "odometry"}, "lidar": {**lidar, "range_min_m": 1e9}},
    ]
    with service_client(tmp_path) as client:
        for calibration in bad:
            response = client.post("/v1/sessions", json={"name": "x", "calibration": calibration})
            assert response.status_code == 422, calibration
            assert response.json()["error"]["code"] == "validation_error"
        good = client.post("/v1/sessions", json={"name": "ok", "calibration": {
            "vehicle": {"kind": "odometry"}, "lidar": {**lidar, "T_vehicle_from_lidar": [
                [1, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, 1, 0.3], [0, 0, 0, 1]]}}})
        assert good.status_code == 201
