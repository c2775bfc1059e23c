"""End to end through HTTP with the real engine: upload intel.clf, map it, fetch and decode every
product; the live map while running; cancelling a real run; streaming a simulated log as chunks
(with a duplicate, a retry and reordering) gives the same map as uploading it whole."""

from __future__ import annotations

import io

import numpy as np
import pytest
import yaml
from PIL import Image
from service_helpers import map_sessions, new_session, service_client, upload_log_file, wait_for

from service.storage.stream_log import calibration_from_log, messages_of_log

pytestmark = pytest.mark.slow

DEAD_RECKONING_INTEL_M = 6.74  # mean relation error of intel's odometry (benchmark README)


def test_upload_map_and_fetch_every_product(tmp_path, dataset) -> None:
    import rasterio

    from slam_engine.evaluation.metrics import read_relations, relation_errors
    from slam_engine.model.result import Trajectory

    intel = dataset("benchmark/intel.clf")
    relations = read_relations(dataset("benchmark/intel.relations"))
    with service_client(tmp_path, workers=2) as client:
        sid = new_session(client, name="intel")
        with intel.open("rb") as f:
            assert client.post(f"/v1/sessions/{sid}/logs", files={"file": ("intel.clf", f)}).status_code == 201
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 10, "seed": 1, "resolution_m": 0.05,
                                                           "snapshot_every_scans": 25}).json()
        doomed = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 10}).json()

        # live map while running
        live = wait_for(client, job["id"], {"running"}, timeout_s=300,
                        condition=lambda j: {"occupancy.png", "trajectory.json"} <= set(j["products"]))
        assert 0 < live["scans_done"] < live["scans_total"] == 910
        preview = Image.open(io.BytesIO(client.get(f"/v1/jobs/{job['id']}/occupancy.png").content))
        assert preview.size[0] > 10 and preview.size[1] > 10
        tile = client.get(f"/v1/jobs/{job['id']}/tiles/occupancy/0/0/0.png")
        assert tile.status_code == 200 and Image.open(io.BytesIO(tile.content)).size == (256, 256)
        partial = client.get(f"/v1/jobs/{job['id']}/trajectory").json()  # the trajectory so far
        assert 0 < partial["count"] < 910
        assert partial["poses"][0]["x_m"] == pytest.approx(0.0, abs=1e-6)

        # cancelling a real run stops it at its next progress report, not by terminating its worker
        # (past the first hundred scans, so that a cold numba cache has compiled every kernel the run uses)
        wait_for(client, doomed["id"], {"running"}, timeout_s=300, condition=lambda j: j["scans_done"] > 100)
        client.delete(f"/v1/jobs/{doomed['id']}")
        stopped = wait_for(client, doomed["id"], timeout_s=60)
        assert stopped["status"] == "cancelled" and stopped["error"] == "cancelled by request"
        assert stopped["scans_done"] < 910

        done = wait_for(client, job["id"], timeout_s=900)
        assert done["status"] == "succeeded", done
        assert done["input"]["summary"]["streams"]["scans"] == 910
        assert done["scans_done"] == done["scans_total"] == 910

        base = f"/v1/jobs/{job['id']}"
        traj = client.get(f"{base}/trajectory").json()
        assert traj["count"] == 910 and traj["kind"] == "slam"
        slam = Trajectory(t_s=np.array([p["t_s"] for p in traj["poses"]]),
                          poses=np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in traj["poses"]]))
        error_m = relation_errors(slam, relations).all.trans_mean_m
        print(f"intel relation error: SLAM {error_m:.3f} m (dead reckoning {DEAD_RECKONING_INTEL_M} m)")
        dr = client.get(f"{base}/dead-reckoning").json()
        dead = Trajectory(t_s=np.array([p["t_s"] for p in dr["poses"]]),
                          poses=np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in dr["poses"]]))
        assert relation_errors(dead, relations).all.trans_mean_m == pytest.approx(DEAD_RECKONING_INTEL_M, abs=0.05)
        assert error_m < 0.3, f"SLAM relation error {error_m:.3f} m (dead reckoning {DEAD_RECKONING_INTEL_M} m)"

        tum = client.get(f"{base}/trajectory", params={"format": "tum"}).text.splitlines()
        assert len([line for line in tum if not line.startswith("#")]) == 910
        png = Image.open(io.BytesIO(client.get(f"{base}/occupancy.png").content))
        with rasterio.open(io.BytesIO(client.get(f"{base}/occupancy.tif").content)) as tif:
            assert (tif.width, tif.height) == png.size and tif.read(1).max() > 0.5
        ros = yaml.safe_load(client.get(f"{base}/map.yaml").text)
        assert ros["resolution"] == pytest.approx(0.05)
        assert Image.open(io.BytesIO(client.get(f"{base}/map.pgm").content)).size == png.size
        gif = Image.open(io.BytesIO(client.get(f"{base}/animation.gif").content))
        assert gif.n_frames > 2
        assert Image.open(io.BytesIO(client.get(f"{base}/tiles/occupancy/0/0/0.png").content)).size == (256, 256)
        run = client.get(f"{base}/run").json()
        assert run == client.get(f"{base}/run.json").json()
        assert run["config"]["particles"] == 10 and run["timings"]["scans"] == 910
        assert client.get(f"{base}/texture.png").status_code == 404  # no camera in intel
        assert set(done["products"]) >= {"trajectory.json", "occupancy.png", "occupancy.tif", "map.yaml",
                                         "map.pgm", "animation.gif", "run.json"}


