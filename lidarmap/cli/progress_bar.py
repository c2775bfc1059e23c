"""The run's progress bar on stderr: the stage (mapping scans, closing loops, ... writing products), the
whole run's share done (``RunProgress.fraction``: the bar reaches its end only when the products are
written), scans, scans/s, elapsed time and ETA."""

from __future__ import annotations

import time
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    Progress,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

DONE = "done"


class StageProgressBar:
    """A context manager; call it with each ``RunProgress``; :meth:`finish` when the products are written.
    ``stages`` lists the stages shown, in order."""

    def __init__(self, console: Console | None = None):
        self.stages: list[str] = []
        self._started_s = time.perf_counter()
        self._bar = Progress(TextColumn("{task.description:<19}"), BarColumn(), TaskProgressColumn(),
                             TextColumn("{task.fields[scans]}"), TextColumn("{task.fields[rate]}"),
                             TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                             console=console or Console(stderr=True), transient=False)
        self._task = self._bar.add_task("starting", total=1.0, scans="", rate="")

    def __enter__(self) -> StageProgressBar:
        self._bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._bar.stop()

    def __call__(self, progress: Any) -> None:
        """Show a ``slam_engine.pipeline.RunProgress``."""
        mapping = progress.stage_fraction is None  # the scans' stage: their rate means something
        rate = f"{progress.scans_done / progress.elapsed_s:.1f} scans/s" if mapping and progress.elapsed_s > 0 else ""
        self._bar.update(self._task, scans=f"{progress.scans_done}/{progress.scans_total} scans", rate=rate)
        self._show(progress.stage, progress.fraction)

    def finish(self) -> None:
        """The products are written: the bar at its end."""
        self._show(DONE, 1.0)

    def _show(self, stage: str, fraction: float) -> None:
        self._bar.update(self._task, completed=fraction, description=stage)
        if not self.stages or self.stages[-1] != stage:
            self.stages.append(stage)
            self._bar.refresh()  # every stage is drawn, however short
