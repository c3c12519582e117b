"""The progress bar of long runs (``integrate(..., progress=True)`` and ``lieflow run``): a
:class:`~lieflow.stepping.Monitor`."""

from __future__ import annotations

import time
from typing import Any

from . import _signals
from .errors import InputError


def start_live(display: Any) -> None:
    """Start a rich live display (a ``Progress``) with Ctrl-C and SIGTERM held until it is
    done (:func:`lieflow._signals.deferred`): rich starts one in several steps (its console's
    stack of live displays, the hidden cursor, its render hook), and stopping a half-started
    one fails (``IndexError: pop from empty list``, the cursor left hidden)."""
    with _signals.deferred():
        display.start()


def stop_live(display: Any) -> None:
    """Stop a rich live display with Ctrl-C and SIGTERM held: the cursor is always shown
    again (:func:`start_live`)."""
    with _signals.deferred():
        display.stop()


class ProgressBar:
    """A rich progress bar on stderr: steps done of the total, steps per second, mean
    iterations per step and, when reported, the largest relative energy error so far.

    A :class:`~lieflow.stepping.Monitor`: the bar appears at :meth:`start` and stays on the
    terminal after :meth:`stop`. The numbers are refreshed at most every 0.1 s (the bar
    itself on every call), so a fast run does not spend its time drawing.
    An interrupt in a run's first milliseconds stops a whole bar (:func:`start_live`).

    Raises
    ------
    InputError
        If ``rich`` is not installed.
    """

    def __init__(self) -> None:
        try:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )
        except ImportError as exc:
            raise InputError(
                "a progress bar needs the 'rich' package: pip install 'lieflow[cli]'"
            ) from exc
        self._progress: Any = Progress(
            BarColumn(bar_width=16),
            MofNCompleteColumn(),
            TextColumn("{task.fields[rate]} steps/s, {task.fields[its]} it/step{task.fields[err]}"),
            TimeRemainingColumn(),
            console=Console(stderr=True),
        )
        self._task: Any = None
        self._completed = self._steps = self._iterations = 0
        self._max_err: float | None = None
        self._start = self._last_refresh = time.perf_counter()

    def start(self, done: int, total: int) -> None:
        """Show the bar: ``done`` of ``total`` steps (``done > 0`` for a resumed run)."""
        self._task = self._progress.add_task(
            "run", total=total, completed=done, rate="-", its="-", err=""
        )
        self._completed = done
        self._start = self._last_refresh = time.perf_counter()
        start_live(self._progress)

    def advance(self, steps: int, iterations: int, energy_error: float | None = None) -> None:
        """Record ``steps`` more steps that took ``iterations`` in all, and (optionally) the
        largest relative energy error among them."""
        self._completed += steps
        self._steps += steps
        self._iterations += iterations
        if energy_error is not None:
            self._max_err = max(self._max_err or 0.0, energy_error)
        now = time.perf_counter()
        if now - self._last_refresh < 0.1:
            self._progress.update(self._task, completed=self._completed)
            return
        self._last_refresh = now
        self._progress.update(
            self._task,
            completed=self._completed,
            rate=f"{self._steps / max(now - self._start, 1e-9):,.0f}",
            its=f"{self._iterations / max(self._steps, 1):.1f}",
            err="" if self._max_err is None else f", dE/E {self._max_err:.2e}",
        )

    def stop(self) -> None:
        """Stop drawing (the bar stays on the terminal)."""
        stop_live(self._progress)
