"""``lidarmap run LOG --out DIR``: SLAM on a drive log, every map product into DIR.

A relations file beside the log (``NAME.relations``, or the one ``*.relations`` in its folder) and a
ground-truth file (``NAME.gt.txt`` / ``ground_truth.txt``) are used automatically for run.json's
accuracy figures (``slam_engine.evaluation.metrics.files_beside_log``, as the benchmark finds them). A
simulated log's ``ground_texture.json`` adds the texture's colour error and placement against the
simulator's floor (``accuracy.texture``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from lidarmap.cli.bad_input import bad_input_exits
from slam_engine.errors import ConfigError

if TYPE_CHECKING:
    from slam_engine.config import SlamConfig

SNAPSHOT_FRAMES = 40  # = slam_engine.products.animation.ANIMATION_FRAMES (for the help text; not imported here)


def load_config(path: Path | None, particles: int | None = None, seed: int | None = None,
                resolution_m: float | None = None, snapshot_every: int | None = None) -> SlamConfig:
    """SlamConfig from a YAML/JSON file (or defaults), then the command-line overrides; validated."""
    from slam_engine.config import load_config as load_slam_config  # imported when used (pydantic, PyYAML)
    from slam_engine.config import shortcut_overrides

    shortcuts = {"particles": particles, "seed": seed, "resolution_m": resolution_m,
                 "snapshot_every_scans": snapshot_every}
    return load_slam_config(path, shortcut_overrides(shortcuts))


def prepare_out_dir(out: Path, force: bool) -> None:
    """Refuse an existing, non-empty output folder unless ``force`` (then its product files are replaced)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: --out is a file, not a folder")
    if out.exists() and any(out.iterdir()) and not force:
        raise ConfigError(f"{out}: output folder exists and is not empty (--force writes into it, replacing "
                          "the products it holds)")


def geo_origin(lat: float | None, lon: float | None, heading: float | None):
    """GeoOrigin from --lat --lon --heading (all three or none)."""
    from slam_engine.products import GeoOrigin

    given = [v is not None for v in (lat, lon, heading)]
    if not any(given):
        return None
    if not all(given):
        raise ConfigError("--lat, --lon and --heading go together: give all three (heading in degrees "
                          "clockwise from north) or none")
    assert lat is not None and lon is not None and heading is not None
    return GeoOrigin(latitude_deg=lat, longitude_deg=lon, heading_deg=heading)


def run_with_progress(drive_log, config, bar):
    """run_slam reporting to ``bar`` (a :class:`~lidarmap.cli.progress_bar.StageProgressBar`)."""
    from slam_engine.pipeline import run_slam

    return run_slam(drive_log, config, progress=bar, live_previews=False)  # the bar shows no preview maps


def extend(saved, result, config: SlamConfig, out: Path, relations) -> dict[str, Path]:
    """The drive of ``result`` (mapped on its own) joined with the ``saved`` map; its products into ``out``.
    A drive that cannot be placed is kept in the new bundle as a disconnected part (said on stderr)."""
    from slam_engine.multisession.joining import join
    from slam_engine.multisession.localization import refusal_reason
    from slam_engine.products.multisession import write_joined_products

    assert result.bundle is not None  # a mapping run always makes one
    joined = join(saved, result.bundle, config)
    if not joined.connected:
        typer.echo("warning: the drive could not be placed in the saved map "
                   f"({refusal_reason(joined.placement, config.localization.min_score)}): it is kept in the new "
                   "map bundle as a disconnected part, joined when a later drive links it; the map products show "
                   "the saved map", err=True)
    return write_joined_products(joined, config, out, relations=relations, base_result=result)


def texture_figures(result, truth, floor) -> dict | None:
    """Colour error and placement of the run's texture against a simulated floor (None when the
    run made no texture, or there is no floor or ground truth to compare with)."""
    if result.texture is None or truth is None or floor is None:
        return None
    from slam_engine.texture.accuracy import map_to_truth_frame, texture_accuracy

    try:
        rotation, translation = map_to_truth_frame(result.trajectory, truth)
    except ValueError as error:
        return {"error": str(error)}
    return texture_accuracy(result.texture, floor, rotation, translation).as_dict()


def print_summary(result, written: dict[str, Path], out: Path) -> None:
    """Products written, speed, and accuracy when known (stdout)."""
    import json

    from rich.console import Console
    from rich.table import Table

    console = Console()
    table = Table("product", "bytes", title=f"products in {out}")
    for name, path in sorted(written.items()):
        table.add_row(name, f"{path.stat().st_size:,}")
    console.print(table)
    if "animation.gif" not in written and "map_bundle.npz" in written:
        console.print(f"animation.gif not drawn: lidarmap animate {out} draws it from the map bundle (or run with "
                      "--animation)", highlight=False)
    run = json.loads(written["run.json"].read_text())
    timings = run["timings"]
    rate = timings["scans_per_s"]
    console.print(f"{timings['scans']} scans in {timings['wall_time_s']:.1f} s"
                  + (f" ({rate:.1f} scans/s)" if rate else "")
                  + f"; map {run['map']['width_cells']} x {run['map']['height_cells']} cells of "
                  f"{run['map']['resolution_m']} m")
    accuracy = run.get("accuracy") or {}
    if "relations" in accuracy:
        stats = accuracy["relations"]["all"]
        console.print(f"relation error: {_fmt(stats['trans_mean_m'], '.3f')} +- {_fmt(stats['trans_std_m'], '.3f')}"
                      f" m, {_fmt(stats['rot_mean_deg'], '.2f')} +- {_fmt(stats['rot_std_deg'], '.2f')} deg "
                      f"({stats['n_relations']} relations, {stats['n_failed']} failed)")
    changes = run.get("changes")
    if changes:
        console.print(f"changed since the saved map: {changes['added_m2']:.2f} m^2 added, "
                      f"{changes['removed_m2']:.2f} m^2 removed ({100 * changes['changed_share']:.2f} % of "
                      f"{changes['observed_m2']:.0f} m^2 seen; changes.png, changes.geojson)")
    if accuracy.get("ate_m") is not None:
        console.print(f"absolute trajectory error: {accuracy['ate_m']:.3f} m")
    texture = accuracy.get("texture") or {}
    if "colour_error_mean" in texture:
        console.print(f"texture: colour error {texture['colour_error_mean']:.1f} of 255 over "
                      f"{texture['observed_cells']} cells, placed {texture['placement_offset_m']:.2f} m off")


