"""A live localisation through the API: the simulated office mapped from an upload, then driven again and
streamed chunk by chunk into a live job of mode 'localize'; its poses read as they are made, by polling
and as server-sent events, then its products."""

from __future__ import annotations

import json
import threading
from typing import Any

import numpy as np
import pytest
from service_helpers import assert_error, new_session, service_client, wait_for

from service.storage.stream_log import calibration_from_log, messages_of_log
from slam_engine.evaluation.metrics import align_rigid_2d
from slam_engine.formats import load_log
from slam_engine.simulation import simulate, write_simulated

pytestmark = pytest.mark.slow


def _sse(lines) -> list[dict]:
    """Server-sent events from an iterator of lines: [{"event", "id", "data"}]."""
    events, current = [], {}
    for line in lines:
        if not line:
            if current:
                events.append(current)
                if current.get("event") == "end":
                    return events
            current = {}
        elif not line.startswith(":"):
            field, _, value = line.partition(": ")
            current[field] = json.loads(value) if field == "data" else value
    return events


def test_a_live_localisation_reports_each_scan_as_it_arrives(tmp_path) -> None:
    before = simulate("office", seed=0, cameras=False)
    later = simulate("office", seed=1, cameras=False)
    with service_client(tmp_path / "data", workers=2) as client:
        sid, map_job, chunks, streamed = _map_and_stream(client, tmp_path, before, later)

        jobs = f"/v1/sessions/{sid}/jobs"
        assert "name it as 'map_job_id'" in assert_error(client.post(jobs, json={"live": True, "mode": "localize"}),
                                                         422)["message"]
        assert_error(client.post(jobs, json={"live": True, "mode": "extend", "map_job_id": map_job}), 422)
        assert_error(client.get(f"/v1/jobs/{map_job}/poses"), 404)
        live = client.post(jobs, json={"live": True, "mode": "localize", "map_job_id": map_job,
                                       "idle_timeout_s": 60}).json()
        assert live["live"] and live["mode"] == "localize"

        events: list[dict] = []

        def follow() -> None:  # server-sent events, read while the chunks are posted
            with client.stream("GET", f"/v1/jobs/{live['id']}/poses", params={"stream": "true"}) as response:
                assert response.headers["content-type"].startswith("text/event-stream")
                events.extend(_sse(response.iter_lines()))

        follower = threading.Thread(target=follow)
        follower.start()
        half = len(chunks) // 2
        for seq, chunk in enumerate(chunks[:half]):
            assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunk}).status_code == 201
        posted = sum(m["type"] == "scan" for chunk in chunks[:half] for m in chunk)
        so_far = wait_for(client, live["id"], {"running"}, timeout_s=120,
                          condition=lambda job: job["scans_done"] >= posted - 2)
        assert so_far["status"] == "running"
        polled = client.get(f"/v1/jobs/{live['id']}/poses").json()
        assert polled["status"] == "running" and polled["count"] >= posted - 2
        for seq, chunk in enumerate(chunks[half:], start=half):
            assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunk}).status_code == 201
        client.post(f"/v1/sessions/{sid}/chunks/finish", json={"last_seq": len(chunks) - 1})
        follower.join(timeout=180)
        assert not follower.is_alive()
        finished = wait_for(client, live["id"], timeout_s=60)
        assert finished["status"] == "succeeded", finished

        # every scan once, in order (TestClient hands a streamed body over whole: the events' timing is
        # tested against a real server, tests/cli/test_client.py)
        poses = [e["data"] for e in events if e.get("event") == "pose"]
        assert events[-1] == {"event": "end", "data": {"status": "succeeded"}}
        assert [p["scan"] for p in poses] == list(range(len(streamed.scans)))
        assert [int(e["id"]) for e in events if e.get("event") == "pose"] == [p["scan"] for p in poses]
        states = [p["state"] for p in poses]
        first = states.index("found")
        assert set(states[:first]) == {"searching"} and all(p["pose"] is None for p in poses[:first])
        assert states[first:].count("found") >= 0.95 * (len(states) - first)
        assert all(p["latency_s"] >= 0 and p["seq"] is not None for p in poses[:-5])
        # the found poses where the simulator says the robot was (the map's frame carried onto the world)
        trajectory = client.get(f"/v1/jobs/{map_job}/trajectory").json()["poses"]
        t = np.array([p["t_s"] for p in trajectory])
        rotation, translation = align_rigid_2d(np.array([[p["x_m"], p["y_m"]] for p in trajectory]),
                                               before.pose_at(t)[:, :2])
        found = [p for p in poses if p["state"] == "found"]
        placed = np.array([p["pose"][:2] for p in found]) @ rotation.T + translation
        truth = later.pose_at(np.array([p["t_s"] for p in found]))[:, :2]
        assert np.hypot(*(placed - truth).T).max() < 0.1

        # resumed after a scan (as an EventSource does with Last-Event-ID), and the products
        with client.stream("GET", f"/v1/jobs/{live['id']}/poses", headers={"Accept": "text/event-stream",
                                                                          "Last-Event-ID": "400"}) as response:
            resumed = _sse(response.iter_lines())
        assert [int(e["id"]) for e in resumed if e.get("event") == "pose"] == list(range(401, len(poses)))
        assert {"poses.jsonl", "trajectory.json", "confidence.json", "run.json", "localization.png", "changes.png",
                "changes.geojson"} <= set(finished["products"])
        report = client.get(f"/v1/jobs/{live['id']}/run.json").json()
        assert report["changes"]["changed_share"] < 0.005  # the same office: nothing changed
        run = report["localization"]
        assert run["localised"] and run["states"]["found"] == states.count("found")
        assert run["latency_s"]["count"] > 0 and run["first_found_travel_m"] > 0  # later: posted faster than real time
        lines = client.get(f"/v1/jobs/{live['id']}/poses.jsonl").text.splitlines()
        assert [json.loads(line) for line in lines] == poses


