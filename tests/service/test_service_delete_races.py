"""Deleting a session while its work goes on leaves nothing behind; a start-up sweep removes what a
crash left (issue 18, item 6)."""

from __future__ import annotations

import time
import uuid

from service_helpers import assert_error, new_session, service_client, streaming_session, wait_for

from service.storage.inspection import LogInspector

JOBS = "service_job_functions"


def test_deleting_a_session_stops_its_writing_jobs_first(tmp_path) -> None:
    with service_client(tmp_path, job_function=f"{JOBS}:live_writer", workers=2, cancel_grace_s=0.5) as client:
        sid = streaming_session(client)
        polite = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 1000, "seed": 10}).json()["id"]
        stubborn = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 1000, "seed": 10,
                                                                  "linear_update_m": 1.0}).json()["id"]
        for job_id in (polite, stubborn):
            wait_for(client, job_id, {"running"},
                     condition=lambda job: (tmp_path / "jobs" / job["id"] / "live").is_dir())
        deleted = client.delete(f"/v1/sessions/{sid}")
        assert deleted.status_code == 200 and deleted.json()["jobs_cancelled"] == 2
        time.sleep(0.5)  # the jobs wrote a frame every 10 ms: they would have recreated live/ by now
        assert not any((tmp_path / "jobs").iterdir()), list((tmp_path / "jobs").iterdir())
        assert_error(client.get(f"/v1/jobs/{polite}"), 404)
        # the terminated workers are replaced (after a back-off when they had just started): ready again
        deadline = time.monotonic() + 30.0
        while client.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert client.get("/readyz").status_code == 200


def test_an_upload_into_a_session_deleted_meanwhile_stores_nothing(tmp_path, monkeypatch) -> None:
    inspect = LogInspector.summary
    with service_client(tmp_path) as client:
        sid = new_session(client)

        async def delete_then_inspect(self, *args, **kwargs):
            client.app.state.store.delete_session(sid)  # the DELETE lands while the upload is checked
            return await inspect(self, *args, **kwargs)

        monkeypatch.setattr(LogInspector, "summary", delete_then_inspect)
        log = b"".join(b"ODOM %d 0 0 0 0 0 %d.0 h %d.0\n" % (i, i, i) for i in range(1, 7))
        err = assert_error(client.post(f"/v1/sessions/{sid}/logs", files={"file": ("a.clf", log)}), 404)
        assert "deleted" in err["message"]
        assert not any((tmp_path / "uploads").iterdir()) and not any((tmp_path / "tmp").iterdir())


def test_the_start_up_sweep_removes_folders_nothing_refers_to(tmp_path) -> None:
    with service_client(tmp_path, job_function=f"{JOBS}:counting") as client:
        sid = streaming_session(client)
        job_id = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 1, "seed": 1}).json()["id"]
        wait_for(client, job_id)
    orphans = [tmp_path / sub / str(uuid.uuid4()) for sub in ("jobs", "uploads", "chunks")]
    for folder in orphans:
        (folder / "live").mkdir(parents=True)
    with service_client(tmp_path, job_function=f"{JOBS}:counting") as client:
        assert client.get(f"/v1/jobs/{job_id}").json()["status"] == "succeeded"
        assert (tmp_path / "jobs" / job_id / "run.json").is_file()
        assert not any(folder.exists() for folder in orphans)
        assert (tmp_path / "chunks" / sid).is_dir()