def print_warnings(run_json: Path) -> None:
    """run.json's warnings, one line each on stderr (``warning: ...``)."""
    import json

    for warning in json.loads(run_json.read_text()).get("warnings", []):
        typer.echo(f"warning: {warning}", err=True)


def _fmt(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def register(app: typer.Typer) -> None:
    @app.command()
    def run(
        log: Path = typer.Argument(..., metavar="LOG", help="Drive log: a file or a folder (see lidarmap formats)."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for the products (created)."),
        format: str = typer.Option("auto", "--format", "-f", help="Log format, or auto to detect it."),
        particles: int | None = typer.Option(None, help="Number of particles (overrides the config; the most, "
                                              "with a min_particles below it in the config)."),
        seed: int | None = typer.Option(None, help="Random seed (overrides the config)."),
        resolution_m: float | None = typer.Option(None, "--resolution-m", "--resolution",
                                                  help="Grid cell size [m] (overrides the config)."),
        config_file: Path | None = typer.Option(None, "--config", "-c", help="SlamConfig as YAML or JSON "
                                                "(lidarmap config prints the defaults)."),
        relations: Path | None = typer.Option(None, help="Relations file for accuracy figures "
                                              "(default: NAME.relations beside the log)."),
        ground_truth: Path | None = typer.Option(None, "--ground-truth", help="Ground truth 't x y theta' "
                                                 "(default: NAME.gt.txt or ground_truth.txt beside the log)."),
        lat: float | None = typer.Option(None, help="Start latitude [deg, WGS 84]: GeoTIFFs in UTM."),
        lon: float | None = typer.Option(None, help="Start longitude [deg, WGS 84]."),
        heading: float | None = typer.Option(None, help="Start heading [deg clockwise from north]."),
        animation: bool = typer.Option(False, "--animation", help="Also draw animation.gif, the map being built "
                                       f"(about {SNAPSHOT_FRAMES} frames; about a tenth of a run's time, so only "
                                       "when asked for)."),
        snapshot_every: int | None = typer.Option(None, help="Animation frame every N processed scans (draws "
                                                  "animation.gif; 0 = none, also with --animation)."),
        map_dir: Path | None = typer.Option(None, "--map", "-m", help="Extend this saved map (a mapping run's "
                                            "--out folder or its map_bundle.npz) with the drive."),
        force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty --out folder."),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Show tracebacks."),
    ) -> None:
        """Build the map of a drive log and write every product (PNG, GeoTIFF, ROS map, trajectories,
        point cloud, map bundle, run.json; the animation when asked for) into --out. With --map, the drive
        extends a saved map: it is placed in it, loops between the drives are closed, and the products
        cover both."""
        from lidarmap.cli.progress_bar import StageProgressBar
        from slam_engine.evaluation import metrics as evaluation
        from slam_engine.formats import load_log
        from slam_engine.pipeline import WRITING_PRODUCTS, stage_progress
        from slam_engine.products import write_products
        from slam_engine.products.map_bundle import read_bundle
        from slam_engine.simulation import floor_beside_log

        with bad_input_exits(verbose):
            geo = geo_origin(lat, lon, heading)
            prepare_out_dir(out, force)
            slam_config = load_config(config_file, particles, seed, resolution_m, snapshot_every)
            relations_beside, truth_beside = evaluation.files_beside_log(log)
            relations = relations or relations_beside
            ground_truth = ground_truth or truth_beside
            # Read the side files before the long run, so a bad one fails in seconds.
            relation_table = None if relations is None else evaluation.read_relations(relations)
            truth = None if ground_truth is None else evaluation.read_ground_truth(ground_truth)
            drive_log = load_log(log, format)
            if animation and snapshot_every is None and slam_config.snapshot_every_scans == 0 \
                    and drive_log.scans is not None:
                from slam_engine.products.animation import snapshot_interval

                every = snapshot_interval(len(drive_log.scans))
                slam_config = slam_config.model_copy(update={"snapshot_every_scans": every})
            floor = floor_beside_log(log)
            saved = None if map_dir is None else read_bundle(map_dir)  # before the long run: fail in seconds
            with StageProgressBar() as bar:
                started_s = time.perf_counter()
                result = run_with_progress(drive_log, slam_config, bar)
                bar(stage_progress(WRITING_PRODUCTS, len(drive_log.scans or ()), started_s))
                if saved is not None:
                    written = extend(saved, result, slam_config, out, relation_table)
                else:
                    written = write_products(result, out, geo=geo, relations=relation_table, ground_truth=truth,
                                             log=drive_log, texture_accuracy=texture_figures(result, truth, floor))
                bar.finish()
            print_summary(result, written, out)
            print_warnings(written["run.json"])
