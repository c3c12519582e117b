"""Euler–Zeitlin on a device: ms per step and per update, updates per step, ms per unit of fluid
time and agreement with the CPU engine, for each engine.

One command, a few minutes on one H100/H200 (most of it the CPU reference, computed once per
size and scheme after all device rows, up to ``--reference-max``, 1024 by default)::

    python -m benchmarks.device                     # every engine the machine has
    python -m benchmarks.device --engines traced hand --sizes 256 1024 2048
    python -m benchmarks.device --dry-run           # JAX, array_api_strict on the CPU
    python -m benchmarks.device --out table.md

Engines (rows):

* ``traced`` — lieflow's traced engine (``engine="jax"``, :mod:`lieflow.engines.traced`): the
  whole step compiled by ``jax.jit``, a chunk of steps per call, the default warm start
  (extrapolation from up to five steps), with ``FixedPoint`` and, per ``--anderson m``,
  ``FixedPoint(anderson=m)``; JAX arrays on JAX's default device.
* ``hand`` — a hand-written ``jax.jit`` midpoint of the same equations, the yardstick of the
  engine's overhead: the map ``M <- W + (h/2)(BM - (BM)^†) + (h²/4) BMB`` with the plugin's
  ``B``, a plain relative-update stop, every step started from ``M = W``, the steps as one
  ``lax.scan`` (no warm start, no diagnostics, no failure handling).
* ``eager`` — the array library's eager steps (CuPy, PyTorch; JAX or ``array_api_strict`` in a
  dry run), ``FixedPoint(check_every=k)`` per ``--check-every k``, each step warm-started from
  the previous step's unknowns.

Sizes and step sizes: ``h = 1/128`` fluid time, ``1/256`` from N = 2048 on (where the fixed
point diverges at ``1/128``: issue 34); complex128 at ``rtol = 1e-13`` and complex64 at
``rtol = 1e-6`` (single precision's own tolerance). One untimed step, then ``--steps`` timed
steps (the device synchronised before reading the clock). From a smooth random vorticity field
of rms 1 (:func:`initial_state`). The CPU reference runs the same number of steps on the numpy
engine; the table gives ``max |W - W_cpu| / max |W_cpu|``.

Exits with status 2 and a message when no engine runs on this machine.
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

#: Step size in fluid time at each N (the largest power of two at which the fixed point
#: converges on this field, halving as N doubles beyond 1024), and the solver tolerances.
H = 1.0 / 128
H_LARGE = 1.0 / 256
RTOL = {"complex128": 1e-13, "complex64": 1e-6}
SCHEMES = ("midpoint", "gauss2")


def step_size(N: int) -> float:
    """The benchmark's step size in fluid time at size ``N``."""
    return H if N < 2048 else H_LARGE


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


def _jax(gpu_only: bool) -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str] | None:
    try:
        import jax
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    device = jax.devices()[0]
    if gpu_only and device.platform == "cpu":
        return None

    def put(a: np.ndarray) -> Any:
        return jax.device_put(np.ascontiguousarray(a), device)

    def sync() -> None:
        (jax.device_put(0.0, device) + 0).block_until_ready()

    kind = getattr(device, "device_kind", device.platform)
    return put, sync, f"JAX {jax.__version__}, {kind}"


def select(library: str) -> tuple[Callable[[np.ndarray], Any], Callable[[], None], str] | None:
    """``(to_device, synchronize, description)`` of the requested array library for the
    eager rows, or ``None`` when it (or its GPU) is unavailable. ``"auto"``: CuPy, PyTorch
    or JAX with a GPU, whichever imports first."""
    if library == "numpy":
        return _numpy()
    if library == "array_api_strict":
        return _strict()
    if library == "cupy":
        return _cupy()
    if library == "torch":
        return _torch()
    if library == "jax":
        return _jax(gpu_only=False)
    return _cupy() or _torch() or _jax(gpu_only=True)


def run_steps(
    system: Any,
    scheme: Any,
    W: Any,
    steps: int,
    sync: Callable[[], None],
    h: float,
    rtol: float,
    warm: Any = None,
    check_every: int = 1,
) -> tuple[Any, list[int], float, Any]:
    """``steps`` eager warm-started steps from ``W`` (and the previous step's unknowns
    ``warm``): ``(W_end, updates per step, seconds, warm_end)``."""
    solver = lf.solvers.FixedPoint(rtol=rtol, max_iter=200, check_every=check_every)
    updates = []
    sync()
    start = time.perf_counter()
    for _ in range(steps):
        r = scheme.step(W, h, system, solver, warm)
        W, warm = system.project(r.W), r.warm
        updates.append(r.stats.iterations)
    sync()
    return W, updates, time.perf_counter() - start, warm


