"""An interlaced laser's CARMEN log uploaded and mapped through HTTP: accepted (not refused for its
changing start angle) and mapped as well as the same simulated drive without interlacing."""

from __future__ import annotations

import numpy as np
import pytest
from service_helpers import new_session, service_client, wait_for

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
            with open(log_path, "rb") as f:
                upload = client.post(f"/v1/sessions/{sid}/logs", files={"file": (log_path.name, f)})
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
