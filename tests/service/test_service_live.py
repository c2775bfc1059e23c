"""Live jobs: a job that maps a session's stream as its chunks arrive (service/jobs/live.py).

With the real engine over a simulated drive: the job waits at a gap, its live map and trajectory
grow as chunks are posted, the stream's end makes it finish, and its products equal those of a
regular job over the same chunks. Then the rules: one live job per session, the stream's end
(idempotent, nothing beyond it), cancel, a killed worker, and the idle timeout.
"""

from __future__ import annotations

import io
import json
import os
import signal
import time

import numpy as np
from PIL import Image
from service_helpers import CALIBRATION, assert_error, new_session, service_client, wait_for

from service.storage.stream_log import calibration_from_log, messages_of_log

PARAMS = {"particles": 5, "seed": 7, "resolution_m": 0.1, "snapshot_every_scans": 10}


def scans_in(chunks: list[list[dict]]) -> int:
    return sum(m["type"] == "scan" for chunk in chunks for m in chunk)


def free_pixels(png: bytes) -> int:
    """Cells of the map image seen as free (white)."""
    return int((np.asarray(Image.open(io.BytesIO(png))) > 230).sum())


def simulated_chunks(tmp_path) -> tuple[dict, list[list[dict]]]:
    from slam_engine.formats import load_log
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=20.0)
    loaded = load_log(write_simulated(drive, "carmen", tmp_path / "sim"))
    messages = messages_of_log(loaded)
    return calibration_from_log(loaded), [messages[i:i + 60] for i in range(0, len(messages), 60)]


def test_live_job_maps_chunks_as_they_arrive_and_equals_a_regular_job(tmp_path) -> None:
    calibration, chunks = simulated_chunks(tmp_path)
    n = len(chunks)
    assert n >= 6 and scans_in(chunks) == 100
    with service_client(tmp_path / "data") as client:
        sid = new_session(client, name="live", calibration=calibration)
        url = f"/v1/sessions/{sid}/chunks"
        created = client.post(f"/v1/sessions/{sid}/jobs", json={**PARAMS, "live": True})
        assert created.status_code == 202, created.text
        job = created.json()
        assert job["source"] == "stream" and job["config"]["live"] is True and job["config"]["idle_timeout_s"] == 600
        assert job["progress"] is None and job["scans_total"] is None
        wait_for(client, job["id"], {"running"})

        def scans_done(expected: int) -> dict:
            return wait_for(client, job["id"], {"running"}, timeout_s=60,
                            condition=lambda j: j["scans_done"] == expected and "occupancy.png" in j["products"])

        # chunk 2 overtakes chunk 1: the job maps chunk 0, then waits at the gap
        assert client.post(url, json={"seq": 0, "messages": chunks[0]}).status_code == 201
        first = scans_done(scans_in(chunks[:1]))
        assert first["progress"] is None and first["scans_total"] is None and first["eta_s"] is None
        assert client.post(url, json={"seq": 2, "messages": chunks[2]}).json()["stream"]["missing_seqs"] == [1]
        time.sleep(1.0)
        assert client.get(f"/v1/jobs/{job['id']}").json()["scans_done"] == scans_in(chunks[:1])
        assert client.post(url, json={"seq": 1, "messages": chunks[1]}).status_code == 201
        scans_done(scans_in(chunks[:3]))
        early_trajectory = client.get(f"/v1/jobs/{job['id']}/trajectory").json()
        early_png = client.get(f"/v1/jobs/{job['id']}/occupancy.png").content
        assert scans_in(chunks[:3]) - 1 <= early_trajectory["count"] <= scans_in(chunks[:3])

        # the rest: the map so far grows; without the stream's end the job keeps waiting
        for seq in range(3, n):
            assert client.post(url, json={"seq": seq, "messages": chunks[seq]}).status_code == 201
        caught_up = scans_done(100)
        assert caught_up["status"] == "running" and caught_up["progress"] is None
        # the live trajectory file is written after the step that counts the scan: wait for it (bounded)
        deadline = time.monotonic() + 30.0
        late_trajectory = client.get(f"/v1/jobs/{job['id']}/trajectory").json()
        while late_trajectory["count"] < 99 and time.monotonic() < deadline:
            time.sleep(0.1)
            late_trajectory = client.get(f"/v1/jobs/{job['id']}/trajectory").json()
        assert late_trajectory["count"] >= 99 > early_trajectory["count"]
        late_png = client.get(f"/v1/jobs/{job['id']}/occupancy.png").content
        assert free_pixels(late_png) > free_pixels(early_png) > 0
        tile = client.get(f"/v1/jobs/{job['id']}/tiles/occupancy/0/0/0.png")
        assert tile.status_code == 200 and Image.open(io.BytesIO(tile.content)).size == (256, 256)

        finished = client.post(f"{url}/finish", json={})
        assert finished.status_code == 200, finished.text
        assert finished.json()["finished"] is True and finished.json()["last_seq"] == n - 1
        live = wait_for(client, job["id"], timeout_s=60)
        assert live["status"] == "succeeded", live
        assert live["scans_done"] == live["scans_total"] == 100 and live["progress"] == 1.0
        assert live["input"]["ended"] == "finished" and live["input"]["chunks_used"] == n
        assert live["input"]["messages"] == sum(len(c) for c in chunks)
        err = assert_error(client.post(url, json={"seq": n, "messages": chunks[-1]}), 409, "conflict")
        assert "finished at seq" in err["message"] and err["detail"] == {"seq": n, "last_seq": n - 1}

        # a regular job over the same chunks, same seed: the same trajectory and map, bit for bit
        whole = new_session(client, name="whole", calibration=calibration)
        for seq, chunk in enumerate(chunks):
            assert client.post(f"/v1/sessions/{whole}/chunks", json={"seq": seq, "messages": chunk}).status_code == 201
        regular = wait_for(client, client.post(f"/v1/sessions/{whole}/jobs", json=PARAMS).json()["id"], timeout_s=60)
        assert regular["status"] == "succeeded", regular
        assert set(live["products"]) == set(regular["products"])
        assert {"trajectory.json", "occupancy.png", "occupancy.tif", "map.yaml", "map.pgm", "run.json",
                "animation.gif"} <= set(live["products"])
        a, b = (client.get(f"/v1/jobs/{j['id']}/trajectory").json()["poses"] for j in (live, regular))
        assert a == b and len(a) == 100
        for product in ("occupancy.png", "map.pgm", "dead_reckoning.json"):
            assert client.get(f"/v1/jobs/{live['id']}/{product}").content == \
                client.get(f"/v1/jobs/{regular['id']}/{product}").content, product
        run_live, run_regular = (client.get(f"/v1/jobs/{j['id']}/run").json() for j in (live, regular))
        assert run_live["config"] == run_regular["config"] and run_live["warnings"] == run_regular["warnings"]