def _map_and_stream(client, tmp_path, before, later) -> tuple[str, str, list[list[dict]], Any]:
    """The simulated drive ``before`` mapped from an upload, and ``later`` as chunks of 40 messages: (session,
    saved map's job, chunks, ``later``'s log as the stream carries it)."""
    mapped_log = write_simulated(before, "carmen", tmp_path / "before")
    streamed = load_log(write_simulated(later, "carmen", tmp_path / "later"))
    messages = messages_of_log(streamed)
    sid = new_session(client, calibration=calibration_from_log(streamed))
    with mapped_log.open("rb") as f:
        client.post(f"/v1/sessions/{sid}/logs", files={"file": (mapped_log.name, f)})
    mapped = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 10}).json()
    done = wait_for(client, mapped["id"], timeout_s=300)
    assert done["status"] == "succeeded", done
    return sid, mapped["id"], [messages[i:i + 40] for i in range(0, len(messages), 40)], streamed


def _short_map_and_stream(client, tmp_path, map_s: float, drive_s: float) -> tuple[str, str, list[list[dict]]]:
    """The office's first ``map_s`` mapped from an upload, and the office driven again (seed 1, its first
    ``drive_s``) as chunks of 40 messages: (session, saved map's job, chunks)."""
    sid, map_job, chunks, _ = _map_and_stream(client, tmp_path,
                                              simulate("office", seed=0, cameras=False, max_duration_s=map_s),
                                              simulate("office", seed=1, cameras=False, max_duration_s=drive_s))
    return sid, map_job, chunks


