"""A throw-away PostgreSQL server for the job store's tests (Debian's binaries in
/usr/lib/postgresql/<version>/bin; package ``postgresql``), skipped where there is none, a failure on
CI (``CI=true``). The fixture ``postgres`` (``tests/conftest.py``) starts one per test module."""

from __future__ import annotations

import glob
import os
import pwd
import secrets
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

PG_USER = "lidarmap"


def require(condition: bool, reason: str) -> None:
    if not condition:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(reason)
        pytest.skip(reason)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def postgres_bin() -> Path | None:
    """The newest PostgreSQL server binaries on this machine (Debian layout, else PATH)."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb else None


@dataclass
class PostgresServer:
    port: int
    password: str
    _databases: int = 0

    def url(self, database: str, password: str | None = None) -> str:
        return f"postgresql://{PG_USER}:{password or self.password}@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """The URL of a new, empty database."""
        import psycopg

        self._databases += 1
        name = f"store_{self._databases}"
        with psycopg.connect(self.url("postgres"), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)


@contextmanager
def running_postgres() -> Iterator[PostgresServer]:
    """A throw-away PostgreSQL server: loopback only, a random free port, its socket and data in a
    temporary folder, password authentication (SCRAM), no fsync; stopped and deleted afterwards."""
    bin_dir = postgres_bin()
    require(bin_dir is not None, "PostgreSQL server binaries not found (Debian package postgresql: "
             "/usr/lib/postgresql/<version>/bin/initdb): the PostgreSQL job store tests need a real server")
    try:
        import psycopg  # noqa: F401
    except ImportError:
        require(False, "psycopg not installed: pip install '.[distributed]'")
    as_user: list[str] = []
    owner = os.getuid()
    if owner == 0:  # postgres refuses to run as root: run it as the 'postgres' system user
        try:
            owner = pwd.getpwnam("postgres").pw_uid
        except KeyError:
            require(False, "running as root and no 'postgres' user to run the PostgreSQL server as")
        as_user = ["runuser", "-u", "postgres", "--"]
    folder = Path(tempfile.mkdtemp(prefix="lidarmap-pg-"))
    password = secrets.token_hex(12)
    (folder / "password").write_text(password + "\n")
    (folder / "socket").mkdir()
    os.chown(folder, owner, -1)
    for child in folder.iterdir():
        os.chown(child, owner, -1)
    data, log = folder / "data", folder / "server.log"

    def run(*args: str) -> None:
        result = subprocess.run([*as_user, *args], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, f"{' '.join(args)} failed:\n{result.stdout}\n{result.stderr}\n" + (
            log.read_text() if log.exists() else "")

    port = free_port()
    try:
        run(str(bin_dir / "initdb"), "-D", str(data), "-U", PG_USER, "--auth=scram-sha-256",
            f"--pwfile={folder / 'password'}", "-E", "UTF8", "--no-sync")
        run(str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(log), "-w", "-t", "30", "-o",
            f"-h 127.0.0.1 -p {port} -k {folder / 'socket'} -F -c synchronous_commit=off -c full_page_writes=off",
            "start")
        yield PostgresServer(port, password)
    finally:
        if (data / "postmaster.pid").exists():
            run(str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop")
        shutil.rmtree(folder, ignore_errors=True)
