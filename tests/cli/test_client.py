"""lidarmap.client and ``lidarmap submit`` against a real running service: uvicorn in its own process
on 127.0.0.1, a free port, its own data folder."""

from __future__ import annotations

import io
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from PIL import Image
from typer.testing import CliRunner

from api_schemas.jobs import JobCreate, JobStatus
from bench.serve_process import free_port, serving
from lidarmap.cli import app
from lidarmap.client import ApiError, LidarmapClient

ROOT = Path(__file__).resolve().parents[2]
ROOM_JOB = "viewer_job_functions:synthetic_room"  # every product of a known room, no SLAM (fast)


def start_service(data_dir: Path, job_function: str | None) -> Iterator[str]:
    port = free_port()
    path = [str(ROOT), str(ROOT / "tests"), str(ROOT / "tests" / "service")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path)}
    args = [sys.executable, str(ROOT / "tests" / "service" / "live_server.py"), str(data_dir), str(port)]
    with serving(args + ([job_function] if job_function else []), env, port, quiet=False):
        yield f"http://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def room_service(tmp_path_factory) -> Iterator[str]:
    yield from start_service(tmp_path_factory.mktemp("room-service"), ROOM_JOB)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory) -> Path:
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=20.0)
    return write_simulated(drive, "carmen", tmp_path_factory.mktemp("sim"))


def test_client_uploads_starts_waits_and_downloads(room_service: str, small_log: Path, tmp_path: Path) -> None:
    with LidarmapClient(room_service) as api:
        session = api.create_session("client test")
        uploaded = api.upload_log(session.id, small_log)
        assert uploaded.summary.format == "carmen" and uploaded.size_bytes == small_log.stat().st_size
        job = api.start_job(session.id, JobCreate(particles=6, seed=20))  # the room job: 6 steps of 20 ms
        assert job.status in (JobStatus.QUEUED, JobStatus.RUNNING) and job.config["particles"] == 6
        seen: list[tuple[str, int]] = []
        done = api.wait(job.id, on_progress=lambda j: seen.append((j.status.value, j.scans_done)), poll_s=0.01)
        assert done.status is JobStatus.SUCCEEDED and done.scans_done == 6
        assert seen[-1] == ("succeeded", 6) and [n for _, n in seen] == sorted(n for _, n in seen)

        files = api.download_products(job.id, tmp_path / "products")
        assert set(files) == {name for name in done.products if not name.startswith("tiles/")}
        assert {"occupancy.png", "trajectory.json", "run.json", "map.yaml"} <= set(files)
        for name, path in files.items():
            assert path.read_bytes() == httpx.get(f"{room_service}/v1/jobs/{job.id}/{name}").content, name
        assert not list((tmp_path / "products").glob("*.part"))

        trajectory = api.trajectory(job.id)
        assert trajectory.count == 6 and trajectory.poses[0].x_m == pytest.approx(1.5)
        scheme = api.tile_scheme(job.id)
        tile = Image.open(io.BytesIO(api.tile(job.id, scheme.min_zoom, 0, 0)))
        assert tile.size == (256, 256)

        with pytest.raises(ApiError) as missing:
            api.job("no-such-job")
        assert missing.value.status == 404 and "no-such-job" in missing.value.message
        with pytest.raises(ApiError) as bad_log:
            api.start_job(session.id, JobCreate(log_id="not-an-upload"))
        assert bad_log.value.status == 404 and bad_log.value.detail == {"field": "log_id"}


