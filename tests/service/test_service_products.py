"""Every product a job lists downloads under that name (GET /v1/jobs/{id}/{name}), with HEAD
answering the same headers without a body; the older routes (/run, /trajectory?format=tum) stay."""

from __future__ import annotations

import json

from service_helpers import new_session, service_client, streaming_session, wait_for

from service.jobs.products import MEDIA_TYPES
from service.storage.data_dir import DataDir


def test_every_listed_product_downloads_under_its_name(tmp_path) -> None:
    with service_client(tmp_path, job_function="viewer_job_functions:synthetic_room") as client:
        sid = streaming_session(client)
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 4, "seed": 1}).json()
        done = wait_for(client, job["id"])
        assert done["status"] == "succeeded", done
        listed = set(done["products"])
        # what the engine writes, each under its file name (texture: the synthetic room has a floor texture)
        # no snapshots; no key frames (a drawn room, not a SLAM run): no map bundle and no point cloud;
        # not a localisation or an extension (tests/service/test_service_saved_maps.py downloads theirs, with
        # their change maps; tests/service/test_service_live_localization.py a live localisation's poses)
        assert listed == set(MEDIA_TYPES) - {"animation.gif", "map_bundle.npz", "map_points.ply",
                                             "localization.png", "confidence.json", "drives.png", "changes.png",
                                             "changes.geojson", "poses.jsonl"}, listed
        job_dir = DataDir(tmp_path).job_dir(job["id"])
        for name in sorted(listed):
            url = f"/v1/jobs/{job['id']}/{name}"
            got = client.get(url)
            assert got.status_code == 200, (name, got.text)
            assert got.headers["content-type"].split(";")[0] == MEDIA_TYPES[name], name
            assert got.content == (job_dir / name).read_bytes(), name  # the file itself
            head = client.head(url)
            assert head.status_code == 200 and head.content == b"", name
            assert head.headers["content-length"] == str(len(got.content)), name
            assert head.headers["content-type"] == got.headers["content-type"], name

        # the older routes answer the same content
        run_file = client.get(f"/v1/jobs/{job['id']}/run.json").json()
        assert client.get(f"/v1/jobs/{job['id']}/run").json() == run_file
        assert run_file["config"]["particles"] == 30  # synthetic_room's SlamConfig()
        assert client.get(f"/v1/jobs/{job['id']}/trajectory", params={"format": "tum"}).content == \
            client.get(f"/v1/jobs/{job['id']}/trajectory.tum").content
        poses = json.loads(client.get(f"/v1/jobs/{job['id']}/trajectory.json").content)["poses"]
        api = client.get(f"/v1/jobs/{job['id']}/trajectory").json()["poses"]
        assert len(poses) == len(api) == 4
        assert poses == api  # one naming of pose fields: the file's are the API's (t_s, x_m, y_m, theta_rad)

        for path in ("run", "trajectory", "dead-reckoning", "trajectory?format=tum"):  # HEAD on the older routes
            got, head = client.get(f"/v1/jobs/{job['id']}/{path}"), client.head(f"/v1/jobs/{job['id']}/{path}")
            assert got.status_code == head.status_code == 200 and head.content == b"", path
            assert head.headers["content-length"] == str(len(got.content)), path
            assert head.headers["content-type"] == got.headers["content-type"], path

        tile = client.get(f"/v1/jobs/{job['id']}/tiles/occupancy/0/0/0.png")
        head = client.head(f"/v1/jobs/{job['id']}/tiles/occupancy/0/0/0.png")
        assert tile.status_code == head.status_code == 200 and head.content == b""
        assert head.headers["content-length"] == str(len(tile.content)) and len(tile.content) > 100
        scheme = client.get(f"/v1/jobs/{job['id']}/tiles/occupancy")
        head = client.head(f"/v1/jobs/{job['id']}/tiles/occupancy")
        assert head.status_code == 200 and head.content == b""
        assert head.headers["content-length"] == str(len(scheme.content))


def test_head_of_a_missing_product_is_the_get_status(tmp_path) -> None:
    with service_client(tmp_path, job_function="service_job_functions:counting") as client:
        sid = new_session(client)
        assert client.head(f"/v1/jobs/{sid}/occupancy.png").status_code == 404  # no such job
        sid = streaming_session(client)
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 2, "seed": 1}).json()
        assert wait_for(client, job["id"])["status"] == "succeeded"
        for method in (client.get, client.head):  # the counting job writes run.json only
            assert method(f"/v1/jobs/{job['id']}/run.json").status_code == 200
            assert method(f"/v1/jobs/{job['id']}/occupancy_trajectory.png").status_code == 404


def test_pose_reads_the_api_naming_and_that_of_version_1_files() -> None:
    from api_schemas.products import Pose

    api = Pose.model_validate({"t_s": 1.5, "x_m": 2.0, "y_m": -1.0, "theta_rad": 0.25})
    old_file = Pose.model_validate({"t": 1.5, "x": 2.0, "y": -1.0, "theta": 0.25})
    assert api == old_file and api.model_dump() == {"t_s": 1.5, "x_m": 2.0, "y_m": -1.0, "theta_rad": 0.25}


def test_byte_ranges_serve_parts_and_bad_ranges_answer_the_json_error_body(tmp_path) -> None:
    """A valid Range gets 206 with those bytes; a malformed one 400 and one past the file's end 416 with
    Content-Range, each in the API's JSON error body (Starlette alone answers them in plain text)."""
    with service_client(tmp_path, job_function="service_job_functions:counting") as client:
        sid = streaming_session(client)
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 2, "seed": 1}).json()
        assert wait_for(client, job["id"])["status"] == "succeeded"
        url = f"/v1/jobs/{job['id']}/run.json"
        whole = client.get(url).content
        part = client.get(url, headers={"Range": "bytes=0-9"})
        assert part.status_code == 206 and part.content == whole[:10]
        for method in (client.get, client.head):
            bad = method(url, headers={"Range": "bytes=abc"})
            assert bad.status_code == 400 and bad.headers["content-type"] == "application/json"
            if method is client.get:
                assert bad.json()["error"]["code"] == "bad_range" and "Range header" in bad.json()["error"]["message"]
            past = method(url, headers={"Range": f"bytes={len(whole) + 10}-"})
            assert past.status_code == 416 and past.headers["content-range"] == f"bytes */{len(whole)}"
            if method is client.get:
                assert past.json()["error"]["code"] == "range_not_satisfiable"
        # a Range that an If-Range no longer matches is ignored, as Starlette does: the whole file
        stale = client.get(url, headers={"Range": "bytes=abc", "If-Range": '"not-the-etag"'})
        assert stale.status_code == 200 and stale.content == whole