def test_a_live_localisation_says_when_it_is_ready_and_counts_latency_from_then(tmp_path) -> None:
    """The map's index held while chunks come: the job runs in stage 'loading the map' meanwhile, keeps the
    chunks, then localises them in stage 'localising scans' with their latency counted from its readiness
    (not from the chunks accepted, which came seconds before)."""
    import time

    with service_client(tmp_path / "data", job_function="service_job_functions:map_index_held",
                        workers=2) as client:
        (tmp_path / "data" / "release").write_text("")  # the mapping job's own index (none) is not held
        sid, map_job, chunks = _short_map_and_stream(client, tmp_path, 30.0, 6.0)
        (tmp_path / "data" / "release").unlink()
        live = client.post(f"/v1/sessions/{sid}/jobs", json={"live": True, "mode": "localize", "map_job_id": map_job,
                                                               "idle_timeout_s": 60}).json()
        loading = wait_for(client, live["id"], {"running"}, timeout_s=60,
                           condition=lambda job: job["stage"] is not None)
        assert loading["stage"] == "loading the map" and loading["scans_done"] == 0
        for seq, chunk in enumerate(chunks):
            assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunk}).status_code == 201
        client.post(f"/v1/sessions/{sid}/chunks/finish", json={"last_seq": len(chunks) - 1})
        posted = time.time()
        time.sleep(2.0)  # the chunks wait for the job to be ready
        still = client.get(f"/v1/jobs/{live['id']}").json()
        assert still["status"] == "running" and still["stage"] == "loading the map" and still["scans_done"] == 0
        held_s = time.time() - posted
        (tmp_path / "data" / "release").write_text("")
        scans = sum(m["type"] == "scan" for chunk in chunks for m in chunk)
        localising = wait_for(client, live["id"], {"running", "succeeded"}, timeout_s=60,
                              condition=lambda job: job["scans_done"] > 0)
        assert localising["stage"] in ("localising scans", None)  # None: already succeeded
        finished = wait_for(client, live["id"], timeout_s=120)
        assert finished["status"] == "succeeded", finished
        poses = client.get(f"/v1/jobs/{live['id']}/poses").json()["poses"]
        latencies = [p["latency_s"] for p in poses if p["seq"] is not None]
        assert len(poses) == scans and len(latencies) >= scans - 5
        # counted from the chunks accepted, every one would be over held_s (2 s): from the job ready, the
        # time the scans took to localise (measured: 0.02-0.04 s)
        assert max(latencies) < held_s


def test_a_placement_the_search_delivers_as_the_stream_ends_is_reported(tmp_path) -> None:
    """A search's placement taken only when the stream has ended (the job function holds it until then): the
    last scan is reported again, found, and the products hold that pose."""
    with service_client(tmp_path / "data", job_function="service_job_functions:placement_held_to_the_end",
                        workers=2) as client:
        sid, map_job, chunks = _short_map_and_stream(client, tmp_path, 30.0, 24.0)
        live = client.post(f"/v1/sessions/{sid}/jobs", json={"live": True, "mode": "localize", "map_job_id": map_job,
                                                               "idle_timeout_s": 60}).json()
        for seq, chunk in enumerate(chunks):
            assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunk}).status_code == 201
        client.post(f"/v1/sessions/{sid}/chunks/finish", json={"last_seq": len(chunks) - 1})
        finished = wait_for(client, live["id"], timeout_s=180)
        assert finished["status"] == "succeeded", finished
        poses = client.get(f"/v1/jobs/{live['id']}/poses").json()["poses"]
        scans = sum(m["type"] == "scan" for chunk in chunks for m in chunk)
        # every scan searching as it came; then the last one again, found, where the search put it
        assert [p["scan"] for p in poses] == [*range(scans), scans - 1]
        assert {p["state"] for p in poses[:-1]} == {"searching"}
        last = poses[-1]
        assert last["state"] == "found" and last["pose"] is not None and last["confidence"] >= 0.5
        assert last["t_s"] == poses[-2]["t_s"] and last["seq"] is None
        assert last["revised"] is True and not any("revised" in p for p in poses[:-1])
        # a client that had the last scan's first report and resumes after it still gets the revision
        assert client.get(f"/v1/jobs/{live['id']}/poses", params={"after": scans - 1}).json()["poses"] == [last]
        events = client.get(f"/v1/jobs/{live['id']}/poses", params={"stream": "true"},
                            headers={"Last-Event-ID": str(scans - 1)}).text
        assert events.count("event: pose") == 1 and '"revised": true' in events and "event: end" in events
        lines = client.get(f"/v1/jobs/{live['id']}/poses.jsonl").text.splitlines()
        assert [json.loads(line) for line in lines] == poses
        run = client.get(f"/v1/jobs/{live['id']}/run.json").json()["localization"]
        assert run["localised"] and run["scans"] == scans
        assert run["states"]["found"] == 1 and run["states"]["searching"] == scans - 1
        assert run["first_found_t_s"] == round(last["t_s"], 3)
        trajectory = client.get(f"/v1/jobs/{live['id']}/trajectory").json()["poses"]
        assert len(trajectory) == 1 and trajectory[0]["t_s"] == pytest.approx(last["t_s"], abs=1e-6)
        assert [trajectory[0]["x_m"], trajectory[0]["y_m"]] == pytest.approx(last["pose"][:2], abs=1e-4)
