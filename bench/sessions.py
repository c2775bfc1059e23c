"""``python -m bench sessions``: maps that outlive a drive, on the two-session drives of the shared
datasets (``sessions/``: each benchmark drive cut in two halves, ``NAME-a`` and ``NAME-b``, the second
with its odometry starting at an unrelated pose).

For every seed, each half is mapped on its own (``run_slam``: its map bundle and the engine's wall
time; with ``NAME-a.gt.txt`` beside it, the ``a`` map's absolute trajectory error: how far the saved map is
bent, which its relations do not show and a drive localised in it inherits), then:

- **localise**: ``NAME-b`` in ``NAME-a``'s map, without a start pose (``localize_log``, what ``lidarmap
  localize`` runs). ``NAME-a``'s trajectory (from its bundle) followed by ``NAME-b``'s localised one is
  scored against ``NAME-ab.relations`` (the cross-session placement) and ``NAME-all.relations``. The
  localisation's wall time (reading the drive's scans and matching them to each other while the saved
  map's index is built, then placing and tracking) is set against the time it took to map ``NAME-b``;
- **refuse**: every ``b`` half in the other buildings' ``a`` maps, which must be refused;
- **which map**: every ``b`` half given all the ``a`` maps (``localize_in_maps``, what ``lidarmap localize
  --map A --map B`` runs): it must be placed in its own building's, in at most twice the time of that map
  alone;
- **changes**: the change map of ``NAME-b`` localised in ``NAME-a``'s map (hours apart: only people moved),
  the share of the observed area it reports changed, its time against the localisation's;
- **extend**: ``NAME-a``'s bundle joined with ``NAME-b``'s (what ``lidarmap run NAME-b --map
  NAME-a-out`` does), the joint trajectory scored against both relation files;
- **merge**: both bundles written and read back as saved maps, then merged (what ``lidarmap merge``
  does; refused when they do not overlap). The merge is the extension's join on the saved files, so
  the two agree unless a bundle does not survive its file.

Prints one table of checks against the targets (median / worst seed when there are several seeds) and
one of the numbers per seed, and writes ``sessions.json`` into the results folder (with a copy as
``bench/results/latest-sessions.json`` when under ``bench/results``).
"""

from __future__ import annotations

import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import typer

from bench.options import SEEDS_HELP, parse_seeds, read_overrides, report_console

# The two-session drives, in the order of the tables.
DRIVES = ("intel", "aces-rough")
# Targets of the issue: relation error [m], mean translation, by drive. Drives not named have no target.
LOCALISE_TARGETS_M = {"intel": 0.04, "aces-rough": 0.06}  # NAME-ab.relations (cross-session placement)
EXTEND_TARGETS_M = {"intel": 0.025, "aces-rough": 0.05}  # NAME-all.relations
MERGE_TARGETS_M = {"intel": 0.03}  # NAME-all.relations
TIME_RATIO_TARGET = 0.2  # localising a half may take at most a fifth of mapping it
WHICH_MAP_TIME_RATIO = 2.0  # finding the map among several may take at most twice localising in it alone
# intel-b in intel-a's map (the same day, only people moved): at most this share of the observed area changed
CHANGED_SHARE_TARGET = 0.01
CHANGES_TIME_RATIO = 0.1  # the change map may take at most a tenth of localising the drive
RESULTS_FILE = "sessions.json"
LATEST_FILE = "latest-sessions.json"


@dataclass(frozen=True)
class Targets:
    """What each check must reach; a drive missing from a mapping has no target."""

    localise_m: dict[str, float]
    extend_m: dict[str, float]
    merge_m: dict[str, float]
    time_ratio: float = TIME_RATIO_TARGET


DEFAULT_TARGETS = Targets(LOCALISE_TARGETS_M, EXTEND_TARGETS_M, MERGE_TARGETS_M)


@dataclass(frozen=True)
class SessionDrive:
    """One drive cut in two: the logs of its halves and its relation files."""

    name: str
    a_log: str
    b_log: str
    all_relations: str
    ab_relations: str

    @classmethod
    def in_folder(cls, folder: Path, name: str) -> SessionDrive | None:
        """``NAME-a.clf``, ``NAME-b.clf``, ``NAME-all.relations``, ``NAME-ab.relations`` in ``folder``, or
        None when one is missing."""
        paths = [folder / f"{name}-{suffix}" for suffix in ("a.clf", "b.clf", "all.relations", "ab.relations")]
        if not all(p.is_file() for p in paths):
            return None
        return cls(name, *(str(p.resolve()) for p in paths))


