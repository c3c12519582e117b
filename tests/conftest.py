"""Shared fixtures: every registered system and scheme (plugins included) is tested, and
every child process a test starts ends with it (``children``)."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator

import pytest
from processes import Children

import lieflow as lf

if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    # One BLAS thread per test process when pytest-xdist runs the suite in several (README
    # command 2 runs one per core): each with a BLAS thread per core oversubscribes the
    # cores, and OpenBLAS's threads spin while they wait for one another. With two busy
    # loops beside it on 2 cores, the BLAS-heavy files took 70 s with the default threads
    # and 56 s with one (issue 37). threadpoolctl limits the libraries already loaded (a
    # pytest plugin imports numpy before this file); the variables reach the processes the
    # tests start (the variables a sweep's local pool sets for its workers). A user's own
    # setting of a variable is kept. (threadpoolctl: the `test` extra, like pytest-xdist.)
    import threadpoolctl

    from lieflow.app.sweeps._worker import _THREAD_VARS

    for _name in _THREAD_VARS:
        os.environ.setdefault(_name, "1")
    threadpoolctl.threadpool_limits(int(os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")

REGISTRY = lf.default_registry()
SYSTEMS = sorted(REGISTRY.systems)
SCHEMES = sorted(REGISTRY.schemes)


def make_system(name: str) -> lf.IsospectralSystem:
    """The registered system ``name`` with its default parameters (the plugin contract)."""
    return lf.systems.get(name)


@pytest.fixture(params=SYSTEMS)
def system(request: pytest.FixtureRequest) -> lf.IsospectralSystem:
    return make_system(request.param)


@pytest.fixture(params=SCHEMES)
def scheme(request: pytest.FixtureRequest) -> lf.Scheme:
    return lf.schemes.get(request.param)


@pytest.fixture
def children() -> Iterator[Children]:
    """Start child processes with ``children.popen(args, ...)``: each in its own process
    group, all killed (with what they started) when the test ends, pass or fail."""
    started = Children()
    try:
        yield started
    finally:
        started.end()


@pytest.fixture
def one_step_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    """A numpy flow stepped one step per chunk (``lieflow.stepping.BATCH_STEPS = 1``), so a
    monitor or an interrupt between chunks falls at any step a test names, not at the end
    of a batch of steps."""
    monkeypatch.setattr(lf.stepping, "BATCH_STEPS", 1)


def pytest_configure(config: pytest.Config) -> None:
    """The processes that tests interrupt must hear ``SIGINT``: a suite started in the
    background by a non-interactive shell (``pytest &``, ``nohup``) inherits SIGINT
    ignored, and so would every ``lieflow run`` it starts (which then rightly ignores it,
    as a sweep's workers do). A Python handler here is reset to the default in children."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
