"""Job functions injected into the service's worker processes by the stress and fault tests
(imported by name in the spawned workers)."""

from __future__ import annotations

import json
import time

import numpy as np

from service.jobs.settings import engine_config


def instant(ctx) -> None:
    """Finish at once with a run record (the fuzzer creates many jobs: they must cost nothing)."""
    ctx.progress(1, 1, force=True)
    (ctx.out_dir / "run.json").write_text(json.dumps({"steps": 1}))
    ctx.store.set_products(ctx.job_id, {"run.json": "run.json"})


def sleepy(ctx) -> None:
    """Report progress for ``particles`` x ``seed`` ms, then finish (a job other faults must not disturb)."""
    config = engine_config(ctx.job.config)
    steps, step_s = config.particles, config.seed / 1000.0
    for i in range(steps):
        ctx.progress(i, steps)
        time.sleep(step_s)
    ctx.progress(steps, steps, force=True)
    (ctx.out_dir / "run.json").write_text(json.dumps({"steps": steps}))
    ctx.store.set_products(ctx.job_id, {"run.json": "run.json"})


def hog(ctx) -> None:
    """Allocate (and touch) ``particles`` x 10 MB, as a runaway job would."""
    blocks = []
    particles = engine_config(ctx.job.config).particles
    for i in range(particles):
        blocks.append(np.ones(10 * 1024 * 1024 // 8))
        ctx.progress(i, particles)
    (ctx.out_dir / "run.json").write_text(json.dumps({"blocks": len(blocks)}))
    ctx.store.set_products(ctx.job_id, {"run.json": "run.json"})
