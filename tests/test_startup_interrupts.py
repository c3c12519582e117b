"""Ctrl-C in the first milliseconds of ``lieflow run`` (issue 29 item 3): a real process and a
real SIGINT, sent by the process to itself at an exact point of its start-up (no timing),
always ends with the file marked "interrupted" and the resume hint, or with nothing written
and saying so; the progress bar gives the cursor back; an interrupt Python swallowed is not
lost."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from processes import Children, on_a_terminal

from lieflow.app import io

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

CONFIG = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }
[initial]
random = true
seed = 2
[scheme]
name = "midpoint"
[run]
h = 0.1
steps = 400
save_every = 10
output = "traj.h5"
engine = "numpy"
"""

#: The child: patch one function so that it sends SIGINT to its own process at that point,
#: then run ``lieflow`` as the command line does.
CHILD = r"""
import os, signal, sys
from lieflow import progress
from lieflow.app import config, io
from lieflow.app.io import _writer
from lieflow import stepping

def interrupt():
    os.kill(os.getpid(), signal.SIGINT)

point = sys.argv[1]
if point == "load_config":
    original_load = config.load_config
    def load_config(*a, **k):
        interrupt()
        return original_load(*a, **k)
    config.load_config = load_config
elif point in ("after_create", "after_reopen"):
    name = point.split("_")[1]
    original = getattr(io.TrajectoryWriter, name).__func__
    def opened(cls, *a, **k):
        result = original(cls, *a, **k)
        interrupt()
        return result
    setattr(io.TrajectoryWriter, name, classmethod(opened))
elif point == "inside_create":
    original_publish = _writer._publish
    def publish(*a, **k):
        original_publish(*a, **k)
        interrupt()
    _writer._publish = publish
elif point == "bar_start":
    original_start = progress.ProgressBar.start
    def start(self, done, total):
        original_start(self, done, total)  # the cursor is hidden now
        interrupt()
    progress.ProgressBar.start = start
elif point in ("rich_set_live", "rich_hide_cursor"):  # inside rich's Live.start
    from rich.console import Console
    name = {"rich_set_live": "set_live", "rich_hide_cursor": "show_cursor"}[point]
    original_method = getattr(Console, name)
    def method(self, *a, **k):
        if point == "rich_set_live":  # before the Live is on the console's stack
            interrupt()
        result = original_method(self, *a, **k)
        if point == "rich_hide_cursor" and a == (False,):  # its render hook not pushed yet
            interrupt()
        return result
    setattr(Console, name, method)
elif point == "swallowed":
    original_advance = stepping.advance
    class Finalizer:
        def __del__(self):
            interrupt()  # the KeyboardInterrupt raised here is printed and swallowed
    def advance(*a, **k):
        for i, chunk in enumerate(original_advance(*a, **k)):
            if i == 1:
                Finalizer()
            yield chunk
    stepping.advance = advance
from lieflow.app.cli import main
sys.exit(main(sys.argv[2:]))
"""


def _child(children: Children, point: str, *args: str, terminal: bool = False) -> tuple[int, str]:
    command = [sys.executable, "-c", CHILD, point, "run", *args]
    if terminal:
        return on_a_terminal(children, command, timeout=300)
    proc = children.popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    text, _ = proc.communicate(timeout=300)
    return proc.returncode, text


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "run.toml"
    path.write_text(CONFIG, encoding="utf-8")
    return path


@pytest.mark.parametrize("point", ["inside_create", "after_create", "swallowed"])
def test_an_interrupt_once_the_file_exists_marks_it_and_gives_the_hint(
    config: Path, point: str, children: Children
) -> None:
    """``after_create`` used to leave the file "running" with only "lieflow: interrupted";
    ``swallowed`` (the KeyboardInterrupt raised in a finalizer, which Python only prints)
    used to run to completion, exit 0."""
    out = config.parent / "traj.h5"
    code, text = _child(children, point, str(config), "--no-progress")
    assert code == 130, text
    assert io.read_trajectory(out).status == "interrupted"
    assert f"continue with: lieflow run {config} --no-progress --resume" in text, text
    if point != "swallowed":  # there Python itself prints the swallowed exception
        assert "Traceback (most recent call last)" not in text
    code, text = _child(children, "none", str(config), "--no-progress", "--resume")
    assert code == 0, text
    assert io.read_trajectory(out).completed_steps == 400


def test_an_interrupt_while_resuming_keeps_the_file_resumable(
    config: Path, children: Children
) -> None:
    out = config.parent / "traj.h5"
    assert _child(children, "none", str(config), "--no-progress")[0] == 0
    config.write_text(CONFIG.replace("steps = 400", "steps = 500"), encoding="utf-8")
    code, text = _child(children, "after_reopen", str(config), "--no-progress", "--resume")
    assert code == 130, text
    traj = io.read_trajectory(out)
    assert (traj.status, traj.completed_steps) == ("interrupted", 400)
    assert f"continue with: lieflow run {config} --no-progress --resume" in text


def test_an_interrupt_before_the_file_exists_says_nothing_was_written(
    config: Path, children: Children
) -> None:
    other = config.parent / "other.h5"  # in the test's folder, not the working directory
    code, text = _child(children, "load_config", str(config), "--out", str(other), "--force")
    assert code == 130, text
    assert "lieflow: interrupted before the run started: nothing was written" in text
    assert not (config.parent / "traj.h5").exists() and not other.exists()
    assert sorted(p.name for p in config.parent.iterdir()) == ["run.toml"]


@pytest.mark.parametrize("point", ["bar_start", "rich_set_live", "rich_hide_cursor"])
def test_the_progress_bar_gives_the_cursor_back(
    config: Path, children: Children, point: str
) -> None:
    """Interrupted right after the bar hid the cursor (rich: ESC[?25l), or inside rich's
    start of the bar (Ctrl-C in the first milliseconds: the bar's stop then failed with
    rich's ``IndexError: pop from empty list``, exit 1, the cursor left hidden)."""
    code, text = _child(children, point, str(config), terminal=True)
    assert "Traceback" not in text and "IndexError" not in text, text
    assert code == 130, text
    assert "\x1b[?25l" in text  # the bar was drawn
    assert text.rfind("\x1b[?25h") > text.rfind("\x1b[?25l"), text
    assert io.read_trajectory(config.parent / "traj.h5").status == "interrupted"
