"""The API process stays bounded whatever the job produced (issue 41, items 1 and 4): a real
``lidarmap serve`` asked at once for a long trajectory (HEAD and GET) and for cold tiles of a huge grid.
Scaled cases with generous bounds; bench/api_attacks.py runs the full-size ones."""

from __future__ import annotations

import httpx

from bench.api_attacks import concurrently, lidarmap_serve, long_trajectory_job, measure, trajectory_requests

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
