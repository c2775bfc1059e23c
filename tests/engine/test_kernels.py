"""Compiled ahead: the set-up's warm-up leaves numba's cache warm, so a second process maps a small
log without compiling anything; and a caller is told while a kernel does compile."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba

from slam_engine.kernels import ENTRY_KERNELS, compile_notices, kernels

REPO = Path(__file__).resolve().parents[2]
WARM_UP = "-m slam_engine.kernels"


def run_kernels(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_DEBUG")}
    return subprocess.run([sys.executable, "-m", "slam_engine.kernels", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)


def test_setup_and_docker_build_run_the_warm_up() -> None:
    assert f"python {WARM_UP}" in (REPO / "scripts" / "setup_env.sh").read_text()
    assert f"python {WARM_UP}" in (REPO / "docker" / "Dockerfile").read_text()
    makefile = (REPO / "Makefile").read_text()
    for target in ("serve", "bench"):  # the service's first job, and the benchmark's first timed run
        recipe = makefile.split(f"\n{target}:", 1)[1].split("\n\n", 1)[0]
        assert f"python {WARM_UP}" in recipe, target


def test_after_the_warm_up_a_second_process_maps_without_compiling() -> None:
    first = run_kernels()  # what the set-up runs (compiles only when the cache is cold or stale)
    assert first.returncode == 0, first.stdout + first.stderr
    second = run_kernels("--check")  # a new process: maps a tiny simulated drive, fails if anything compiled
    assert second.returncode == 0, second.stdout + second.stderr
    assert f"{len(ENTRY_KERNELS)} loaded from the cache, 0 compiled" in second.stdout


LOOP_CLOSING_RUN = """
import numpy as np

from slam_engine.backend.correlative import search
from slam_engine.backend.submaps import match_grid_from_points
from slam_engine.config import SlamConfig
from slam_engine.kernels import compile_report
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate

result = run_slam(simulate("office", seed=0, cameras=False).log, SlamConfig(seed=0, particles=10))
assert result.input_summary["loop_closing"]["closures_accepted"] > 0
xs = np.arange(-6.0, 40.0, 0.03)
# a featureless corridor: a match slides along it (the corridor-line check)
corridor = np.concatenate([np.stack([xs, np.full_like(xs, y)], 1) for y in (-1.0, 1.0)])
match = search(match_grid_from_points(corridor, 0.05, 1.0), corridor[np.abs(corridor[:, 0]) < 6.0],
               np.array([19.0, 0.2, 0.02]), 6.0, 0.1, 0.3, ambiguity_m=1.0, ambiguity_rad=0.15,
               runner_up_share=0.9, line_half_width_m=0.3, line_half_width_rad=0.03)
assert match is not None and match.line_direction is not None
print("compiled:", ",".join(compile_report()["compiled"]))
"""


def test_after_the_warm_up_a_drive_that_closes_loops_compiles_nothing() -> None:
    """The warm-up must compile the signatures a real run calls, not only its own: a whole office
    loop and a corridor search (ambiguity and corridor-line checks) in a new process."""
    assert run_kernels().returncode == 0
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_DEBUG")}
    run = subprocess.run([sys.executable, "-c", LOOP_CLOSING_RUN], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "compiled: \n" in run.stdout, run.stdout


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
