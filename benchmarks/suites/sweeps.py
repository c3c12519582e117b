"""Sweeps (issue 16): the local process pool against the same runs one after another, Dask's
overhead per run, and opening a 100-run sweep as one dataset.

Three measurements, each a ratio or a difference of timings taken in this process, medians of
interleaved rounds (:func:`benchmarks.timing.compare`):

* **pool speed-up** — ``lieflow.sweep(grid)`` with the default local pool of 2 worker
  processes (started with ``spawn`` by the call, so their start-up is included) against the
  same runs one after another in this process (a one-thread executor);
* **Dask overhead per run** — a real ``distributed.LocalCluster`` (2 worker processes × 1
  thread) against a process pool of 2, both started and warmed up before timing, on the same
  runs: ``(dask − pool) / runs`` is what Dask adds to every run (scheduling, the task's round
  trips), apart from the one-off start of the cluster, reported on its own;
* **opening a sweep** — ``lieflow.open_sweep`` on a directory of 100 complete runs, and one
  reduction over all of them (the largest energy error of every run, which reads each file);
* **the Zarr store** — the same runs one after another with ``store="zarr"`` (each run's
  group written as it steps, by a second sink of its loop) against without a store: what
  the store adds per run.

Every timed sweep writes into a fresh directory, so nothing is skipped as already complete.
"""

from __future__ import annotations

import concurrent.futures as cf
import itertools
import multiprocessing
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import attrs

import lieflow as lf
from lieflow.app.sweeps import SweepResult, parse_sweep

from ..config import BenchContext
from ..report import Section, Table, TargetCheck, seconds
from ..timing import Timing, compare

#: Issue 16: the local pool at least this many times faster than one run after another.
TARGET_SPEEDUP = 1.8
#: Issue 16: Dask's overhead per run at most this many seconds.
TARGET_DASK_OVERHEAD = 0.050
#: Issue 16: opening a 100-run sweep (and one reduction) within this many seconds.
TARGET_OPEN = 1.0
#: Processes of the pools and of the Dask cluster (the issue's targets are for 2 cores).
WORKERS = 2


@attrs.frozen
class Sizes:
    """The sizes of the three measurements.

    Attributes
    ----------
    runs : int
        Runs of the pool and Dask sweeps.
    pool_steps : int
        Steps per run of the pool speed-up sweep (enough work for the pool's start to be
        worth it: about half a second per run).
    dask_steps : int
        Steps per run of the Dask overhead sweep (little work: the overhead shows).
    open_runs : int
        Runs of the sweep that is opened.
    repeats : int
        Interleaved rounds (medians reported).
    """

    runs: int
    pool_steps: int
    dask_steps: int
    open_runs: int
    repeats: int


def sizes(ctx: BenchContext) -> Sizes:
    """The issue's sizes, or tiny ones in quick mode."""
    if ctx.config.quick:
        return Sizes(runs=4, pool_steps=20, dask_steps=2, open_runs=6, repeats=1)
    return Sizes(runs=32, pool_steps=2000, dask_steps=50, open_runs=100, repeats=3)


def grid_text(runs: int, steps: int) -> str:
    """A grid of ``runs`` small runs: Manakov's generalized rigid body (n = 5), gauss2, one
    random initial condition per run (``initial.seed`` swept), ``steps`` steps of 0.01."""
    return f"""
[system]
name = "generalized_rigid_body"

[initial]
random = true
seed = 0

[scheme]
name = "gauss2"

[solver]
name = "fixed_point"
params = {{ rtol = 1e-14 }}

[run]
h = 0.01
steps = {steps}
save_every = {max(1, steps // 4)}
engine = "numpy"

[sweep]
"initial.seed" = {list(range(runs))}
"""


def _fresh(root: Path, prefix: str) -> Iterator[Path]:
    """New directories ``root/prefix-0``, ``root/prefix-1``, ... (one per timed sweep)."""
    for k in itertools.count():
        yield root / f"{prefix}-{k}"


