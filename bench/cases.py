"""Which logs a benchmark runs: the shared datasets' benchmark logs, the maps-only logs, and any
log or folder given on the command line, each with its relations / ground-truth files if present."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

from slam_engine.evaluation.metrics import files_beside_log

REPO_ROOT = Path(__file__).resolve().parent.parent  # a source checkout, or site-packages when installed
SOURCE_CHECKOUT = (REPO_ROOT / "pyproject.toml").exists()

# Original logs with real wheel odometry and official relations (folders inside the datasets folder):
# every log there with NAME.relations beside it, named "real-NAME" beside the benchmark's own logs.
REAL_ODOMETRY_FOLDERS = ("real",)

# Published relation errors on the original logs [m]: the field's best known result, for the tables.
PUBLISHED = {"real-intel": ("Cartographer (Hess et al. 2016)", 0.0229),
             "real-fr079": ("Cartographer (Hess et al. 2016)", 0.0452)}

# Logs without ground truth whose maps a person should look at (paths inside the datasets folder).
MAP_ONLY_LOGS = ("breezyslam/exp2.dat", "malaga/*.clf")

# Simulated drives mapped beside the shared logs, written afresh by the project's simulator (simulation
# seed 0, the rig's own scenario) in a log format with its exact ground truth: (rig, format).
SIMULATED_LOGS = (("car", "ece276a-car"),)

# Files beside a log that are never logs themselves.
_COMPANION_SUFFIXES = (".relations", ".txt", ".md", ".json", ".yaml", ".yml", ".png", ".csv", ".log")


@dataclass(frozen=True)
class BenchCase:
    """One log to benchmark: where it is, and its ground truth when it has some."""

    name: str
    log_path: str
    relations_path: str | None = None
    ground_truth_path: str | None = None

    @property
    def scored(self) -> bool:
        return self.relations_path is not None

    def as_dict(self) -> dict:
        return asdict(self)


def datasets_root() -> Path:
    """The shared datasets folder: ``LIDARMAP_DATASETS``, or ``../shared/datasets`` beside the checkout
    (beside the working folder in an installed copy)."""
    override = os.environ.get("LIDARMAP_DATASETS")
    if override:
        return Path(override)
    return (REPO_ROOT.parent if SOURCE_CHECKOUT else Path.cwd().parent) / "shared" / "datasets"


def _stem(path: Path) -> str:
    return path.name.split(".", 1)[0] if path.is_file() else path.name


def case_for_log(log_path: Path) -> BenchCase:
    """A case for one log file (or log folder), with its relations and ground truth when they exist
    (:func:`slam_engine.evaluation.metrics.files_beside_log`)."""
    log_path = Path(log_path).resolve()
    name = _stem(log_path)
    relations, truth = files_beside_log(log_path)
    return BenchCase(name=name, log_path=str(log_path),
                     relations_path=None if relations is None else str(relations),
                     ground_truth_path=None if truth is None else str(truth))


def cases_for_path(path: Path) -> list[BenchCase]:
    """Cases for a command-line argument: a log file, or a folder holding logs (files beside a
    ``*.relations`` file, or every non-companion file; a folder with none of these is itself the log)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such log or folder")
    if path.is_file():
        return [case_for_log(path)]
    files = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    named = [p for p in files if p.with_name(f"{_stem(p)}.relations").exists()
             and not p.name.endswith(_COMPANION_SUFFIXES)]
    logs = named or [p for p in files if not p.name.endswith(_COMPANION_SUFFIXES)]
    if len(logs) == 0:
        return [case_for_log(path)]
    return [case_for_log(p) for p in logs]


def real_odometry_cases(root: Path | None = None) -> list[BenchCase]:
    """The original logs with real odometry (:data:`REAL_ODOMETRY_FOLDERS`): each log file with its
    ``NAME.relations`` beside it, as case ``real-NAME``."""
    root = datasets_root() if root is None else Path(root)
    cases = []
    for folder in REAL_ODOMETRY_FOLDERS:
        if (root / folder).is_dir():
            for case in cases_for_path(root / folder):
                if case.scored:
                    cases.append(BenchCase(name=f"{folder}-{case.name}", log_path=case.log_path,
                                           relations_path=case.relations_path,
                                           ground_truth_path=case.ground_truth_path))
    return cases


def default_cases(root: Path | None = None, map_only: bool = True) -> list[BenchCase]:
    """The benchmark logs (``benchmark/*.clf`` with relations), the original logs with real odometry
    (:func:`real_odometry_cases`) and, with ``map_only``, the logs without ground truth listed in
    :data:`MAP_ONLY_LOGS`. Missing files are skipped."""
    root = datasets_root() if root is None else Path(root)
    cases = [case_for_log(p) for p in sorted((root / "benchmark").glob("*.clf"))]
    cases.extend(real_odometry_cases(root))
    if map_only:
        for pattern in MAP_ONLY_LOGS:
            cases.extend(case_for_log(p) for p in sorted(root.glob(pattern)))
    return cases


def simulated_cases(folder: Path) -> list[BenchCase]:
    """The drives of :data:`SIMULATED_LOGS`, written under ``folder`` as ``sim-<rig>-<scenario>/``
    the way ``lidarmap simulate --format FORMAT`` writes them (without camera frames: the bench
    scores trajectories), each with its ground truth and relations."""
    from slam_engine.simulation import simulate, write_simulated

    cases = []
    for rig, log_format in SIMULATED_LOGS:
        drive = simulate(None, seed=0, rig=rig, cameras=False)
        out = Path(folder) / f"sim-{rig}-{drive.scenario}"
        out.mkdir(parents=True, exist_ok=True)
        write_simulated(drive, log_format, out)
        cases.append(case_for_log(out))
    return cases
