"""The numpy engine against its floor: Euler–Zeitlin midpoint, seconds per step over the
time of the products and Laplacian solves the step cannot avoid, measured in one process.

    python -m benchmarks.floor                  # N = 256, the threads BLAS has
    python -m benchmarks.floor --sizes 256 512 --cpu-time
    OPENBLAS_NUM_THREADS=1 python -m benchmarks.floor    # the one-thread check (target 1.25x)
    python -m benchmarks.floor --sizes 512 --threads 1 2 4 8 16   # a thread-scaling table

Floor of a step with ``u`` fixed-point updates (``lf.integrate`` with diagnostics, rtol
1e-14, ``h = 1/N`` of fluid time, smooth random vorticity of rms 1, warm starts):
``u (2 GEMM + B)`` for the midpoint maps, ``GEMM + B`` for the update, ``GEMM`` for the
Casimirs ``tr W^k``, ``k <= 4`` and ``B`` for the energy — each term the best time of that
operation alone: ``GEMM`` a complex ``N × N`` product of random matrices (the hardware's
rate), ``B`` on the state. (A map's second product, ``BMB``, is skew-Hermitian and formed
from its upper block triangle, ``lieflow.algebras.skew_matmul``: about 0.7 GEMM at
N = 256, so the ``2 GEMM`` of an update is more than the map computes.) The product of
the state with itself is reported beside it ("state GEMM"): a state of a wide dynamic
range (entries down to ``1e-280`` at N = 1024) makes subnormal partial sums, which Intel
cores compute at a fraction of the rate (issue 38; the underflow guard,
``lieflow.underflow``, is what keeps the steps' own products off that path), so
timing the floor on the state understated it. The fluids plugin's
extra diagnostics (spectra, vorticity levels) are off (``diagnostics_every=0``): they are
not part of a step. ``--cpu-time`` reads process CPU time instead of the wall clock: on a
shared machine the wall clock of a 40 ms step includes other processes' time slices, which
best-of-k timings of a 3 ms product mostly avoid (one BLAS thread only).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np

import lieflow as lf


def best(f: Callable[[], object], repeats: int, clock: Callable[[], float]) -> float:
    """Best-of-``repeats`` seconds of ``f()`` (after one untimed call)."""
    f()
    times = []
    for _ in range(repeats):
        start = clock()
        f()
        times.append(clock() - start)
    return min(times)


def measure(N: int, steps: int, repeats: int, clock: Callable[[], float]) -> dict[str, float]:
    """Seconds per step, its floor and their parts at size ``N``."""
    import lieflow_zeitlin as lz

    system = lf.systems.get("euler_zeitlin", N=N, time="fluid", diagnostics_every=0)
    W0 = lz.random_vorticity(N, degree=8, seed=0)
    scheme = lf.schemes.get("midpoint")
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    h = 1.0 / N
    sol = lf.integrate(system, scheme, W0, h=h, steps=steps, solver=solver, engine="numpy")

    def run() -> None:
        lf.integrate(system, scheme, W0, h=h, steps=steps, solver=solver, engine="numpy")

    step = best(run, repeats, clock) / steps
    W = sol.W[-1]
    out = np.empty_like(W)
    rng = np.random.default_rng(N)
    X, Y = (rng.standard_normal((N, N)) + 1j * rng.standard_normal((N, N)) for _ in "XY")
    gemm = best(lambda: np.matmul(X, Y, out=out), 5 * repeats, clock)
    state_gemm = best(lambda: np.matmul(W, W, out=out), 5 * repeats, clock)
    B = best(lambda: system.B(W), 5 * repeats, clock)
    updates = float(sol.iterations.mean())
    floor = updates * (2 * gemm + B) + (gemm + B) + gemm + B
    return {"N": N, "updates": updates, "step": step, "gemm": gemm, "state_gemm": state_gemm,
            "B": B, "floor": floor}  # fmt: skip


#: Environment variables that set the thread count of the BLAS libraries NumPy may use.
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def scaling(args: argparse.Namespace) -> int:
    """One subprocess per thread count (BLAS reads its thread count at start-up), each
    printing its rows; a ``threads`` column in front."""
    print("| threads | N | updates/step | ms/step | GEMM ms | state GEMM ms | B ms | floor ms "
          "| step / floor |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for t in args.threads:
        env = dict(os.environ, **{v: str(t) for v in THREAD_VARIABLES})
        command = [sys.executable, "-m", "benchmarks.floor", "--sizes", *map(str, args.sizes)]
        command += ["--steps", str(args.steps), "--repeats", str(args.repeats)]
        command += ["--cpu-time"] if args.cpu_time else []
        out = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
        for line in out.stdout.splitlines():
            if line.startswith("| ") and line[2].isdigit():
                print(f"| {t} {line}", flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.floor", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256])
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cpu-time", action="store_true", help="process CPU time, not wall")
    parser.add_argument(
        "--threads",
        type=int,
        nargs="+",
        help="a scaling table: one run per BLAS thread count (e.g. 1 2 4 8 16)",
    )
    args = parser.parse_args(argv)
    if args.threads:
        return scaling(args)
    clock = time.process_time if args.cpu_time else time.perf_counter
    print("| N | updates/step | ms/step | GEMM ms | state GEMM ms | B ms | floor ms "
          "| step / floor |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for N in args.sizes:
        r = measure(N, args.steps, args.repeats, clock)
        print(
            f"| {N} | {r['updates']:.2f} | {1e3 * r['step']:.1f} | {1e3 * r['gemm']:.2f} | "
            f"{1e3 * r['state_gemm']:.2f} | {1e3 * r['B']:.2f} | {1e3 * r['floor']:.1f} | "
            f"{r['step'] / r['floor']:.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
