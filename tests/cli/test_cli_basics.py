"""The console script's command group exists and its commands parse."""

from __future__ import annotations

from typer.testing import CliRunner

from lidarmap.cli import app


def test_serve_is_a_subcommand_with_bounded_port() -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["serve", "--help"])
    assert result.exit_code == 0
    assert "--port" in result.output
    bad = runner.invoke(app, ["serve", "--port", "70000"])
    assert bad.exit_code == 2


def test_help_keeps_units_in_brackets_and_shows_no_bool_metavar() -> None:
    result = CliRunner().invoke(app, ["run", "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0
    for text in ("Grid cell size [m]", "Start heading [deg clockwise from north]", "Start latitude [deg, WGS 84]",
                 "--force", "LOG"):
        assert text in result.output, text
    assert "<bool>" not in result.output


def test_version_is_the_package_version() -> None:
    from lidarmap.cli import package_version

    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.output.strip() == f"lidarmap {package_version()}" and package_version() == "0.1.0"


def test_config_prints_the_documented_defaults_as_a_valid_config_file() -> None:
    import json

    import yaml

    from slam_engine.config import SlamConfig

    result = CliRunner().invoke(app, ["config"])
    assert result.exit_code == 0
    assert SlamConfig.model_validate(yaml.safe_load(result.output)) == SlamConfig()
    line = next(x for x in result.output.splitlines() if x.strip().startswith("no_return_clear_m:"))
    assert line.startswith("  no_return_clear_m: 30.0  # Beams without a return") and "(>= 0.0, <= 200.0)" in line
    schema = CliRunner().invoke(app, ["config", "--schema"])
    assert schema.exit_code == 0 and json.loads(schema.output) == SlamConfig.model_json_schema()


def test_run_refuses_a_non_empty_out_folder_unless_forced(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    refused = CliRunner().invoke(app, ["run", str(tmp_path / "nope.clf"), "--out", str(out)])
    assert refused.exit_code == 2 and refused.stderr.strip().splitlines() == [
        f"error: {out}: output folder exists and is not empty (--force writes into it, replacing the products it "
        "holds)"]
    assert (out / "keep.txt").read_text() == "mine"
    forced = CliRunner().invoke(app, ["run", str(tmp_path / "nope.clf"), "--out", str(out), "--force"])
    assert forced.exit_code == 2 and "nope.clf" in forced.stderr and "not empty" not in forced.stderr


def test_bench_is_a_real_command_of_an_installed_copy() -> None:
    """`bench` is in the package list (so `lidarmap bench` is not a stub after pip install); results/ is not."""
    import tomllib
    from pathlib import Path

    from setuptools import find_namespace_packages

    root = Path(__file__).resolve().parents[2]
    find = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    packages = find_namespace_packages(str(root), include=find["include"])
    assert "bench" in packages and not [p for p in packages if p.startswith("bench.")]
    result = CliRunner().invoke(app, ["bench", "--help"])
    assert result.exit_code == 0 and "--seeds" in result.output


def test_the_command_line_process_freezes_what_is_alive_before_teardown() -> None:
    """``main`` registers gc.freeze as the last exit handler (the teardown's collections then skip
    numba's objects: about 0.35 s of every ``lidarmap run``); a handler registered before ``main``
    runs after it and sees the objects frozen."""
    import subprocess
    import sys

    code = ("import atexit, gc, sys\n"
            "atexit.register(lambda: print('frozen objects:', gc.get_freeze_count()))\n"
            "from lidarmap.cli import main\n"
            "sys.argv = ['lidarmap', '--version']\n"
            "main()\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("lidarmap ")
    assert int(out.stdout.rsplit("frozen objects:", 1)[1]) > 10_000
