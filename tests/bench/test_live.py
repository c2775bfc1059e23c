"""``python -m bench live``: the simulated car streamed into a live job, its table and live.json."""

from __future__ import annotations

import json

import pytest

from bench.__main__ import main


def test_bench_live_streams_the_car_and_writes_its_numbers(tmp_path, capsys) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main(["live", "--duration-s", "5", "--speed", "5", "--busy", "0", "--out", str(out)])
    assert exit_info.value.code == 0
    results = json.loads((out / "live.json").read_text())
    assert results["params"] == {"particles": 30, "seed": 0} and len(results["code"]["commit"]) == 40
    (row,) = results["rows"]
    assert row["status"] == "succeeded" and row["scans"] == 50 and row["drive_s"] == 5.0
    assert (row["busy"], row["speed"], row["chunk_s"]) == (0, 5.0, 1.0)
    assert len(row["backlog"]) == 4 and row["backlog_max"] == max(row["backlog"]) <= 50
    assert 0 <= row["lag_s"] <= row["end_s"] < row["wall_s"]
    assert row["snapshots"] >= 0 and 0 < row["mapping_s"] < row["wall_s"]  # at 5x it seldom catches up
    assert row["mapping_scans_per_s"] == pytest.approx(50 / row["mapping_s"])
    assert 0 < row["ate_m"] < 0.2
    assert "Live car job" in capsys.readouterr().out


@pytest.mark.parametrize("flags", [["--speed", "0"], ["--busy", "-1"], ["--chunk-s", "0.01"], ["--duration-s", "1"]])
def test_bench_live_refuses_bad_options(flags, tmp_path) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["live", *flags, "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    assert not (tmp_path / "live.json").exists()
