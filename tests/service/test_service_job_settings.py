"""A job's settings are the engine's SlamConfig: any engine setting can be set through the API, with the
engine's own bounds; the shortcut fields override their slam.* counterparts."""

from __future__ import annotations

from service_helpers import assert_error, service_client, streaming_session, wait_for

from service.jobs.settings import JOB_SNAPSHOT_EVERY_SCANS, engine_config
from slam_engine.config import SlamConfig


def test_any_engine_setting_through_the_api_with_the_engines_bounds(tmp_path) -> None:
    with service_client(tmp_path, job_function="service_job_functions:counting") as client:
        sid = streaming_session(client)
        url = f"/v1/sessions/{sid}/jobs"
        body = {"particles": 7, "seed": 1, "slam": {"grid": {"no_return_clear_m": 4.0, "resolution_m": 0.2},
                                                      "matcher": {"search_xy_m": 0.5}, "particles": 99}}
        created = client.post(url, json=body)
        assert created.status_code == 202, created.text
        config = created.json()["config"]
        expected = SlamConfig(particles=7, seed=1, snapshot_every_scans=JOB_SNAPSHOT_EVERY_SCANS,
                              grid={"no_return_clear_m": 4.0, "resolution_m": 0.2}, matcher={"search_xy_m": 0.5})
        assert engine_config(config) == expected  # what the mapping job runs with
        assert (config["particles"], config["resolution_m"], config["live"]) == (7, 0.2, False)
        assert wait_for(client, created.json()["id"])["status"] == "succeeded"  # counting: 7 steps of 1 ms

        plain = client.post(url, json={}).json()["config"]
        assert engine_config(plain) == SlamConfig(snapshot_every_scans=JOB_SNAPSHOT_EVERY_SCANS)
        quiet = client.post(url, json={"slam": {"snapshot_every_scans": 0}}).json()["config"]
        assert engine_config(quiet).snapshot_every_scans == 0

        too_far = assert_error(client.post(url, json={"slam": {"grid": {"no_return_clear_m": 500}}}), 422)
        assert too_far["message"].startswith("body.slam.grid.no_return_clear_m: Input should be less than or equal "
                                             "to 200")
        unknown = assert_error(client.post(url, json={"slam": {"grid": {"no_return": 1}}}), 422)
        assert "slam.grid.no_return" in unknown["message"]
        zero = assert_error(client.post(url, json={"particles": 0}), 422, "config")
        assert zero["message"] == "job settings: bad config: particles: Input should be greater than or equal to 1"
        huge = assert_error(client.post(url, json={"resolution_m": 5.0}), 422, "config")
        assert "grid.resolution_m" in huge["message"]

        schema = client.get("/openapi.json").json()["components"]["schemas"]
        job_body = next(s for name, s in schema.items() if name.startswith("JobSettings"))
        assert job_body["properties"]["slam"]["$ref"].endswith("/SlamConfig")
        assert schema["GridConfig"]["properties"]["no_return_clear_m"]["maximum"] == 200.0


def test_rows_stored_before_slam_settings_still_run() -> None:
    legacy = {"particles": 12, "seed": 3, "resolution_m": 0.1, "max_range_m": 20.0, "linear_update_m": 0.5,
              "angular_update_rad": 0.2, "snapshot_every_scans": 50, "live": False, "idle_timeout_s": 600.0}
    config = engine_config(legacy)
    assert (config.particles, config.seed, config.grid.resolution_m, config.grid.max_range_m) == (12, 3, 0.1, 20.0)
    assert (config.scheduling.linear_update_m, config.scheduling.angular_update_rad) == (0.5, 0.2)
    assert config.snapshot_every_scans == 50 and config.matcher == SlamConfig().matcher