def _sweeper(
    text: str, dirs: Iterator[Path], executor: Any, **options: Any
) -> Callable[[], SweepResult]:
    """A callable that runs the grid in the next fresh directory and checks it completed."""

    def run() -> SweepResult:
        result = lf.sweep(parse_sweep(text, directory=next(dirs)), executor, **options)
        if not result.ok:
            raise RuntimeError(f"the benchmark sweep did not complete: {result.counts}")
        return result

    return run


def _env_one_thread() -> dict[str, str | None]:
    """Set one BLAS thread for processes started from now on; the previous values."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    previous = {n: os.environ.get(n) for n in names}
    for n in names:
        os.environ[n] = "1"
    return previous


def _restore(previous: dict[str, str | None]) -> None:
    for name, value in previous.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def measure_pool(root: Path, size: Sizes) -> dict[str, Timing[SweepResult]]:
    """The default local pool (started by each call) against one run after another here."""
    text = grid_text(size.runs, size.pool_steps)
    dirs = _fresh(root, "sequential")

    def one_after_another() -> SweepResult:
        with cf.ThreadPoolExecutor(max_workers=1) as thread:
            return _sweeper(text, dirs, thread)()

    pool = _sweeper(text, _fresh(root, "pool"), "local", workers=WORKERS)
    return compare({"one after another": one_after_another, "local pool": pool}, size.repeats)


@attrs.frozen
class DaskResult:
    """Timings of the Dask overhead measurement."""

    timings: dict[str, Timing[SweepResult]]
    cluster_start: float
    error: str | None = None


def measure_dask(root: Path, size: Sizes) -> DaskResult:
    """A real LocalCluster against a process pool, both warm, on the same runs."""
    try:
        import distributed
    except ImportError as exc:
        return DaskResult({}, float("nan"), f"distributed is not installed ({exc})")
    text = grid_text(size.runs, size.dask_steps)
    warm = grid_text(WORKERS, 2)
    previous = _env_one_thread()
    try:
        start = time.perf_counter()
        cluster = distributed.LocalCluster(
            n_workers=WORKERS, threads_per_worker=1, processes=True, dashboard_address=None
        )
        client = distributed.Client(cluster)
        cluster_start = time.perf_counter() - start
        pool = cf.ProcessPoolExecutor(WORKERS, mp_context=multiprocessing.get_context("spawn"))
    finally:
        _restore(previous)
    try:
        # warm up: every worker imports lieflow and runs a step before timing
        for name, executor in (("dask", client), ("pool", pool)):
            _sweeper(warm, _fresh(root, f"warm-{name}"), executor)()
        timings = compare(
            {
                "process pool (warm)": _sweeper(text, _fresh(root, "pool-warm"), pool),
                "Dask LocalCluster (warm)": _sweeper(text, _fresh(root, "dask"), client),
            },
            size.repeats,
        )
    finally:
        pool.shutdown(wait=True)
        client.close()
        cluster.close()
    return DaskResult(timings, cluster_start)


def measure_open(root: Path, size: Sizes) -> dict[str, Timing[Any]]:
    """Write a sweep of ``open_runs`` runs (untimed), then time opening it and a reduction."""
    directory = root / "open"
    result = lf.sweep(parse_sweep(grid_text(size.open_runs, 20), directory=directory), "local",
                      workers=WORKERS)  # fmt: skip
    if not result.ok:
        raise RuntimeError(f"the sweep to open did not complete: {result.counts}")

    def open_only() -> Any:
        return lf.open_sweep(directory)

    def open_and_reduce() -> Any:
        ds = lf.open_sweep(directory)
        worst = abs(ds.energy_error).max("step").values  # reads every run's diagnostics
        if worst.shape != (size.open_runs,):
            raise RuntimeError(f"unexpected shape {worst.shape}")
        return worst

    open_only()  # first import of xarray's machinery
    return compare({"open_sweep": open_only, "open_sweep + reduction": open_and_reduce},
                   max(3, size.repeats))  # fmt: skip


def measure_store(root: Path, size: Sizes) -> dict[str, Timing[SweepResult]]:
    """A quarter of the pool's runs one after another here, with and without a Zarr store."""
    text = grid_text(max(2, size.runs // 4), size.pool_steps)

    def sequential(prefix: str, **options: Any) -> Callable[[], SweepResult]:
        dirs = _fresh(root, prefix)

        def one() -> SweepResult:
            with cf.ThreadPoolExecutor(max_workers=1) as thread:
                return _sweeper(text, dirs, thread, **options)()

        return one

    return compare({"no store": sequential("no-store"),
                    "store zarr": sequential("store", store="zarr")}, size.repeats)  # fmt: skip


def _spin(count: int) -> float:
    """Seconds of a pure-Python loop of ``count`` additions (CPU-bound, no BLAS, no I/O)."""
    start = time.perf_counter()
    total = 0
    for i in range(count):
        total += i
    return time.perf_counter() - start


def parallel_ceiling(count: int) -> float:
    """How many cores two CPU-bound processes get here now: ``2 t_alone / t_together``
    (2.0 on two idle cores), the ceiling of any pool's speed-up at the time of measuring."""
    with cf.ProcessPoolExecutor(WORKERS, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_spin, [1000] * WORKERS))  # started
        alone = _spin(count)
        start = time.perf_counter()
        list(pool.map(_spin, [count] * WORKERS))
        together = time.perf_counter() - start
    return WORKERS * alone / together


def _load() -> str:
    try:
        return "load average " + ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "load average unknown"


def run(ctx: BenchContext) -> Section:
    """The three measurements and their targets."""
    start = time.perf_counter()
    title = "Sweeps: local pool, Dask, opening a sweep"
    try:
        import xarray  # noqa: F401
    except ImportError:
        return Section(title, "Skipped: xarray is not installed (`pip install 'lieflow[sweep]'`).")
    size = sizes(ctx)
    load_before = _load()
    with tempfile.TemporaryDirectory(prefix="lieflow-bench-sweeps-") as tmp:
        root = Path(tmp)
        ceiling = parallel_ceiling(200_000 if ctx.config.quick else 5_000_000)
        pool = measure_pool(root, size)
        dask = measure_dask(root, size)
        opening = measure_open(root, size)
        stored = measure_store(root, size)
    load_after = _load()

    seq, loc = pool["one after another"].median, pool["local pool"].median
    speedup = seq / loc if loc > 0 else float("nan")
    rows = [
        (
            f"{size.runs} runs × {size.pool_steps} steps",
            "one after another, this process",
            seconds(seq),
            seconds(seq / size.runs),
            "1.00×",
        ),
        (
            f"{size.runs} runs × {size.pool_steps} steps",
            f"local pool, {WORKERS} processes (started by the call)",
            seconds(loc),
            seconds(loc / size.runs),
            f"{speedup:.2f}×",
        ),
    ]
    targets = [
        TargetCheck(
            target=f"a sweep of {size.runs} small runs on the local pool ≥ {TARGET_SPEEDUP}× "
            f"faster than one after another on {WORKERS} cores",
            measured=f"{speedup:.3f}× (median of {size.repeats} interleaved rounds; "
            f"{seconds(seq / size.runs)} of work per run; {speedup / ceiling:.0%} of the "
            f"{ceiling:.2f}× that two CPU-bound processes got)",
            met=speedup >= TARGET_SPEEDUP,
            gap="" if speedup >= TARGET_SPEEDUP else f"{TARGET_SPEEDUP / speedup:.3f}× short",
            limit=f"two CPU-bound processes got {ceiling:.2f} cores' worth when measured "
            "(the machine's other jobs share its 2 cores), the ceiling of any pool's "
            "speed-up; the pool's start (spawned interpreters importing lieflow) is paid "
            "once per call",
        )
    ]
    if dask.error is None:
        t_pool = dask.timings["process pool (warm)"].median
        t_dask = dask.timings["Dask LocalCluster (warm)"].median
        overhead = (t_dask - t_pool) / size.runs
        for label, t in (("process pool, 2 processes, warm", t_pool),
                         ("Dask LocalCluster, 2 × 1 thread, warm", t_dask)):  # fmt: skip
            rows.append(
                (
                    f"{size.runs} runs × {size.dask_steps} steps",
                    label,
                    seconds(t),
                    seconds(t / size.runs),
                    "—",
                )
            )
        targets.append(
            TargetCheck(
                target=f"Dask overhead ≤ {TARGET_DASK_OVERHEAD * 1e3:.0f} ms per run",
                measured=f"{overhead * 1e3:.1f} ms per run ((Dask − pool) / {size.runs} runs, "
                f"both warm; starting the LocalCluster took {seconds(dask.cluster_start)} "
                "once"
                + (
                    "; below zero: Dask was no slower than the pool, the difference is "
                    "the machine's noise"
                    if overhead < 0
                    else ""
                )
                + ")",
                met=overhead <= TARGET_DASK_OVERHEAD,
                gap=""
                if overhead <= TARGET_DASK_OVERHEAD
                else f"{overhead / TARGET_DASK_OVERHEAD:.1f}× over",
                limit="a scheduler round trip and the task's pickled arguments and result per "
                "run; the files are written by the workers, nothing large goes through Dask",
            )
        )
    else:
        targets.append(
            TargetCheck(
                target=f"Dask overhead ≤ {TARGET_DASK_OVERHEAD * 1e3:.0f} ms per run",
                measured="not measured",
                met=None,
                limit=dask.error,
            )
        )
    t_open = opening["open_sweep"].median
    t_reduce = opening["open_sweep + reduction"].median
    rows.append((f"{size.open_runs} complete runs", "open_sweep", seconds(t_open),
                 seconds(t_open / size.open_runs), "—"))  # fmt: skip
    rows.append((f"{size.open_runs} complete runs", "open_sweep + max energy error of every run",
                 seconds(t_reduce), seconds(t_reduce / size.open_runs), "—"))  # fmt: skip
    targets.append(
        TargetCheck(
            target=f"opening a {size.open_runs}-run sweep as a dataset (and one reduction) "
            f"≤ {TARGET_OPEN:g} s",
            measured=f"{seconds(t_open)} to open, {seconds(t_reduce)} with the reduction",
            met=t_reduce <= TARGET_OPEN,
            gap="" if t_reduce <= TARGET_OPEN else f"{t_reduce / TARGET_OPEN:.1f}× over",
            limit="opening reads each file's header and checkpoint; the reduction reads one "
            "diagnostic of every file",
        )
    )
    store_runs = max(2, size.runs // 4)
    bare, with_store = stored["no store"].median, stored["store zarr"].median
    store_rows = (
        ("one after another, no store", bare),
        ('one after another, store = "zarr" (written as it steps)', with_store),
    )
    for label, t in store_rows:
        rows.append((f"{store_runs} runs × {size.pool_steps} steps", label, seconds(t),
                     seconds(t / store_runs), f"{bare / t:.2f}×" if t > 0 else "—"))  # fmt: skip
    table = Table(
        ("case", "how", "median", "per run", "speed-up"),
        tuple(rows),
        caption="Generalized rigid body (n = 5), gauss2, h = 0.01, engine numpy, one BLAS "
        "thread per process; each timed sweep writes a fresh directory.",
    )
    notes = (
        f"Machine load during the section: {load_before} before, {load_after} after "
        f"(2 cores shared with other jobs); two CPU-bound processes ran {ceiling:.2f}× as "
        "fast together as one alone (2.00× on two idle cores).",
        "One after another: `lieflow.sweep(grid, ThreadPoolExecutor(1))`, every run in this "
        "process in turn, with the same files and manifest as the pool.",
        "Warm: the pool and the cluster were started, and every worker had imported lieflow "
        "and run a step, before the timed rounds.",
    )
    return Section(
        title=title,
        intro="`lieflow sweep` and `lieflow.sweep` on the default local process pool and on "
        "Dask distributed, and `lieflow.open_sweep` on a large sweep directory (issue 16).",
        tables=(table,),
        targets=tuple(targets),
        notes=notes,
        seconds=time.perf_counter() - start,
    )
