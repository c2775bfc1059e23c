"""``lidarmap run`` and a service job write the same set of products for the same drive: a user who
moves from one to the other finds every file again (the API also lists them in the job)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from service_helpers import new_session, service_client, wait_for

from slam_engine.simulation import simulate, write_simulated

REPO_ROOT = Path(__file__).resolve().parents[2]
SETTINGS = {"particles": 5, "seed": 1, "resolution_m": 0.1, "snapshot_every_scans": 20}


def test_the_command_line_and_the_api_write_the_same_products(tmp_path: Path) -> None:
    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=20.0)
    log_path = write_simulated(drive, "carmen", tmp_path / "sim")
    out = tmp_path / "cli"
    done = subprocess.run([sys.executable, "-m", "lidarmap.cli", "run", str(log_path), "--out", str(out),
                           "--particles", "5", "--seed", "1", "--resolution-m", "0.1", "--snapshot-every", "20"],
                          capture_output=True, text=True, timeout=300, cwd=REPO_ROOT)
    assert done.returncode == 0, done.stderr
    cli_products = {p.name for p in out.iterdir()}

    with service_client(tmp_path / "data") as client:
        sid = new_session(client)
        with log_path.open("rb") as f:
            assert client.post(f"/v1/sessions/{sid}/logs", files={"file": ("office.clf", f)}).status_code == 201
        job_id = client.post(f"/v1/sessions/{sid}/jobs", json=SETTINGS).json()["id"]
        job = wait_for(client, job_id, timeout_s=120)
        assert job["status"] == "succeeded", job
        api_products = set(job["products"])

    assert "dead_reckoning.tum" in cli_products and "animation.gif" in cli_products
    assert cli_products == api_products
