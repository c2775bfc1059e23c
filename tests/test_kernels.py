"""Compiled ahead: the set-up's warm-up leaves numba's cache warm, so a second process maps a small
log without compiling anything; and a caller is told while a kernel does compile."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba

from slam_engine.kernels import ENTRY_KERNELS, compile_notices, kernels

REPO = Path(__file__).resolve().parent.parent
WARM_UP = "-m slam_engine.kernels"


def run_kernels(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_DEBUG")}
    return subprocess.run([sys.executable, "-m", "slam_engine.kernels", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)


def test_setup_and_docker_build_run_the_warm_up() -> None:
    assert f"python {WARM_UP}" in (REPO / "scripts" / "setup_env.sh").read_text()
    assert f"python {WARM_UP}" in (REPO / "docker" / "Dockerfile").read_text()
    assert f"python {WARM_UP}" in (REPO / "Makefile").read_text()


def test_after_the_warm_up_a_second_process_maps_without_compiling() -> None:
    first = run_kernels()  # what the set-up runs (compiles only when the cache is cold or stale)
    assert first.returncode == 0, first.stdout + first.stderr
    second = run_kernels("--check")  # a new process: maps a tiny simulated drive, fails if anything compiled
    assert second.returncode == 0, second.stdout + second.stderr
    assert f"{len(ENTRY_KERNELS)} loaded from the cache, 0 compiled" in second.stdout


def test_every_entry_kernel_is_an_engine_kernel() -> None:
    assert set(ENTRY_KERNELS) <= set(kernels())


def test_compile_notices_report_a_compilation_and_its_end() -> None:
    seen: list[bool] = []

    @numba.njit  # a new function: nothing cached, so calling it compiles
    def add_one(x):
        return x + 1

    with compile_notices(seen.append):
        assert add_one(1) == 2
        assert seen == [True, False]
        assert add_one(2) == 3  # compiled already: no notice
    assert seen == [True, False]
