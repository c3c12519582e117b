"""One run of a sweep on a worker (:func:`run_task`): the default pool's workers (one BLAS
thread, signals, exiting with their coordinator) and the progress file a run reports to."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import threading
import time
import traceback
from collections.abc import Mapping
from pathlib import Path
from types import FrameType
from typing import Any

from ...errors import LieflowError
from ..config import ConfigError, build, parse_config
from ._store import _store_run, _store_sink

_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)


#: True while a worker of the default pool runs a task (its SIGTERM handler then raises
#: KeyboardInterrupt, which lieflow.app.io.run turns into an "interrupted", resumable file).
_BUSY = False
#: Set by SIGTERM in a worker of the default pool: tasks it has not started return at once.
_STOP = False
#: True in the default pool's workers (which then report their OS threads: BLAS's included).
_POOL_WORKER = False


def _worker_init() -> None:
    """Initializer of the default pool's workers: one BLAS thread (the variables are also
    set before the workers start), Ctrl-C left to the coordinator, SIGTERM stops the run
    at its next step with its file marked "interrupted"."""
    global _POOL_WORKER
    _POOL_WORKER = True
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    with contextlib.suppress(ImportError):
        import threadpoolctl

        threadpoolctl.threadpool_limits(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def on_term(signum: int, frame: FrameType | None) -> None:
        global _STOP
        _STOP = True
        if _BUSY:  # through the SIGINT handler a run installed (it stops at a safe point)
            handler = signal.getsignal(signal.SIGINT)
            if callable(handler):
                handler(signal.SIGINT, frame)
            else:
                raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    threading.Thread(target=_exit_with_parent, name=_WATCH, daemon=True).start()


#: The name of a pool worker's thread that watches its coordinator (:func:`_exit_with_parent`).
_WATCH = "lieflow-parent-watch"


#: Seconds a worker whose coordinator died waits for its run to stop (at its next step)
#: before it exits anyway (the file is then resumable from its last checkpoint, as after a
#: kill).
_ORPHAN_GRACE = 60.0


def _exit_with_parent() -> None:
    """A default-pool worker's watch of its coordinator: once the coordinator is gone (a
    ``kill -9`` runs no cleanup, and its workers used to live on, blocked on the task queue
    for ever, a running run stepping to its end), stop the run at its next step as SIGTERM
    does (its file marked "interrupted"), then exit. Waits on the spawn start method's
    parent sentinel (readable once the parent process has died), so it costs nothing."""
    import multiprocessing.connection

    parent = multiprocessing.parent_process()
    if parent is None:  # pragma: no cover - not a spawned worker
        return
    multiprocessing.connection.wait([parent.sentinel])
    os.kill(os.getpid(), signal.SIGTERM)  # the run stops at its next step (on_term)
    deadline = time.monotonic() + _ORPHAN_GRACE
    while _BUSY and time.monotonic() < deadline:
        time.sleep(0.05)
    os._exit(1)


class _ProgressFile:
    """A :class:`~lieflow.stepping.Monitor` that writes a run's step count to a small JSON
    file (atomically, at most once a second) for the coordinator's progress display, and
    stops the run (:class:`KeyboardInterrupt`, which marks its file "interrupted") once the
    coordinator's stop file exists — how an interrupted sweep stops runs on Dask workers,
    which no signal of the coordinator reaches."""

    def __init__(self, path: Path | None, stop: Path | None = None) -> None:
        self.path = path
        self.stop_file = stop
        self.done = self.total = 0
        self.last = self.checked = 0.0

    def _stop_requested(self) -> bool:
        return self.stop_file is not None and self.stop_file.exists()

    def _write(self) -> None:
        self.last = time.monotonic()
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(
                json.dumps(
                    {
                        "done": self.done,
                        "total": self.total,
                        "host": socket.gethostname(),
                        "pid": os.getpid(),
                    }
                )
            )
            os.replace(tmp, self.path)
        except OSError:  # progress is a courtesy: never fail a run for it
            pass

    def start(self, done: int, total: int) -> None:
        self.done, self.total = done, total
        self._write()

    def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
        self.done += steps
        now = time.monotonic()
        if now - self.last >= 1.0:
            self._write()
        if now - self.checked >= 0.1:
            self.checked = now
            if self._stop_requested():
                raise KeyboardInterrupt

    def stop(self) -> None:
        self._write()


def run_task(task: Mapping[str, Any]) -> dict[str, Any]:
    """Run (or resume) one run of a sweep; what a worker executes.

    ``task`` holds the run's configuration text, ``source``, ``base_dir``, ``output`` and
    ``progress`` (paths). Never raises for the run's own errors: returns a dictionary with
    ``status`` (``"complete"``, ``"interrupted"``, ``"failed"`` or ``"busy"`` when another
    process holds the file's lock) and the run's numbers, or its ``error``.
    """
    global _BUSY
    from .. import io

    started = time.time()
    out: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid(), "started": started}
    if _POOL_WORKER and os.path.isdir("/proc/self/task"):  # 1: one BLAS thread, no pool
        watch = sum(t.name == _WATCH for t in threading.enumerate())  # lieflow's own
        out["threads"] = len(os.listdir("/proc/self/task")) - watch
    stop = Path(task["stop"]) if task.get("stop") else None
    if _STOP or (stop is not None and stop.exists()):  # interrupted before it started
        return {**out, "status": "pending", "error": "", "finished": started}
    _BUSY = True
    try:
        config = parse_config(task["text"], source=task["source"], base_dir=task["base_dir"])
        setup = build(config, output=task["output"], replace=False)
        monitor = _ProgressFile(Path(task["progress"]) if task.get("progress") else None, stop)
        stored: list[Any] = []  # the run's ZarrSink, once its file is open
        more_sinks = _store_sink(task, stored)
        try:
            try:
                summary = io.run(setup, resume=True, monitor=monitor, more_sinks=more_sinks)
            except io.DamagedOutputError as exc:
                # a worker killed during a write (the lost attempt of a Dask task) can leave
                # the file unreadable past its last good checkpoint; the run is deterministic,
                # so running it again from the start gives the same bits
                out["restarted"] = str(exc)
                setup = build(config, output=task["output"], replace=True)
                stored.clear()
                summary = io.run(setup, monitor=monitor, more_sinks=more_sinks)
        except LieflowError:
            _store_run(task, out, stored)  # a failed run: its steps before the failure
            raise
        _store_run(task, out, stored)
        out.update(
            status=summary.status,
            completed_steps=summary.completed_steps,
            requested_steps=summary.requested_steps,
            new_steps=summary.new_steps,
            wall_time=summary.wall_time,
            max_energy_error=summary.max_energy_error,
            error=summary.failure,
        )
    except io.OutputBusyError as exc:
        out.update(status="busy", error=str(exc))
    except ConfigError as exc:
        # another attempt created the file between this one's check and its create: try
        # again (it will resume it); any other configuration error is the run's failure
        raced = exc.key == "[run] output" and "already exists" in str(exc)
        out.update(status="busy" if raced else "failed", error=str(exc))
    except LieflowError as exc:
        out.update(status="failed", error=str(exc))
    except KeyboardInterrupt:
        out.update(status="interrupted", error="")
    except Exception as exc:  # a bug or an environment problem: record it, go on
        tb = traceback.format_exc(limit=-6)
        out.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=tb)
    finally:
        _BUSY = False
    out["finished"] = time.time()
    return out
