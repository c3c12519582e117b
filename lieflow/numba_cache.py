"""Where lieflow's compiled code is cached on disk: a per-user cache directory, never the
installed package.

numba's ``cache=True`` writes its cache next to the module (``<package>/__pycache__``) when
that folder is writable. For an installed lieflow that folder is in ``site-packages``, and
the files numba leaves there are not in the wheel's record: uninstalling lieflow (e.g. to
reinstall it in editable mode, as the README's second command does after its first) leaves
a ``site-packages/lieflow/`` folder that Python then imports as an empty namespace package
in place of the editable install (``cannot import name '__version__' from 'lieflow'``).

:func:`cached_njit` compiles like ``numba.njit`` with its disk cache in
:func:`cache_directory` instead; lieflow's loops and the plugins' compiled maps use it. It
imports numba: import this module only where numba is installed.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import attrs
import numba
import numpy as np
from numba.core import caching, config

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no lock, each process compiles
    fcntl = None  # type: ignore[assignment]

F = TypeVar("F", bound=Callable[..., Any])

logger = logging.getLogger(__name__)

#: Seconds a process waits for another one compiling the same function (then it compiles
#: the function itself): a bound on the wait, not a time the compilation is expected to take
#: (an entry point of the compiled engine takes 5–15 s on an idle core).
COMPILE_WAIT = 600.0


def cache_directory() -> Path:
    """The directory of lieflow's numba cache.

    numba's own cache directory if the user set one (``NUMBA_CACHE_DIR``, as numba read it
    at import), else ``$XDG_CACHE_HOME/lieflow/numba``, else ``~/.cache/lieflow/numba``
    (the XDG base directory specification's default). Below it, numba's cache of each
    source folder has a subfolder of its own (named by a hash of the folder's path), so two
    installations of lieflow never share cache files.
    """
    numba_dir = getattr(config, "CACHE_DIR", "")
    if numba_dir:
        return Path(numba_dir)
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "lieflow" / "numba"


class _UserCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """numba's cache locator for a function of a source file, in :func:`cache_directory`
    (numba's ``UserProvidedCacheLocator``, with lieflow's directory in place of
    ``NUMBA_CACHE_DIR``)."""

    def __init__(self, py_func: Callable[..., Any], py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        subpath = self.get_suitable_cache_subpath(py_file)
        self._cache_path = str(cache_directory() / subpath)

    def get_cache_path(self) -> str:
        return self._cache_path


class _UserCacheImpl(caching.CompileResultCacheImpl):
    """numba's cache of compiled functions, located only by :class:`_UserCacheLocator`
    (never in the source tree). An explicit ``NUMBA_CACHE_LOCATOR_CLASSES`` still wins."""

    _locator_classes = [_UserCacheLocator]  # noqa: RUF012 - numba's attribute, a list


class _UserFunctionCache(caching.FunctionCache):
    _impl_class = _UserCacheImpl


def cached_njit(func: F, *, signature: Any = None, **options: Any) -> F:
    """``numba.njit(signature, cache=True, **options)(func)``, cached in
    :func:`cache_directory`.

    Without ``signature`` the function compiles at its first call for the types it is
    called with, as ``numba.njit`` does; with one it compiles now for that signature only,
    holding a lock beside its cache files meanwhile (:func:`_compiling`), so that of several
    processes asking for it at once on an empty cache one compiles and the others load its
    result. Where no cache directory can be created or written, the function is compiled in
    memory in every process (numba's own fallback is to raise ``RuntimeError``).
    """
    dispatcher = numba.njit(**options)(func)
    cache: _UserFunctionCache | None
    try:
        cache = _UserFunctionCache(func)
    except RuntimeError:  # no writable cache location: compile in memory
        cache = None
    else:
        dispatcher._cache = cache  # what numba's enable_caching() does, with our locator
    if signature is not None:
        with _compiling(cache, func.__qualname__):
            dispatcher.compile(signature)  # loaded from the disk cache if there
        dispatcher.disable_compile()
    return dispatcher


@contextlib.contextmanager
def _compiling(cache: _UserFunctionCache | None, name: str) -> Iterator[None]:
    """Hold the lock of ``cache``'s function (``flock`` on ``<function>-<line>.pyXY.lock``
    beside its cache files) while this process compiles it or loads it from the cache, so that
    processes starting at once on an empty cache (a sweep's workers, a test suite's)
    compile it once: the others wait, then load what the first one saved. Waits at most
    :data:`COMPILE_WAIT` seconds; where no lock can be taken (no cache directory, a file
    system without ``flock``, not POSIX) each process compiles for itself, as without one."""
    fd = -1
    if cache is not None and fcntl is not None:
        try:
            cache._impl.locator.ensure_cache_path()
            lock = Path(cache.cache_path) / f"{cache._impl.filename_base}.lock"
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except (OSError, AttributeError):
            fd = -1
    try:
        if fd >= 0:
            _lock(fd, name)
        yield
    finally:
        if fd >= 0:
            os.close(fd)  # releases the lock


def _lock(fd: int, name: str) -> None:
    """Take the ``flock`` of ``fd``, waiting (polled: a wait that cannot hang) while another
    process holds it, at most :data:`COMPILE_WAIT` seconds."""
    deadline = time.monotonic() + COMPILE_WAIT
    waiting = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                logger.info("%s: still locked after %.0f s, compiling it here", name, COMPILE_WAIT)
                return
            if not waiting:
                logger.info("%s: another process is compiling it; waiting for its cache", name)
                waiting = True
            time.sleep(0.05)
        except OSError:  # no flock on this file system
            return


#: Passes over at least this many numbers (a ``1024 × 1024`` complex matrix, where a pass
#: takes milliseconds) split their work among numba's threads (:class:`SplitKernel`).
#: Only where the cores are the run's own: a thread that waits for a busy core holds up
#: the whole pass (measured on a loaded 2-core machine, Euler–Zeitlin midpoint, numpy
#: engine, two numba threads against one: N = 512 2.6x the CPU time and 2x the wall time,
#: N = 1024 1.2x the CPU time, 3-4x the wall time). ``NUMBA_NUM_THREADS=1`` (or
#: ``numba.set_num_threads(1)``) keeps every pass on one thread.
SPLIT_SIZE = 2 * 1024 * 1024


def _probe(out: Any) -> None:  # pragma: no cover - compiled
    for i in numba.prange(out.size):
        out[i] = i


@functools.cache
def _threads_safe() -> bool:
    """Whether numba's threading layer lets several Python threads launch parallel code at
    once (``tbb``, ``omp``; its ``workqueue`` aborts the process when they do): the layer
    numba chose for a first, tiny parallel launch."""
    cached_njit(_probe, parallel=True)(np.empty(2))
    return str(numba.threading_layer()) != "workqueue"


def work_groups(size: int) -> int:
    """How many groups a :class:`SplitKernel` splits a pass over ``size`` numbers into: 1
    below :data:`SPLIT_SIZE`, with one numba thread (``NUMBA_NUM_THREADS=1``,
    ``numba.set_num_threads(1)``) or where the threading layer is not safe to launch from
    several Python threads (:func:`_threads_safe`); else numba's thread count."""
    if size < SPLIT_SIZE:
        return 1
    threads = numba.get_num_threads()
    return threads if threads > 1 and _threads_safe() else 1


@attrs.frozen
class SplitKernel:
    """A compiled pass whose first argument ``groups`` splits its work into that many
    independent parts (a loop ``for g in prange(groups)``, each part writing its own
    outputs, any sum over parts added in a fixed order), compiled twice: serial, for one
    group, and ``parallel=True``, for more (on first use), with ``prange`` bound to
    ``numba.prange`` (the module that defines the pass binds ``prange = range``, so that
    it needs no numba to import). Each output number is the same
    arithmetic on the same operands in either, so the bits do not depend on the number of
    groups or threads (tested). ``options``: :func:`cached_njit`'s."""

    func: Callable[..., Any]
    options: dict[str, Any] = attrs.field(factory=dict)

    def __call__(self, groups: int, *args: Any) -> Any:
        return self.dispatcher(groups > 1)(groups, *args)

    def dispatcher(self, parallel: bool = False) -> Any:
        """numba's compiled function, serial or parallel (compiled once each)."""
        options = tuple(
            sorted((k, frozenset(v) if isinstance(v, set) else v) for k, v in self.options.items())
        )
        return _split_compile(self.func, parallel, options)


@functools.cache
def _split_compile(func: Callable[..., Any], parallel: bool, options: tuple[Any, ...]) -> Any:
    if parallel:
        # a copy under its own name (numba's disk cache tells functions apart by their
        # qualified names and signatures, not by how they were compiled) whose ``prange``
        # is numba's
        names = dict(func.__globals__, prange=numba.prange)
        copy = types.FunctionType(
            func.__code__, names, func.__name__, func.__defaults__, func.__closure__
        )
        copy.__qualname__ = func.__qualname__ + "_parallel"
        func = copy
    kwargs = {k: set(v) if isinstance(v, frozenset) else v for k, v in options}
    return cached_njit(func, parallel=parallel, **kwargs)
