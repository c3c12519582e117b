"""docs/study.md ("Running a study") runs as written, and every number on it is the output.

The page's Python blocks read the sweeps that its ``lieflow sweep`` commands write from the
grid files in ``examples/sweeps/``, so the docs harness (``tests/test_docs.py``, which runs
blocks in an empty directory) skips them (``<!-- docs: skip -->``). Here they run for real:
the grid files are copied into a temporary tree laid out like the repository, both grids run
through the command line (``lieflow sweep``, then ``lieflow plot``), and then every Python
block of the page executes in order in one namespace; what a block prints must be the
```text block that follows it on the page (compared token by token, so column padding does
not matter). The ```toml blocks are the grid files (without their comment headers).
"""

from __future__ import annotations

import contextlib
import io
import re
import shutil
from pathlib import Path

import pytest

pytest.importorskip("xarray")
pytest.importorskip("scipy")
pytest.importorskip("lieflow_zeitlin")

from test_docs import FENCE

from lieflow.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "study.md"
GRIDS = ("study_convergence", "study_ensemble")


def fenced_blocks(text: str) -> list[tuple[int, str, str]]:
    """``(line, language, body)`` of every fenced block of ``text``, skipped or not."""
    lines = text.splitlines()
    out: list[tuple[int, str, str]] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m is None or m.group("indent"):
            i += 1
            continue
        fence, lang = m.group("fence"), m.group("info").strip().split(" ")[0].lower()
        start, body = i, []
        i += 1
        while i < len(lines) and lines[i].strip() != fence:
            body.append(lines[i])
            i += 1
        i += 1
        out.append((start + 1, lang, "\n".join(body) + "\n"))
    return out


def tokens(text: str) -> list[str]:
    """Whitespace-separated tokens (pandas pads its columns differently across versions)."""
    return text.split()


def without_header(grid: str) -> str:
    """A grid file without its leading comment lines (the page shows the rest)."""
    lines = grid.splitlines()
    while lines and (lines[0].startswith("#") or not lines[0].strip()):
        lines.pop(0)
    return "\n".join(lines) + "\n"


def test_page_shows_the_grid_files() -> None:
    tomls = [body for _, lang, body in fenced_blocks(PAGE.read_text("utf-8")) if lang == "toml"]
    for name in GRIDS:
        grid = without_header((ROOT / "examples" / "sweeps" / f"{name}.toml").read_text("utf-8"))
        assert grid in tomls, f"docs/study.md does not show examples/sweeps/{name}.toml"


def test_page_runs_and_prints_what_it_shows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The whole page, end to end: both sweeps, the figures, every block and its output."""
    pytest.importorskip("matplotlib").use("Agg")
    sweeps = tmp_path / "examples" / "sweeps"
    sweeps.mkdir(parents=True)
    for name in GRIDS:
        shutil.copy(ROOT / "examples" / "sweeps" / f"{name}.toml", sweeps)
    monkeypatch.chdir(tmp_path)
    text = PAGE.read_text("utf-8")

    # the commands of the page (one worker: the test machine is shared)
    for name in GRIDS:
        grid = f"examples/sweeps/{name}.toml"
        assert main(["sweep", grid, "--workers", "1", "--no-progress"]) == 0
        summary = capsys.readouterr().out.strip().splitlines()[-1]
        if name == "study_convergence":  # the summary line shown, its seconds aside
            shown = next(ln for ln in text.splitlines() if ln.startswith(f"sweep {grid}:"))
            pattern = re.escape(shown).replace(r"2\.3\ s", r"[0-9.]+\ s")
            pattern = pattern.replace(re.escape("-> examples"), r"-> \S*examples")
            assert re.fullmatch(pattern, summary), summary
    assert main(["plot", "examples/sweeps/study_convergence"]) == 0
    figures = {Path(p).name for p in capsys.readouterr().out.split()}
    assert {"convergence.png", "work_precision.png"} <= figures

    # every Python block in order; a ```text block right after one is its output
    blocks = fenced_blocks(text)
    namespace: dict[str, object] = {"__name__": "docs_study"}
    ran = 0
    for j, (line, lang, body) in enumerate(blocks):
        if lang != "python":
            continue
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            exec(compile(body, f"docs/study.md:{line}", "exec"), namespace)
        ran += 1
        following = blocks[j + 1] if j + 1 < len(blocks) else None
        if following is not None and following[1] == "text" and out.getvalue():
            assert tokens(out.getvalue()) == tokens(following[2]), (
                f"docs/study.md:{line} printed\n{out.getvalue()}\nthe page shows\n{following[2]}"
            )
        else:
            assert not out.getvalue(), f"docs/study.md:{line} printed output the page omits"
    assert ran >= 8
