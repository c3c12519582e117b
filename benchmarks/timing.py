"""Timing and memory measurement: medians of interleaved rounds, in one process.

Shared machines are noisy, so absolute seconds drift from run to run; the *ratio* of two
codes timed alternately in the same process on the same input is stable. :func:`compare`
runs every contender once per round, for ``repeats`` rounds; the page reports each one's
median round (:attr:`Timing.median`), not its fastest.
"""

from __future__ import annotations

import math
import resource
import subprocess
import time
import tracemalloc
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Generic, TypeVar

import attrs
import numpy as np

T = TypeVar("T")


@attrs.frozen
class Timing(Generic[T]):
    """Wall times of repeated runs of one callable and the last run's result.

    Attributes
    ----------
    runs : tuple of float
        Seconds of each run (empty if the first run raised).
    result : object or None
        What the last run returned (e.g. statistics carrying iteration counts).
    error : str or None
        ``"ExceptionName: message"`` if the callable raised (an engine that cannot run a
        case, a baseline that does not converge); it is then not run again.
    """

    runs: tuple[float, ...]
    result: T | None = attrs.field(repr=False)
    error: str | None = None

    @property
    def best(self) -> float:
        """The fastest run, seconds (``inf`` if none completed)."""
        return min(self.runs, default=math.inf)

    @property
    def median(self) -> float:
        """The median run, seconds (``inf`` if none completed): what the page reports, so
        that one lucky round does not set a figure."""
        return float(np.median(self.runs)) if self.runs else math.inf

    @property
    def value(self) -> T:
        """The last result; raises if the callable failed."""
        if self.result is None:
            raise RuntimeError(f"a required benchmark run failed: {self.error}")
        return self.result

    @property
    def ok(self) -> bool:
        """Whether every run completed."""
        return self.error is None


def best_of(fn: Callable[[], T], repeats: int) -> Timing[T]:
    """Run ``fn`` ``repeats`` times; every run's seconds and the last result."""
    start = time.perf_counter()
    result = fn()
    runs = [time.perf_counter() - start]
    for _ in range(repeats - 1):
        start = time.perf_counter()
        result = fn()
        runs.append(time.perf_counter() - start)
    return Timing(tuple(runs), result)


def compare(contenders: Mapping[str, Callable[[], T]], repeats: int) -> dict[str, Timing[T]]:
    """Time every contender once per round, ``repeats`` rounds, interleaved.

    Interleaving puts every contender under the same background load, so ratios of the
    median rounds are robust to noise that comes and goes.
    """
    runs: dict[str, list[float]] = {name: [] for name in contenders}
    results: dict[str, T] = {}
    errors: dict[str, str] = {}
    for _ in range(max(1, repeats)):
        for name, fn in contenders.items():
            if name in errors:
                continue
            start = time.perf_counter()
            try:
                results[name] = fn()
            except Exception as exc:  # recorded and reported as n/a, never hidden
                errors[name] = f"{type(exc).__name__}: {exc}"
                continue
            runs[name].append(time.perf_counter() - start)
    return {
        name: Timing(tuple(runs[name]), results.get(name), errors.get(name)) for name in contenders
    }


def peak_memory(fn: Callable[[], object]) -> int:
    """Peak bytes allocated while ``fn`` runs (``tracemalloc``; numpy reports its buffers).

    Run it separately from timed runs: tracing slows allocation down.
    """
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    try:
        fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        if not was_tracing:
            tracemalloc.stop()
    return max(0, peak - base)


def matmul_seconds(n: int, count: int, repeats: int, dtype: type = np.float64) -> float:
    """Best-of-``repeats`` seconds of ``count`` ``n×n`` products into a preallocated output.

    The BLAS bound of an iteration that needs ``count`` products.
    """
    rng = np.random.default_rng(0)
    a: np.ndarray = rng.standard_normal((n, n)).astype(dtype)
    b: np.ndarray = rng.standard_normal((n, n)).astype(dtype)
    out: np.ndarray = np.empty((n, n), dtype=dtype)

    def products() -> None:
        for _ in range(count):
            np.matmul(a, b, out=out)

    products()
    return best_of(products, repeats).best


@attrs.frozen
class ProcessTime:
    """A finished child process (its :class:`subprocess.CompletedProcess`), its wall
    seconds and the CPU seconds (user + system) of all it ran."""

    done: subprocess.CompletedProcess[Any]
    wall: float
    cpu: float


def run_process(args: Sequence[str], **options: Any) -> ProcessTime:
    """``subprocess.run(args, **options)``, timed: the wall clock around it and the CPU of
    the child and of every descendant it waited for (the growth of
    ``resource.getrusage(RUSAGE_CHILDREN)``, which other processes on the machine do not
    enter, unlike the wall clock); the caller's other children must not end meanwhile."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(args, **options)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return ProcessTime(done, wall, cpu)
