"""README command 2 (install, then the test suite) on a busy machine: issue 37's first target.

    python -m benchmarks.suite_under_load              # two busy loops, cold then warm
    python -m benchmarks.suite_under_load --busy 0     # the same on the idle machine
    python -m benchmarks.suite_under_load --dry-run    # what it would run, nothing run

Target (issue 37): README command 2 green on 2 cores with two busy loops beside it, in
≤ 10 minutes, an empty numba cache included.

What it does: clones this checkout's ``HEAD`` into a temporary folder, starts ``--busy``
processes that spin (``while True: pass``, the load of the target), and runs README command
2 exactly as written there (the second command of the README's first ``bash`` block, as
``.ci/run`` takes it) twice in that clone:

1. **cold**: a fresh ``.venv``, an empty pip cache and an empty numba cache
   (``NUMBA_CACHE_DIR``, which :func:`lieflow.numba_cache.cache_directory` follows) — the
   target's condition;
2. **warm numba cache**: a fresh ``.venv`` and an empty pip cache again, but the numba
   cache the cold run left, so numba compiles nothing: the floor that no compile-time work
   can go below.

Per run it prints the wall seconds of the whole command and of its ``pytest`` part (from
pytest's summary line; the rest is creating the ``.venv`` and ``pip``), the CPU seconds of
everything the command ran (``resource.getrusage(RUSAGE_CHILDREN)``, taken before the busy
loops end so that theirs is not counted), and pytest's summary. The difference of the two
runs' pytest CPU is what numba's compiling costs the suite under that load.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import attrs

from benchmarks.timing import run_process

ROOT = Path(__file__).resolve().parents[1]

#: The minutes the target allows a run (issue 37).
TARGET_MINUTES = 10.0

#: pytest's last line: ``1911 passed, 14 skipped in 763.51s (0:12:43)``.
_SUMMARY = re.compile(r"^=*\s*(?P<counts>\d+ \w+.*) in (?P<seconds>[\d.]+)s\b", re.MULTILINE)


def readme_commands(readme: str) -> list[str]:
    """The commands of the README's first ``bash`` block: its non-empty lines that are not
    comments (as ``.ci/run`` reads them)."""
    commands: list[str] = []
    inside = False
    for line in readme.splitlines():
        if not inside:
            inside = line == "```bash"
        elif line == "```":
            return commands
        elif line.strip() and not line.lstrip().startswith("#"):
            commands.append(line)
    raise ValueError("the README has no closed ```bash block")


@attrs.frozen
class Run:
    """One run of the command: its label, exit status, wall seconds of the command and of
    its ``pytest`` part, CPU seconds of all it ran, and pytest's summary."""

    label: str
    returncode: int
    wall: float
    pytest_wall: float | None
    cpu: float
    summary: str

    def row(self) -> str:
        pytest_wall = "?" if self.pytest_wall is None else f"{self.pytest_wall / 60:.1f}"
        rest = "?" if self.pytest_wall is None else f"{(self.wall - self.pytest_wall) / 60:.1f}"
        verdict = "met" if self.returncode == 0 and self.wall <= 60 * TARGET_MINUTES else "not met"
        return (
            f"| {self.label} | {self.returncode} | {self.wall / 60:.1f} | {pytest_wall} | "
            f"{rest} | {self.cpu / 60:.1f} | {self.summary} | {verdict} |"
        )


HEADER = (
    "| run | exit | command: wall min | pytest: wall min | venv + pip: wall min "
    "| CPU min (all it ran) | pytest | ≤ 10 min |\n|---|---|---|---|---|---|---|---|"
)


@contextmanager
def busy_loops(count: int) -> Iterator[None]:
    """``count`` processes spinning on a core each for as long as the block runs."""
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for loop in loops:
            loop.kill()
        for loop in loops:
            loop.wait()


def run_command(command: str, clone: Path, label: str, busy: int, log: Path) -> Run:
    """Run ``command`` in ``clone`` (a fresh ``.venv`` and pip cache; the numba cache in
    ``clone/../numba`` is kept) beside ``busy`` busy loops."""
    shutil.rmtree(clone / ".venv", ignore_errors=True)
    shutil.rmtree(clone.parent / "pip-cache", ignore_errors=True)
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(clone.parent / "numba"),
        "XDG_CACHE_HOME": str(clone.parent / "pip-cache"),
    }
    with busy_loops(busy), log.open("w", encoding="utf-8") as out:
        timed = run_process(  # while the loops spin: their CPU is not counted
            ["bash", "-euo", "pipefail", "-c", command],
            cwd=clone, env=env, stdout=out, stderr=subprocess.STDOUT, check=False,
        )  # fmt: skip
    found = list(_SUMMARY.finditer(log.read_text(encoding="utf-8", errors="replace")))
    last = found[-1] if found else None
    return Run(
        label,
        timed.done.returncode,
        timed.wall,
        None if last is None else float(last["seconds"]),
        timed.cpu,
        "no summary (see the log)" if last is None else last["counts"],
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--busy", type=int, default=2, help="busy loops beside each run (2)")
    parser.add_argument("--cold-only", action="store_true", help="skip the warm-cache run")
    parser.add_argument("--dry-run", action="store_true", help="print the plan, run nothing")
    args = parser.parse_args(argv)
    command = readme_commands((ROOT / "README.md").read_text(encoding="utf-8"))[1]
    runs = ["cold"] if args.cold_only else ["cold", "warm numba cache"]
    print(f"README command 2: {command}")
    print(f"runs: {', '.join(runs)}; {args.busy} busy loop(s) beside each; {os.cpu_count()} cores")
    if args.dry_run:
        return 0
    with tempfile.TemporaryDirectory(prefix="lieflow-load-") as tmp:
        clone = Path(tmp) / "repo"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        print(HEADER)
        for label in runs:
            log = Path(tmp) / f"{label.split()[0]}.log"
            run = run_command(command, clone, label, args.busy, log)
            print(run.row(), flush=True)
            if run.returncode != 0:
                print(log.read_text(encoding="utf-8", errors="replace")[-4000:])
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