def sessions_root() -> Path:
    """``sessions/`` of the shared datasets (``LIDARMAP_DATASETS`` or ``../shared/datasets``)."""
    from bench.cases import datasets_root

    return datasets_root() / "sessions"


def session_drives(folder: Path | None = None) -> list[SessionDrive]:
    """Every drive whose four files are in ``folder`` (default :func:`sessions_root`): those of
    :data:`DRIVES` first, in its order, then the others by name."""
    folder = sessions_root() if folder is None else Path(folder)
    names = sorted((p.name[: -len("-a.clf")] for p in folder.glob("*-a.clf")),
                   key=lambda n: (DRIVES.index(n) if n in DRIVES else len(DRIVES), n))
    found = (SessionDrive.in_folder(folder, name) for name in names)
    return [drive for drive in found if drive is not None]


# ------------------------------------------------------------------------------------------ one seed


def _concatenated(first_t_s, first_poses, second):
    """One trajectory of two parts (both in one map frame), in time order."""
    import numpy as np

    from slam_engine.model.result import Trajectory

    t_s = np.concatenate([np.asarray(first_t_s, np.float64), np.asarray(second.t_s, np.float64)])
    poses = np.concatenate([np.asarray(first_poses, np.float64), np.asarray(second.poses, np.float64)])
    order = np.argsort(t_s, kind="stable")
    return Trajectory(t_s[order], poses[order])


def _scores(trajectory, relations: dict) -> dict:
    """Relation errors over all relations of each file in ``relations`` (name -> Relations)."""
    from slam_engine.evaluation.metrics import relation_errors

    return {name: relation_errors(trajectory, rel).all.as_dict() for name, rel in relations.items()}


