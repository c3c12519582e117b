"""lieflow sweep on Dask distributed (issue 16.2): a LocalCluster, and a real cluster of
separate processes (``dask scheduler`` + two ``dask worker``) connected by address on
127.0.0.1, one worker killed mid-sweep."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.config import build
from lieflow.app.sweeps import load_sweep

distributed = pytest.importorskip("distributed")

BASE = """
[system]
name = "rigid_body"
params = {{ inertia = [1.0, 2.0, 3.0] }}

[initial]
random = true
seed = 0

[scheme]
name = "gauss2"

[run]
h = 0.01
steps = {steps}
save_every = {save_every}
engine = "numpy"

[sweep]
"initial.seed" = {seeds}
"""


def write_grid(tmp_path: Path, steps: int, seeds: list[int], save_every: int = 10) -> Path:
    grid = tmp_path / "grid.toml"
    grid.write_text(BASE.format(steps=steps, seeds=seeds, save_every=save_every))
    return grid


def reference(spec: Any, out: Path) -> Path:
    """The run computed here, in this process, from scratch."""
    io.run(build(spec.config, output=out))
    return out


def assert_same(a: Path, b: Path) -> None:
    ta, tb = io.read_trajectory(a), io.read_trajectory(b)
    for name in ("W", "energy", "casimirs", "iterations", "residual", "step"):
        np.testing.assert_array_equal(getattr(ta, name), getattr(tb, name), err_msg=name)


def test_local_cluster_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    grid = write_grid(tmp_path, 30, [0, 1, 2])
    assert main(["sweep", str(grid), "--executor", "dask", "--workers", "2", "--no-progress"]) == 0
    assert "3 runs: 3 complete (0 already), 0 failed" in capsys.readouterr().out
    manifest = json.loads((tmp_path / "grid" / "manifest.json").read_text())
    assert {r["pid"] for r in manifest["runs"]}.isdisjoint({os.getpid()})
    spec = load_sweep(grid).runs[1]
    assert_same(spec.output, reference(spec, tmp_path / "ref.h5"))
    # a Client is an executor too; nothing left to do
    with distributed.Client(
        processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None
    ) as client:
        assert lf.sweep(grid, client).skipped == 3


def test_unreachable_scheduler_is_a_clear_error(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, 5, [0])
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    import dask

    with (
        dask.config.set({"distributed.comm.timeouts.connect": "2s"}),
        pytest.raises(lf.LieflowError, match="cannot connect to the Dask scheduler"),
    ):
        lf.sweep(grid, "dask", scheduler=f"tcp://127.0.0.1:{port}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def dask_cluster(
    tmp_path: Path, workers: int = 2
) -> Iterator[tuple[str, list[subprocess.Popen[bytes]]]]:
    """``dask scheduler`` and ``workers`` × ``dask worker`` (no nanny: the worker is the
    process), each in its own process group on 127.0.0.1; all killed on exit."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "DASK_DISTRIBUTED__WORKER__DAEMON": "False",
    }
    procs: list[subprocess.Popen[bytes]] = []
    logs = []

    def start(args: list[str], name: str) -> subprocess.Popen[bytes]:
        log = open(tmp_path / f"{name}.log", "wb")
        logs.append(log)
        p = subprocess.Popen(
            [sys.executable, "-m", "dask", *args],
            cwd=tmp_path,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        procs.append(p)
        return p

    try:
        start(
            ["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], "scheduler"
        )
        workers_ = [
            start(
                [
                    "worker",
                    address,
                    "--nthreads",
                    "1",
                    "--no-nanny",
                    "--host",
                    "127.0.0.1",
                    "--no-dashboard",
                    "--name",
                    f"w{i}",
                    "--death-timeout",
                    "60",
                ],
                f"w{i}",
            )
            for i in range(workers)
        ]
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(workers, timeout=120)
        yield address, workers_
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=3)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)
        for log in logs:
            log.close()


def test_real_cluster_survives_a_killed_worker(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, 1000, [0, 1, 2, 3], save_every=25)
    g = load_sweep(grid)
    with dask_cluster(tmp_path) as (address, workers):
        result: dict[str, Any] = {}

        def go() -> None:
            try:
                result["res"] = lf.sweep(g, "dask", scheduler=address)
            except BaseException as exc:  # pragma: no cover - reported below
                result["exc"] = exc

        thread = threading.Thread(target=go, daemon=True)
        thread.start()
        # the victim is the first worker seen in the middle of a run (its progress file
        # says so: written when the run starts, then at most once a second), whichever of
        # the two the scheduler gave it to: what the test waits for is that event, not a
        # time, and not one worker's being given a run at all
        by_pid = {w.pid: w for w in workers}
        killed: dict[str, Any] = {}
        deadline = time.monotonic() + 240
        while not killed and thread.is_alive() and time.monotonic() < deadline:
            for p in (g.directory / ".progress").glob("*.json"):
                with contextlib.suppress(OSError, ValueError, KeyError):
                    info = json.loads(p.read_text())
                    if info["pid"] in by_pid and info["done"] < info["total"]:
                        victim = by_pid[info["pid"]]
                        os.killpg(victim.pid, signal.SIGKILL)  # the worker dies mid-run
                        victim.wait(timeout=30)
                        killed.update(info, id=p.stem)
                        break
            time.sleep(0.05)
        thread.join(timeout=300)
        assert not thread.is_alive(), "the sweep did not finish after a worker was killed"
    assert "exc" not in result, result.get("exc")
    assert killed, "no worker was seen in the middle of a run"
    res = result["res"]
    assert res.ok, [r["error"] for r in res.runs]
    rec = next(r for r in res.runs if r["id"] == killed["id"])
    assert rec["pid"] != killed["pid"]  # finished by the surviving worker ...
    tr = io.read_trajectory(res.directory / rec["output"])
    assert tr.meta["resumes"] >= 1 and tr.completed_steps == 1000  # ... from its checkpoint
    spec = next(s for s in g.runs if s.id == killed["id"])
    assert_same(spec.output, reference(spec, tmp_path / "ref.h5"))  # bit for bit
