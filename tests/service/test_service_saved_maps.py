"""Jobs that start from a saved map, through HTTP with the real engine: the simulated office loop cut in
two halves, uploaded as two logs; the first mapped, the second localised in its map and used to extend
it; a drive in another building refused; bad references answered 404 / 409 / 422."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image
from service_helpers import assert_error, new_session, service_client, wait_for

from slam_engine.formats import write_log
from slam_engine.products.map_bundle import BUNDLE_VERSION
from slam_engine.simulation import simulate

pytestmark = pytest.mark.slow


def _upload(client, sid: str, log, folder) -> str:
    path = write_log(log, "carmen", folder)
    with path.open("rb") as f:
        response = client.post(f"/v1/sessions/{sid}/logs", files={"file": (path.name, f)})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def test_localize_and_extend_jobs_start_from_a_finished_job(tmp_path) -> None:
    office = simulate("office", seed=0, cameras=False)
    start, end = office.log.time_span_s()
    middle = (start + end) / 2
    first, second = office.log.between(start, middle), office.log.between(middle, end + 1.0)
    elsewhere = simulate("campus", seed=1, rig="robot", cameras=False, max_duration_s=40.0).log
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
    with service_client(tmp_path / "data", workers=2) as client:
        sid = new_session(client)
        log_a = _upload(client, sid, first, tmp_path / "a")
        # a localisation that names no map searches the key's saved maps: 409 while it has none
        none_yet = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_a, "mode": "localize"})
        assert "no saved map to localise in" in assert_error(none_yet, 409)["message"]
        mapped = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_a, "particles": 10}).json()
        log_b = _upload(client, sid, second, tmp_path / "b")
        log_c = _upload(client, sid, elsewhere, tmp_path / "c")

        # a saved map must exist and be finished: 422 extending none, 404 unknown, 409 not finished
        assert_error(client.post(f"/v1/sessions/{sid}/jobs", json={"mode": "extend"}), 422)
        assert_error(client.post(f"/v1/sessions/{sid}/jobs", json={"map_job_id": mapped["id"]}), 422)
        assert_error(client.post(f"/v1/sessions/{sid}/jobs", json={"mode": "localize", "map_job_id": "nope"}), 404)
        if client.get(f"/v1/jobs/{mapped['id']}").json()["status"] != "succeeded":
            assert_error(client.post(f"/v1/sessions/{sid}/jobs",
                                     json={"mode": "localize", "map_job_id": mapped["id"]}), 409)
        done = wait_for(client, mapped["id"], timeout_s=300)
        assert done["status"] == "succeeded" and "map_bundle.npz" in done["products"], done
        bundle = client.get(f"/v1/jobs/{mapped['id']}/map_bundle.npz")
        assert bundle.status_code == 200 and np.load(io.BytesIO(bundle.content))["poses"].shape[1] == 3

        localized = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_b, "mode": "localize",
                                                                 "map_job_id": mapped["id"]}).json()
        extended = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_b, "mode": "extend",
                                                                "map_job_id": mapped["id"], "particles": 10}).json()
        refused = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_c, "mode": "localize",
                                                               "map_job_id": mapped["id"]}).json()

        got = wait_for(client, localized["id"], timeout_s=300)
        assert got["status"] == "succeeded", got
        assert {"trajectory.json", "localization.png", "confidence.json", "run.json"} <= set(got["products"])
        trajectory = client.get(f"/v1/jobs/{localized['id']}/trajectory").json()
        assert trajectory["count"] == len(second.scans)
        confidence = client.get(f"/v1/jobs/{localized['id']}/confidence.json").json()
        assert len(confidence["confidence"]) == len(second.scans) and max(confidence["confidence"]) > 0.5
        overlay = Image.open(io.BytesIO(client.get(f"/v1/jobs/{localized['id']}/localization.png").content))
        assert overlay.mode == "RGB" and overlay.size[0] > 50
        run = client.get(f"/v1/jobs/{localized['id']}/run.json").json()
        assert run["localization"]["localised"] is True

        # no map named: the drive is localised in whichever of the key's saved maps it is in
        anywhere = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_b, "mode": "localize"})
        assert anywhere.status_code == 202, anywhere.text
        found = wait_for(client, anywhere.json()["id"], timeout_s=300)
        assert found["status"] == "succeeded", found
        which = client.get(f"/v1/jobs/{found['id']}/run.json").json()["localization"]["which_map"]
        # the office's map, or its extension when that finished first (both hold the office)
        assert which["chosen"] in (mapped["id"], extended["id"]) and which["maps"][0]["localised"] is True
        nowhere = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_c, "mode": "localize"}).json()
        lost = wait_for(client, nowhere["id"], timeout_s=300)
        assert lost["status"] == "failed" and "refused: the drive is in none of the" in lost["error"], lost

        bad = wait_for(client, refused["id"], timeout_s=300)
        assert bad["status"] == "failed", bad
        assert bad["error"].startswith("MapBundleError: refused: the drive has no place in the saved map"), bad

        grown = wait_for(client, extended["id"], timeout_s=300)
        assert grown["status"] == "succeeded", grown
        assert {"drives.png", "map_bundle.npz", "occupancy.png"} <= set(grown["products"])
        joint = client.get(f"/v1/jobs/{extended['id']}/trajectory").json()
        assert joint["count"] == len(first.scans) + len(second.scans)
        run = client.get(f"/v1/jobs/{extended['id']}/run.json").json()
        assert run["input"]["drives"] == 2
        tile = client.get(f"/v1/jobs/{extended['id']}/tiles/occupancy/0/0/0.png")
        assert tile.status_code == 200


def test_an_uploaded_map_is_checked_and_a_job_can_start_from_it(tmp_path) -> None:
    """A map bundle made elsewhere (here: by the engine directly) uploaded to a session is listed as a
    finished job of source 'map'; a localisation starts from it. Not a bundle, a bundle of a future
    version and one whose array header claims more than the file holds are 422, never read whole."""
    import zipfile

    from slam_engine.config import SlamConfig
    from slam_engine.pipeline import run_slam
    from slam_engine.products.map_bundle import write_bundle

    office = simulate("office", seed=0, cameras=False)
    start, end = office.log.time_span_s()
    middle = (start + end) / 2
    first, second = office.log.between(start, middle), office.log.between(middle, end + 1.0)
    bundle = write_bundle(run_slam(first, SlamConfig(particles=10)).bundle, tmp_path / "map_bundle.npz")
    (tmp_path / "b").mkdir()
    with service_client(tmp_path / "data") as client:
        sid = new_session(client)
        with bundle.open("rb") as f:
            uploaded = client.post(f"/v1/sessions/{sid}/maps", files={"file": ("map_bundle.npz", f)})
        assert uploaded.status_code == 201, uploaded.text
        saved = uploaded.json()
        assert saved["status"] == "succeeded" and saved["source"] == "map" and saved["products"] == ["map_bundle.npz"]
        assert saved["input"]["summary"]["drives"] == 1 and saved["input"]["summary"]["key_frames"] > 50
        assert client.get(f"/v1/jobs/{saved['id']}/map_bundle.npz").content == bundle.read_bytes()

        log_b = _upload(client, sid, second, tmp_path / "b")
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_b, "mode": "localize",
                                                           "map_job_id": saved["id"]}).json()
        done = wait_for(client, job["id"], timeout_s=300)
        assert done["status"] == "succeeded", done
        assert_error(client.post(f"/v1/sessions/{sid}/jobs", json={"source": "map"}), 422)

        (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not really a zip")
        future = tmp_path / "future.npz"
        lying = tmp_path / "lying.npz"
        with zipfile.ZipFile(bundle) as source, zipfile.ZipFile(future, "w") as target:
            for item in source.namelist():
                data = source.read(item)
                if item == "header.npy":
                    data = data.replace(f'"version": {BUNDLE_VERSION}'.encode(), b'"version": 7')
                target.writestr(item, data)
        with zipfile.ZipFile(bundle) as source, zipfile.ZipFile(lying, "w") as target:
            for item in source.namelist():
                data = source.read(item)
                if item == "ends_v.npy":  # claims 10^12 rows: reading it would allocate terabytes
                    data = data.replace(b"'shape': (", b"'shape': (1000000000000, ", 1).replace(b", 2)", b")", 0)
                target.writestr(item, data)
        # values an uploaded log may not hold, in a bundle (they were taken, and localise then failed with
        # an OverflowError), a boolean cell size and a billion beams
        far, boolean, beams = tmp_path / "far.npz", tmp_path / "boolean.npz", tmp_path / "beams.npz"
        arrays = dict(np.load(bundle))
        header = json.loads(arrays["header"].tobytes())
        poses = arrays["poses"].copy()
        poses[3, 0] = 1e308
        np.savez(far, **{**arrays, "poses": poses})
        for target, change in ((boolean, {"resolution_m": True}),
                               (beams, {"sensors": {**header.get("sensors", {}), "lidar": {"num_beams": 10**9}}})):
            text = json.dumps({**header, **change}).encode()
            np.savez(target, **{**arrays, "header": np.frombuffer(text, np.uint8)})
        for path, words in ((tmp_path / "junk.npz", "not a readable map bundle"),
                            (future, "format version 7"), (lying, "claims shape"),
                            (far, "poses holds 1e+308, beyond +-1e+06 m"), (boolean, "resolution_m True"),
                            (beams, "num_beams 1000000000")):
            with path.open("rb") as f:
                answer = client.post(f"/v1/sessions/{sid}/maps", files={"file": (path.name, f)})
            body = assert_error(answer, 422, "map_bundle")
            assert words in body["message"], body
            assert str(tmp_path) not in body["message"]  # no server paths in messages
            # nor the upload's temporary file or exception class names
            assert "upload-" not in body["message"] and "Error" not in body["message"], body
            assert not body["message"].startswith(":"), body
        listed = client.get(f"/v1/jobs?session={sid}").json()
        assert sum(j["source"] == "map" for j in listed["data"]) == 1  # nothing half-stored


def test_a_merge_job_makes_one_map_of_two_saved_maps_or_refuses_them(tmp_path) -> None:
    """``{"mode": "merge", "map_job_id": A, "merge_job_id": B}``: the office's two halves, mapped apart and
    uploaded as saved maps, become one map in A's frame (what ``lidarmap merge`` writes); a map of another
    building is refused; a merge names two saved maps and nothing to map (422), each one known (404)."""
    from slam_engine.config import SlamConfig
    from slam_engine.pipeline import run_slam
    from slam_engine.products.map_bundle import read_bundle, write_bundle

    office = simulate("office", seed=0, cameras=False)
    start, end = office.log.time_span_s()
    middle = (start + end) / 2
    drives = {"a": office.log.between(start, middle), "b": office.log.between(middle, end + 1.0),
              "c": simulate("campus", seed=1, rig="robot", cameras=False, max_duration_s=40.0).log}
    config = SlamConfig(particles=10)
    with service_client(tmp_path / "data") as client:
        sid = new_session(client)
        saved = {}
        for name, log in drives.items():
            path = write_bundle(run_slam(log, config).bundle, tmp_path / f"{name}.npz")
            with path.open("rb") as f:
                saved[name] = client.post(f"/v1/sessions/{sid}/maps", files={"file": (path.name, f)}).json()["id"]

        def merge(first: str, second: str) -> dict:
            job = client.post(f"/v1/sessions/{sid}/jobs", json={"mode": "merge", "map_job_id": saved[first],
                                                               "merge_job_id": saved[second]})
            assert job.status_code == 202, job.text
            assert job.json()["merge_job_id"] == saved[second] and job.json()["source"] == "map"
            return wait_for(client, job.json()["id"], timeout_s=300)

        merged = merge("a", "b")
        assert merged["status"] == "succeeded", merged
        assert {"map_bundle.npz", "drives.png", "occupancy.png", "run.json"} <= set(merged["products"])
        trajectory = client.get(f"/v1/jobs/{merged['id']}/trajectory").json()
        assert trajectory["count"] == len(drives["a"].scans) + len(drives["b"].scans)
        bundle = tmp_path / "merged.npz"
        bundle.write_bytes(client.get(f"/v1/jobs/{merged['id']}/map_bundle.npz").content)
        assert read_bundle(bundle).drives == 2
        assert client.get(f"/v1/jobs/{merged['id']}/tiles/occupancy/0/0/0.png").status_code == 200

        refused = merge("a", "c")
        assert refused["status"] == "failed" and "refused: the maps do not overlap" in refused["error"], refused

        for body in ({"mode": "merge", "map_job_id": saved["a"]},  # no second map
                     {"merge_job_id": saved["b"]},  # not a merge
                     {"mode": "merge", "map_job_id": saved["a"], "merge_job_id": saved["b"], "source": "log"},
                     {"mode": "merge", "map_job_id": saved["a"], "merge_job_id": saved["b"], "live": True}):
            assert_error(client.post(f"/v1/sessions/{sid}/jobs", json=body), 422)
        unknown = client.post(f"/v1/sessions/{sid}/jobs", json={"mode": "merge", "map_job_id": saved["a"],
                                                                 "merge_job_id": "nope"})
        assert assert_error(unknown, 404)["detail"] == {"field": "merge_job_id"}


def test_an_extend_job_lists_what_changed_placed_on_earth_with_its_session(tmp_path) -> None:
    """The simulated office mapped, then extended by a drive there days later in a session with a geo
    origin: changes.png and changes.geojson among its products, the GeoJSON in WGS 84 near that origin."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with service_client(tmp_path / "data", workers=1) as client:
        sid = new_session(client, geo={"lat_deg": 47.99, "lon_deg": 7.84, "heading_deg": 0.0})
        log_a = _upload(client, sid, simulate("office", seed=0, cameras=False).log, tmp_path / "a")
        mapped = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_a, "particles": 10}).json()
        assert wait_for(client, mapped["id"], timeout_s=300)["status"] == "succeeded"
        log_b = _upload(client, sid, simulate("office-changed", seed=1, cameras=False).log, tmp_path / "b")
        extended = client.post(f"/v1/sessions/{sid}/jobs", json={"log_id": log_b, "mode": "extend",
                                                                "map_job_id": mapped["id"], "particles": 10}).json()
        done = wait_for(client, extended["id"], timeout_s=300)
        assert done["status"] == "succeeded", done
        assert {"changes.png", "changes.geojson", "drives.png"} <= set(done["products"])
        geojson = client.get(f"/v1/jobs/{extended['id']}/changes.geojson")
        assert geojson.status_code == 200 and geojson.headers["content-type"].startswith("application/geo+json")
        features = geojson.json()["features"]
        assert {f["properties"]["kind"] for f in features} == {"added", "removed"}
        for feature in features:
            lon, lat = np.array(feature["geometry"]["coordinates"][0]).T
            assert np.all(np.abs(lat - 47.99) < 3e-4) and np.all(np.abs(lon - 7.84) < 4e-4)  # within 30 m
            assert feature["properties"]["map_frame_geometry"]["type"] == "Polygon"
        run = client.get(f"/v1/jobs/{extended['id']}/run.json").json()
        assert run["changes"]["removed_regions"] == 2 and run["changes"]["changed_share"] < 0.02
        image = Image.open(io.BytesIO(client.get(f"/v1/jobs/{extended['id']}/changes.png").content))
        assert (np.asarray(image) == (224, 49, 49)).all(axis=2).any()
