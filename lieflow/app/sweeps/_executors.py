"""Where a sweep's runs execute: the default process pool (spawned workers, one BLAS thread
each, renewed if one dies), Dask distributed (a scheduler's cluster or a new local one),
or any :class:`concurrent.futures.Executor`."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import os
import signal
import threading
from collections.abc import Iterator
from typing import Any

from ...errors import InputError, LieflowError
from ._worker import _THREAD_VARS, _worker_init


def _require(module: str, extra: str = "sweep") -> Any:
    """Import an optional dependency or say which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise InputError(
            f"this needs the {module.split('.')[0]!r} package ({exc}). To fix: "
            f"pip install 'lieflow[{extra}]'."
        ) from None


@contextlib.contextmanager
def _thread_env() -> Iterator[None]:
    """One BLAS/OpenMP thread in processes started inside the block."""
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update(dict.fromkeys(_THREAD_VARS, "1"))
    try:
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


class _LocalPool:
    """The default executor: a spawn-started process pool, re-created if a worker dies."""

    def __init__(self, workers: int) -> None:
        import multiprocessing

        self.workers = workers
        self._ctx = multiprocessing.get_context("spawn")
        self.pool = self._new()

    def _new(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(self.workers, mp_context=self._ctx, initializer=_worker_init)

    def renew(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = self._new()

    def stop_workers(self) -> None:
        """SIGTERM to every worker: a running run stops at its next step, "interrupted"."""
        for proc in list(getattr(self.pool, "_processes", {}).values()):
            with contextlib.suppress(Exception):
                proc.terminate()


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT while worker processes are started, so that they inherit "ignored"
    (Python keeps an ignored SIGINT ignored): Ctrl-C on a terminal signals the whole
    process group, and the coordinator alone decides how runs stop (their files marked
    "interrupted"), instead of each worker dying with a traceback mid-write."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _dask_executor(
    scheduler: str | None, workers: int | None, stack: contextlib.ExitStack
) -> cf.Executor:
    distributed = _require("distributed")
    if scheduler:
        try:
            client = distributed.Client(scheduler)  # distributed.comm.timeouts.connect
        except (OSError, TimeoutError) as exc:
            raise LieflowError(
                f"cannot connect to the Dask scheduler at {scheduler!r} ({exc}). To fix: start "
                "it (`dask scheduler`) and give the address it prints (tcp://HOST:8786)."
            ) from None
    else:
        with _thread_env(), _sigint_ignored():  # the workers inherit it: Ctrl-C is ours
            cluster = distributed.LocalCluster(
                n_workers=workers or os.cpu_count() or 1,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            )
        stack.callback(cluster.close)
        client = distributed.Client(cluster)
    stack.callback(client.close)
    return client.get_executor(pure=False)


def _executor_of(obj: Any) -> cf.Executor:
    """A ``distributed.Client`` -> its executor; an Executor as it is."""
    if isinstance(obj, cf.Executor):
        return obj
    if hasattr(obj, "get_executor") and hasattr(obj, "submit"):
        return obj.get_executor(pure=False)
    raise InputError(
        f"executor must be 'local', 'dask', a concurrent.futures.Executor or a "
        f"distributed.Client, got {obj!r}"
    )
