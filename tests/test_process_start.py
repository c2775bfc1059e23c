"""Each process imports only what it uses: the heavy packages (numba, SciPy, Open3D, rasterio, PIL,
SQLAlchemy, Alembic...) are imported by the code that needs them, not when a package is imported.
Each case runs in a fresh interpreter and reads its ``sys.modules`` at the end."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def packages_loaded_by(code: str) -> set[str]:
    """The top-level packages in ``sys.modules`` once ``code`` has run in a new interpreter."""
    probe = f"{code}\nimport sys\nprint(' '.join(sorted({{name.split('.')[0] for name in sys.modules}})))"
    run = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return set(run.stdout.splitlines()[-1].split())


def test_the_command_lines_help_imports_no_engine_library() -> None:
    help_run = ("import sys\nsys.argv = ['lidarmap', '--help']\nfrom lidarmap.cli import main\n"
                "try:\n    main()\nexcept SystemExit:\n    pass")
    loaded = packages_loaded_by(help_run)
    assert "typer" in loaded
    assert loaded.isdisjoint({"numpy", "numba", "scipy", "pydantic", "yaml", "rich", "PIL", "open3d", "rasterio",
                              "sqlalchemy", "fastapi", "httpx"}), loaded


def test_a_mapping_run_writes_its_products_without_open3d(tmp_path: Path) -> None:
    """map_points.ply is filtered and written without Open3D (its package import alone cost a run
    0.5-0.8 s and 45-70 MB); a run without cameras or a tilted LiDAR never imports it."""
    mapping_run = f"""
from slam_engine import SlamConfig, run_slam, simulate, write_products
drive = simulate("office", seed=0, rig="carmen-robot", max_duration_s=20.0, cameras=False)
written = write_products(run_slam(drive.log, SlamConfig(particles=4, seed=0)), {str(tmp_path)!r})
assert "map_points.ply" in written
"""
    loaded = packages_loaded_by(mapping_run)
    assert {"numba", "rasterio", "PIL"} <= loaded  # it did map and write
    assert "open3d" not in loaded
    assert (tmp_path / "map_points.ply").stat().st_size > 1000


def test_the_services_storage_imports_no_map_writer_and_workers_no_migrations() -> None:
    """The API and every worker import the data folder (``slam_engine.products.files`` inside): it
    loads neither numpy nor PIL; a worker process, which never migrates the job store, no Alembic."""
    assert packages_loaded_by("import service.storage.data_dir").isdisjoint({"numpy", "PIL", "scipy"})
    loaded = packages_loaded_by("import service.runners.worker")
    assert "sqlalchemy" in loaded
    assert loaded.isdisjoint({"alembic", "mako", "open3d", "rasterio"}), loaded
