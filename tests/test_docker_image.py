"""The Docker image's file set starts: a wheel built from exactly what docker/Dockerfile copies, installed
into a fresh virtual environment (its dependencies from the running one, not this checkout), runs
``lidarmap --help`` and serves /healthz, /docs and the image's HEALTHCHECK; the build context leaves out
what the image does not need; compose publishes on loopback and has no default password; the README's
"Deploy with Docker" commands run as far as this machine allows.

No image is built here: the base image needs a registry this machine may not reach. Where compose is
installed (the docker plugin, or the standalone ``docker-compose``), the README's ``docker compose ...
config`` is run too: it needs no daemon.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
import time
import urllib.request
import venv
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = REPO / "docker" / "Dockerfile"
COMPOSE = REPO / "docker" / "compose.yaml"
ENV_EXAMPLE = REPO / "docker" / "env.example"


def dockerfile_copies() -> list[str]:
    """The build-context paths the Dockerfile's COPY instructions take (none from other stages)."""
    sources: list[str] = []
    for line in DOCKERFILE.read_text().splitlines():
        words = line.split()
        if words[:1] == ["COPY"] and not any(w.startswith("--from") for w in words):
            sources += words[1:-1]
    return sources


def healthcheck_command() -> list[str]:
    """The HEALTHCHECK's CMD (exec form) as an argument list."""
    text = DOCKERFILE.read_text().replace("\\\n", " ")
    match = re.search(r"^HEALTHCHECK .*?CMD (\[.*\])\s*$", text, re.MULTILINE)
    assert match, "docker/Dockerfile has no HEALTHCHECK ... CMD [...]"
    return json.loads(match.group(1))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def image_venv(tmp_path_factory) -> Path:
    """A virtual environment with the wheel of the Dockerfile's file set installed; the running
    environment's packages are its dependencies (a .pth line: its editable lidarmap is not loaded)."""
    root = tmp_path_factory.mktemp("image")
    context = root / "context"
    context.mkdir()
    patterns = dockerignore_patterns()

    def left_out(folder: str, names: list[str]) -> set[str]:  # what docker leaves out of the context
        below = Path(folder).relative_to(REPO).as_posix()
        return {name for name in names if ignored(f"{below}/{name}", patterns)}

    for source in dockerfile_copies():
        path = REPO / source
        assert path.exists(), f"docker/Dockerfile copies {source}, which the checkout lacks"
        if path.is_dir():  # as the build context has it: a local bench/results (gigabytes) is not copied
            shutil.copytree(path, context / source, ignore=left_out)
        else:
            shutil.copy2(path, context / source)
    wheels = root / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(context)],
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-3000:]
    env_dir = root / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib, "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
                              "--no-index", "-q", *map(str, wheels.glob("*.whl"))],
                             capture_output=True, text=True, timeout=300)
    assert install.returncode == 0, install.stderr[-3000:]
    return env_dir