def test_submit_maps_a_log_on_the_service_and_downloads_every_product(room_service: str, small_log: Path,
                                                                       tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "out"
    result = runner.invoke(app, ["submit", str(small_log), "--server", room_service, "--out", str(out),
                                 "--particles", "3", "--seed", "1"])
    assert result.exit_code == 0, result.output
    job_id = result.stdout.strip().splitlines()[-1].split()[1].rstrip(":")
    job = httpx.get(f"{room_service}/v1/jobs/{job_id}", params={"include": "config"}).json()
    assert job["status"] == "succeeded" and job["config"]["particles"] == 3
    listed = {name for name in job["products"] if not name.startswith("tiles/")}
    assert {p.name for p in out.iterdir()} == listed
    assert (out / "run.json").read_bytes() == httpx.get(f"{room_service}/v1/jobs/{job_id}/run.json").content

    again = runner.invoke(app, ["submit", str(small_log), "--server", room_service, "--out", str(out)])
    assert again.exit_code == 2 and again.stderr.strip().splitlines() == [
        f"error: {out}: output folder exists and is not empty (--force writes into it, replacing the products it "
        "holds)"]
    bad = runner.invoke(app, ["submit", str(small_log), "--server", room_service, "--out", str(tmp_path / "o2"),
                              "--particles", "0"])
    assert bad.exit_code == 2 and bad.stderr.strip().splitlines() == [
        "error: job settings: bad config: particles: Input should be greater than or equal to 1"]
    assert not (tmp_path / "o2").exists()
    # a log the service refuses: the line it names is in the one line printed (the API's detail.location)
    broken = tmp_path / "broken.clf"
    broken.write_text(small_log.read_text() + "FLASER 4 1.0 2.0\n")
    lines = len(broken.read_text().splitlines())
    refused = runner.invoke(app, ["submit", str(broken), "--server", room_service, "--out", str(tmp_path / "o4")])
    assert refused.exit_code == 2 and len(refused.stderr.strip().splitlines()) == 1, refused.output
    assert f"line {lines}" in refused.stderr and "HTTP 422" in refused.stderr, refused.stderr
    unreachable = runner.invoke(app, ["submit", str(small_log), "--server", f"http://127.0.0.1:{free_port()}",
                                      "--out", str(tmp_path / "o3")])
    assert unreachable.exit_code == 2 and unreachable.stderr.startswith("error: http://127.0.0.1:")


@pytest.mark.slow
def test_submit_with_the_real_engine(small_log: Path, tmp_path: Path) -> None:
    """The same through the real mapping job: the downloaded trajectory has one pose per scan."""
    from slam_engine.products import read_trajectory

    for url in start_service(tmp_path / "data", None):
        out = tmp_path / "out"
        result = CliRunner().invoke(app, ["submit", str(small_log), "--server", url, "--out", str(out),
                                          "--particles", "3", "--resolution", "0.1", "--timeout", "600"])
        assert result.exit_code == 0, result.output
        assert len(read_trajectory(out / "trajectory.json")) == 100  # the simulated log's scans
        assert {"occupancy.png", "occupancy_trajectory.png", "map.pgm", "run.json"} <= {p.name for p in out.iterdir()}


@pytest.mark.slow
def test_the_client_reads_what_changed_since_a_saved_map(tmp_path: Path) -> None:
    """The simulated office mapped on a real service, a drive there days later (a desk moved, a pillar
    gone, a door closed, a partition put up) localised in that map: the client reads the change map."""
    from slam_engine.simulation import simulate, write_simulated

    before = write_simulated(simulate("office", seed=0, cameras=False), "carmen", tmp_path / "before")
    after = write_simulated(simulate("office-changed", seed=1, cameras=False), "carmen", tmp_path / "after")
    for url in start_service(tmp_path / "data", None):
        with LidarmapClient(url) as api:
            session = api.create_session("changes")
            api.upload_log(session.id, before)
            mapped = api.wait(api.start_job(session.id, JobCreate(particles=10)).id, timeout_s=600)
            assert mapped.status is JobStatus.SUCCEEDED, mapped
            later = api.upload_log(session.id, after)
            job = api.start_job(session.id, JobCreate(log_id=later.id, mode="localize", map_job_id=mapped.id))
            done = api.wait(job.id, timeout_s=600)
            assert done.status is JobStatus.SUCCEEDED, done
            assert {"changes.png", "changes.geojson"} <= set(done.products)

            changes = api.changes(job.id)
            kinds = [f["properties"]["kind"] for f in changes["features"]]
            assert kinds.count("removed") == 2 and kinds.count("added") >= 3, changes  # desk, pillar; desk, door, wall
            run = httpx.get(f"{url}/v1/jobs/{job.id}/run.json").json()
            assert sum(f["properties"]["area_m2"] for f in changes["features"]) == pytest.approx(
                run["changes"]["added_m2"] + run["changes"]["removed_m2"], abs=0.01)
            files = api.download_products(job.id, tmp_path / "products")
            assert Image.open(files["changes.png"]).size == Image.open(files["localization.png"]).size


def _follow(url: str, job_id: str, reports: list, enough: int, seen) -> None:
    """Collect a live localisation's reports into ``reports``; ``seen`` set once there are ``enough``."""
    with LidarmapClient(url) as reader:
        for report in reader.follow_poses(job_id):
            reports.append(report)
            if len(reports) >= enough:
                seen.set()


@pytest.mark.slow
def test_the_client_follows_a_live_localisation_while_it_streams(tmp_path: Path) -> None:
    """A real service: the simulated office mapped, then driven again and sent chunk by chunk into a live
    localisation; the client reads each scan's pose while the drive is still being sent."""
    import threading

    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log
    from slam_engine.simulation import simulate, write_simulated

    before = write_simulated(simulate("office", seed=0, cameras=False), "carmen", tmp_path / "before")
    later = load_log(write_simulated(simulate("office", seed=1, cameras=False), "carmen", tmp_path / "later"))
    messages = messages_of_log(later)
    chunks = [messages[i:i + 40] for i in range(0, len(messages), 40)]
    half = len(chunks) // 2
    first_half_scans = sum(m["type"] == "scan" for chunk in chunks[:half] for m in chunk)
    for url in start_service(tmp_path / "data", None):
        with LidarmapClient(url) as api:
            session = api.create_session("live", calibration=calibration_from_log(later))
            api.upload_log(session.id, before)
            mapped = api.wait(api.start_job(session.id, JobCreate(particles=10)).id, timeout_s=600)
            assert mapped.status is JobStatus.SUCCEEDED, mapped
            job = api.start_job(session.id, JobCreate(live=True, mode="localize", map_job_id=mapped.id))
            reports: list[dict] = []
            first_half_seen = threading.Event()

            follower = threading.Thread(target=_follow, args=(url, job.id, reports, first_half_scans - 1,
                                                              first_half_seen))
            follower.start()
            for seq, chunk in enumerate(chunks[:half]):
                api.send_chunk(session.id, seq, chunk)
            # the first half's poses come while the rest of the drive is not sent yet
            assert first_half_seen.wait(timeout=120), len(reports)
            assert api.job(job.id).status is JobStatus.RUNNING
            for seq, chunk in enumerate(chunks[half:], start=half):
                api.send_chunk(session.id, seq, chunk)
            api.finish_stream(session.id)
            follower.join(timeout=180)
            assert not follower.is_alive()
            assert [r["scan"] for r in reports] == list(range(len(later.scans)))
            states = [r["state"] for r in reports]
            first = states.index("found")  # after a search on the scans so far (sent faster than real time here)
            assert set(states[:first]) == {"searching"}
            assert states[first:].count("found") >= 0.95 * (len(states) - first)
            assert api.wait(job.id, timeout_s=60).status is JobStatus.SUCCEEDED

            # the same from the command line: the log sent as a robot streams it, each pose printed as it comes
            out = tmp_path / "live"
            result = CliRunner().invoke(app, ["submit", str(tmp_path / "later"), "--server", url, "--out", str(out),
                                              "--live", "--mode", "localize", "--map-job", mapped.id, "--rate", "0"])
            assert result.exit_code == 0, result.output
            assert ": localising scans\n" in result.stderr  # the job said it is ready (stderr), then its poses
            printed = [line for line in result.stdout.splitlines() if line.startswith("scan ")]
            assert printed[0].startswith("scan 0 ") and ": searching, confidence 0.00" in printed[0]
            assert any(": found at x " in line for line in printed)
            assert {"poses.jsonl", "trajectory.json", "run.json"} <= {p.name for p in out.iterdir()}
            refused = CliRunner().invoke(app, ["submit", str(tmp_path / "later"), "--server", url, "--out",
                                               str(tmp_path / "no"), "--live", "--mode", "localize"])
            assert refused.exit_code == 2 and "name it as 'map_job_id'" in refused.stderr
