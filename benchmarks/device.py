"""Euler–Zeitlin on a GPU: ms/step, updates/step and agreement with the CPU engine.

One command, a few minutes on one H100/H200 with 16 CPU cores (most of it the CPU reference,
computed once per size and scheme after all device rows, up to ``--reference-max``, 1024 by
default)::

    python -m benchmarks.device                 # CuPy or PyTorch (CUDA), whichever imports
    python -m benchmarks.device --library torch --sizes 256 1024
    python -m benchmarks.device --dry-run       # array_api_strict on the CPU, small N (a test)
    python -m benchmarks.device --out table.md --check-every 1 2 4

For each N, scheme (midpoint, gauss2) and precision (complex128; complex64 with the solver's
stagnation-aware stop — the roundoff floor scales with machine epsilon, so an rtol below
single precision ends as "roundoff", not as a failure) it runs the same lieflow source on
the device's arrays (``lieflow.backends``: schemes, maps, FixedPoint, and the Hoppe–Yau solve
as one batched parallel cyclic reduction), from a smooth random vorticity field of rms 1,
``h = 1/128`` of fluid time, ``FixedPoint(rtol=1e-13)``, warm starts from the previous step.
One untimed step first (it places the Laplacian's multipliers on the device), then
``--steps`` timed steps (device synchronised before reading the clock), once per
``FixedPoint(check_every=k)`` of ``--check-every`` (the host reads the stopping test once per
``k`` updates). The CPU reference
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
    system: Any,
    scheme: Any,
    W: Any,
    steps: int,
    sync: Callable[[], None],
    warm: Any = None,
    check_every: int = 1,
) -> tuple[Any, list[int], float, Any]:
    """``steps`` warm-started steps from ``W`` (and the previous step's unknowns ``warm``):
    ``(W_end, updates per step, seconds, warm_end)``."""
    solver = lf.solvers.FixedPoint(rtol=RTOL, max_iter=200, check_every=check_every)
    updates = []
    sync()
    start = time.perf_counter()
    for _ in range(steps):
        r = scheme.step(W, H, system, solver, warm)
        W, warm = r.W, r.warm
        updates.append(r.stats.iterations)
    sync()
    return W, updates, time.perf_counter() - start, warm


#: Above this size ``random_vorticity`` takes its O(N⁴) reference path (minutes at 2048).
RECURRENCE_MAX = 1400


def initial_state(N: int) -> np.ndarray:
    """The smooth random vorticity field of rms 1 (``‖W‖_F² = N``) that every row at size
    ``N`` starts from: ``lieflow_zeitlin.random_vorticity`` (degrees 1..8) up to
    :data:`RECURRENCE_MAX`; above it a random quadratic polynomial in the spin matrices
    ``S_a`` — the quantized coordinate functions, so a field of degrees 1..2 — made
    traceless and skew-Hermitian, built in seconds."""
    import lieflow_zeitlin as lz

    if N <= RECURRENCE_MAX:
        W: np.ndarray = lz.random_vorticity(N, degree=8, seed=N)
        return W
    rng = np.random.default_rng(N)
    S = [a / ((N - 1) / 2) for a in lz.spin_matrices(N)]
    H = sum(rng.standard_normal() * a for a in S)
    for i in range(3):
        for j in range(i, 3):
            H = H + rng.standard_normal() * (S[i] @ S[j] + S[j] @ S[i]) / 2
    H = (H + H.conj().T) / 2
    H -= (np.trace(H) / N) * np.eye(N)
    W = 1j * H
    return np.asarray(W * (np.sqrt(N) / np.linalg.norm(W)))


def measure(
    system: Any,
    W0c: np.ndarray,
    scheme_name: str,
    dtype: Any,
    steps: int,
    put: Callable[[np.ndarray], Any],
    sync: Callable[[], None],
    check_every: int,
) -> tuple[dict[str, Any], np.ndarray]:
    """One row of the table (agreement still to be filled in) and the end state on the
    host. ``system`` is built once per size: its Laplacian multipliers (extended precision,
    seconds at N = 2048) are computed once and placed on the device once per precision."""
    N = W0c.shape[-1]
    scheme = lf.schemes.get(scheme_name)
    W0 = W0c.astype(dtype)
    # one untimed step (it places the constants on the device and compiles the library's
    # kernels), then the timed ones: the same steps + 1 warm-started steps as the reference
    W1, _, _, warm = run_steps(system, scheme, put(W0), 1, sync, None, check_every)
    W, updates, seconds, _ = run_steps(system, scheme, W1, steps, sync, warm, check_every)
    row: dict[str, Any] = {
        "N": N,
        "scheme": scheme_name,
        "dtype": np.dtype(dtype).name,
        "check_every": check_every,
        "ms/step": 1e3 * seconds / steps,
        "updates/step": float(np.mean(updates)),
        "agreement": float("nan"),
    }
    return row, to_numpy(W).astype(np.complex128)


def reference(
    system: Any, W0c: np.ndarray, scheme_name: str, steps: int
) -> tuple[np.ndarray, float]:
    """The NumPy engine's end state after ``steps`` warm-started steps from ``W0c`` (on the
    host, all BLAS threads) and its seconds per step."""
    W, _, seconds, _ = run_steps(system, lf.schemes.get(scheme_name), W0c, steps, lambda: None)
    return W, seconds / steps


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a Markdown table."""
    head = "| N | scheme | dtype | check every | ms/step | updates/step | rel. diff. vs CPU |"
    lines = [head, "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['N']} | {r['scheme']} | {r['dtype']} | {r['check_every']} | "
            f"{r['ms/step']:.2f} | {r['updates/step']:.1f} | {r['agreement']:.1e} |"
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
        "--check-every",
        type=int,
        nargs="+",
        default=[1, 2, 4],
        help="FixedPoint(check_every=k) values, one row each (host reads per k updates)",
    )
    parser.add_argument(
        "--reference-max",
        type=int,
        default=1024,
        help="compare with the CPU engine up to this N (the CPU reference dominates the time)",
    )
    parser.add_argument("--no-single", action="store_true", help="skip complex64")
    parser.add_argument("--out", help="also write the table (Markdown) to this file")
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
    title = f"# Euler–Zeitlin on {description}; h = 1/128 fluid time, rtol {RTOL:g}"
    print(title, flush=True)
    dtypes: list[Any] = [np.complex128] + ([] if args.no_single else [np.complex64])
    rows: list[dict[str, Any]] = []
    ends: list[np.ndarray] = []
    failures: list[str] = []
    import lieflow_zeitlin as lz

    states = {N: initial_state(N) for N in args.sizes}
    systems = {N: lz.EulerZeitlin(N, time="fluid") for N in args.sizes}

    def write() -> None:
        if args.out:
            with open(args.out, "w", encoding="utf-8") as f:
                f.write(f"{title}\n\n{table(rows)}\n")

    # the device rows first (seconds), then the CPU references (minutes at N = 1024)
    for N in args.sizes:
        for dtype in dtypes:
            for name in SCHEMES:
                for k in args.check_every:
                    try:
                        row, end = measure(
                            systems[N], states[N], name, dtype, args.steps, put, sync, k
                        )
                    except lf.errors.ConvergenceError as exc:  # a row, not the whole table
                        failures.append(f"N={N} {name} {np.dtype(dtype).name} k={k}: {exc}")
                        print(f"  {failures[-1]}", flush=True)
                        continue
                    rows.append(row)
                    ends.append(end)
                    print(
                        f"  N={N} {name} {row['dtype']} check_every={k}: "
                        f"{row['ms/step']:.2f} ms/step, {row['updates/step']:.1f} updates/step",
                        flush=True,
                    )
                    write()
    for N in (n for n in args.sizes if n <= args.reference_max):
        for name in SCHEMES:
            try:
                Wc, per_step = reference(systems[N], states[N], name, args.steps + 1)
            except lf.errors.ConvergenceError as exc:
                failures.append(f"CPU reference N={N} {name}: {exc}")
                continue
            print(f"  CPU reference N={N} {name}: {1e3 * per_step:.1f} ms/step", flush=True)
            for row, end in zip(rows, ends, strict=True):
                if row["N"] == N and row["scheme"] == name:
                    row["agreement"] = float(np.max(np.abs(end - Wc)) / np.max(np.abs(Wc)))
            write()
    print(table(rows))
    for failure in failures:
        print(f"failed: {failure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
