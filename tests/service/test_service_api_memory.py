"""The API process stays bounded whatever the job produced (issue 41, items 1 and 4): a real
``lidarmap serve`` asked at once for a long trajectory (HEAD and GET) and for cold tiles of a huge grid.
Scaled cases with generous bounds; bench/api_attacks.py runs the full-size ones."""

from __future__ import annotations

import json

import httpx

from bench.api_attacks import (
    cold_tiles,
    concurrently,
    grid_job,
    lidarmap_serve,
    long_trajectory_job,
    measure,
    tile_requests,
    trajectory_requests,
)

MB = 1024**2


def test_concurrent_trajectory_requests_keep_the_api_small(tmp_path) -> None:
    """100 000 poses (an 11 MB file), 8 HEADs and 4 GETs at once. Before: each request built every pose
    as an object and the JSON body (HEAD too, to count it): the API grew by ~1 GB. Now: the file's
    bytes are streamed and HEAD takes the size from the file."""
    data_dir = tmp_path / "data"
    job_id = long_trajectory_job(data_dir, 100_000)
    with lidarmap_serve(data_dir) as (url, process):
        expected = httpx.get(f"{url}/v1/jobs/{job_id}/trajectory", timeout=120)
        assert expected.status_code == 200
        body = expected.json()
        assert body["count"] == len(body["poses"]) == 100_000 and body["kind"] == "slam"
        assert body["poses"][1] == {"t_s": 0.05, "x_m": body["poses"][1]["x_m"], "y_m": body["poses"][1]["y_m"],
                                    "theta_rad": body["poses"][1]["theta_rad"]}
        dead_reckoning = httpx.get(f"{url}/v1/jobs/{job_id}/dead-reckoning", timeout=120)
        head = httpx.head(f"{url}/v1/jobs/{job_id}/dead-reckoning", timeout=120)
        assert head.status_code == 200 and head.content == b""
        assert head.headers["content-length"] == str(len(dead_reckoning.content))
        assert dead_reckoning.json()["poses"] == body["poses"]  # the same poses, written twice
        cost = measure(url, process, lambda: concurrently(
            trajectory_requests(url, job_id, "HEAD", 8) + trajectory_requests(url, job_id, "GET", 4)
            + trajectory_requests(url, job_id, "HEAD", 2, route="dead-reckoning")))
    assert set(cost.statuses) == {200}
    assert cost.rss_peak - cost.rss_before < 120 * MB, (cost.rss_peak - cost.rss_before) / MB
    assert cost.healthz_max_s < 3.0, cost.healthz_max_s


def test_cold_tiles_of_a_huge_grid_keep_the_api_small(tmp_path) -> None:
    """A 6000 x 6000 grid (144 MB), ten cold tiles at once (zoom 0 pools the whole map). Before: each
    request loaded its own copy of the grid and pooled all of it: the API grew by GBs. Now: each tile
    reads its window of one level of the pyramid the job wrote."""
    data_dir = tmp_path / "data"
    job_id = grid_job(data_dir, 6000)
    with lidarmap_serve(data_dir) as (url, process):
        tiles = cold_tiles(url, job_id)
        cost = measure(url, process, lambda: concurrently(tile_requests(url, job_id, tiles)))
        z0 = httpx.get(f"{url}/v1/jobs/{job_id}/tiles/occupancy/0/0/0.png", timeout=60)
    assert set(cost.statuses) == {200}, cost.statuses
    assert z0.headers["content-type"] == "image/png" and len(z0.content) > 500
    assert cost.rss_peak - cost.rss_before < 100 * MB, (cost.rss_peak - cost.rss_before) / MB
    assert cost.healthz_max_s < 3.0, cost.healthz_max_s


def test_a_grid_written_before_pyramids_is_converted_once(tmp_path) -> None:
    """The same grid as a plain .npz (jobs of earlier versions): ten cold tiles at once convert it once
    (read band by band from its mapping; the other requests wait), then read the pyramid."""
    data_dir = tmp_path / "data"
    job_id = grid_job(data_dir, 6000, legacy=True)
    with lidarmap_serve(data_dir) as (url, process):
        tiles = cold_tiles(url, job_id)
        cost = measure(url, process, lambda: concurrently(tile_requests(url, job_id, tiles)))
    assert set(cost.statuses) == {200}, cost.statuses
    assert len(list(data_dir.rglob("grid.pyramid.npz"))) == 1
    assert cost.rss_peak - cost.rss_before < 120 * MB, (cost.rss_peak - cost.rss_before) / MB  # the grid: 144 MB


def test_a_trajectory_file_of_the_first_format_is_still_served(tmp_path) -> None:
    """Version 1 files (pose fields t, x, y, theta) are converted, GET and HEAD agreeing on the length."""
    from service_helpers import service_client

    from bench.api_attacks import stored_job

    def write(job_dir):
        (job_dir / "products").mkdir(parents=True)
        (job_dir / "products" / "trajectory.json").write_text(json.dumps(
            {"format": "lidarmap-trajectory", "version": 1, "poses": [{"t": 0.5, "x": 1.0, "y": 2.0, "theta": 0.1}]}))
        return {"trajectory.json": "products/trajectory.json"}

    job_id = stored_job(tmp_path, write)
    with service_client(tmp_path) as client:
        got = client.get(f"/v1/jobs/{job_id}/trajectory")
        head = client.head(f"/v1/jobs/{job_id}/trajectory")
    assert got.json() == {"job_id": job_id, "kind": "slam", "count": 1,
                          "poses": [{"t_s": 0.5, "x_m": 1.0, "y_m": 2.0, "theta_rad": 0.1}]}
    assert head.status_code == 200 and head.headers["content-length"] == str(len(got.content))
