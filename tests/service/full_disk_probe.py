"""Run inside a private mount namespace (``unshare -rm``): the service on a tiny tmpfs that is then
filled, and every write route tried once ("full: ..."); then with 512 kB left, so that the database
still works and big writes fail on the files ("nearly full: ..."); then with room again, what was
stored. Then a job fills the disk as it runs ("job on a full disk": its status, seconds taken, whether
the disk was still full). Prints one JSON object: try -> [status, error code] (and the counts stored).

``python full_disk_probe.py MOUNT_POINT`` (the mount point must exist; it is mounted over here)."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.settings import Settings

TMPFS_BYTES = 8 * 1024**2
ODOMETRY = {"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}
CALIBRATION = {"vehicle": {"kind": "odometry"},
               "lidar": {"num_beams": 2, "angle_min_rad": 0.0, "angle_increment_rad": 0.5,
                         "range_min_m": 0.1, "range_max_m": 20.0}}


def fill(folder: Path, leave_bytes: int = 0) -> None:
    """Write a file until the file system is full, then free ``leave_bytes`` of it."""
    with open(folder / "filler", "wb", buffering=0) as out:
        try:
            while True:
                out.write(b"\0" * 4096)
        except OSError:
            pass
        out.truncate(max(out.tell() - leave_bytes, 0))


def free_bytes(folder: Path) -> int:
    return shutil.disk_usage(folder).free


def outcome(response) -> list:
    try:
        code = response.json().get("error", {}).get("code")
    except ValueError:
        code = None
    return [response.status_code, code]


def main(mount: Path) -> None:
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_BYTES}", "tmpfs", str(mount)], check=True)
    data_dir = mount / "data"
    settings = Settings(data_dir=data_dir, workers=1, min_free_bytes=0, heartbeat_s=1.0, worker_lost_s=10.0)
    results: dict[str, list] = {}
    app = create_app(settings, job_function="service_job_functions:fills_the_disk")
    with TestClient(app, raise_server_exceptions=False) as client:
        sid = client.post("/v1/sessions", json={"name": "before", "calibration": CALIBRATION}).json()["id"]
        assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [ODOMETRY]}).status_code == 201
        fill(mount)
        zipped = io.BytesIO()
        with zipfile.ZipFile(zipped, "w") as archive:
            archive.writestr("log/a.txt", b"x" * 200_000)
        tries = {
            "create session": lambda: client.post("/v1/sessions", json={"name": "full"}),
            "post chunk": lambda: client.post(f"/v1/sessions/{sid}/chunks", json={
                "seq": 1, "messages": [{**ODOMETRY, "t_s": 0.1, "x_m": float(i)} for i in range(2000)]}),
            "finish stream": lambda: client.post(f"/v1/sessions/{sid}/chunks/finish", json={"last_seq": 5}),
            "create job": lambda: client.post(f"/v1/sessions/{sid}/jobs", json={}),
            "upload log": lambda: client.post(f"/v1/sessions/{sid}/logs",
                                              files={"file": ("log.clf", b"# carmen\n" * 300_000)}),
            "upload zip": lambda: client.post(f"/v1/sessions/{sid}/logs",
                                              files={"file": ("log.zip", zipped.getvalue())}),
            "upload map": lambda: client.post(f"/v1/sessions/{sid}/maps",
                                              files={"file": ("m.npz", b"\0" * 300_000)}),
        }
        for name, attempt in tries.items():
            results[f"full: {name}"] = outcome(attempt())
        results["full: healthz"] = [client.get("/healthz").status_code, None]
        (mount / "filler").unlink()
        fill(mount, leave_bytes=512 * 1024)
        results["nearly full: create session"] = outcome(tries["create session"]())
        results["nearly full: post chunk"] = outcome(client.post(f"/v1/sessions/{sid}/chunks", json={
            "seq": 1, "messages": [{**ODOMETRY, "t_s": 0.1, "x_m": float(i)} for i in range(10_000)]}))
        results["nearly full: upload log"] = outcome(client.post(f"/v1/sessions/{sid}/logs", files={
            "file": ("log.clf", b"# carmen\n" * 300_000)}))
        (mount / "filler").unlink()
        # a session whose log takes room, then a full disk: deleting it frees the room (it answered 507)
        big = client.post("/v1/sessions", json={"name": "big"}).json()["id"]
        odometry_log = "".join(f"ODOM {0.001 * i:.3f} 0 0 0 0 0 {0.01 * i:.2f} h {0.01 * i:.2f}\n"
                               for i in range(60_000))
        stored = client.post(f"/v1/sessions/{big}/logs", files={"file": ("odometry.clf", odometry_log.encode())})
        results["big log stored"] = [stored.status_code, None]
        fill(mount)
        results["delete on a full disk"] = outcome(client.delete(f"/v1/sessions/{big}"))
        results["deleted session"] = [client.get(f"/v1/sessions/{big}").status_code, None]
        (mount / "filler").unlink()
        results["stored afterwards"] = [client.get(f"/v1/sessions/{sid}/logs").json()["count"],
                                        client.get(f"/v1/sessions/{sid}/chunks").json()["received"]]
        # a job that meets a disk filled meanwhile: it ends failed "disk full" while the disk stays full
        job_id = client.post(f"/v1/sessions/{sid}/jobs", json={}).json()["id"]
        started, job = time.monotonic(), {}
        while time.monotonic() - started < 30 and job.get("status") not in ("succeeded", "failed", "cancelled"):
            time.sleep(0.1)
            job = client.get(f"/v1/jobs/{job_id}").json()
        results["job on a full disk"] = [job.get("status"), job.get("error"), round(time.monotonic() - started, 1),
                                         (data_dir / "filler").exists(), free_bytes(mount)]
        (data_dir / "filler").unlink(missing_ok=True)
    print(json.dumps(results))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