def run_traced(
    system: Any, scheme: Any, W: Any, steps: int, h: float, solver: Any
) -> tuple[Any, list[int], float]:
    """One untimed step of the traced engine (it compiles), then ``steps`` timed steps as
    one chunk: ``(W_end, updates per step, seconds)``."""
    from lieflow import stepping
    from lieflow.engines import scheme_flow

    flow = scheme_flow(system, scheme, solver, W, steps + 1, engine="jax")
    recording = stepping.Recording(save_every=steps + 1, last=steps + 1)
    first = flow.step_many(W, 0, h, 1, flow.init(W), recording=recording)
    if not first.size:
        raise lf.ConvergenceError("not_accepted", solver=solver.name, step=1)
    start = time.perf_counter()  # step_many returns once the device is done (one sync)
    chunk = flow.step_many(first.W[-1], 1, h, steps, first.state, recording=recording)
    seconds = time.perf_counter() - start
    if chunk.size < steps:
        raise lf.ConvergenceError("not_accepted", solver=solver.name, step=2 + chunk.size)
    return chunk.W[-1], chunk.iterations.tolist(), seconds


def hand_written(system: Any, h: float, rtol: float, steps: int) -> Callable[[Any], Any]:
    """The hand-written ``jax.jit`` midpoint (module docstring): ``f(W) -> (W_end,
    updates per step)``."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    def step(W: Any) -> tuple[Any, Any]:
        def F(M: Any) -> Any:
            B = system.B(M)
            BM = B @ M
            return W + (h / 2) * (BM - jnp.conj(jnp.swapaxes(BM, -1, -2))) + (h * h / 4) * (BM @ B)

        def body(c: tuple[Any, ...]) -> tuple[Any, ...]:
            M, _, k = c
            G = F(M)
            return G, jnp.linalg.norm(G - M) / jnp.linalg.norm(G), k + 1

        M, _, k = lax.while_loop(
            lambda c: (c[1] > rtol) & (c[2] < 200), body, (W, jnp.asarray(1.0), 0)
        )
        B = system.B(M)
        BM = B @ M
        return system.project(W + h * (BM - jnp.conj(jnp.swapaxes(BM, -1, -2)))), k

    def run(W: Any) -> Any:
        return lax.scan(lambda W, _: step(W), W, None, length=steps)

    return jax.jit(run)


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


def _row(
    N: int, h: float, scheme: str, dtype: Any, engine: str, seconds: float, updates: Sequence[int]
) -> dict[str, Any]:
    steps = len(updates)
    per_step = 1e3 * seconds / steps
    return {
        "N": N,
        "h": h,
        "scheme": scheme,
        "dtype": np.dtype(dtype).name,
        "engine": engine,
        "ms/step": per_step,
        "updates/step": float(np.mean(updates)),
        "ms/update": 1e3 * seconds / max(int(np.sum(updates)), 1),
        "ms/time": per_step / h,
        "agreement": float("nan"),
    }


def reference(system: Any, W0c: np.ndarray, scheme_name: str, steps: int, h: float) -> np.ndarray:
    """The numpy engine's end state after ``steps`` steps from ``W0c`` (host, all BLAS
    threads; the default warm start, as the traced rows)."""
    sol = lf.integrate(
        system,
        lf.schemes.get(scheme_name),
        W0c,
        h,
        steps=steps,
        solver=lf.solvers.FixedPoint(rtol=RTOL["complex128"], max_iter=200),
        save_every=steps,
        diagnostics=False,
        engine="numpy",
    )
    return np.asarray(sol.W_final)


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a Markdown table."""
    head = (
        "| N | h | scheme | dtype | engine | ms/step | updates/step | ms/update | "
        "ms per unit time | rel. diff. vs CPU |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['N']} | 1/{round(1 / r['h'])} | {r['scheme']} | {r['dtype']} | {r['engine']} | "
            f"{r['ms/step']:.2f} | {r['updates/step']:.1f} | {r['ms/update']:.3f} | "
            f"{r['ms/time']:.0f} | {r['agreement']:.1e} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.device", description=__doc__)
    parser.add_argument(
        "--library",
        choices=("auto", "cupy", "torch", "jax", "numpy", "array_api_strict"),
        default="auto",
        help="the array library of the eager rows",
    )
    parser.add_argument(
        "--engines",
        nargs="+",
        choices=("traced", "hand", "eager"),
        default=["traced", "hand", "eager"],
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument(
        "--anderson",
        type=int,
        nargs="+",
        default=[0, 5],
        help="traced rows: FixedPoint(anderson=m) for each m (0: plain)",
    )
    parser.add_argument(
        "--check-every",
        type=int,
        nargs="+",
        default=[1, 4],
        help="eager rows: FixedPoint(check_every=k) for each k",
    )
    parser.add_argument(
        "--reference-max",
        type=int,
        default=1024,
        help="compare with the CPU engine up to this N (minutes at 1024)",
    )
    parser.add_argument("--no-single", action="store_true", help="skip complex64")
    parser.add_argument("--out", help="also write the table (Markdown) to this file")
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="JAX (CPU) and array_api_strict at N = 16, 2 steps",
    )
    args = parser.parse_args(argv)
    if args.dry_run:
        args.library, args.sizes, args.steps = "array_api_strict", [16], 2
    eager = select(args.library) if "eager" in args.engines else None
    traced = _jax(gpu_only=not args.dry_run and args.library != "jax")
    engines = [e for e in args.engines if (e == "eager" and eager) or (e != "eager" and traced)]
    if not engines:
        print(
            "benchmarks.device: no engine runs here: no GPU for JAX, CuPy or PyTorch "
            f"(--library {args.library}); run it on a machine with an NVIDIA GPU, or use "
            "--dry-run (or --library jax) to check the script on the CPU",
            file=sys.stderr,
        )
        return 2
    described = [d for _, _, d in (x for x in (traced, eager) if x is not None)]
    title = f"# Euler–Zeitlin on {'; '.join(dict.fromkeys(described))}"
    print(title, flush=True)
    import lieflow_zeitlin as lz

    dtypes: list[Any] = [np.complex128] + ([] if args.no_single else [np.complex64])
    states = {N: initial_state(N) for N in args.sizes}
    systems = {N: lz.EulerZeitlin(N, time="fluid") for N in args.sizes}
    rows: list[dict[str, Any]] = []
    ends: list[np.ndarray] = []
    failures: list[str] = []

    def write() -> None:
        if args.out:
            with open(args.out, "w", encoding="utf-8") as f:
                f.write(f"{title}\n\n{table(rows)}\n")

    def record(row: dict[str, Any], end: Any) -> None:
        rows.append(row)
        ends.append(to_numpy(end).astype(np.complex128))
        print(f"  {table([row]).splitlines()[-1]}", flush=True)
        write()

    for N in args.sizes:
        h, system = step_size(N), systems[N]
        for dtype in dtypes:
            rtol = RTOL[np.dtype(dtype).name]
            W0 = states[N].astype(dtype)
            for name in SCHEMES:
                scheme = lf.schemes.get(name)
                label = f"N={N} {name} {np.dtype(dtype).name}"
                if "traced" in engines and traced is not None:
                    for m in args.anderson:
                        solver = lf.solvers.FixedPoint(rtol=rtol, max_iter=200, anderson=m)
                        what = "traced" + (f", Anderson({m})" if m else "")
                        try:
                            end, updates, seconds = run_traced(
                                system, scheme, traced[0](W0), args.steps, h, solver
                            )
                        except (lf.ConvergenceError, lf.InputError) as exc:
                            failures.append(f"{label} {what}: {exc}")
                            continue
                        record(_row(N, h, name, dtype, what, seconds, updates), end)
                if "hand" in engines and traced is not None and name == "midpoint":
                    run = hand_written(system, h, rtol, args.steps)
                    after, _ = run(traced[0](W0))  # compiles; then as many steps from there
                    traced[1]()
                    start = time.perf_counter()
                    end, counts = run(after)
                    traced[1]()
                    seconds = time.perf_counter() - start
                    updates = np.asarray(counts).tolist()
                    record(_row(N, h, name, dtype, "hand-written jit", seconds, updates), end)
                if "eager" in engines and eager is not None:
                    put, sync, _ = eager
                    for k in args.check_every:
                        try:
                            W1, _, _, warm = run_steps(
                                system, scheme, put(W0), 1, sync, h, rtol, None, k
                            )
                            end, updates, seconds, _ = run_steps(
                                system, scheme, W1, args.steps, sync, h, rtol, warm, k
                            )
                        except lf.ConvergenceError as exc:
                            failures.append(f"{label} eager k={k}: {exc}")
                            continue
                        record(
                            _row(N, h, name, dtype, f"eager, check every {k}", seconds, updates),
                            end,
                        )
    # the CPU references last (minutes at N = 1024); the hand-written rows started one step
    # later than they ended (scan of `steps` from the state after `steps`): compared with
    # 2 * steps steps
    for N in (n for n in args.sizes if n <= args.reference_max):
        for name in SCHEMES:
            wanted = {args.steps + 1, 2 * args.steps}
            refs: dict[int, np.ndarray] = {}
            for steps in sorted(wanted):
                try:
                    refs[steps] = reference(systems[N], states[N], name, steps, step_size(N))
                except lf.ConvergenceError as exc:
                    failures.append(f"CPU reference N={N} {name}: {exc}")
            for row, end in zip(rows, ends, strict=True):
                steps = 2 * args.steps if row["engine"] == "hand-written jit" else args.steps + 1
                if row["N"] == N and row["scheme"] == name and steps in refs:
                    Wc = refs[steps]
                    row["agreement"] = float(np.max(np.abs(end - Wc)) / np.max(np.abs(Wc)))
            write()
    print(table(rows))
    for failure in failures:
        print(f"failed: {failure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
