"""The benchmark's command line (``python -m bench`` and ``lidarmap bench``): thin wrapper over
:func:`bench.harness.run_benchmark` and :func:`bench.report.print_report`, the scored logs against
the record (:mod:`bench.regression`), followed by the sessions
table (:mod:`bench.sessions`) on the shared datasets' two-session drives, the margin table
(:mod:`bench.margin`: the sparse logs at 15 particles, seeds 0-9), the live table (:mod:`bench.live`:
the simulated car streamed at real time into a live job) and the live localisation table
(:mod:`bench.live_localization`: the simulated office streamed at real time into a live localize job)."""

from __future__ import annotations

from pathlib import Path

import typer

from bench.options import SEEDS_HELP, parse_seeds, read_overrides, report_console


def readable_cases(cases: list, loader: str, console) -> list:
    """The cases whose log format the default loader recognises; the others are named and skipped."""
    if loader != "slam_engine.formats:load_log":
        return cases
    from slam_engine.errors import LogFormatError
    from slam_engine.formats import detect_format

    kept = []
    for case in cases:
        try:
            detect_format(case.log_path)
        except LogFormatError as error:
            console.print(f"[yellow]skipped {case.name}:[/yellow] {error}", highlight=False)
            continue
        kept.append(case)
    return kept


def accuracy(
    paths: list[Path] = typer.Argument(None, help="More logs or folders to run (NAME.relations and "
                                       "NAME.gt.txt / ground_truth.txt beside a log are used when present)."),
    seeds: str = typer.Option("0-4", help=SEEDS_HELP),
    particles: int | None = typer.Option(None, min=1, max=1000,
                                         help="Particles per run (default: the SlamConfig default)."),
    quick: bool = typer.Option(False, help="One seed (the first), benchmark logs only (no maps-only logs, "
                               "no simulated drives)."),
    datasets: bool = typer.Option(True, help="Include the shared datasets' logs (LIDARMAP_DATASETS or "
                                  "../shared/datasets)."),
    config: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                       help="YAML or JSON file with SlamConfig overrides."),
    simulated: bool = typer.Option(True, help="Also map the simulated car (written into the output folder "
                                   "with its exact ground truth)."),
    sessions: bool = typer.Option(True, help="Then the sessions table (localise, extend, merge on the datasets' "
                                  "sessions/ drives, same seeds; not with --quick or --no-datasets)."),
    margin: bool = typer.Option(True, help="Then the margin table (aces-rough and infinite-corridor-rough at 15 "
                                "particles, seeds 0-9; not with --quick or --no-datasets)."),
    live: bool = typer.Option(True, help="Then the live table (the simulated car streamed at real time into a "
                              "live job beside one busy process, about 2 minutes; not with --quick)."),
    live_localization: bool = typer.Option(True, help="Then the live localisation table (the simulated office "
                                           "mapped, driven again and streamed at real time into a live localize job "
                                           "beside one busy process, a foreign drive after it; and a robot carried "
                                           "off in eight made-up floors; about 4 minutes; not with --quick)."),
    places: bool = typer.Option(True, help="Then the place index's retrieval at the benchmark logs' true revisits "
                                "(recall@5, precision@1; not with --quick or --no-datasets)."),
    peers: bool = typer.Option(True, help="Then lidarmap and Karto side by side (whole processes, interleaved, "
                               "median of 3; needs ../shared/peers built; not with --quick)."),
    changes: bool = typer.Option(True, help="Then the change map against the simulated office's known changes "
                                 "(precision, recall, seeds 0-4; not with --quick)."),
    which_map: bool = typer.Option(True, help="Then which map among ten (the sessions' a halves and made-up office "
                                   "floors): every drive in its own building's, foreign ones refused, the time "
                                   "against one map alone (seeds 0-2, about 4 minutes; not with --quick or "
                                   "--no-datasets)."),
    out: Path | None = typer.Option(None, help="Output folder (default bench/results/<date-time>)."),
    record: bool = typer.Option(False, help="Write this run's relation errors and ATE (median and worst seed per "
                                "log) and flagged maps into bench/recorded.json, the record later runs are "
                                "compared with."),
    timeout_s: float = typer.Option(3600.0, min=1.0, help="Time limit per run, seconds."),
    busy: int = typer.Option(0, min=0, max=64, help="CPU-bound processes to run beside every run "
                             "('while True: pass'): timings on a busy machine."),
    runner: str = typer.Option("slam_engine.pipeline:run_slam", hidden=True,
                               help="SLAM function to benchmark (module:function)."),
    loader: str = typer.Option("slam_engine.formats:load_log", hidden=True, help="Log loader (module:function)."),
) -> None:
    """Accuracy and speed of SLAM on the benchmark logs (relation errors, ATE, time, memory) over
    several seeds, plus maps of logs without ground truth. Writes JSON and map PNGs."""

    from bench.cases import cases_for_path, datasets_root, default_cases, simulated_cases
    from bench.harness import BenchOptions, default_out_dir, run_benchmark
    from bench.report import fmt, print_report
    from bench.worker import DEFAULT_LOADER, DEFAULT_RUNNER, resolve

    seed_list = parse_seeds(seeds)[:1] if quick else parse_seeds(seeds)
    cases = default_cases(map_only=not quick) if datasets else []
    try:
        for path in paths or []:
            cases.extend(cases_for_path(path))
    except FileNotFoundError as exc:
        raise typer.BadParameter(str(exc)) from None
    out = out if out is not None else default_out_dir()
    if simulated and not quick:
        cases.extend(simulated_cases(out / "simulated"))
    if not cases:
        raise typer.BadParameter(f"nothing to run: no logs under {datasets_root()} and none given")
    overrides = read_overrides(config)
    console = report_console()
    for dotted in (runner, loader):
        try:
            resolve(dotted)
        except (ImportError, AttributeError, ValueError) as error:
            raise typer.BadParameter(f"cannot use {dotted!r}: {error}") from None
    cases = readable_cases(cases, loader, console)
    console.print(f"{len(cases)} logs × {len(seed_list)} seeds, {particles or 'default'} particles, "
                  "one process at a time" + (f", {busy} busy processes beside each" if busy else ""))

    def progress(record: dict) -> None:
        if record.get("status") == "ok":
            console.print(f"  {record['case']} seed {record['seed']}: run {fmt(record.get('run_process_s'), 1)} s "
                          f"(process with scoring {fmt(record.get('process_s'), 1)} s), "
                          f"SLAM {fmt(record.get('wall_s'), 1)} s, products {fmt(record.get('products_s'), 2)} s, "
                          f"peak run {fmt(record.get('peak_run_mb'), 0)} MB (process with scoring "
                          f"{fmt(record.get('peak_memory_mb'), 0)} MB)", highlight=False)
        else:
            console.print(f"  [red]{record['case']} seed {record['seed']} failed[/red]")

    options = BenchOptions(seeds=seed_list, particles=particles, config=overrides or {}, out_dir=out,
                           timeout_s=timeout_s, runner=runner, loader=loader, busy=busy)
    results = run_benchmark(cases, options, on_run=progress)
    print_report(results, console)
    report_regressions(results, console, record)
    if sessions and datasets and not quick and (runner, loader) == (DEFAULT_RUNNER, DEFAULT_LOADER):
        run_sessions_table(seed_list, out, overrides or {}, particles, console)
    if margin and datasets and not quick and (runner, loader) == (DEFAULT_RUNNER, DEFAULT_LOADER):
        from bench.margin import MARGIN_PARTICLES, MARGIN_SEEDS, run_margin_table

        run_margin_table(out, parse_seeds(MARGIN_SEEDS), MARGIN_PARTICLES, overrides or {}, console)
    if live and not quick and (runner, loader) == (DEFAULT_RUNNER, DEFAULT_LOADER):
        from bench.live import run_live_table

        run_live_table(out, console)
    if live_localization and not quick:
        from bench.live_localization import run_live_localization_table

        run_live_localization_table(out, console)
        from bench import kidnap

        console.print("\n[bold]Kidnapped[/bold] in made-up office floors (python -m bench.kidnap)")
        console.print(kidnap.table([kidnap.measure(number) for number in range(1, kidnap.FLOORS + 1)]),
                      highlight=False)
        console.print("\nKidnapped in the simulated office, nearly symmetric under a half turn")
        console.print(kidnap.office_table(kidnap.office_rows()), highlight=False)
    if places and datasets and not quick:
        from bench import place_recall

        console.print("\n[bold]Place index[/bold]: retrieval at the true revisits (python -m bench.place_recall)")
        console.print(place_recall.table([place_recall.measure(name) for name in place_recall.DEFAULT_LOGS], 5),
                      highlight=False)
    if changes and not quick:
        from bench import changes as change_map

        console.print("\n[bold]Change map[/bold]: the simulated office's known changes (python -m bench.changes)")
        console.print(change_map.table([change_map.measure(seed) for seed in range(5)]), highlight=False)
    if which_map and datasets and not quick:
        from bench import which_map as among_maps

        console.print(f"\n[bold]Which map[/bold] among {among_maps.MAPS} (python -m bench.which_map)")
        answers = [row for seed in range(3) for row in among_maps.measure(seed, say=lambda line: None)]
        console.print(among_maps.table(answers), highlight=False)
    if peers and not quick:
        from bench import peers as side_by_side

        karto = side_by_side.karto_binary()
        console.print("\n[bold]Side by side with Karto[/bold] (python -m bench.peers)")
        if karto is None:
            console.print("Karto is not built: ../shared/peers/build_karto.sh (../shared/peers/README.md)",
                          highlight=False)
        else:
            rows = [side_by_side.side_by_side(datasets_root() / "benchmark" / f"{name}.clf", karto, 3)
                    for name in side_by_side.DEFAULT_LOGS]
            console.print(side_by_side.table(rows, 3), highlight=False)


