"""Seconds per transform (spherical harmonics ↔ matrix ↔ grid), recurrence vs reference.

Usage (single-threaded BLAS: one core, reproducible on a shared machine)::

    OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \
        python plugins/lieflow-zeitlin/benchmarks/transforms.py [--sizes 256 512 1024] \
        [--reference-up-to 512] [--repeat 3]

For each N: a random real field with all degrees ``< N`` (seed 0), best of ``repeat`` timings
of ``sh_to_matrix``, ``matrix_to_sh``, ``sh_to_grid`` and ``grid_to_sh`` (Gauss grid of
``N × 2N``) with ``method="recurrence"`` (after one untimed call that loads numba's cache)
and, up to ``--reference-up-to``, ``method="reference"`` (eigensolver per diagonal; scipy's
Legendre functions); the round-trip errors ``max |ω - matrix_to_sh(sh_to_matrix(ω))|`` and
``max |ω - grid_to_sh(sh_to_grid(ω))|`` relative to ``max |ω|``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import lieflow_zeitlin as lz
import numpy as np


def _best(f: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = f()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--reference-up-to", type=int, default=512)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    lz.sh_to_matrix(lz.random_sh(8, 7, seed=0))  # load the compiled kernels
    lz.sh_to_grid(lz.random_sh(8, 7, seed=0), lz.SphereGrid.for_size(8))
    print(
        f"{'N':>5} {'method':>10} {'sh→mat':>8} {'mat→sh':>8} {'sh→grid':>8} "
        f"{'grid→sh':>8} {'err mat':>9} {'err grid':>9}"
    )
    for N in args.sizes:
        c = lz.random_sh(N, N - 1, seed=0)
        grid = lz.SphereGrid.for_size(N)
        methods = ["recurrence"] + (["reference"] if N <= args.reference_up_to else [])
        for method in methods:
            r = args.repeat if method == "recurrence" else 1
            t1, W = _best(lambda: lz.sh_to_matrix(c, method=method), r)  # noqa: B023
            t2, c1 = _best(lambda: lz.matrix_to_sh(W, method=method), r)  # noqa: B023
            t3, f = _best(lambda: lz.sh_to_grid(c, grid, method=method), r)  # noqa: B023
            t4, c2 = _best(lambda: lz.grid_to_sh(f, grid, N, method=method), r)  # noqa: B023
            scale = np.abs(c).max()
            e1 = np.abs(c1 - c).max() / scale
            e2 = np.abs(c2 - c).max() / scale
            print(
                f"{N:>5} {method:>10} {t1:8.3f} {t2:8.3f} {t3:8.3f} {t4:8.3f} {e1:9.1e} {e2:9.1e}",
                flush=True,
            )


if __name__ == "__main__":
    main()
