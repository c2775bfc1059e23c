"""API keys: every route but /healthz needs one; a key sees only its own sessions and jobs."""

from __future__ import annotations

from service_helpers import assert_error, service_client


def test_api_keys_guard_and_scope(tmp_path) -> None:
    with service_client(tmp_path, api_keys="alpha-key, beta-key") as client:
        assert client.get("/healthz").status_code == 200
        assert_error(client.get("/readyz"), 401, "unauthorized")
        assert_error(client.get("/v1/sessions"), 401, "unauthorized")
        assert_error(client.post("/v1/sessions", json={"name": "x"}), 401)
        assert_error(client.get("/v1/jobs"), 401)
        assert_error(client.get("/v1/formats"), 401)
        assert_error(client.get("/v1/sessions", headers={"X-API-Key": "wrong"}), 401)

        alpha = {"X-API-Key": "alpha-key"}
        beta = {"Authorization": "Bearer beta-key"}
        assert client.get("/readyz", headers=alpha).status_code == 200
        created = client.post("/v1/sessions", json={"name": "alpha's"}, headers=alpha)
        assert created.status_code == 201
        session_id = created.json()["id"]
        assert client.get("/v1/sessions", headers=alpha).json()["count"] == 1
        assert client.get("/v1/sessions", headers=beta).json()["count"] == 0
        assert_error(client.get(f"/v1/sessions/{session_id}", headers=beta), 404)
        assert_error(client.delete(f"/v1/sessions/{session_id}", headers=beta), 404)
        assert client.get(f"/v1/sessions/{session_id}", headers=alpha).status_code == 200
