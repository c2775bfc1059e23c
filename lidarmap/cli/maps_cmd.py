"""``lidarmap localize``, ``lidarmap merge`` and ``lidarmap animate``: use a saved map (the
``map_bundle.npz`` every mapping run writes) again. ``lidarmap run LOG --map DIR`` (extending a map) lives with ``run``
(:mod:`lidarmap.cli.run_cmd`); the work itself is the engine's (:mod:`slam_engine.multisession`)."""

from __future__ import annotations

from pathlib import Path

import typer

from lidarmap.cli.bad_input import bad_input_exits
from lidarmap.cli.run_cmd import SNAPSHOT_FRAMES, load_config, prepare_out_dir

REFUSED_EXIT_CODE = 1  # the drive (or map) was understood, but has no place in the saved map
MAX_ANIMATION_FRAMES = 1000


def parse_pose(text: str | None) -> tuple[float, float, float] | None:
    """``X,Y,THETA`` [m, m, rad] -> a pose; None for None."""
    from slam_engine.errors import ConfigError

    if text is None:
        return None
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(abs(v) < 1e6 for v in values):
        raise ConfigError(f"--start {text!r}: expected X,Y,THETA (metres, metres, radians), e.g. 1.5,-2,0.3")
    return values[0], values[1], values[2]


def saved_maps(paths: list[Path]) -> list[Path]:
    """The saved maps that ``--map`` names, in order: each a run's folder or bundle file, or a folder whose
    sub-folders hold them (each taken in name order). A folder that holds none is an error."""
    from slam_engine.errors import ConfigError
    from slam_engine.products.map_bundle import BUNDLE_FILE

    found: list[Path] = []
    for path in paths:
        if path.is_dir() and not (path / BUNDLE_FILE).exists():
            inside = sorted(p for p in path.iterdir() if (p / BUNDLE_FILE).is_file())
            if not inside:
                raise ConfigError(f"--map {path}: no saved map here ({BUNDLE_FILE}, or folders holding one)")
            found.extend(inside)
        else:
            found.append(path)
    return found


def _refused(which):
    """The refusal of a drive localised in none of several maps, as one map's result: the best score seen."""
    from slam_engine.multisession.localization import LocalizationResult

    best = max((t.best_score or 0.0 for t in which.tries), default=0.0)
    return LocalizationResult(False, best, wall_time_s=which.wall_time_s)


def changed(changes) -> str:
    """``, changed since the map: ...`` for a (change map, grid) pair; '' for None."""
    if changes is None:
        return ""
    figures = changes[0].summary()
    return (f"; changed since the map: {figures['added_m2']:.2f} m^2 added, {figures['removed_m2']:.2f} m^2 removed "
            f"({100 * figures['changed_share']:.2f} % of {figures['observed_m2']:.0f} m^2 seen)")


