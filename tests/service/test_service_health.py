"""The service answers its health check and serves its OpenAPI docs."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.settings import Settings


def test_healthz_and_docs(tmp_path) -> None:
    client = TestClient(create_app(Settings(data_dir=tmp_path)))
    response = client.get("/healthz")
    assert response.status_code == 200
    assert response.json()["status"] == "ok"
    assert client.get("/docs").status_code == 200
    assert "/healthz" in client.get("/openapi.json").json()["paths"]


def test_readyz_is_not_ready_while_a_worker_is_missing(tmp_path, monkeypatch) -> None:
    """Issue 64 item 1: /readyz said ready with 1 of 2 workers alive (the other could not be started
    again on a full disk) while jobs waited. Every worker the runner keeps must be alive; a Celery
    runner counts the workers that answer."""
    from service_helpers import service_client

    from service.runners.base import RunnerHealth

    assert RunnerHealth("local", 2, 2, 0, 0).ready and RunnerHealth("celery", 3, 3, 1, 0).ready
    assert not RunnerHealth("local", 2, 1, 0, 0).ready and not RunnerHealth("celery", 0, 0, 0, 0).ready
    with service_client(tmp_path, workers=2) as client:
        ready = client.get("/readyz")
        assert ready.status_code == 200 and ready.json()["workers"]["workers_alive"] == 2, ready.json()
        runner = client.app.state.runner
        monkeypatch.setattr(runner, "health", lambda: RunnerHealth("local", 2, 1, 0, 3))
        missing = client.get("/readyz")
        assert missing.status_code == 503 and missing.json()["ready"] is False
        assert missing.json()["workers"] == {"runner": "local", "workers_total": 2, "workers_alive": 1, "busy": 0,
                                             "queued": 3}
