"""Seconds per step of the Euler–Zeitlin system for N = 128, 256, 512 (midpoint and gauss2).

Usage (single-threaded BLAS gives reproducible numbers on a shared machine)::

    OPENBLAS_NUM_THREADS=1 python plugins/lieflow-zeitlin/benchmarks/seconds_per_step.py \
        [--sizes 128 256 512] [--schemes midpoint gauss2] [--steps 8] [--rtol 1e-12] [--h 0.5]

Setup: smooth random vorticity (degrees 1..8, rms 1, seed 0), unscaled bracket
``dW/dt = [P, W]``, fixed-point solver with relative tolerance ``rtol`` and lieflow's warm
starts (:func:`lieflow.iterate`); ``warmup`` steps are run first (the cold first steps need
more iterations), then the next ``steps`` steps are timed (no diagnostics). Also reported:
the time of one ``B`` solve and of one complex ``N×N`` product (best of 5).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import lieflow_zeitlin as lz
import numpy as np

import lieflow as lf


def _best(f: Callable[..., Any], *args: Any, repeat: int = 5) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        f(*args)
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--schemes", nargs="+", default=["midpoint", "gauss2"])
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--rtol", type=float, default=1e-12)
    parser.add_argument("--h", type=float, default=0.5, help="step in matrix time")
    args = parser.parse_args()
    print(f"h = {args.h}, FixedPoint(rtol={args.rtol:g}), warm starts, {args.steps} timed steps")
    print(f"{'N':>5} {'scheme':>9} {'s/step':>9} {'its/step':>9} {'B (ms)':>8} {'NxN (ms)':>9}")
    for N in args.sizes:
        system = lz.EulerZeitlin(N, time="matrix")  # the timings below: h in matrix time
        W0 = lz.random_vorticity(N, degree=8, seed=0)
        t_B = _best(system.B, W0) * 1e3
        t_mm = _best(np.matmul, W0, W0) * 1e3
        solver = lf.solvers.FixedPoint(rtol=args.rtol)
        for name in args.schemes:
            steps = lf.iterate(system, lf.schemes.get(name), W0, args.h, solver)
            for _ in range(args.warmup):
                next(steps)
            its = 0
            t = time.perf_counter()
            for _ in range(args.steps):
                its += next(steps).result.iterations
            per_step = (time.perf_counter() - t) / args.steps
            print(
                f"{N:>5} {name:>9} {per_step:>9.4f} {its / args.steps:>9.1f} {t_B:>8.2f} "
                f"{t_mm:>9.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
