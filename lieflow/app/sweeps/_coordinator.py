"""The coordinator of a sweep: submits the runs to the executor (longest first, a few per
worker), collects their outcomes, retries lost and busy runs, stops them on Ctrl-C, keeps
the manifest and reports progress."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import datetime as _dt
import json
import os
import time
from collections import deque
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ...errors import LieflowError
from ..datasets import SWEEP_FORMAT
from ._executors import _LocalPool
from ._files import _file_state, _is_complete, _max_energy_error
from ._grid import Sweep, SweepRun
from ._progress import SweepMonitor
from ._store import _consolidate, _store_complete_runs
from ._worker import run_task

SWEEP_FORMAT_VERSION = 1
#: Statuses of a run in the manifest.
STATUSES = ("pending", "running", "complete", "failed", "interrupted")


def _write_json(path: Path, data: Any) -> None:
    """Write JSON atomically: a temporary file in the same directory, fsync, rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1, default=str, allow_nan=True)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class _Coordinator:
    """Submits runs, collects outcomes, retries, writes the manifest, reports progress."""

    def __init__(
        self,
        grid: Sweep,
        pool: cf.Executor,
        local: _LocalPool | None,
        monitor: SweepMonitor | None,
        max_attempts: int,
        busy_timeout: float,
        store: Path | None = None,
    ) -> None:
        self.grid, self.pool, self.local, self.store = grid, pool, local, store
        self.monitor, self.max_attempts, self.busy_timeout = monitor, max_attempts, busy_timeout
        self.progress_dir = grid.directory / ".progress"
        #: created on Ctrl-C: every run (on any worker) stops at its next chunk of steps
        self.stop_file = self.progress_dir / "stop"
        self.records: list[dict[str, Any]] = []
        self.last_write = 0.0
        self.dirty = False
        self.skipped = 0
        self.worked = False  # a task started or returned (the pool's workers can start)
        self.t0 = time.time() - 1.0

    def _record(
        self, spec: SweepRun, state: Mapping[str, Any] | None, previous: Mapping[str, Any]
    ) -> dict[str, Any]:
        complete = _is_complete(spec, state)
        carried = {}
        if complete:  # what the last sweep recorded of it, or the file's own numbers
            carried = {k: previous[k] for k in ("host", "pid") if k in previous}
            error = previous.get("max_energy_error")
            carried["max_energy_error"] = (
                error if isinstance(error, float) else _max_energy_error(spec.output)
            )
        return {
            "id": spec.id,
            "index": list(spec.index),
            "params": dict(spec.params),
            "output": os.path.relpath(spec.output, self.grid.directory),
            "status": "complete" if complete else "pending",
            "error": "",
            "completed_steps": state["completed_steps"] if state else 0,
            "requested_steps": spec.config.run.steps,
            "wall_time": state["wall_time"] if state else 0.0,
            "max_energy_error": None,
            "attempts": previous.get("attempts", 0) if complete else 0,
            **carried,
        }

    def write_manifest(self, force: bool = False) -> None:
        now = time.monotonic()
        every = 0.5 + len(self.records) / 4000  # 3 s for 10,000 runs: writes stay cheap
        if not force and (not self.dirty or now - self.last_write < every):
            return
        g = self.grid
        from ... import __version__

        _write_json(
            g.manifest,
            {
                "format": SWEEP_FORMAT,
                "format_version": SWEEP_FORMAT_VERSION,
                "lieflow_version": __version__,
                "grid_source": g.source,
                "grid": g.text,
                "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "axes": [
                    {"name": a.name, "keys": list(a.keys), "values": [list(v) for v in a.values]}
                    for a in g.axes
                ],
                "counts": self.counts(),
                "runs": self.records,
            },
        )
        self.last_write, self.dirty = now, False

    def counts(self) -> dict[str, int]:
        out = dict.fromkeys(STATUSES, 0)
        for r in self.records:
            out[r["status"]] += 1
        return out

    def _task(self, i: int) -> dict[str, Any]:
        spec = self.grid.runs[i]
        return {
            "text": spec.config.text,
            "source": self.grid.source,
            "base_dir": str(self.grid.base_dir),
            "output": str(spec.output),
            "progress": str(self.progress_dir / f"{spec.id}.json"),
            "id": spec.id,
            "store": str(self.store) if self.store is not None else "",
            "stop": str(self.stop_file),
        }

    def _capacity(self, runs: int) -> int:
        """How many runs to keep submitted: two per worker where the pool's size is known
        (the default pool, a ProcessPoolExecutor, a Dask cluster: its threads now), so that
        an interrupt has little to cancel and progress is read from few files; else all."""
        if self.local is not None:
            return 2 * self.local.workers
        client = getattr(self.pool, "_client", None)  # a Dask ClientExecutor
        if client is not None:
            try:
                threads = sum(client.nthreads().values())
            except Exception:
                threads = 0
            return max(2 * threads, 8)
        size = getattr(self.pool, "_max_workers", 0)
        return 2 * size if isinstance(size, int) and size > 0 else runs

    def _started_any(self) -> bool:
        """Whether a worker of this sweep has reported progress (so workers can start)."""
        try:
            return any(p.stat().st_mtime >= self.t0 for p in self.progress_dir.glob("*.json"))
        except OSError:
            return False

    def _steps_now(self, in_flight: Sequence[int]) -> int:
        """Steps done in all runs, those of in-flight runs as their workers report them; an
        in-flight run is "running" once its worker has reported, "pending" (queued) before."""
        flying = set(in_flight)
        steps = sum(r["completed_steps"] for j, r in enumerate(self.records) if j not in flying)
        for i in flying:
            rec = self.records[i]
            p = self.progress_dir / f"{self.grid.runs[i].id}.json"
            try:
                steps += int(json.loads(p.read_text())["done"])
            except (OSError, ValueError, KeyError, TypeError):
                steps += rec["completed_steps"]
            else:
                if rec["status"] == "pending":
                    rec["status"] = "running"
                    self.dirty = self.worked = True
        return steps

    def run(self) -> bool:
        grid = self.grid
        with contextlib.suppress(OSError):
            self.progress_dir.mkdir(exist_ok=True)
            self.stop_file.unlink(missing_ok=True)  # left by a coordinator that was killed
        try:
            old = json.loads(grid.manifest.read_text(encoding="utf-8"))
            before = {r["id"]: r for r in old["runs"]}
        except (OSError, ValueError, KeyError, TypeError):
            before = {}
        self.records = [self._record(s, _file_state(s), before.get(s.id, {})) for s in grid.runs]
        # longest runs first (by steps, then grid order): the last runs to finish are then
        # short ones, so workers fall idle together at the end (LPT scheduling)
        todo: deque[tuple[float, int]] = deque(
            sorted(
                ((0.0, i) for i, r in enumerate(self.records) if r["status"] != "complete"),
                key=lambda item: -grid.runs[item[1]].config.run.steps,
            )
        )
        self.skipped = skipped = len(grid.runs) - len(todo)
        if self.store is not None:
            _store_complete_runs(self.store, grid.runs, self.records)
        self.dirty = True
        self.write_manifest(force=True)
        total_steps = sum(s.config.run.steps for s in grid.runs)
        if self.monitor is not None:
            self.monitor.start(len(grid.runs), skipped)
        in_flight: dict[cf.Future[Any], int] = {}
        busy_since: dict[int, float] = {}
        interrupted = False
        cap, cap_checked, scanned = self._capacity(len(grid.runs)), time.monotonic(), 0.0
        try:
            while todo or in_flight:
                now = time.monotonic()
                if now - cap_checked > 5.0:  # a Dask cluster may grow or shrink
                    cap, cap_checked = self._capacity(len(grid.runs)), now
                for _ in range(len(todo)):
                    if len(in_flight) >= cap:
                        break
                    not_before, i = todo.popleft()
                    if not_before > now:
                        todo.append((not_before, i))
                        continue
                    rec = self.records[i]
                    rec["attempts"] += 1
                    rec["status"], rec["error"] = "pending", ""  # queued: "running" once started
                    with contextlib.suppress(OSError):  # a lost attempt's
                        (self.progress_dir / f"{grid.runs[i].id}.json").unlink()
                    try:
                        in_flight[self.pool.submit(run_task, self._task(i))] = i
                    except Exception as exc:  # a broken pool, a closed client, a lost scheduler
                        rec["attempts"] -= 1
                        if self.local is not None:  # our pool broke: its futures tell which
                            todo.appendleft((0.0, i))
                            if not in_flight:
                                self.local.renew()
                                self.pool = self.local.pool
                            break
                        raise LieflowError(
                            f"the executor refused to run more runs ({type(exc).__name__}: "
                            f"{exc}); the manifest records where the sweep stands. To fix: "
                            "restart the executor (the Dask scheduler and workers) and run "
                            "the sweep again: it continues where it stopped."
                        ) from None
                    self.dirty = True
                done, _ = cf.wait(list(in_flight), timeout=0.5, return_when=cf.FIRST_COMPLETED)
                broken = False
                for fut in done:
                    i = in_flight.pop(fut)
                    broken |= self._collect(fut, i, todo, busy_since)
                if broken and self.local is not None:
                    for fut, i in list(in_flight.items()):  # the whole pool died with it
                        in_flight.pop(fut)
                        self._collect(fut, i, todo, busy_since)
                    self.local.renew()
                    self.pool = self.local.pool
                if time.monotonic() - scanned >= 0.5 or not in_flight:
                    scanned = time.monotonic()
                    steps = self._steps_now(list(in_flight.values()))
                    if self.monitor is not None:
                        self.monitor.update(self.counts(), steps, total_steps)
                self.write_manifest()
        except KeyboardInterrupt:
            interrupted = True
            self._interrupt(in_flight, todo)
        finally:
            if self.monitor is not None:
                self.monitor.stop()
            self.write_manifest(force=True)
            if self.store is not None:
                _consolidate(self.store)
        return interrupted

    def _collect(
        self,
        fut: cf.Future[Any],
        i: int,
        todo: deque[tuple[float, int]],
        busy_since: dict[int, float],
    ) -> bool:
        """Record a finished future; requeue a lost or busy run. True if the pool broke."""
        rec = self.records[i]
        spec = self.grid.runs[i]
        broken = False
        try:
            out = fut.result(timeout=0)
            self.worked = True
        except cf.CancelledError:
            rec["status"] = "pending"
            return False
        except Exception as exc:  # the task did not run to its end: the worker died ...
            from concurrent.futures.process import BrokenProcessPool

            broken = isinstance(exc, BrokenProcessPool)
            if broken and self.local is not None and not (self.worked or self._started_any()):
                raise LieflowError(
                    "the sweep's worker processes could not start (they died before running "
                    f"any run: {exc}). If lieflow.sweep is called from a script, protect the "
                    'call with `if __name__ == "__main__":` (Python starts the workers by '
                    "importing the script, as for any process pool); otherwise see the "
                    'workers\' errors above, or pass executor="dask" or another Executor.'
                ) from None
            state = _file_state(spec)
            if _is_complete(spec, state):
                out = {"status": "complete", **(state or {})}
            elif rec["attempts"] < self.max_attempts:
                rec["status"] = "pending"
                rec["error"] = f"attempt {rec['attempts']}: {type(exc).__name__}: {exc}"
                todo.append((time.monotonic() + 0.5 * rec["attempts"], i))
                self.dirty = True
                return broken
            else:
                out = {
                    "status": "failed",
                    "error": f"{type(exc).__name__}: {exc} (the task "
                    f"was lost {rec['attempts']} times; its file stays resumable)",
                }
        if out["status"] == "busy":
            first = busy_since.setdefault(i, time.monotonic())
            if time.monotonic() - first < self.busy_timeout:
                rec["attempts"] -= 1  # waiting for another writer is not an attempt
                rec["status"] = "pending"
                rec["error"] = out["error"]
                todo.append((time.monotonic() + min(5.0, 0.5 + (time.monotonic() - first)), i))
                self.dirty = True
                return broken
            out["status"] = "failed"
        busy_since.pop(i, None)
        for key in (
            "status",
            "error",
            "completed_steps",
            "requested_steps",
            "new_steps",
            "wall_time",
            "max_energy_error",
            "host",
            "pid",
            "traceback",
            "threads",
            "store_error",
        ):
            if key in out:
                rec[key] = out[key]
        rec["error"] = out.get("error", "") if out["status"] == "failed" else ""
        if rec["status"] not in STATUSES:  # pragma: no cover
            rec["status"] = "failed"
        state = _file_state(spec)
        if state is not None:
            rec["completed_steps"] = state["completed_steps"]
            rec["wall_time"] = state["wall_time"]
        with contextlib.suppress(OSError):
            (self.progress_dir / f"{spec.id}.json").unlink()
        self.dirty = True
        if self.monitor is not None:
            self.monitor.finished(rec)
        return broken

    def _interrupt(
        self, in_flight: dict[cf.Future[Any], int], todo: deque[tuple[float, int]]
    ) -> None:
        """Ctrl-C: stop what runs, where it runs (files marked interrupted), and collect it.

        The stop file stops every run at its next chunk of steps, and a task that starts
        after it returns at once; the default pool's workers also get SIGTERM. Futures are
        then waited for (not cancelled: a cancelled Dask task is killed mid-write, its run
        recorded "pending" with 0 steps) so each run's record says where it stopped."""
        with contextlib.suppress(OSError):
            self.stop_file.touch()
        if self.local is not None:
            for fut in in_flight:
                fut.cancel()
            self.local.stop_workers()
        deadline = time.monotonic() + 60.0
        pending = [f for f in in_flight if not f.cancelled()]
        with contextlib.suppress(Exception):
            cf.wait(pending, timeout=max(0.0, deadline - time.monotonic()))
        with contextlib.suppress(OSError):
            self.stop_file.unlink(missing_ok=True)
        for fut, i in in_flight.items():
            if fut.done() and not fut.cancelled():
                with contextlib.suppress(Exception):
                    self._collect(fut, i, deque(), {})
            rec = self.records[i]
            if rec["status"] in ("running", "pending", "interrupted"):
                # the file's own word: a worker stopped twice (the stop file, then SIGTERM
                # while it closed the file) reports "interrupted" without its steps
                state = _file_state(self.grid.runs[i])
                rec["status"] = "interrupted" if state else "pending"
                if state:
                    rec["completed_steps"] = state["completed_steps"]
        self.dirty = True
