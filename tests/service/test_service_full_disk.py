"""A full disk is 507 with the JSON error body on every write route, and nothing half-stored (issue 41,
item 7). For real: the service runs on a small tmpfs in a private mount namespace (``unshare -rm``,
no root needed where user namespaces are allowed), which is then filled."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from ci_skips import skip_or_fail_on_ci

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


def _can_mount_privately() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0


def test_every_write_route_answers_507_on_a_full_disk(tmp_path) -> None:
    """Before: 500 internal_error on every one (SQLite's 'disk I/O error' was not taken for a full disk)."""
    if not _can_mount_privately():
        skip_or_fail_on_ci("no private mount namespaces here (unshare -rm)")
    mount = tmp_path / "mnt"
    mount.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(HERE)])}
    done = subprocess.run(["unshare", "-rm", sys.executable, str(HERE / "full_disk_probe.py"), str(mount)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads(done.stdout.strip().splitlines()[-1])
    full = {name: outcome for name, outcome in results.items() if name.startswith("full: ")}
    assert full.pop("full: healthz") == [200, None]
    assert len(full) == 7
    assert all(outcome == [507, "insufficient_storage"] for outcome in full.values()), full
    assert results["nearly full: create session"] == [201, None]  # a row still fits
    assert results["nearly full: post chunk"] == [507, "insufficient_storage"]
    assert results["nearly full: upload log"] == [507, "insufficient_storage"]
    assert results["stored afterwards"] == [0, 1]  # no log, only the chunk stored before the disk filled
    # deleting a session on a full disk frees its files first, and then its rows fit
    assert results["big log stored"] == [201, None]
    assert results["delete on a full disk"][0] == 200, results
    assert results["deleted session"] == [404, None]
    # a job that meets a disk another writer filled ends failed "disk full" while the disk stays full
    # (the status written in the room of the data folder's spare file): before, its worker died on the
    # write and the job read "running" until space came back, then failed "worker process exited with code 1"
    status, error, seconds, filled, free = results["job on a full disk"]
    assert status == "failed" and error.startswith("disk full: "), results["job on a full disk"]
    assert filled and free <= 1024**2, results["job on a full disk"]  # no more room than the spare gave
    print(f"job on a full disk: failed 'disk full' after {seconds} s, {free} bytes free")