def run_seed(drives: list[SessionDrive], seed: int, overrides: dict | None = None, particles: int | None = None,
             say: Callable[[str], None] = print) -> dict:
    """Every check's numbers for one seed (see the module docstring); JSON-ready."""
    from slam_engine.config import SlamConfig, merge_settings, shortcut_overrides
    from slam_engine.errors import MapBundleError
    from slam_engine.evaluation.metrics import absolute_trajectory_error, read_ground_truth, read_relations
    from slam_engine.formats import load_log
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.multisession.joining import join, merge
    from slam_engine.multisession.localization import localize_log
    from slam_engine.multisession.which_map import localize_in_maps
    from slam_engine.pipeline import run_slam
    from slam_engine.products.map_bundle import read_bundle, write_bundle

    config = SlamConfig.model_validate(merge_settings(overrides or {},
                                                      shortcut_overrides({"seed": seed, "particles": particles})))
    threads = engine_threads()
    logs, bundles = {}, {}
    mapping: dict[str, dict[str, Any]] = {}
    localisations: dict[str, dict[str, Any]] = {}
    extensions: dict[str, dict[str, Any]] = {}
    merges: dict[str, dict[str, Any]] = {}
    relations = {d.name: {"ab": read_relations(d.ab_relations), "all": read_relations(d.all_relations)}
                 for d in drives}
    for drive in drives:
        for part, path in (("a", drive.a_log), ("b", drive.b_log)):
            name = f"{drive.name}-{part}"
            logs[name] = load_log(path)
            result = run_slam(logs[name], config)
            assert result.bundle is not None  # a mapping run always makes one
            bundles[name] = result.bundle
            scans = logs[name].scans
            mapping[name] = {"scans": 0 if scans is None else len(scans), "wall_s": result.wall_time_s,
                             "key_frames": len(result.bundle), "ate_m": None}
            truth = Path(path).with_name(f"{name}.gt.txt")  # beside the log, as lidarmap run finds it
            if truth.is_file():
                mapping[name]["ate_m"] = absolute_trajectory_error(result.trajectory, read_ground_truth(truth))
            say(f"  seed {seed}: mapped {name} ({mapping[name]['scans']} scans) in {result.wall_time_s:.1f} s")
            del result

    for drive in drives:  # each b half in its own building's map first, then in the others'
        for other in sorted(drives, key=lambda d: d.name != drive.name):
            map_name, drive_name = f"{other.name}-a", f"{drive.name}-b"
            started = time.perf_counter()
            drive_scans, placed = localize_log(bundles[map_name], logs[drive_name], config, threads=threads)
            wall_s = time.perf_counter() - started
            scans_s = wall_s - placed.search_s
            mapping_s = mapping[drive_name]["wall_s"]
            record: dict[str, Any] = {
                "map": map_name, "drive": drive_name, "same_building": other.name == drive.name,
                "localised": placed.localised, "best_score": placed.best_score, "scans_s": scans_s,
                "localize_s": placed.search_s, "wall_s": wall_s, "mapping_s": mapping_s,
                "time_ratio": wall_s / mapping_s, "summary": placed.summary(), "relations": None}
            if other.name == drive.name and placed.trajectory is not None:
                a = bundles[map_name]
                record["relations"] = _scores(_concatenated(a.trajectory_t_s, a.trajectory, placed.trajectory),
                                              relations[drive.name])
                record["changes"] = _changes(a, drive_scans, placed, config, wall_s)
            localisations[f"{drive_name} in {map_name}"] = record
            outcome = (f"{record['relations']['ab']['trans_mean_m']:.3f} m across"
                       if record["relations"] else "localised" if placed.localised else "refused")
            say(f"  seed {seed}: {drive_name} in {map_name}'s map: {outcome} (best score {placed.best_score:.3f}), "
                f"{wall_s:.1f} s ({scans_s:.1f} s its scans)")

    which: dict[str, dict[str, Any]] = {}
    saved_maps = [(f"{d.name}-a", bundles[f"{d.name}-a"]) for d in drives]
    for drive in drives:  # which map: each b half among every a map
        name = f"{drive.name}-b"
        found = localize_in_maps(saved_maps, logs[name], config, threads=threads)
        chosen = None if found.chosen is None else found.tries[found.chosen].name
        one_map_s = localisations[f"{name} in {drive.name}-a"]["wall_s"]
        which[name] = {"chosen": chosen, "right": chosen == f"{drive.name}-a", "wall_s": found.wall_time_s,
                       "one_map_s": one_map_s, "time_ratio": found.wall_time_s / one_map_s,
                       "maps": found.summary()["maps"]}
        say(f"  seed {seed}: which map for {name} among {len(saved_maps)}: {chosen or 'none'} in "
            f"{found.wall_time_s:.1f} s ({one_map_s:.1f} s in its own map alone)")

    for drive in drives:
        joined = join(bundles[f"{drive.name}-a"], bundles[f"{drive.name}-b"], config, threads=threads)
        extensions[drive.name] = {"connected": joined.connected, "wall_s": joined.wall_time_s,
                                  "key_frames": len(joined.bundle), "summary": joined.summary,
                                  "relations": _scores(joined.trajectory, relations[drive.name])
                                  if joined.connected else None}
        say(f"  seed {seed}: extended {drive.name}-a with {drive.name}-b in {joined.wall_time_s:.1f} s: "
            + (f"{extensions[drive.name]['relations']['all']['trans_mean_m']:.3f} m" if joined.connected
               else "not connected"))

    with tempfile.TemporaryDirectory(prefix="lidarmap-sessions-") as tmp:
        for drive in drives:
            saved = [write_bundle(bundles[f"{drive.name}-{part}"], Path(tmp) / f"{drive.name}-{part}.npz")
                     for part in ("a", "b")]
            started = time.perf_counter()
            try:
                merged = merge(read_bundle(saved[0]), read_bundle(saved[1]), config, threads=threads)
            except MapBundleError as error:
                merges[drive.name] = {"merged": False, "error": str(error), "relations": None,
                                      "wall_s": time.perf_counter() - started}
            else:
                merges[drive.name] = {"merged": True, "error": None, "wall_s": merged.wall_time_s,
                                      "relations": _scores(merged.trajectory, relations[drive.name])}
            say(f"  seed {seed}: merged the maps of {drive.name}-a and {drive.name}-b: "
                + (f"{merges[drive.name]['relations']['all']['trans_mean_m']:.3f} m" if merges[drive.name]["merged"]
                   else "refused"))
    from bench.worker import finite_or_none

    return finite_or_none({"seed": seed, "threads": threads, "config": config.model_dump(mode="json"),
                           "mapping": mapping, "localise": localisations, "which_map": which, "extend": extensions,
                           "merge": merges})


