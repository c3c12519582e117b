"""Child processes that end with the test that started them, whether it passes or fails.

A test that starts ``lieflow run`` (or a sweep and its workers) and then fails an assertion,
times out or is interrupted used to leave the child running, at 100 % CPU, long after pytest
exited. :class:`Children` (the ``children`` fixture of ``conftest.py``) starts every child in
a process group of its own and kills each group (the child and whatever it started) when the
test ends.
"""

from __future__ import annotations

import contextlib
import os
import pty
import signal
import subprocess
import threading
from collections.abc import Callable
from typing import Any


def alive(pid: int) -> bool:
    """Whether process ``pid`` is running (a zombie, dead but not yet reaped, is not; reads
    ``/proc``)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


class Children:
    """The processes one test started (:meth:`popen`), each leading its own process group."""

    def __init__(self) -> None:
        self._procs: list[subprocess.Popen[Any]] = []

    def popen(self, args: list[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """``subprocess.Popen(args, **kwargs)`` in a new session (its own process group, as a
        shell job has: a signal to the group reaches everything it started)."""
        proc: subprocess.Popen[Any] = subprocess.Popen(args, start_new_session=True, **kwargs)
        self._procs.append(proc)
        return proc

    def end(self) -> None:
        """Kill every group (SIGKILL: a child stuck or ignoring SIGINT/SIGTERM too) and reap
        the children."""
        for proc in self._procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
        for proc in self._procs:
            with contextlib.suppress(subprocess.TimeoutExpired, ValueError, OSError):
                proc.communicate(timeout=60)  # reaped, its pipes drained and closed


def on_a_terminal(
    children: Children,
    command: list[str],
    watch: Callable[[bytes, subprocess.Popen[Any]], None] | None = None,
    timeout: float = 600,
) -> tuple[int, str]:
    """Run ``command`` with stdin, stdout and stderr on a pseudo-terminal (so that a progress
    bar draws) and return its exit code and everything it wrote there. ``watch(tail,
    proc)``: called with the last 256 bytes written after each read (to act on what the
    child reports: a step count, not a time that a busy machine stretches)."""
    leader, follower = pty.openpty()
    proc = children.popen(command, stdin=follower, stdout=follower, stderr=follower)
    os.close(follower)
    chunks: list[bytes] = []

    def drain() -> None:  # keep reading, or a full terminal buffer would block the child
        tail = b""
        while True:
            try:
                data = os.read(leader, 1 << 16)
            except OSError:  # the terminal closed: the process is gone
                return
            if not data:
                return
            chunks.append(data)
            tail = (tail + data)[-256:]
            if watch is not None:
                watch(tail, proc)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        code = proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        reader.join(timeout=10)
        os.close(leader)
    return code, b"".join(chunks).decode(errors="replace")
