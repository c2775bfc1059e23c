"""The console script's command group exists and its commands parse."""

from __future__ import annotations

from typer.testing import CliRunner

from service.cli import app


def test_serve_is_a_subcommand_with_bounded_port() -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["serve", "--help"])
    assert result.exit_code == 0
    assert "--port" in result.output
    bad = runner.invoke(app, ["serve", "--port", "70000"])
    assert bad.exit_code == 2
