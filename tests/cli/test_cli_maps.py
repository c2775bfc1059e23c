"""``lidarmap localize``, ``lidarmap run --map``, ``lidarmap merge`` and ``lidarmap animate`` on the simulated
office loop cut in two halves (written as CARMEN logs) and a drive in another building."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from lidarmap.cli import app
from slam_engine.formats import write_log
from slam_engine.model.poses import relative
from slam_engine.products.map_bundle import read_bundle
from slam_engine.simulation import simulate

pytestmark = pytest.mark.slow


def invoke(*args) -> object:
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("logs")
    office = simulate("office", seed=0, cameras=False)
    start, end = office.log.time_span_s()
    middle = (start + end) / 2
    parts = {"a": office.log.between(start, middle), "b": office.log.between(middle, end + 1.0),
             "elsewhere": simulate("campus", seed=1, rig="robot", cameras=False, max_duration_s=40.0).log}
    written = {name: write_log(log, "carmen", folder / name) for name, log in parts.items()}
    # b's relations beside it (NAME.relations), from the truth's consecutive scans: localize finds them as run does
    truth = office.ground_truth
    inside = truth.t_s >= middle
    t, poses = truth.t_s[inside], truth.poses[inside]
    motion = relative(poses[:-1], poses[1:])
    table = np.column_stack([t[:-1], t[1:], motion[:, 0], motion[:, 1], np.zeros((len(motion), 3)), motion[:, 2]])
    b = written["b"] if written["b"].is_file() else next(written["b"].glob("*.clf"))
    np.savetxt(b.with_name(b.name.split(".", 1)[0] + ".relations"), table, fmt="%.6f")
    return written


def test_localize_extend_and_merge_from_the_command_line(tmp_path, logs) -> None:
    mapped = invoke("run", logs["a"], "--out", tmp_path / "a", "--particles", "10")
    assert mapped.exit_code == 0, mapped.output
    assert f"animation.gif not drawn: lidarmap animate {tmp_path / 'a'} draws it" in " ".join(mapped.stdout.split())
    assert read_bundle(tmp_path / "a").drives == 1

    found = invoke("localize", logs["b"], "--map", tmp_path / "a", "--out", tmp_path / "loc")
    assert found.exit_code == 0, found.output
    run = json.loads((tmp_path / "loc" / "run.json").read_text())
    assert run["localization"]["localised"] is True
    assert {"trajectory.tum", "trajectory.json", "confidence.json", "localization.png"} <= set(run["products"])
    trajectory = np.loadtxt(tmp_path / "loc" / "trajectory.tum")
    assert len(trajectory) == run["localization"]["scans"]
    # NAME.relations beside the log is used without --relations, as lidarmap run does
    scored = run["accuracy"]["relations"]["all"]
    assert scored["n_relations"] > 100 and scored["trans_mean_m"] < 0.05

    refused = invoke("localize", logs["elsewhere"], "--map", tmp_path / "a", "--out", tmp_path / "refused")
    assert refused.exit_code == 1 and refused.stderr.startswith("refused: ")
    assert len(refused.stderr.strip().splitlines()) == 1
    placement = json.loads((tmp_path / "refused" / "run.json").read_text())["localization"]
    assert placement["localised"] is False
    # the line says why: what became of each stretch tried, as run.json counts them
    tried = sum(placement["failed_tries"].values())
    assert tried > 0 and f"of {tried} stretches tried: " in refused.stderr

    extended = invoke("run", logs["b"], "--map", tmp_path / "a", "--out", tmp_path / "ab", "--particles", "10")
    assert extended.exit_code == 0, extended.output
    both = read_bundle(tmp_path / "ab")
    assert both.drives == 2 and (tmp_path / "ab" / "drives.png").stat().st_size > 1000
    assert len(np.loadtxt(tmp_path / "ab" / "trajectory.tum")) == len(both.trajectory)

    # the animation, asked for after the run (lidarmap run draws it only with --animation): from the bundle
    assert not (tmp_path / "a" / "animation.gif").exists()
    drawn = invoke("animate", tmp_path / "a")
    assert drawn.exit_code == 0, drawn.output
    assert Image.open(tmp_path / "a" / "animation.gif").n_frames == 40
    again = invoke("animate", tmp_path / "a")
    assert again.exit_code == 2 and "--force" in again.stderr and len(again.stderr.strip().splitlines()) == 1
    assert invoke("animate", tmp_path / "ab", "--frames", "6", "--out", tmp_path / "ab.gif").exit_code == 0
    assert Image.open(tmp_path / "ab.gif").n_frames == 6  # an extended map: both drives' key frames
    for bad, said in ((["--frames", "0"], "--frames 0"), (["--frames", "5000"], "--frames 5000")):
        refused_frames = invoke("animate", tmp_path / "ab", "--force", *bad)
        assert refused_frames.exit_code == 2 and said in refused_frames.stderr
    assert "no map bundle here" in invoke("animate", tmp_path / "nothing", "--out", tmp_path / "n.gif").stderr

    other = invoke("run", logs["elsewhere"], "--out", tmp_path / "c", "--particles", "10")
    assert other.exit_code == 0, other.output
    merged = invoke("merge", tmp_path / "a", tmp_path / "c", "--out", tmp_path / "merged")
    assert merged.exit_code == 1 and "do not overlap" in merged.stderr

    bad_start = invoke("localize", logs["b"], "--map", tmp_path / "a", "--out", tmp_path / "x", "--start", "1,2")
    assert bad_start.exit_code == 2 and "--start" in bad_start.stderr

    # which map: a folder of saved maps (the office's first half, the other building), and the maps named
    # one by one in the other order: the office's second half is localised in the office's map each time
    maps = tmp_path / "maps"
    maps.mkdir()
    for name in ("a", "c"):
        (maps / name).symlink_to(tmp_path / name, target_is_directory=True)
    for given in (["--map", maps], ["--map", tmp_path / "c", "--map", tmp_path / "a"]):
        picked = invoke("localize", logs["b"], *given, "--out", tmp_path / "which", "--force")
        assert picked.exit_code == 0, picked.output
        which = json.loads((tmp_path / "which" / "run.json").read_text())["localization"]
        assert which["localised"] is True and Path(which["which_map"]["chosen"]).name == "a"
        assert [Path(m["map"]).name for m in which["which_map"]["maps"]][0] == "a"  # ranked first by the index
    lost = invoke("localize", logs["elsewhere"], "--map", tmp_path / "a", "--map", tmp_path / "ab",
                  "--out", tmp_path / "lost")
    assert lost.exit_code == 1 and lost.stderr.startswith("refused: ") and "none of the 2 maps" in lost.stderr
    tried = json.loads((tmp_path / "lost" / "run.json").read_text())["localization"]["which_map"]["maps"]
    assert [m["localised"] for m in tried] == [False, False] and all(m["best_score"] is not None for m in tried)
    empty = tmp_path / "no_maps"
    empty.mkdir()
    nothing = invoke("localize", logs["b"], "--map", empty, "--out", tmp_path / "y")
    assert nothing.exit_code == 2 and "no saved map here" in nothing.stderr
    hinted = invoke("localize", logs["b"], "--map", maps, "--out", tmp_path / "z", "--start", "1,2,0")
    assert hinted.exit_code == 2 and "--start" in hinted.stderr


def test_localize_and_extend_say_what_changed_since_the_map(tmp_path) -> None:
    """The simulated office mapped, then driven days later with a desk moved, a pillar gone, a door closed
    and a partition put up: both the localisation and the extension write the change map."""
    from slam_engine.simulation import write_simulated

    before = write_simulated(simulate("office", seed=0, cameras=False), "carmen", tmp_path / "before")
    after = write_simulated(simulate("office-changed", seed=1, cameras=False), "carmen", tmp_path / "after")
    assert (tmp_path / "after" / "changes.json").is_file()
    assert invoke("run", before, "--out", tmp_path / "map", "--particles", "10").exit_code == 0

    found = invoke("localize", after, "--map", tmp_path / "map", "--out", tmp_path / "loc")
    assert found.exit_code == 0, found.output
    assert "changed since the map:" in found.stdout and "m^2 removed" in found.stdout
    run = json.loads((tmp_path / "loc" / "run.json").read_text())
    assert {"changes.png", "changes.geojson"} <= set(run["products"])
    assert run["changes"]["removed_regions"] == 2 and run["changes"]["added_regions"] >= 3
    features = json.loads((tmp_path / "loc" / "changes.geojson").read_text())["features"]
    assert sorted({f["properties"]["kind"] for f in features}) == ["added", "removed"]
    assert sum(f["properties"]["area_m2"] for f in features) == pytest.approx(
        run["changes"]["added_m2"] + run["changes"]["removed_m2"], abs=0.01)

    extended = invoke("run", after, "--map", tmp_path / "map", "--out", tmp_path / "ext", "--particles", "10")
    assert extended.exit_code == 0, extended.output
    assert "changed since the saved map:" in extended.stdout
    run = json.loads((tmp_path / "ext" / "run.json").read_text())
    assert {"changes.png", "changes.geojson", "drives.png"} <= set(run["products"])
    assert run["changes"]["removed_regions"] == 2 and 0.002 < run["changes"]["changed_share"] < 0.02

    off = tmp_path / "off.yaml"
    off.write_text("changes:\n  enabled: false\n")
    quiet = invoke("localize", after, "--map", tmp_path / "map", "--out", tmp_path / "quiet", "--config", off)
    assert quiet.exit_code == 0 and "changed since" not in quiet.stdout
    assert not (tmp_path / "quiet" / "changes.png").exists()
    assert "changes" not in json.loads((tmp_path / "quiet" / "run.json").read_text())
