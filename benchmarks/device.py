"""Euler–Zeitlin on a GPU: ms/step, updates/step and agreement with the CPU engine.

One command, at most about 5 minutes on one H100/H200 with 16 CPU cores (most of it the CPU
reference at N = 2048, computed once per size and scheme; ``--reference-max 1024`` skips it)::

    python -m benchmarks.device                 # CuPy or PyTorch (CUDA), whichever imports
    python -m benchmarks.device --library torch --sizes 256 1024
    python -m benchmarks.device --dry-run       # array_api_strict on the CPU, small N (a test)

For each N, scheme (midpoint, gauss2) and precision (complex128; complex64 with the solver's
stagnation-aware stop — the roundoff floor scales with machine epsilon, so an rtol below
single precision ends as "roundoff", not as a failure) it runs the same lieflow source on
the device's arrays (``lieflow.backends``: schemes, maps, FixedPoint, and the Hoppe–Yau solve
as one batched parallel cyclic reduction), from a smooth random vorticity field of rms 1,
``h = 1/128`` of fluid time, ``FixedPoint(rtol=1e-13)``, warm starts from the previous step.
One untimed step first (it places the Laplacian's multipliers on the device), then
``--steps`` timed steps (device synchronised before reading the clock). The CPU reference
runs the same steps on NumPy arrays (the numpy engine: sequential sweeps for ``B``) and the
table gives ``max |W_gpu - W_cpu| / max |W_cpu|`` after them.

Exits with status 2 and a message when neither CuPy nor PyTorch sees a CUDA device.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

import lieflow as lf
from lieflow.backends import to_numpy

#: Step size in fluid time and the solver tolerance (issue 28's comparison).
H = 1.0 / 128
RTOL = 1e-13
SCHEMES = ("midpoint", "gauss2")


def _cupy() -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str] | None:
    try:
        import cupy as cp
    except ImportError:
        return None
    try:
        if cp.cuda.runtime.getDeviceCount() < 1:
            return None
        name = cp.cuda.runtime.getDeviceProperties(0)["name"].decode()
    except Exception:
        return None
    return cp.asarray, cp.cuda.Device().synchronize, f"CuPy {cp.__version__}, {name}"


def _torch() -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str] | None:
    try:
        import torch
    except ImportError:
        return None
    if not torch.cuda.is_available():
        return None

    def put(a: np.ndarray) -> Any:
        return torch.from_numpy(np.ascontiguousarray(a)).to("cuda")

    name = torch.cuda.get_device_name(0)
    return put, torch.cuda.synchronize, f"PyTorch {torch.__version__}, {name}"


def _numpy() -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str]:
    return np.array, lambda: None, f"NumPy {np.__version__} (CPU)"


def _strict() -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str] | None:
    try:
        import array_api_strict as xps
    except ImportError:
        return None
    return xps.asarray, lambda: None, f"array_api_strict {xps.__version__} (CPU, the device path)"


def select(library: str) -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str] | None:
    """``(to_device, synchronize, description)`` of the requested array library, or
    ``None`` when it (or its GPU) is unavailable."""
    if library == "numpy":
        return _numpy()
    if library == "array_api_strict":
        return _strict()
    if library == "cupy":
        return _cupy()
    if library == "torch":
        return _torch()
    return _cupy() or _torch()


def run_steps(
    system: Any, scheme: Any, W: Any, steps: int, sync: Callable[[], None], warm: Any = None
) -> tuple[Any, list[int], float, Any]:
    """``steps`` warm-started steps from ``W`` (and the previous step's unknowns ``warm``):
    ``(W_end, updates per step, seconds, warm_end)``."""
    solver = lf.solvers.FixedPoint(rtol=RTOL, max_iter=200)
    updates = []
    sync()
    start = time.perf_counter()
    for _ in range(steps):
        r = scheme.step(W, H, system, solver, warm)
        W, warm = r.W, r.warm
        updates.append(r.stats.iterations)
    sync()
    return W, updates, time.perf_counter() - start, warm


def initial_state(N: int) -> np.ndarray:
    """The smooth random vorticity field of rms 1 that every row at size ``N`` starts from
    (built once per size: at N = 2048 it takes tens of seconds on the host)."""
    import lieflow_zeitlin as lz

    W: np.ndarray = lz.random_vorticity(N, degree=8, seed=N)
    return W


def measure(
    W0c: np.ndarray,
    scheme_name: str,
    dtype: Any,
    steps: int,
    put: Callable[[np.ndarray], Any],
    sync: Callable[[], None],
    references: dict[tuple[int, str], np.ndarray] | None,
) -> dict[str, Any]:
    """One row of the table; ``references`` caches the CPU engine's end states by ``(N,
    scheme)`` (one complex128 reference serves both precisions), ``None``: no comparison."""
    import lieflow_zeitlin as lz

    N = W0c.shape[-1]
    system = lz.EulerZeitlin(N, time="fluid")
    scheme = lf.schemes.get(scheme_name)
    W0 = W0c.astype(dtype)
    # one untimed step (it places the constants on the device), then the timed ones: the
    # same steps + 1 warm-started steps as the CPU reference
    W1, _, _, warm = run_steps(system, scheme, put(W0), 1, sync)
    W, updates, seconds, _ = run_steps(system, scheme, W1, steps, sync, warm)
    row: dict[str, Any] = {
        "N": N,
        "scheme": scheme_name,
        "dtype": np.dtype(dtype).name,
        "ms/step": 1e3 * seconds / steps,
        "updates/step": float(np.mean(updates)),
        "agreement": float("nan"),
    }
    if references is not None:
        key = (N, scheme_name)
        if key not in references:
            references[key] = run_steps(system, scheme, W0c, steps + 1, lambda: None)[0]
        Wc = references[key]
        Wd = to_numpy(W).astype(np.complex128)
        row["agreement"] = float(np.max(np.abs(Wd - Wc)) / np.max(np.abs(Wc)))
    return row


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a Markdown table."""
    head = "| N | scheme | dtype | ms/step | updates/step | rel. diff. vs CPU |"
    lines = [head, "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['N']} | {r['scheme']} | {r['dtype']} | {r['ms/step']:.2f} | "
            f"{r['updates/step']:.1f} | {r['agreement']:.1e} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.device", description=__doc__)
    parser.add_argument(
        "--library", choices=("auto", "cupy", "torch", "numpy", "array_api_strict"), default="auto"
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument(
        "--reference-max",
        type=int,
        default=2048,
        help="compare with the CPU engine up to this N (the CPU reference dominates the time)",
    )
    parser.add_argument("--no-single", action="store_true", help="skip complex64")
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="array_api_strict arrays on the CPU (the device code path) at N = 16, 32, 2 steps",
    )
    args = parser.parse_args(argv)
    if args.dry_run:
        args.library, args.sizes, args.steps = "array_api_strict", [16, 32], 2
    chosen = select(args.library)
    if chosen is None:
        print(
            "benchmarks.device: no GPU array library with a CUDA device found "
            f"(--library {args.library}); install CuPy or PyTorch with CUDA on a machine "
            "with an NVIDIA GPU, or use --dry-run to check the script on the CPU",
            file=sys.stderr,
        )
        return 2
    put, sync, description = chosen
    print(f"# Euler–Zeitlin on {description}; h = 1/128 fluid time, rtol {RTOL:g}")
    dtypes: list[Any] = [np.complex128] + ([] if args.no_single else [np.complex64])
    rows = []
    references: dict[tuple[int, str], np.ndarray] = {}
    for N in args.sizes:
        W0 = initial_state(N)
        for dtype in dtypes:
            for name in SCHEMES:
                compare = references if N <= args.reference_max else None
                row = measure(W0, name, dtype, args.steps, put, sync, compare)
                rows.append(row)
                print(
                    f"  N={N} {name} {row['dtype']}: {row['ms/step']:.2f} ms/step, "
                    f"{row['updates/step']:.1f} updates/step, diff {row['agreement']:.1e}",
                    flush=True,
                )
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