def _changes(bundle, scans, placed, config, localise_s: float) -> dict | None:
    """The change map of a drive localised in ``bundle``'s map (the same building, hours apart: only people
    moved), with its time against the localisation's ``localise_s`` (and the saved map's grid it is found on,
    which the localisation's picture renders anyway)."""
    from slam_engine.multisession.changes import localization_changes
    from slam_engine.products.multisession import saved_map_grid

    started = time.perf_counter()
    grid = saved_map_grid(bundle, config)
    grid_s = time.perf_counter() - started
    changes = localization_changes(grid, scans, placed, config.changes)
    if changes is None:
        return None
    return {**changes.summary(), "grid_s": grid_s, "time_ratio": changes.wall_time_s / localise_s}


# ------------------------------------------------------------------------------------------- checks


@dataclass(frozen=True)
class Check:
    """One row of the table: a number at ``path`` in each seed's record and what it must be.
    ``kind`` "at_most": the number is at most ``target`` (None: not measured, a miss); "refused":
    the value (whether the drive was localised) is False; "right": it is True."""

    id: str
    label: str
    path: tuple[str, ...]
    kind: str
    target: float | None = None
    unit: str = "m"


def checks_for(drives: list[SessionDrive], targets: Targets = DEFAULT_TARGETS) -> list[Check]:
    """The table's rows for ``drives``, in the issue's order: localise, extend, refuse, merge, time."""
    names = [d.name for d in drives]
    rows = [Check(f"localise:{n}", f"localise {n}-b in {n}-a's map, cross-session relations ({n}-ab)",
                  ("localise", f"{n}-b in {n}-a", "relations", "ab", "trans_mean_m"), "at_most",
                  targets.localise_m.get(n)) for n in names]
    # no target: how far the saved map itself is bent (its relations do not show it), which a drive localised
    # in it inherits
    rows += [Check(f"map-ate:{n}", f"{n}-a's map: absolute trajectory error against its ground truth",
                   ("mapping", f"{n}-a", "ate_m"), "at_most") for n in names]
    rows += [Check(f"extend:{n}", f"extend {n}-a with {n}-b, all relations",
                   ("extend", n, "relations", "all", "trans_mean_m"), "at_most", targets.extend_m.get(n))
             for n in names]
    rows += [Check(f"refuse:{b}:{a}", f"{b}-b in {a}-a's map", ("localise", f"{b}-b in {a}-a", "localised"),
                   "refused", unit="") for b in names for a in names if a != b]
    rows += [Check(f"merge:{n}", f"merge the maps of {n}-a and {n}-b, all relations",
                   ("merge", n, "relations", "all", "trans_mean_m"), "at_most", targets.merge_m.get(n))
             for n in names]
    rows += [Check(f"time:{n}", f"localise {n}-b / map {n}-b, wall time", ("localise", f"{n}-b in {n}-a",
                   "time_ratio"), "at_most", targets.time_ratio, unit="") for n in names]
    rows += [Check(f"which:{n}", f"which map: {n}-b among the {len(names)} a maps", ("which_map", f"{n}-b", "right"),
                   "right", unit="") for n in names]
    rows += [Check(f"which-time:{n}", f"which map: {n}-b among them / in {n}-a alone, wall time",
                   ("which_map", f"{n}-b", "time_ratio"), "at_most", WHICH_MAP_TIME_RATIO, unit="") for n in names]
    rows += [Check(f"changes:{n}", f"changes: {n}-b in {n}-a's map, share of the observed area reported changed",
                   ("localise", f"{n}-b in {n}-a", "changes", "changed_share"), "at_most",
                   CHANGED_SHARE_TARGET if n == "intel" else None, unit="share") for n in names]
    rows += [Check(f"changes-time:{n}", f"changes: the change map of {n}-b / localising it, wall time",
                   ("localise", f"{n}-b in {n}-a", "changes", "time_ratio"), "at_most", CHANGES_TIME_RATIO, unit="")
             for n in names]
    return rows


def _get(record, path: tuple[str, ...]):
    for key in path:
        if not isinstance(record, dict):
            return None
        record = record.get(key)
    return record


