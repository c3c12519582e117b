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

from helpers import needs_zeitlin
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


#: A printed decimal number (``0.541``, ``5.8e-14``, ``-3``, ``26.2`` of ``26.2%``).
NUMBER = re.compile(r"[-+]?\d+(?:\.(\d*))?(?:[eE]([-+]?\d+))?")


#: Errors below this are roundoff (the page says so): their digits are the machine's.
ROUNDOFF = 1e-12


def printed_as_shown(printed: str, shown: str) -> bool:
    """Whether ``printed`` is the page's ``shown`` output: the same words, and every number
    within 2 units of the last digit the page shows (another machine's BLAS and libm round
    differently: 5.8e-14 here is 5.9e-14 there), or within a factor of 2 for an error at
    roundoff (below :data:`ROUNDOFF`); a number shown without decimals (a count, a size,
    numpy's ``4.``) exactly."""
    a, b = tokens(printed), tokens(shown)
    if len(a) != len(b):
        return False
    for got, want in zip(a, b, strict=True):
        if NUMBER.sub("#", got) != NUMBER.sub("#", want):  # the words around the numbers
            return False
        for g, w in zip(NUMBER.finditer(got), NUMBER.finditer(want), strict=True):
            x, y = float(g.group()), float(w.group())
            digits, exponent = len(w.group(1) or ""), int(w.group(2) or 0)
            unit = 10.0 ** (exponent - digits) if digits else 0.0
            close = abs(x - y) <= 2 * unit * (1 + 1e-9)
            if not close and not (0 < abs(y) < ROUNDOFF and 0.5 <= x / y <= 2):
                return False
    return True


@pytest.mark.parametrize(
    ("printed", "shown", "same"),
    [
        ("gauss3 1.6e-08 5.9e-14", "gauss3 1.6e-08 5.8e-14", True),
        ("gauss3 1.6e-08 1.1e-13", "gauss3 1.6e-08 5.8e-14", True),  # roundoff
        ("gauss2 3.5e-05", "gauss2 3.2e-05", False),  # not roundoff: 3 units off
        ("midpoint 1.98", "midpoint 1.99", True),
        ("midpoint 1.95", "midpoint 1.99", False),
        ("nu = 0.002: 12.4% above", "nu = 0.002: 12.5% above", True),
        ("nu = 0.002: 12.4% below", "nu = 0.002: 12.4% above", False),
        ("[0.4 0.2]", "[0.4 0.2 0.1]", False),
        ("16 0.0 0.033", "16 0.0 0.034", True),
        ("[16 24] [4. 4.899]", "[16 24] [4. 4.899]", True),
        ("[16 25]", "[16 24]", False),  # counts exactly
    ],
)
def test_printed_numbers_are_compared_to_their_shown_digits(
    printed: str, shown: str, same: bool
) -> None:
    assert printed_as_shown(printed, shown) is same


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


@needs_zeitlin  # examples/sweeps/study_ensemble.toml: an Euler–Zeitlin ensemble
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
            assert printed_as_shown(out.getvalue(), following[2]), (
                f"docs/study.md:{line} printed\n{out.getvalue()}\nthe page shows\n{following[2]}"
            )
        else:
            assert not out.getvalue(), f"docs/study.md:{line} printed output the page omits"
    assert ran >= 8
