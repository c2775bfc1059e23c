"""The run's progress bar on stderr: the stage (mapping scans, closing loops, ... writing products), the
whole run's share done (``RunProgress.fraction``: the bar reaches its end only when the products are
written), scans, scans/s, elapsed time and ETA.

Where stderr is not a terminal (a log file, a CI job, a pipe) no bar is drawn: one plain line is
written when each stage starts and at every tenth of the scans mapped (elapsed time, stage, share
done, scans, scans/s), so a log shows how far the run got."""

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
PLAIN_EVERY = 0.1  # without a terminal, a line at every tenth of the scans mapped


class StageProgressBar:
    """A context manager; call it with each ``RunProgress``; :meth:`finish` when the products are written.
    ``stages`` lists the stages shown, in order."""

    def __init__(self, console: Console | None = None):
        self.stages: list[str] = []
        self._started_s = time.perf_counter()
        self._console = console or Console(stderr=True)
        self._plain = not self._console.is_terminal
        self._next_plain_share = PLAIN_EVERY
        self._scans, self._rate = "", ""
        self._bar = Progress(TextColumn("{task.description:<19}"), BarColumn(), TaskProgressColumn(),
                             TextColumn("{task.fields[scans]}"), TextColumn("{task.fields[rate]}"),
                             TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                             console=self._console, transient=False)
        self._task = self._bar.add_task("starting", total=1.0, scans="", rate="")

    def __enter__(self) -> StageProgressBar:
        if not self._plain:
            self._bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if not self._plain:
            self._bar.stop()

    def __call__(self, progress: Any) -> None:
        """Show a ``slam_engine.pipeline.RunProgress``."""
        mapping = progress.stage_fraction is None  # the scans' stage: their rate means something
        rate = f"{progress.scans_done / progress.elapsed_s:.1f} scans/s" if mapping and progress.elapsed_s > 0 else ""
        self._scans, self._rate = f"{progress.scans_done}/{progress.scans_total} scans", rate
        self._bar.update(self._task, scans=self._scans, rate=rate)
        if (self._plain and mapping and progress.scans_total
                and progress.scans_done >= self._next_plain_share * progress.scans_total):
            while self._next_plain_share * progress.scans_total <= progress.scans_done:
                self._next_plain_share += PLAIN_EVERY
            if progress.scans_done < progress.scans_total:
                self._line(progress.stage, progress.fraction)
        self._show(progress.stage, progress.fraction)

    def finish(self) -> None:
        """The products are written: the bar at its end."""
        self._show(DONE, 1.0)

    def _show(self, stage: str, fraction: float) -> None:
        self._bar.update(self._task, completed=fraction, description=stage)
        if not self.stages or self.stages[-1] != stage:
            self.stages.append(stage)
            if self._plain:
                self._line(stage, fraction)
            else:
                self._bar.refresh()  # every stage is drawn, however short

    def _line(self, stage: str, fraction: float) -> None:
        """One plain line for a log: elapsed [s], stage, share of the run done, scans, rate."""
        parts = [f"{time.perf_counter() - self._started_s:7.1f} s", f"{stage:<19}", f"{100 * fraction:3.0f}%",
                 self._scans, self._rate]
        self._console.print("  ".join(p for p in parts if p), highlight=False, markup=False, soft_wrap=True)
