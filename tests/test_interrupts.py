"""Ctrl-C at any moment (issue 15.3): ``lieflow run`` on a pseudo-terminal, with its
progress bar drawing, interrupted by SIGINT at random points, always leaves a file that is
marked interrupted (exit code 130) or complete (exit code 0), and whose resumed run equals
an uninterrupted one bit for bit."""

from __future__ import annotations

import os
import pty
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lieflow.app import io

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX pseudo-terminals")

CONFIG = """
[system]
name = "generalized_rigid_body"
params = { J = [1.0, 1.3, 1.7, 2.2, 2.8, 3.1] }
[initial]
random = true
seed = 1
[scheme]
name = "gauss2"
[run]
h = 0.05
steps = 1200
save_every = 7
engine = "numpy"
"""


def _run_on_a_terminal(
    args: list[str], out_file: Path | None = None, delay: float = 0.0
) -> tuple[int, str]:
    """Run ``lieflow`` with stdin/stdout/stderr on a pseudo-terminal (so the progress bar
    draws). With ``out_file``: once the run has created it (stepping has begun), wait
    ``delay`` seconds and send SIGINT. Returns the exit code and the terminal's output."""
    leader, follower = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "lieflow", *args],
        stdin=follower,
        stdout=follower,
        stderr=follower,
        close_fds=True,
    )
    os.close(follower)
    chunks: list[bytes] = []

    def drain() -> None:  # keep reading, or a full terminal buffer would block the run
        while True:
            try:
                data = os.read(leader, 1 << 16)
            except OSError:  # the terminal closed: the process is gone
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    if out_file is not None:
        deadline = time.monotonic() + 60
        while not out_file.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=120)
    reader.join(timeout=10)
    os.close(leader)
    return code, b"".join(chunks).decode(errors="replace")


def test_sigint_at_random_points_on_a_terminal(tmp_path: Path) -> None:
    config = tmp_path / "run.toml"
    config.write_text(CONFIG)
    ref = tmp_path / "ref.h5"
    code, out = _run_on_a_terminal(["run", str(config), "--out", str(ref)])
    assert code == 0, out
    reference = io.read_trajectory(ref)

    rng = np.random.default_rng(20261123)
    interrupted = 0
    for trial, delay in enumerate(rng.uniform(0.0, 0.5, size=5)):
        path = tmp_path / f"t{trial}.h5"
        code, out = _run_on_a_terminal(["run", str(config), "--out", str(path)], path, delay)
        assert code in (0, 130), out  # never the internal-error exit code
        assert "Traceback" not in out and "internal error" not in out, out
        first = io.read_trajectory(path)
        assert first.status == ("interrupted" if code == 130 else "complete")
        interrupted += code == 130
        code, out = _run_on_a_terminal(
            ["run", str(config), "--out", str(path), "--resume", "--no-progress"]
        )
        assert code == 0, out
        resumed = io.read_trajectory(path)
        assert resumed.status == "complete"
        assert np.array_equal(resumed.checkpoint.W, reference.checkpoint.W)
        assert np.array_equal(resumed.energy_error, reference.energy_error)
        assert np.array_equal(resumed.iterations, reference.iterations)
    assert interrupted >= 3  # the test did exercise interrupts