def test_live_map_never_goes_back_to_an_older_snapshot(tmp_path) -> None:
    """A live job hands over the filter's periodic snapshots (every snapshot_every_scans) and, when it
    has caught up, the map as it stands: the next scan's periodic snapshot is older and must not
    replace it (nor cost a write)."""
    from service.jobs.outputs import LiveMap
    from slam_engine.model.result import MapSnapshot, OccupancyGrid, Trajectory

    def snapshot(scans: int) -> MapSnapshot:
        t_s = np.arange(scans, dtype=np.float64) * 0.1
        trajectory = Trajectory(t_s, np.column_stack([t_s, np.zeros(scans), np.zeros(scans)]))
        return MapSnapshot(scan_index=scans - 1, t_s=float(t_s[-1]), trajectory=trajectory,
                           grid=OccupancyGrid(np.zeros((4, 4), np.float32), 0.25, 0.0, 0.0))

    live_map = LiveMap(tmp_path / "live")
    count = lambda: len(json.loads((tmp_path / "live" / "trajectory.json").read_text())["poses"])  # noqa: E731
    assert live_map.update(None) is False
    assert live_map.update(snapshot(50)) is True and count() == 50  # periodic
    assert live_map.update(snapshot(63)) is True and count() == 63  # caught up
    assert live_map.update(snapshot(50)) is False and count() == 63  # the periodic one again: older
    assert live_map.update(snapshot(63)) is False
    assert live_map.update(snapshot(100)) is True and count() == 100


def tiny_chunk(seq: int, scans: int = 3) -> dict:
    """Odometry along x and 2-beam scans (CALIBRATION's lidar), 0.1 s apart, starting at t = seq [s]."""
    messages = []
    for i in range(scans):
        t = seq + 0.1 * i
        messages.append({"type": "odometry", "t_s": t, "x_m": t, "y_m": 0.0, "theta_rad": 0.0})
        messages.append({"type": "scan", "t_s": t, "ranges_m": [2.0, 3.0]})
    return {"seq": seq, "messages": messages}


