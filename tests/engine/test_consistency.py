"""How far a finished map contradicts its own scans (``evaluation.consistency``): a simulated office
mapped as it was driven does not; the same key frames with the second half of the drive turned against
the first (as drift the loop closing missed leaves a map) do, and a map contradicted that widely is
flagged, with a warning in the run."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.backend.map_builder import render_occupancy
from slam_engine.config import SlamConfig
from slam_engine.evaluation.consistency import FLAG_SHARE, WARNING_START, MapConsistency, map_consistency
from slam_engine.model.poses import compose, relative
from slam_engine.model.result import SlamResult
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate

CONFIG = SlamConfig(particles=10, seed=0)


@pytest.fixture(scope="module")
def office_map() -> SlamResult:
    return run_slam(simulate("office", seed=0, cameras=False).log, CONFIG)


def _returns(result: SlamResult) -> list[np.ndarray]:
    assert result.bundle is not None
    return [scan.ends_v[scan.is_hit] for scan in result.bundle.scans()]


def test_a_map_made_as_it_was_driven_agrees_with_its_scans(office_map: SlamResult) -> None:
    bundle = office_map.bundle
    assert bundle is not None
    consistency = map_consistency(office_map.grid, bundle.poses, _returns(office_map))
    assert not consistency.flagged and consistency.warning() is None
    assert consistency.judged > 0.9 * len(bundle)
    assert consistency.contradicted == 0 and consistency.returns_on_free < 0.02  # measured 0 and 0.8 %
    # the run reports the same in run.json's map section and warns of nothing of the kind
    assert office_map.input_summary["map_consistency"] == consistency.as_dict()
    assert not any(w.startswith(WARNING_START) for w in office_map.warnings)


def test_the_second_half_turned_against_the_first_contradicts_the_scans(office_map: SlamResult) -> None:
    """The drive's second half turned 0.1 rad (5.7 deg) about where it begins, as a heading error the
    loop closing never corrected would leave it: its walls cross the first half's free space."""
    bundle = office_map.bundle
    assert bundle is not None
    poses = bundle.poses.copy()
    half = len(poses) // 2
    pivot = poses[half]
    poses[half:] = compose(np.array([pivot[0], pivot[1], pivot[2] + 0.1]), relative(pivot, poses[half:]))
    grid = render_occupancy(bundle.scans(), poses, bundle.origin_v, CONFIG.grid)
    consistency = map_consistency(grid, poses, _returns(office_map))
    # measured 5.6 % of the key frames contradicted, 7.8 % of the returns on free cells: a sound real map
    # gives as much with its clutter (module docstring), so this one is not flagged
    assert consistency.contradicted_share > 0.03 and consistency.returns_on_free > 0.05
    assert not consistency.flagged


def test_a_map_contradicted_widely_is_flagged_with_a_warning() -> None:
    wide = MapConsistency(returns_on_free=0.28, judged=1993, contradicted=738)  # freiburg-campus-rough, seed 0
    assert wide.flagged and wide.as_dict()["flagged"] is True
    warning = wide.warning()
    assert warning is not None and warning.startswith(f"{WARNING_START}: 738 of 1993 key frames (37 %)")
    at_the_bar = MapConsistency(returns_on_free=0.1, judged=100, contradicted=int(FLAG_SHARE * 100))
    assert not at_the_bar.flagged and at_the_bar.warning() is None


def test_key_frames_without_returns_are_not_judged(office_map: SlamResult) -> None:
    poses = np.zeros((3, 3))
    empty = [np.zeros((0, 2))] * 3
    consistency = map_consistency(office_map.grid, poses, empty)
    assert consistency.judged == 0 and not consistency.flagged and consistency.contradicted_share == 0.0
    few = [np.array([[1.0, 0.0]] * 5)] * 3  # fewer than MIN_RETURNS each
    assert map_consistency(office_map.grid, poses, few).judged == 0
    with pytest.raises(ValueError, match="2 poses, 3 key frames"):
        map_consistency(office_map.grid, poses[:2], empty)