def report_regressions(results: dict, console, record: bool) -> None:
    """The scored logs against the record (:mod:`bench.regression`), written into ``regression.json``
    beside the results; with ``record`` this run becomes the record."""
    import json

    from bench.regression import compare, print_regressions, read_recorded
    from bench.regression import record as write_record

    recorded = read_recorded()
    rows = compare(results, recorded)
    print_regressions(rows, recorded, console)
    Path(results["out_dir"]).mkdir(parents=True, exist_ok=True)
    Path(results["out_dir"], "regression.json").write_text(json.dumps(
        {"recorded": recorded.get("recorded"), "rows": rows}, indent=1))
    if record:
        write_record(results)
        console.print("recorded as bench/recorded.json", highlight=False)


def run_sessions_table(seeds: list[int], out: Path, overrides: dict, particles: int | None, console) -> None:
    """The sessions table (:mod:`bench.sessions`) into ``out`` beside the benchmark's results, when the
    datasets hold the two-session drives."""
    from bench.sessions import print_sessions, run_sessions, session_drives, sessions_root

    drives = session_drives() if sessions_root().is_dir() else []
    if not drives:
        console.print(f"[yellow]sessions table skipped:[/yellow] no two-session drives under {sessions_root()}",
                      highlight=False)
        return
    console.print(f"sessions: {', '.join(d.name for d in drives)} × {len(seeds)} seeds", highlight=False)
    results = run_sessions(drives, seeds, out, overrides, particles,
                           say=lambda line: console.print(line, highlight=False))
    print_sessions(results, console)