def clean_env(**extra: str) -> dict[str, str]:
    """The environment without this checkout on the path."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return {**env, **extra}


def test_the_image_cli_starts(image_venv: Path, tmp_path: Path) -> None:
    for argv in (["--help"], ["bench", "--help"], ["serve", "--help"]):
        done = subprocess.run([str(image_venv / "bin" / "lidarmap"), *argv], capture_output=True, text=True,
                              cwd=tmp_path, env=clean_env(), timeout=120)
        assert done.returncode == 0, done.stderr[-3000:]
    where = subprocess.run([str(image_venv / "bin" / "python"), "-c", "import lidarmap, service; "
                            "from api_schemas import JobCreate, JobPublic; "
                            "print(lidarmap.__file__, service.__file__)"], capture_output=True, text=True,
                           cwd=tmp_path, env=clean_env(), check=True).stdout
    assert str(REPO) not in where and str(image_venv) in where  # the installed copy, not the checkout


def test_the_image_app_serves_and_passes_its_healthcheck(image_venv: Path, tmp_path: Path) -> None:
    port = free_port()
    env = clean_env(LIDARMAP_DATA_DIR=str(tmp_path / "data"), LIDARMAP_WORKERS="1")
    server = subprocess.Popen([str(image_venv / "bin" / "lidarmap"), "serve", "--host", "127.0.0.1",
                               "--port", str(port)], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as response:
                    assert json.load(response)["status"] == "ok"
                    break
            except OSError:
                assert server.poll() is None, server.communicate()[1][-3000:]
                assert time.monotonic() < deadline, "the service did not answer /healthz within 120 s"
                time.sleep(0.3)
        command = [part.replace("127.0.0.1:8000", f"127.0.0.1:{port}") for part in healthcheck_command()]
        assert command[0] == "python"
        check = subprocess.run([str(image_venv / "bin" / "python"), *command[1:]], capture_output=True, text=True,
                               env=env, timeout=30)
        assert check.returncode == 0, check.stderr
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/docs", timeout=5) as response:
            page = response.read().decode()
        for asset in re.findall(r'(?:src|href)="(/static/docs/[^"]+)"', page):
            with urllib.request.urlopen(f"http://127.0.0.1:{port}{asset}", timeout=5) as response:
                assert response.status == 200 and response.read(), asset
        assert "/static/docs/" in page  # the docs' assets come from the installed package
    finally:
        server.send_signal(signal.SIGTERM)
        _, stderr = server.communicate(timeout=60)
    assert server.returncode == 0, stderr[-3000:]  # a graceful stop on SIGTERM (docker stop)
    assert "leaked" not in stderr and "Traceback" not in stderr, stderr[-3000:]


def dockerignore_patterns() -> list[str]:
    lines = (REPO / ".dockerignore").read_text().splitlines()
    return [line.strip() for line in lines if line.strip() and not line.startswith("#")]


def ignored(path: str, patterns: list[str]) -> bool:
    """Whether ``path`` (or a folder above it) matches a .dockerignore pattern (``**`` any depth)."""
    parts = Path(path).parts
    prefixes = ["/".join(parts[:i]) for i in range(1, len(parts) + 1)]
    for pattern in patterns:
        regex = re.escape(pattern).replace(r"\*\*/", "(?:.*/)?").replace(r"\*", "[^/]*")
        if any(re.fullmatch(regex, prefix) for prefix in prefixes):
            return True
    return False


def test_the_build_context_leaves_out_what_the_image_does_not_need() -> None:
    patterns = dockerignore_patterns()
    for heavy in (".venv", ".git", "bench/results", "lidarmap-data", "tests", "service/__pycache__/app.pyc",
                  "docker/.env"):
        assert ignored(heavy, patterns), heavy
    for source in dockerfile_copies():
        assert not ignored(source, patterns), f"{source} is copied by the Dockerfile but ignored"
        assert not ignored(f"{source}/__init__.py", patterns) or not (REPO / source).is_dir(), source


def test_compose_publishes_on_loopback_and_has_no_default_password() -> None:
    text = COMPOSE.read_text()
    compose = yaml.safe_load(text)
    assert compose["services"]["api"]["ports"] == ["${LIDARMAP_PUBLISH:-127.0.0.1}:8000:8000"]
    assert "LIDARMAP_API_KEYS" in compose["x-lidarmap-env"]
    uses = re.findall(r"\$\{POSTGRES_PASSWORD([^}]*)\}", text)
    assert uses and all(use.startswith(":?") for use in uses), uses  # required: compose stops with the message
    assert compose["services"]["worker"]["healthcheck"] == {"disable": True}
    # the worker's command reads its concurrency in the container: docker/.env's value must be passed in
    worker_env = compose["services"]["worker"]["environment"]
    assert "$${LIDARMAP_WORKER_CONCURRENCY" in text
    assert worker_env["LIDARMAP_WORKER_CONCURRENCY"] == "${LIDARMAP_WORKER_CONCURRENCY:-1}"
    assert worker_env["LIDARMAP_RUNNER"] == "celery"  # and the shared settings still
    assert "docker/.env" in (REPO / ".gitignore").read_text().splitlines()
    required = set(re.findall(r"\$\{(\w+):\?", text))
    example = dict(line.split("=", 1) for line in ENV_EXAMPLE.read_text().splitlines()
                   if line and not line.startswith("#"))
    assert required <= set(example), f"docker/env.example lacks {required - set(example)}"
    assert all(example[name] == "" for name in required)  # no password shipped


def deploy_commands() -> list[str]:
    """The shell commands of the README's "Deploy with Docker" section (comments dropped)."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## Deploy with Docker", 1)[1].split("\n## ", 1)[0]
    block = section.split("```sh\n", 1)[1].split("```", 1)[0]
    return [line.split("  #", 1)[0].strip() for line in block.splitlines() if line.strip()]


def compose_command() -> list[str] | None:
    """How compose is run here: the docker plugin, else the standalone docker-compose (which reads the
    same file and flags), else None."""
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return ["docker-compose"] if shutil.which("docker-compose") else None


def test_the_readme_deploy_commands(tmp_path: Path) -> None:
    commands = deploy_commands()
    assert commands[0] == "cp docker/env.example docker/.env"
    (tmp_path / "docker").mkdir()
    for name in ("Dockerfile", "compose.yaml", "env.example"):
        shutil.copy2(REPO / "docker" / name, tmp_path / "docker" / name)
    subprocess.run(shlex.split(commands[0]), cwd=tmp_path, check=True)
    env_file = tmp_path / "docker" / ".env"
    env_file.write_text(env_file.read_text().replace("POSTGRES_PASSWORD=\n", "POSTGRES_PASSWORD=s3cret\n"))
    compose_commands = [c for c in commands if c.startswith("docker compose")]
    assert compose_commands, "the section runs docker compose"
    for command in compose_commands:
        argv = shlex.split(command)
        assert argv[argv.index("-f") + 1] == "docker/compose.yaml"
        assert argv[argv.index("--env-file") + 1] == "docker/.env"
    config = shlex.split(next(c for c in compose_commands if " config" in c))
    compose = compose_command()
    if compose is not None:  # the compose file as compose reads it: the password given, then required
        argv = compose + config[2:]
        done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        shown = subprocess.run([a for a in argv if a != "--quiet"], cwd=tmp_path, capture_output=True, text=True)
        assert "127.0.0.1:8000:8000" in shown.stdout and "s3cret@postgres" in shown.stdout, shown.stdout
        env_file.write_text(env_file.read_text().replace("POSTGRES_PASSWORD=s3cret\n", "POSTGRES_PASSWORD=\n"))
        done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True)
        assert done.returncode != 0 and "set POSTGRES_PASSWORD in docker/.env" in done.stderr, done.stderr