def _number(value: float, unit: str) -> str:
    if unit == "share":
        return f"{100 * value:.3f} %"
    return f"{value:.4f} m" if unit == "m" else f"{value:.2f}"  # 0.1 mm: a miss by less still shows


def evaluate(check: Check, runs: list[dict]) -> dict:
    """``check`` over the seeds' records: every value, the median and worst, the shown text, and
    whether it passed (None: no target)."""
    values = [_get(run, check.path) for run in runs]
    row: dict = {**asdict(check), "values": values}
    if check.kind == "right":
        right = [v is True for v in values]
        chosen = [_get(run, check.path[:-1] + ("chosen",)) for run in runs]
        row.update(median=None, worst=None, passed=all(right), target_text="its own building's map",
                   measured=f"right {sum(right)}/{len(right)}" + ("" if all(right) else
                                                                  f" (chose {', '.join(map(str, chosen))})"))
        return row
    if check.kind == "refused":
        refused = [v is False for v in values]
        scores = [_get(run, check.path[:-1] + ("best_score",)) for run in runs]
        best = max((s for s in scores if s is not None), default=None)
        shown = "refused" if all(refused) else "localised" if not any(refused) else \
            f"refused {sum(refused)}/{len(refused)}"
        row.update(median=None, worst=None, passed=all(refused),
                   measured=shown + ("" if best is None else f" (best score {best:.3f})"),
                   target_text="refused")
        return row
    present: list[float] = [v for v in values if v is not None]
    if not present:
        median = worst = None
        passed = None if check.target is None else False
        shown = "not measured"
    else:
        median, worst = statistics.median(present), max(present)
        passed = None if check.target is None else len(present) == len(values) and worst <= check.target
        shown = _number(worst, check.unit) if len(values) == 1 else \
            f"{_number(median, check.unit)} / {_number(worst, check.unit)}".replace(" m /", " /")
        if len(present) < len(values):
            shown += f" ({len(values) - len(present)} seeds not measured)"
    if check.path[-1] == "trans_mean_m":  # relations the trajectory could not score are counted, not dropped
        failed = sum(_get(run, check.path[:-1] + ("n_failed",)) or 0 for run in runs)
        row["failed_relations"] = failed
        if failed:
            shown += f" ({failed} relations failed)"
    if check.id.startswith("time:") and present and len(values) == 1:
        record = _get(runs[0], check.path[:-1])
        shown += f" ({record['wall_s']:.1f} s / {record['mapping_s']:.1f} s)"
    target_text = "–" if check.target is None else (
        f"<= {check.target:g} m" if check.unit == "m" else f"<= {_number(check.target, 'share')}"
        if check.unit == "share" else f"<= {check.target:g}")
    row.update(median=median, worst=worst, passed=passed, measured=shown, target_text=target_text)
    return row


# ------------------------------------------------------------------------------------------- tables


def checks_table(results: dict):
    """The checks against their targets (median / worst seed over several seeds)."""
    from rich.table import Table

    seeds = results["options"]["seeds"]
    several = len(seeds) > 1
    table = Table(title=f"Sessions: localise, extend, merge — seed{'s' if several else ''} "
                  f"{', '.join(map(str, seeds))}" + (" (median / worst seed)" if several else ""),
                  title_justify="left")
    for column in ("check", "measured", "target", "pass"):
        table.add_column(column, justify="left" if column == "check" else "right")
    for row in results["checks"]:
        verdict = "–" if row["passed"] is None else "[green]pass[/green]" if row["passed"] else "[red]FAIL[/red]"
        table.add_row(row["label"], row["measured"], row["target_text"], verdict)
    return table


def _m(value) -> str:
    return "–" if value is None else f"{value:.3f}"


