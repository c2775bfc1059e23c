"""An interlaced laser's CARMEN log uploaded and mapped through HTTP: accepted (not refused for its
changing start angle) and mapped as well as the same simulated drive without interlacing; streamed
as chunks whose scans carry their start angle, the same map as the upload."""

from __future__ import annotations

import numpy as np
import pytest
from service_helpers import assert_error, map_sessions, new_session, service_client, upload_log_file, wait_for

from service.storage.stream_log import calibration_from_log, drive_log_from_messages, messages_of_log
from slam_engine.evaluation.metrics import absolute_trajectory_error
from slam_engine.model.result import Trajectory
from slam_engine.simulation import simulate, write_simulated

pytestmark = pytest.mark.slow

# Measured (seed 0, 40 s, 10 particles, the engine's defaults otherwise): 0.0066 m interlaced, 0.0062 m
# not (the CLI gives the same); seeds 0 / 1 over 60 s differed by 0.0003 / 0.0029 m. Three times that spread:
MARGIN_M = 0.009


def test_uploaded_interlaced_log_maps_as_well_as_without_interlacing(tmp_path) -> None:
    errors = {}
    with service_client(tmp_path / "data", workers=2) as client:
        jobs = {}
        for rig in ("carmen-interlaced", "carmen-robot"):
            drive = simulate("office", seed=0, rig=rig, max_duration_s=40.0, cameras=False)
            log_path = write_simulated(drive, "carmen", tmp_path / rig)
            sid = new_session(client, name=rig)
            upload = upload_log_file(client, sid, log_path)
            assert upload.status_code == 201, upload.text
            job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 10, "seed": 0})
            assert job.status_code in (200, 201, 202), job.text
            jobs[rig] = (job.json()["id"], drive)
        for rig, (job_id, drive) in jobs.items():
            done = wait_for(client, job_id, timeout_s=600)
            assert done["status"] == "succeeded", done
            poses = client.get(f"/v1/jobs/{job_id}/trajectory").json()["poses"]
            slam = Trajectory(t_s=np.array([p["t_s"] for p in poses]),
                              poses=np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in poses]))
            errors[rig] = absolute_trajectory_error(slam, drive.ground_truth)
            if rig == "carmen-interlaced":
                assert any("carried per scan" in w for w in done["input"]["summary"]["warnings"]), done["input"]
    print(f"ATE interlaced {errors['carmen-interlaced']:.4f} m, not interlaced {errors['carmen-robot']:.4f} m")
    assert errors["carmen-robot"] < 0.03
    assert errors["carmen-interlaced"] <= errors["carmen-robot"] + MARGIN_M


def test_streamed_interlaced_chunks_give_the_same_map_as_the_upload(tmp_path) -> None:
    from slam_engine.formats import load_log

    drive = simulate("office", seed=0, rig="carmen-interlaced", max_duration_s=20.0, cameras=False)
    log_path = write_simulated(drive, "carmen", tmp_path / "sim")
    loaded = load_log(log_path)
    messages = messages_of_log(loaded)
    scans = [m for m in messages if m["type"] == "scan"]
    assert np.degrees(sorted({round(m["angle_offset_rad"], 9) for m in scans})) == pytest.approx([0, 0.25, 0.5, 0.75])
    chunks = [messages[i:i + 150] for i in range(0, len(messages), 150)]
    params = {"particles": 5, "seed": 7, "resolution_m": 0.1, "snapshot_every_scans": 0}
    with service_client(tmp_path / "data", workers=2) as client:
        whole = new_session(client, name="whole")
        assert upload_log_file(client, whole, log_path).status_code == 201
        streamed = new_session(client, name="streamed", calibration=calibration_from_log(loaded))
        url = f"/v1/sessions/{streamed}/chunks"
        bad = {**scans[0], "angle_offset_rad": 7.0}  # beyond +-2 pi
        assert_error(client.post(url, json={"seq": 0, "messages": [bad]}), 422)
        for seq, chunk in enumerate(chunks):
            response = client.post(url, json={"seq": seq, "messages": chunk})
            assert response.status_code == 201, response.text
        a, b = map_sessions(client, params, whole, streamed)
        assert a["status"] == b["status"] == "succeeded", (a, b)
        ta = client.get(f"/v1/jobs/{a['id']}/trajectory").json()["poses"]
        tb = client.get(f"/v1/jobs/{b['id']}/trajectory").json()["poses"]
        assert ta == tb and len(ta) == len(drive.ground_truth)
    # the same chunks with the start angles dropped map differently: the offsets reached the engine
    plain = [[{k: v for k, v in m.items() if k != "angle_offset_rad"} for m in chunk] for chunk in chunks]
    dropped = drive_log_from_messages(calibration_from_log(loaded), [m for chunk in plain for m in chunk])
    kept = drive_log_from_messages(calibration_from_log(loaded), messages)
    assert dropped.scans.angle_offset_rad is None
    np.testing.assert_array_equal(kept.scans.angle_offset_rad, loaded.scans.angle_offset_rad)
