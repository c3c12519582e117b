"""A test that fails leaves no process behind (issue 37 item 1): the ``children`` fixture of
``conftest.py`` kills what a test started, and what that started, however the test ends."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from processes import alive

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX process groups")

HERE = Path(__file__).resolve().parent

#: A child that ignores SIGINT and SIGTERM and starts a grandchild that does the same (a
#: ``lieflow run`` stuck in a loop; a sweep and its pool worker), then writes both pids.
STUBBORN = """
import os, signal, subprocess, sys, time
IGNORE = "import signal as s; [s.signal(n, s.SIG_IGN) for n in (s.SIGINT, s.SIGTERM)]"
exec(IGNORE)
grand = subprocess.Popen([sys.executable, "-c", IGNORE + "; import time; time.sleep(600)"])
with open(sys.argv[1] + ".tmp", "w") as f:
    f.write(f"{os.getpid()} {grand.pid}")
os.replace(sys.argv[1] + ".tmp", sys.argv[1])
time.sleep(600)
"""

#: A test that starts the child through the ``children`` fixture, waits for the pids, fails.
FAILING = """
import os, sys, time


def test_fails(children):
    children.popen([sys.executable, "-c", STUBBORN, PIDS])
    deadline = time.monotonic() + 120
    while not os.path.exists(PIDS):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert False, "this test fails on purpose"
"""


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_failing_test_leaves_no_child_or_grandchild_running(tmp_path: Path) -> None:
    for helper in ("conftest.py", "processes.py"):
        shutil.copy(HERE / helper, tmp_path)
    pids = tmp_path / "pids"
    (tmp_path / "test_leak.py").write_text(
        f"PIDS = {str(pids)!r}\nSTUBBORN = {STUBBORN!r}\n{FAILING}", "utf-8"
    )
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_leak.py"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1 and "this test fails on purpose" in done.stdout, done.stdout
    started = [int(p) for p in pids.read_text().split()]
    assert len(started) == 2
    deadline = time.monotonic() + 30  # the orphaned grandchild is reaped by init
    while any(alive(pid) for pid in started) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [pid for pid in started if alive(pid)]
    for pid in left:  # never leave them, even when this test fails
        os.kill(pid, 9)
    assert not left, f"still running after the test ended: {left}"
