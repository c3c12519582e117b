"""Conjugation updates (issue 27, SPEC §4.7): updates per step, accuracy, Casimirs and time
against the commutator update solved to roundoff, and so(10) against scipy.

``python -m benchmarks.conjugation_updates [--quick]`` prints markdown tables (the numbers
of ``docs/conjugation.md``). Every time is a median of interleaved rounds in one process,
reported as a ratio against a baseline timed in the same rounds (the machine is shared and
noisy). BLAS runs single-threaded (set before numpy is imported).

Targets (issue 27):

* Euler–Zeitlin N = 64 (rms-1 vorticity, degrees ≤ 8, ``time="fluid"``, T = 4): Gauss-4 at
  h = 0.25 ≤ 14 updates/step at energy error ≤ 1e-8; midpoint at h = 1/32 ≤ 2
  updates/step at unchanged energy error; Casimir drift ≤ 1e-14 in both;
* the generalized rigid body so(10) (the paper's, T = 20): ≥ 2× the best of scipy
  DOP853/Radau at energy error 1e-8.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

import lieflow as lf
from lieflow import tableaus
from lieflow.app.reproduce import Case
from lieflow.schemes import BlockGauss, SyDIRK

from .suites.scipy_work_precision import (
    Point,
    Problem,
    _accuracy,
    _scipy_run,
    time_to_reach,
)
from .timing import compare

#: Relative energy error at which so(10) is compared with scipy.
TARGET_ERROR = 1e-8


def _run(
    problem: Problem, scheme: lf.Scheme, steps: int, rtol: float, engine: str, shift: Any = 0.0
) -> Callable[[], Any]:
    solver = lf.solvers.FixedPoint(rtol=rtol)

    def go() -> Any:
        sol = lf.integrate(
            problem.system, scheme, problem.W0, problem.T / steps, steps=steps, solver=solver,
            diagnostics=False, engine=engine, casimir_shift=shift,
        )  # fmt: skip
        return sol.W, float(np.mean(sol.iterations))

    return go


def zeitlin(quick: bool, repeats: int) -> list[str]:
    """The Euler–Zeitlin targets: one table row per configuration."""
    import lieflow_zeitlin as lz

    N = 16 if quick else 64
    system = lf.systems.get("euler_zeitlin", N=N, time="fluid")
    W0 = lz.random_vorticity(N, degree=8, seed=0)
    problem = Problem("zeitlin", f"Euler–Zeitlin N = {N}", system, W0, 4.0, (), (), ())
    g4 = tableaus.gauss(4)
    configs = {
        "gauss4+shift h=1/4 commutator rtol=1e-14": (BlockGauss(g4), 16, 1e-14),
        "gauss4+shift h=1/4 conjugation rtol=1e-8": (
            BlockGauss(g4, update="conjugation"), 16, 1e-8),
        "gauss4+shift h=1/4 conjugation rtol=1e-6": (
            BlockGauss(g4, update="conjugation"), 16, 1e-6),
        "midpoint h=1/32 commutator rtol=1e-14": (SyDIRK(), 128, 1e-14),
        "midpoint h=1/32 conjugation rtol=1e-6": (SyDIRK(update="conjugation"), 128, 1e-6),
        "midpoint h=1/32 conjugation rtol=1e-4": (SyDIRK(update="conjugation"), 128, 1e-4),
    }  # fmt: skip
    runs = {
        k: _run(problem, s, n, r, "numpy", "auto" if k.startswith("gauss") else 0.0)
        for k, (s, n, r) in configs.items()
    }
    timings = compare(runs, repeats)
    rows = [
        "| configuration (numpy engine) | updates/step | energy error | Casimir drift | time / commutator |",  # noqa: E501
        "|---|---|---|---|---|",
    ]
    base: dict[str, float] = {}
    for key, t in timings.items():
        if not t.ok or t.result is None:
            rows.append(f"| {key} | failed: {t.error} | | | |")
            continue
        states, its = t.result
        err, drift = _accuracy(system, states, W0)
        family = key.split()[0]
        if "commutator" in key:
            base[family] = t.median
        ratio = t.median / base[family] if family in base else math.nan
        rows.append(f"| {key} | {its:.2f} | {err:.2e} | {drift:.1e} | {ratio:.2f} |")
    return rows


def so10(quick: bool, repeats: int) -> list[str]:
    """so(10) against scipy at energy error :data:`TARGET_ERROR`, compiled engine."""
    system, W0 = Case("generalized_rigid_body", "", 10, 0.01, 1, 1e-14).build(0)
    problem = Problem("grb", "so(10)", system, W0, 20.0, (), (), ())
    steps = (5, 10, 20) if quick else (5, 8, 10, 14, 20, 28, 40, 80)
    runs: dict[str, Callable[[], Any]] = {}
    meta: dict[str, tuple[str, str]] = {}
    for name, stages in (("gauss3", 3), ("gauss4", 4)):
        for update, rtols in (("commutator", (1e-14,)), ("conjugation", (1e-6, 1e-8, 1e-10))):
            scheme = BlockGauss(tableaus.gauss(stages), update=update)
            for rtol in rtols:
                curve = f"lieflow {name}+shift {update} rtol={rtol:g}"
                for n in steps:
                    key = f"{curve} {n}"
                    runs[key] = _run(problem, scheme, n, rtol, "compiled", "auto")
                    meta[key] = ("lieflow", curve)
    for method, tols in (("DOP853", range(5, 14)), ("Radau", range(5, 12))):
        for k in tols:
            key = f"scipy {method} {10.0**-k:g}"
            runs[key] = _scipy_run(problem, method, 10.0**-k)
            meta[key] = ("scipy", f"scipy {method}")
    for fn in runs.values():  # compilation out of the timings
        fn()
        break
    timings = compare(runs, repeats)
    points: list[Point] = []
    for key, t in timings.items():
        if not t.ok or t.result is None:
            continue
        states, work = t.result
        err, drift = _accuracy(system, states, W0)
        side, curve = meta[key]
        points.append(Point(side, curve, key, t.median, err, drift, f"{work}"))
    scipy_best = time_to_reach([p for p in points if p.side == "scipy"], TARGET_ERROR)
    rows = [
        f"| lieflow curve (compiled, T = 20) | time to energy error {TARGET_ERROR:g} | "
        "scipy best / lieflow | worst Casimir drift on the curve |",
        "|---|---|---|---|",
    ]
    curves = sorted({p.curve for p in points if p.side == "lieflow"})
    for curve in curves:
        mine = [p for p in points if p.curve == curve]
        got = time_to_reach(mine, TARGET_ERROR)
        drift = max(p.casimir_drift for p in mine)
        if got is None or scipy_best is None:
            rows.append(f"| {curve} | not reached | | {drift:.1e} |")
            continue
        rows.append(
            f"| {curve} | {got[0] * 1e3:.2f} ms | {scipy_best[0] / got[0]:.2f}× | {drift:.1e} |"
        )
    if scipy_best is not None:
        drift = scipy_best[1].casimir_drift
        rows.append(
            f"| (scipy best: {scipy_best[1].param}) | {scipy_best[0] * 1e3:.2f} ms | 1 | "
            f"{drift:.1e} |"
        )
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--only", choices=("zeitlin", "so10"), default=None)
    args = parser.parse_args(argv)
    if args.only in (None, "zeitlin"):
        print("\n".join(zeitlin(args.quick, args.repeats)), "\n", flush=True)
    if args.only in (None, "so10"):
        print("\n".join(so10(args.quick, args.repeats)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