def details_table(results: dict):
    """Per seed and drive: the relation errors (cross-session / all) and the wall times."""
    from rich.table import Table

    table = Table(title="Per seed: relation error m (ab / all), wall s", title_justify="left")
    for column in ("seed", "drive", "map a ATE m", "localise m", "localise s (scans + search)", "map b s", "ratio",
                   "extend m", "extend s", "merge m", "merge s"):
        table.add_column(column, justify="left" if column == "drive" else "right")
    for run in results["runs"]:
        for name in results["drives"]:
            loc = run["localise"].get(f"{name}-b in {name}-a") or {}
            ext, mrg = run["extend"].get(name) or {}, run["merge"].get(name) or {}

            def pair(record: dict) -> str:
                rel = record.get("relations")
                return "–" if not rel else f"{_m(rel['ab']['trans_mean_m'])} / {_m(rel['all']['trans_mean_m'])}"

            ate = (run.get("mapping", {}).get(f"{name}-a") or {}).get("ate_m")
            table.add_row(str(run["seed"]), name, _m(ate), pair(loc) if loc.get("localised") else "not localised",
                          f"{loc.get('wall_s', 0):.1f} ({loc.get('scans_s', 0):.1f} + {loc.get('localize_s', 0):.1f})",
                          f"{loc.get('mapping_s', 0):.1f}", f"{loc.get('time_ratio', 0):.2f}",
                          pair(ext), f"{ext.get('wall_s', 0):.1f}", pair(mrg) if mrg else "–",
                          f"{mrg['wall_s']:.1f}" if mrg else "–")
    return table


def print_sessions(results: dict, console=None) -> None:
    """Both tables, how many checks pass, and where the JSON is."""
    from rich.console import Console

    console = console or Console()
    console.print(checks_table(results))
    console.print(details_table(results))
    rows = [r for r in results["checks"] if r["passed"] is not None]
    console.print(f"{sum(r['passed'] for r in rows)} of {len(rows)} checks pass", highlight=False)
    if results.get("out_dir"):
        console.print(f"results: {results['out_dir']}/{RESULTS_FILE}", highlight=False)


# --------------------------------------------------------------------------------------------- runs


def run_sessions(drives: list[SessionDrive], seeds: list[int], out_dir: Path | None = None,
                 overrides: dict | None = None, particles: int | None = None, targets: Targets = DEFAULT_TARGETS,
                 say: Callable[[str], None] = print) -> dict:
    """Every seed's record and the checks over them; written as ``sessions.json`` into ``out_dir``
    (default ``bench/results/<date-time>``; a copy as ``bench/results/latest-sessions.json`` when there)."""
    from bench.harness import code_version, default_out_dir, write_results
    from bench.worker import finite_or_none

    out_dir = Path(out_dir) if out_dir is not None else default_out_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    load_at_start = list(os.getloadavg())
    code = code_version()  # of the code this process runs: taken before the (minutes of) runs
    runs = [run_seed(drives, seed, overrides, particles, say) for seed in seeds]
    results = finite_or_none({
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "cpu_count": os.cpu_count(), "processor": platform.processor(),
                    "load_average_at_start": load_at_start, "load_average_at_end": list(os.getloadavg())},
        "code": code,
        "options": {"seeds": seeds, "particles": particles, "config": overrides or {}},
        "drives": [d.name for d in drives],
        "files": [asdict(d) for d in drives],
        "checks": [evaluate(check, runs) for check in checks_for(drives, targets)],
        "runs": runs,
        "out_dir": str(out_dir),
    })
    write_results(results, out_dir, RESULTS_FILE, LATEST_FILE)
    return results


def sessions(
    seeds: str = typer.Option("0", help=SEEDS_HELP),
    particles: int | None = typer.Option(None, min=1, max=1000,
                                         help="Particles per mapping run (default: the SlamConfig default)."),
    config: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                       help="YAML or JSON file with SlamConfig overrides."),
    folder: Path | None = typer.Option(None, "--folder", help="Folder of the two-session drives (default: "
                                       "sessions/ of the shared datasets)."),
    out: Path | None = typer.Option(None, help="Output folder (default bench/results/<date-time>)."),
) -> None:
    """Maps that outlive a drive: localise the second half of a drive in the first half's map, extend
    it, merge the two maps, refuse other buildings' drives; checks against the targets."""


    drives = session_drives(folder)
    if not drives:
        raise typer.BadParameter(f"no two-session drives (NAME-a.clf, NAME-b.clf, NAME-all.relations, "
                                f"NAME-ab.relations) under {folder or sessions_root()}")
    overrides = read_overrides(config)
    console = report_console()
    seed_list = parse_seeds(seeds)
    console.print(f"sessions: {', '.join(d.name for d in drives)} × seeds {seeds}, one after the other")
    results = run_sessions(drives, seed_list, out, overrides, particles,
                           say=lambda line: console.print(line, highlight=False))
    print_sessions(results, console)


if __name__ == "__main__":
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command()(sessions)
    app(prog_name="python -m bench.sessions")
