"""Reporting a sweep's progress: :class:`SweepMonitor` (callbacks) and :class:`SweepProgress`
(``lieflow sweep``'s bar or log lines)."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

from ...progress import start_live, stop_live
from ._grid import _toml_value


class SweepMonitor:
    """Receives a sweep's progress (:func:`sweep`'s ``monitor``); subclass what you need.

    ``counts`` maps each status (``"pending"``, ``"running"``, ``"complete"``, ``"failed"``,
    ``"interrupted"``) to its number of runs; ``steps`` and ``total_steps`` count steps
    over all runs (those of running runs included, as far as their workers reported).
    """

    def start(self, runs: int, skipped: int) -> None:
        """Called once: ``runs`` in the sweep, ``skipped`` of them complete already."""

    def update(self, counts: Mapping[str, int], steps: int, total_steps: int) -> None:
        """Called about twice a second while the sweep runs."""

    def finished(self, record: Mapping[str, Any]) -> None:
        """A run ended (its manifest record: ``id``, ``params``, ``status``, ``error``...)."""

    def stop(self) -> None:
        """Called once when the sweep ends, however it ends."""


def _describe(record: Mapping[str, Any]) -> str:
    params = ", ".join(f"{k} = {_toml_value(v)}" for k, v in record["params"].items())
    return params or record["id"]


class SweepProgress(SweepMonitor):
    """The progress display of ``lieflow sweep``: on a terminal, one rich bar over all the
    steps of all runs (runs complete, running, failed; ETA) with a line per failed run; on
    anything else (a batch job's log), one line per finished run.

    Parameters
    ----------
    stream : file, optional
        Where to write (default ``sys.stderr``).
    live : bool, optional
        Draw the bar (default: whether ``stream`` is a terminal and ``rich`` is installed).
    """

    def __init__(self, stream: Any = None, live: bool | None = None) -> None:
        self.stream = sys.stderr if stream is None else stream
        if live is None:
            live = bool(getattr(self.stream, "isatty", lambda: False)())
        self._progress: Any = None
        if live:
            try:
                from rich.console import Console
                from rich.progress import (
                    BarColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                    TimeRemainingColumn,
                )
            except ImportError:
                live = False
            else:
                self._progress = Progress(
                    TextColumn("sweep"),
                    BarColumn(bar_width=24),
                    TextColumn("{task.fields[runs]}"),
                    TimeElapsedColumn(),
                    TextColumn("ETA"),
                    TimeRemainingColumn(),
                    console=Console(file=self.stream),
                )
        self._task: Any = None
        self.runs = self.ended = 0

    def _line(self, text: str) -> None:
        if self._progress is not None:
            self._progress.console.print(text, markup=False, highlight=False)
        else:
            print(text, file=self.stream, flush=True)

    def start(self, runs: int, skipped: int) -> None:
        self.runs, self.ended = runs, skipped
        if skipped:
            self._line(f"{skipped} of {runs} runs complete already (skipped)")
        if self._progress is not None:
            self._task = self._progress.add_task("sweep", total=None, runs="")
            start_live(self._progress)

    def update(self, counts: Mapping[str, int], steps: int, total_steps: int) -> None:
        if self._progress is None:
            return
        text = (
            f"{counts['complete']}/{self.runs} runs done, {counts['running']} running, "
            f"{counts['failed']} failed"
        )
        self._progress.update(self._task, total=total_steps, completed=steps, runs=text)

    def finished(self, record: Mapping[str, Any]) -> None:
        self.ended += 1
        status = record["status"]
        if status == "failed":
            error = str(record.get("error", "")).strip().splitlines()
            self._line(
                f"[{self.ended}/{self.runs}] failed: {_describe(record)}: "
                f"{error[0] if error else ''}"
            )
        elif self._progress is None:
            self._line(
                f"[{self.ended}/{self.runs}] {status}: {_describe(record)} "
                f"({record.get('completed_steps', 0)} steps, "
                f"{record.get('wall_time', 0.0):.2f} s)"
            )

    def stop(self) -> None:
        if self._progress is not None:
            stop_live(self._progress)
