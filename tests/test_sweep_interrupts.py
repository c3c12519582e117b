"""Ctrl-C on ``lieflow sweep`` (issue 29 item 7), as a terminal sends it: SIGINT to the whole
process group, once two runs have reported steps (an event, not a delay). For both
executors: exit 130, no worker tracebacks, every run that had started recorded
"interrupted" with its steps (Dask used to record them "pending", 0 steps), and the hint
repeats the command that was run (it used to drop --executor and --out)."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from processes import Children, alive

from lieflow.app import io

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX process groups")

GRID = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }
[initial]
random = true
seed = 0
[scheme]
name = "gauss2"
[run]
h = 0.01
steps = 10000000
save_every = 50
engine = "numpy"
[sweep]
"initial.seed" = [1, 2, 3, 4, 5]
"""


def _started(out: Path) -> int:
    """Runs whose workers have reported steps (their progress files)."""
    n = 0
    for path in (out / ".progress").glob("*.json"):
        try:
            n += json.loads(path.read_text())["done"] > 0
        except (OSError, ValueError, KeyError):
            pass
    return n


@pytest.mark.parametrize("executor", ["local", "dask"])
def test_ctrl_c_stops_every_run_where_it_is_and_the_hint_is_the_command(
    tmp_path: Path, executor: str, children: Children
) -> None:
    if executor == "dask":
        pytest.importorskip("distributed")
    grid, out = tmp_path / "long.toml", tmp_path / "out"
    grid.write_text(GRID, encoding="utf-8")
    args = ["sweep", str(grid), "--executor", executor, "--workers", "2", "--out", str(out)]
    proc = children.popen(  # its own process group, as a shell job has
        [sys.executable, "-m", "lieflow", *args, "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    deadline = time.monotonic() + 240
    while _started(out) < 2:
        assert proc.poll() is None, proc.communicate()[0]
        assert time.monotonic() < deadline, "no two runs reported steps in 240 s"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C on a terminal does
    text, _ = proc.communicate(timeout=240)
    assert proc.returncode == 130, text
    for word in ("Traceback", "KeyboardInterrupt", "CancelledError", "killing"):
        assert word not in text, text
    hint = "run the same command again to continue: " + shlex.join(
        ["lieflow", *args, "--no-progress"]
    )
    assert hint in text, text
    runs = json.loads((out / "manifest.json").read_text())["runs"]
    assert {r["status"] for r in runs} <= {"interrupted", "pending"}, runs
    stepped = [r for r in runs if r["status"] == "interrupted" and r["completed_steps"] > 0]
    assert len(stepped) >= 2, [
        (r["status"], r.get("completed_steps"), r.get("error")) for r in runs
    ]
    for r in runs:
        path = out / r["output"] if not Path(r["output"]).is_absolute() else Path(r["output"])
        if r["status"] == "interrupted":
            traj = io.read_trajectory(path)  # verified, resumable
            assert traj.status == "interrupted"
            assert traj.completed_steps == r["completed_steps"]
    assert not (out / ".progress" / "stop").exists()


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_workers_stop_their_runs_and_exit_when_the_coordinator_is_killed(
    tmp_path: Path, children: Children
) -> None:
    """Issue 37 item 7: ``kill -9`` of a local-pool sweep's coordinator (no cleanup runs)
    used to orphan its pool workers, stepping on and then blocked for ever. Each worker
    watches its coordinator: its run stops at its next step, marked "interrupted" (resumable,
    as after Ctrl-C), and the worker exits."""
    grid, out = tmp_path / "long.toml", tmp_path / "out"
    grid.write_text(GRID, encoding="utf-8")
    args = ["sweep", str(grid), "--workers", "2", "--out", str(out), "--no-progress"]
    proc = children.popen([sys.executable, "-m", "lieflow", *args], stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 240
    while _started(out) < 2:
        assert proc.poll() is None, "the sweep ended before two runs reported steps"
        assert time.monotonic() < deadline, "no two runs reported steps in 240 s"
        time.sleep(0.05)
    workers = {}
    for path in (out / ".progress").glob("*.json"):
        info = json.loads(path.read_text())
        workers[info["pid"]] = path.stem
    assert len(workers) == 2 and proc.pid not in workers
    os.kill(proc.pid, signal.SIGKILL)  # the coordinator alone: its workers are orphaned
    proc.wait()
    deadline = time.monotonic() + 120
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [pid for pid in workers if alive(pid)], "workers outlived their coordinator"
    stopped = [io.read_trajectory(p) for p in out.rglob("*.h5")]
    assert len(stopped) >= 2
    assert all(t.status == "interrupted" and t.completed_steps > 0 for t in stopped), [
        (t.status, t.completed_steps) for t in stopped
    ]
