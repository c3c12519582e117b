"""``python -m benchmarks [--quick] [--out docs/benchmarks.md] [--only NAME,...]``.

Runs the benchmarks, prints the markdown page and writes it (figures go to ``img/`` next to
the page).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import lieflow as lf
from lieflow.app.reproduce import machine_description

from . import config as presets
from .config import BenchContext
from .contenders import available_engines, integrate_has_engine
from .report import Section, render
from .suites import (
    call_cost,
    euler_zeitlin,
    file_output,
    iteration_cost,
    quflow_accuracy,
    reproduce_suite,
    rigid_body_scaling,
    scipy_work_precision,
    so3_throughput,
    splitting,
    startup,
    streaming_memory,
    sweeps,
    work_precision,
)

#: The benchmarks by name, in page order.
SUITES: tuple[tuple[str, Callable[[BenchContext], Section]], ...] = (
    ("reproduce", reproduce_suite.run),
    ("scaling", rigid_body_scaling.run),
    ("work_precision", work_precision.run),
    ("scipy", scipy_work_precision.run),
    ("so3", so3_throughput.run),
    ("iteration_cost", iteration_cost.run),
    ("call_cost", call_cost.run),
    ("zeitlin", euler_zeitlin.run),
    ("quflow", quflow_accuracy.run),
    ("splitting", splitting.run),
    ("memory", streaming_memory.run),
    ("file_output", file_output.run),
    ("startup", startup.run),
    ("sweeps", sweeps.run),
)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="lieflow benchmarks: speed ratios against baselines run in this process.",
    )
    parser.add_argument("--quick", action="store_true", help="tiny sizes (well under a minute)")
    parser.add_argument(
        "--out", default="docs/benchmarks.md", help="markdown page to write (default: %(default)s)"
    )
    parser.add_argument(
        "--only",
        default="",
        help="comma-separated subset of: " + ", ".join(name for name, _ in SUITES),
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the random inputs")
    return parser.parse_args(argv)


def _git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    commit = out.stdout.strip()
    try:
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "lieflow", "plugins"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        dirty = ""
    return commit + (" + uncommitted lieflow/plugins changes" if dirty else "")


def header(ctx: BenchContext, total: float, command: str) -> str:
    """The page's title, method and machine."""
    machine = machine_description()
    engine_note = (
        "`lieflow.integrate` has no `engine=` option in this version: no engine columns."
        if not integrate_has_engine()
        else f'Lever comparisons run on `engine="{ctx.base_engine}"`; engine columns compare '
        + (", ".join(f"`{e}`" for e in ctx.engines) or "no other engine")
        + " against it (`auto` is lieflow's default)."
    )
    lines = [
        "# Benchmarks",
        "",
        "Reproduce this page from the repository root with one command:",
        "",
        "```bash",
        "python -m benchmarks            # full run, ~15 min on 2 cores, writes this page",
        "python -m benchmarks --quick    # tiny sizes, well under a minute",
        "```",
        "",
        f"This page: `{command}`, lieflow {lf.__version__} at commit {_git_commit()}, "
        f"{total / 60:.1f} min"
        + (
            " (**quick mode**: tiny sizes — the target verdicts below mean nothing)"
            if ctx.config.quick
            else ""
        )
        + ".",
        "",
        "**Method.** Every speed figure is a ratio of two timings taken in the same process "
        "on the same input, the contenders interleaved round by round and the *median* round "
        "of each reported (never the fastest). The machine is shared (2 cores, other "
        "developers' jobs running concurrently), so absolute seconds are noisy — read the "
        "ratios. Ratios are written ‘k×’ = time(baseline) / time(lieflow): above 1 lieflow is "
        "faster.",
        "",
        "**Baselines.** (a) The paper's block algorithm *as published* "
        "(`benchmarks/paper_baseline.py`): dense sn×sn matrices 𝔸 = A⊗I and 𝔹 = blockdiag(B_k) "
        "rebuilt every iteration, M ← M − [(I − h𝔸𝔹) M (I + h𝔹𝔸ᵀ) − 𝕎₀], cold start from 𝕎₀, "
        "the same relative stopping rule; 7s-SyDIRK as a composition of such midpoint steps. "
        "`tests/test_benchmarks.py` checks it gives the same W1 as lieflow to 1e-12. "
        "(b) The *plain-numpy reduced form* (`PlainScheme` in the same file): lieflow's own "
        "algorithm — the reduced stage form, 3s products per iteration — written as a plain "
        "numpy prototype with cold starts and the same stopping rule, so ‘× vs plain numpy "
        "reduced’ measures lieflow's implementation alone, while ‘× vs as published’ also "
        "credits the algorithm change. "
        '(c) lieflow\'s own earlier formulations: the block form `BlockGauss(form="block")` '
        "(3s² products per iteration) against the default reduced stage form (3s), warm "
        "starts off against on, plain fixed point against `FixedPoint(anderson=3)`. "
        "(d) The paper's published seconds (Tables 1, 3, 5; another machine). "
        "(e) scipy's `solve_ivp` (DOP853, Radau) at equal energy error. " + engine_note,
        "",
        "**Machine.** " + "; ".join(f"{k}: {v}" for k, v in machine.items()) + ".",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the selected benchmarks, print the page and write it."""
    args = parse_args(argv)
    cfg = presets.quick() if args.quick else presets.full()
    out = Path(args.out)
    img_dir = out.parent / "img"
    wanted = {name.strip() for name in args.only.split(",") if name.strip()}
    unknown = wanted - {name for name, _ in SUITES}
    if unknown:  # before the engines are probed (which compiles the compiled engine's loops)
        print(f"unknown benchmark(s): {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    engines = available_engines()
    base = "numpy" if "numpy" in engines else None
    others = tuple(e for e in engines if e != base)
    ctx = BenchContext(cfg, others, base, str(img_dir), "img", args.seed)
    start = time.perf_counter()
    sections = []
    for name, suite in SUITES:
        if wanted and name not in wanted:
            continue
        print(f"[benchmarks] {name} ...", file=sys.stderr, flush=True)
        section = suite(ctx)
        print(f"[benchmarks] {name} done in {section.seconds:.1f} s", file=sys.stderr, flush=True)
        sections.append(section)
    total = time.perf_counter() - start
    command = "python -m benchmarks" + (" --quick" if args.quick else "")
    if args.only:
        command += f" --only {args.only}"
    targets = [t for s in sections for t in s.targets]
    page = render(header(ctx, total, command), targets, sections)
    print(page)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(page, encoding="utf-8")
    return 0
