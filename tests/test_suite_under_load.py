"""``benchmarks.suite_under_load`` (issue 37's first target) reads the command CI runs and
reports each run's times and verdict as measured."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

from benchmarks import suite_under_load as load

ROOT = Path(__file__).resolve().parents[1]


def test_it_takes_the_readme_commands_ci_takes() -> None:
    """The same two commands as ``.ci/run``'s ``awk`` (the first ``bash`` block, without
    blank lines and comments), the second being the install and the tests."""
    script = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    program = re.search(r"<\(awk '(.*?)' README\.md\)", script, re.DOTALL)
    assert program is not None
    ci = subprocess.run(
        ["awk", program[1], str(ROOT / "README.md")], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    commands = load.readme_commands((ROOT / "README.md").read_text(encoding="utf-8"))
    assert commands == ci
    assert len(commands) == 2
    assert "pip install -e" in commands[1] and "python -m pytest" in commands[1]


def test_only_the_first_bash_block_counts_and_an_open_one_is_an_error() -> None:
    text = "intro\n```bash\n# a comment\nfirst\n\n  # indented\nsecond\n```\n```bash\nno\n```\n"
    assert load.readme_commands(text) == ["first", "second"]
    with pytest.raises(ValueError, match="no closed"):
        load.readme_commands("```bash\nfirst\n")


@pytest.mark.parametrize(
    ("line", "counts", "seconds"),
    [
        ("1911 passed, 14 skipped in 763.51s (0:12:43)", "1911 passed, 14 skipped", 763.51),
        ("====== 2 failed, 3 passed in 1.50s ======", "2 failed, 3 passed", 1.5),
    ],
)
def test_pytests_summary_line_is_read(line: str, counts: str, seconds: float) -> None:
    found = load._SUMMARY.search(f"collected\n{line}\n")
    assert found is not None
    assert (found["counts"], float(found["seconds"])) == (counts, seconds)


def test_a_row_gives_the_verdict_of_the_whole_commands_wall_time() -> None:
    def row(returncode: int, minutes: float) -> str:
        return load.Run("cold", returncode, 60 * minutes, 60 * (minutes - 2), 600.0, "x").row()

    assert row(0, 9.9).endswith("| met |")
    assert row(0, 10.1).endswith("| not met |")
    assert row(1, 5.0).endswith("| not met |")  # red is never met
    assert "| 10.1 | 8.1 | 2.0 | 10.0 |" in row(0, 10.1)


def test_the_busy_loops_end_with_the_block() -> None:
    with load.busy_loops(1):
        spinning = subprocess.run(
            ["pgrep", "-f", "-P", str(os.getpid()), "while True: pass"],
            capture_output=True, text=True, check=False,
        ).stdout.split()  # fmt: skip
    assert len(spinning) == 1
    left = subprocess.run(["ps", "-o", "stat=", "-p", spinning[0]], capture_output=True,
                          text=True, check=False).stdout.strip()  # fmt: skip
    assert left == ""  # ended and reaped, not a zombie


def test_dry_run_prints_the_command_and_runs_nothing(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"a dry run started {args}")

    monkeypatch.setattr(load.subprocess, "run", refuse)
    monkeypatch.setattr(load.subprocess, "Popen", refuse)
    assert load.main(["--dry-run", "--busy", "3"]) == 0
    out = capsys.readouterr().out
    assert "README command 2: python3 -m venv .venv" in out
    assert "3 busy loop(s)" in out and "cold, warm numba cache" in out