def test_live_job_rules_cancel_killed_worker_and_idle_timeout(tmp_path) -> None:
    small = {"particles": 2, "seed": 1, "resolution_m": 0.1, "snapshot_every_scans": 1}
    with service_client(tmp_path) as client:
        runner = client.app.state.runner
        sid = new_session(client, calibration=CALIBRATION)
        jobs_url, chunks_url = f"/v1/sessions/{sid}/jobs", f"/v1/sessions/{sid}/chunks"

        # what a live job needs, and its bounds
        assert "calibration" in assert_error(client.post(f"/v1/sessions/{new_session(client)}/jobs",
                                                         json={"live": True}), 409)["message"]
        no_lidar = new_session(client, calibration={"vehicle": CALIBRATION["vehicle"]})
        assert "'lidar'" in assert_error(client.post(f"/v1/sessions/{no_lidar}/jobs", json={"live": True}),
                                         409)["message"]
        for bad in ({"live": True, "source": "log"}, {"live": True, "log_id": "x"}, {"live": True, "idle_timeout_s": 0},
                    {"live": True, "idle_timeout_s": 86_401}, {"live": "soon"}):
            assert_error(client.post(jobs_url, json=bad), 422, "validation_error")

        # one live job per session, even on a stream with no chunk yet; cancel stops it within a second
        first = client.post(jobs_url, json={**small, "live": True})
        assert first.status_code == 202, first.text
        err = assert_error(client.post(jobs_url, json={**small, "live": True}), 409, "conflict")
        assert err["detail"] == {"job_id": first.json()["id"]} and "one live job per session" in err["message"]
        wait_for(client, first.json()["id"], {"running"})
        time.sleep(0.5)  # waiting for chunk 0
        assert client.delete(f"/v1/jobs/{first.json()['id']}").status_code == 202
        cancelled = wait_for(client, first.json()["id"], timeout_s=60)
        # its own cancel check stopped it (a worker terminated after the grace period says "(worker stopped)")
        assert cancelled["status"] == "cancelled" and cancelled["error"] == "cancelled by request"

        # a worker killed under a live job fails it with the reason; the session may start another
        second = client.post(jobs_url, json={**small, "live": True}).json()
        wait_for(client, second["id"], {"running"}, timeout_s=30)
        os.kill(runner.worker_pid(second["id"]), signal.SIGKILL)
        dead = wait_for(client, second["id"], timeout_s=10)
        assert dead["status"] == "failed" and dead["error"] == "worker process died (killed by SIGKILL)"

        # idle with nothing mapped: failed, with the reason
        idle = client.post(jobs_url, json={**small, "live": True, "idle_timeout_s": 1}).json()
        failed = wait_for(client, idle["id"], timeout_s=60)
        assert failed["status"] == "failed"
        assert failed["error"] == "live stream idle: no chunk arrived within idle_timeout_s (1 s), nothing to map"
        assert failed["started_at"] and 1.0 <= _seconds(failed["finished_at"]) - _seconds(failed["started_at"]) < 5

        # the stream's end: checked against what arrived, idempotent, nothing beyond it
        assert "no chunks" in assert_error(client.post(f"{chunks_url}/finish"), 409)["message"]
        for seq in (0, 2):
            assert client.post(chunks_url, json=tiny_chunk(seq)).status_code == 201
        assert "beyond last_seq 1" in assert_error(client.post(f"{chunks_url}/finish", json={"last_seq": 1}),
                                                   409)["message"]
        ended = client.post(f"{chunks_url}/finish", json={"last_seq": 3})
        assert ended.status_code == 200
        assert ended.json() == {"received": 2, "contiguous_through": 0, "next_expected_seq": 1, "missing_seqs": [1],
                                "messages": 6, "finished": True, "last_seq": 3}
        assert client.post(f"{chunks_url}/finish").json()["last_seq"] == 3  # again: same end
        assert "already finished at seq 3" in assert_error(client.post(f"{chunks_url}/finish", json={"last_seq": 4}),
                                                           409)["message"]
        assert_error(client.post(chunks_url, json=tiny_chunk(4)), 409, "conflict")
        assert client.post(chunks_url, json=tiny_chunk(0)).json()["duplicate"] is True  # retries still answered
        assert client.post(chunks_url, json=tiny_chunk(3)).status_code == 201  # a chunk up to the end is welcome

        # idle at the gap (chunk 1 never comes): the job ends with the products of chunk 0 and says why
        job = client.post(jobs_url, json={**small, "live": True, "idle_timeout_s": 1}).json()
        done = wait_for(client, job["id"], timeout_s=60)
        assert done["status"] == "succeeded", done
        assert done["input"]["ended"] == "idle_timeout" and done["input"]["chunks_used"] == 1
        assert done["input"]["missing_seqs_after"] == [1] and done["input"]["last_seq"] == 3
        assert done["scans_done"] == done["scans_total"] == 3
        assert client.get(f"/v1/jobs/{job['id']}/trajectory").json()["count"] == 3
        assert {"occupancy.png", "map.yaml", "run.json"} <= set(done["products"])
        warnings = client.get(f"/v1/jobs/{job['id']}/run").json()["warnings"]
        assert any("no new chunk for idle_timeout_s (1 s): mapped chunks 0..0; chunk 1 never arrived" in w
                   for w in warnings), warnings
        # the finished job frees the session for another live job
        again = client.post(jobs_url, json={**small, "live": True, "idle_timeout_s": 1})
        assert again.status_code == 202
        assert wait_for(client, again.json()["id"], timeout_s=60)["status"] == "succeeded"


def _seconds(iso: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(iso).timestamp()