def register(app: typer.Typer) -> None:
    @app.command()
    def localize(
        log: Path = typer.Argument(..., metavar="LOG", help="Drive log to localise: a file or a folder."),
        map_dirs: list[Path] = typer.Option(..., "--map", "-m", help="A saved map: a mapping run's --out folder "
                                            "or its map_bundle.npz; repeat it, or name a folder of such folders, "
                                            "and the drive is localised in the map it is in."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for the products (created)."),
        format: str = typer.Option("auto", "--format", "-f", help="Log format, or auto to detect it."),
        start: str | None = typer.Option(None, help="Where the drive starts in the map, if known: X,Y,THETA "
                                         "[m, m, rad] (a hint: it is searched near there and still confirmed)."),
        config_file: Path | None = typer.Option(None, "--config", "-c", help="SlamConfig as YAML or JSON."),
        relations: Path | None = typer.Option(None, help="Relations file for accuracy figures "
                                              "(default: NAME.relations beside the log, as lidarmap run)."),
        force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty --out folder."),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Show tracebacks."),
    ) -> None:
        """Localise a drive in a saved map, without being told where it starts: its trajectory in the
        map's frame with a confidence per pose, when it was lost and found, and its scans drawn over the
        map. A drive that is not in the map is refused (exit 1, run.json says localised: false). Given
        several maps, the drive is localised in the one it is in (tried in the order the place index
        ranks them), or refused with every map's best score."""
        import numpy as np

        from slam_engine.errors import ConfigError
        from slam_engine.evaluation.metrics import files_beside_log
        from slam_engine.formats import load_log
        from slam_engine.frontend.particle_filter import engine_threads
        from slam_engine.multisession.changes import localization_changes
        from slam_engine.multisession.localization import localize_log, refusal_reason
        from slam_engine.multisession.which_map import localize_in_maps
        from slam_engine.products.map_bundle import read_bundle
        from slam_engine.products.multisession import localization_image, saved_map_grid, write_localization

        which = None
        with bad_input_exits(verbose):
            prepare_out_dir(out, force)
            hint = parse_pose(start)
            relations = relations or files_beside_log(log)[0]
            config = load_config(config_file)
            maps = saved_maps(map_dirs)
            if len(maps) == 1:
                map_dir, bundle = maps[0], read_bundle(maps[0])
                drive, result = localize_log(bundle, load_log(log, format), config,
                                             hint=None if hint is None else np.array(hint), threads=engine_threads())
            else:
                if hint is not None:
                    raise ConfigError("--start is a pose in one map: give one --map with it")
                bundles = [(str(path), read_bundle(path)) for path in maps]
                which = localize_in_maps(bundles, load_log(log, format), config, threads=engine_threads())
                drive = which.drive
                picked = bundles[0][0] if which.chosen is None else which.tries[which.chosen].name
                map_dir, bundle = Path(picked), dict(bundles)[picked]  # the chosen map (any, when refused)
                result = which.result if which.result is not None else _refused(which)
            image = changes = None
            if result.localised:
                assert result.trajectory is not None
                grid = saved_map_grid(bundle, config)
                image = localization_image(grid, result.trajectory, drive.hits, result.tracked)
                found = localization_changes(grid, drive, result, config.changes)
                changes = None if found is None else (found, grid)
            summary = result.summary()
            if which is not None:
                summary["which_map"] = which.summary()
            write_localization(out, summary, result.trajectory, result.confidence, image, relations=relations,
                               changes=changes)
        if not result.localised:
            if which is not None:
                typer.echo(f"refused: {log} is in none of the {len(which.tries)} maps "
                           f"({which.refusal_reason(config.localization.min_score)})", err=True)
            else:
                typer.echo(f"refused: {log} has no place in the map {map_dir}: "
                           f"{refusal_reason(result, config.localization.min_score)}", err=True)
            raise typer.Exit(REFUSED_EXIT_CODE)
        where = f" in {map_dir}" if which is not None else ""
        typer.echo(f"localised {summary['scans']} scans{where} in {summary['wall_time_s']:.1f} s: "
                   f"{summary['scans_tracked']} matched the map (mean confidence {summary['mean_confidence']})"
                   f"{changed(changes)}; products in {out}")

    @app.command()
    def merge(
        first: Path = typer.Argument(..., metavar="MAP_A", help="The map to merge into (its frame is kept)."),
        second: Path = typer.Argument(..., metavar="MAP_B", help="The map to merge with it."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for the merged map's products (created)."),
        config_file: Path | None = typer.Option(None, "--config", "-c", help="SlamConfig as YAML or JSON."),
        relations: Path | None = typer.Option(None, help="Relations file for accuracy figures."),
        force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty --out folder."),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Show tracebacks."),
    ) -> None:
        """Merge two saved maps of one place into one optimised map (a global search between them, then one
        pose graph); refused (exit 1) when they do not overlap."""
        from slam_engine.errors import MapBundleError
        from slam_engine.multisession.joining import join
        from slam_engine.multisession.localization import refusal_reason
        from slam_engine.products.map_bundle import read_bundle
        from slam_engine.products.multisession import write_joined_products

        with bad_input_exits(verbose):
            prepare_out_dir(out, force)
            config = load_config(config_file)
            joined = join(read_bundle(first), read_bundle(second), config)
        if not joined.connected:
            error = MapBundleError(f"the maps do not overlap: {second} could not be placed in {first}: "
                                   f"{refusal_reason(joined.placement, config.localization.min_score)}")
            typer.echo(f"refused: {error}", err=True)
            raise typer.Exit(REFUSED_EXIT_CODE)
        with bad_input_exits(verbose):
            written = write_joined_products(joined, config, out, relations)
        typer.echo(f"merged: {len(joined.bundle)} key frames of {joined.bundle.drives} drives; products in {out} "
                   f"({', '.join(sorted(written))})")


    @app.command()
    def animate(
        map_dir: Path = typer.Argument(..., metavar="MAP", help="A saved map: a mapping run's --out folder or its "
                                       "map_bundle.npz."),
        out: Path | None = typer.Option(None, "--out", "-o", help="The GIF to write (default: animation.gif beside "
                                        "the map bundle)."),
        frames: int = typer.Option(SNAPSHOT_FRAMES, help=f"Frames in all, the last the final map "
                                   f"(1-{MAX_ANIMATION_FRAMES})."),
        force: bool = typer.Option(False, "--force", help="Replace an existing file."),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Show tracebacks."),
    ) -> None:
        """Draw a saved map's animation.gif (its map being built key frame by key frame, as lidarmap run
        --animation draws it, the final frame the same) from its map bundle, without mapping again."""
        from slam_engine.errors import ConfigError
        from slam_engine.products.animation import write_bundle_animation
        from slam_engine.products.map_bundle import BUNDLE_FILE, read_bundle

        with bad_input_exits(verbose):
            if not 1 <= frames <= MAX_ANIMATION_FRAMES:
                raise ConfigError(f"--frames {frames}: give 1 to {MAX_ANIMATION_FRAMES}")
            target = out if out is not None else (map_dir if map_dir.is_dir() else map_dir.parent) / "animation.gif"
            if target.exists() and not force:
                raise ConfigError(f"{target}: exists (--force replaces it)")
            bundle = read_bundle(map_dir)
            if len(bundle) == 0:
                raise ConfigError(f"{map_dir}: the saved map ({BUNDLE_FILE}) holds no key frames to draw")
            target.parent.mkdir(parents=True, exist_ok=True)
            write_bundle_animation(bundle, target, frames)
        typer.echo(f"animation of {len(bundle)} key frames ({frames} frames, the last the final map): {target}")