def test_streamed_chunks_give_the_same_map_as_the_upload(tmp_path) -> None:
    from slam_engine.formats import load_log
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=40.0)
    log_path = write_simulated(drive, "carmen", tmp_path / "sim")
    loaded = load_log(log_path)  # exactly what the upload route will see
    messages = messages_of_log(loaded)
    chunks = [messages[i:i + 150] for i in range(0, len(messages), 150)]
    assert len(chunks) >= 4
    params = {"particles": 5, "seed": 7, "resolution_m": 0.1, "snapshot_every_scans": 0}

    with service_client(tmp_path / "data", workers=2) as client:
        whole = new_session(client, name="whole")
        assert upload_log_file(client, whole, log_path).status_code == 201
        streamed = new_session(client, name="streamed", calibration=calibration_from_log(loaded))
        url = f"/v1/sessions/{streamed}/chunks"
        order = [0, 2, 1, *range(3, len(chunks))]  # chunk 2 overtakes chunk 1
        for seq in order:
            response = client.post(url, json={"seq": seq, "messages": chunks[seq]})
            assert response.status_code == 201, response.text
            if seq == 2:
                assert response.json()["stream"]["missing_seqs"] == [1]
        retry = client.post(url, json={"seq": 1, "messages": chunks[1]})  # a retry after a lost answer
        assert retry.status_code == 200 and retry.json()["duplicate"] is True
        state = client.get(url).json()
        assert state["contiguous_through"] == len(chunks) - 1 and state["messages"] == len(messages)

        a, b = map_sessions(client, params, whole, streamed)
        assert a["status"] == b["status"] == "succeeded", (a, b)
        assert b["input"]["chunks_used"] == len(chunks)
        ta = client.get(f"/v1/jobs/{a['id']}/trajectory").json()["poses"]
        tb = client.get(f"/v1/jobs/{b['id']}/trajectory").json()["poses"]
        assert ta == tb and len(ta) == len(drive.ground_truth)
        png_a = client.get(f"/v1/jobs/{a['id']}/occupancy.png").content
        png_b = client.get(f"/v1/jobs/{b['id']}/occupancy.png").content
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(png_a))), np.asarray(Image.open(io.BytesIO(png_b))))
