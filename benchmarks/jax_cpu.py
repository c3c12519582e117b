"""Small systems on the CPU: the traced engine on JAX's CPU backend against the numba engine
(issue 34: can one source of the numerics serve small systems, so that the numba twin of the
numerics could go?).

    python -m benchmarks.jax_cpu              # so(3), so(10), Euler–Zeitlin N = 16
    python -m benchmarks.jax_cpu --steps 2000 --repeats 5

For each case: steps per second of the numba engine (``lf.integrate`` with
``engine="compiled"``, without diagnostics, saving the last state only: its fixed cost of a
call, ~50 µs, is negligible over the run) and of the traced engine's steady state (one flow,
``--steps`` steps as chunks of its compiled program; not counted: the ~0.3–0.5 s a new flow
spends tracing its program and loading it from JAX's compilation cache, once per
``lf.integrate`` call), after one untimed run; best of ``--repeats``, interleaved, wall clock
and process CPU time (XLA's CPU backend may use more than one thread).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

import lieflow as lf
from lieflow import stepping
from lieflow.engines import scheme_flow


def cases() -> list[tuple[str, Any, np.ndarray, str, float]]:
    """``(label, system, W0, scheme, h)`` of each row."""
    import lieflow_zeitlin as lz

    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    grb = lf.systems.get("generalized_rigid_body", J=np.linspace(1.0, 3.0, 10))
    ez = lz.EulerZeitlin(16)
    return [
        ("so(3) midpoint", body, body.random_state(0), "midpoint", 0.1),
        ("so(3) gauss2", body, body.random_state(0), "gauss2", 0.1),
        ("so(10) midpoint", grb, grb.random_state(0), "midpoint", 0.1),
        ("so(10) gauss2", grb, grb.random_state(0), "gauss2", 0.1),
        ("Euler–Zeitlin N = 16 midpoint", ez, lz.random_vorticity(16, 6, seed=1), "midpoint", 0.05),
        ("Euler–Zeitlin N = 16 gauss2", ez, lz.random_vorticity(16, 6, seed=1), "gauss2", 0.05),
    ]


def best(run: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Best wall-clock and best CPU seconds of ``run()`` over ``repeats`` calls."""
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        run()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.jax_cpu", description=__doc__)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    lines = [
        "| case | numba steps/s | JAX steps/s | JAX time / numba time (wall) | (CPU time) |",
        "|---|---|---|---|---|",
    ]
    print(lines[0], flush=True)
    for label, system, W0, scheme_name, h in cases():
        scheme = lf.schemes.get(scheme_name)
        solver = lf.solvers.FixedPoint(rtol=1e-14)

        def numba(scheme: Any = scheme, system: Any = system, W0: Any = W0, h: float = h,
                  solver: Any = solver) -> Any:  # fmt: skip
            sol = lf.integrate(system, scheme, W0, h, steps=args.steps, solver=solver,
                               save_every=args.steps, diagnostics=False,
                               engine="compiled")  # fmt: skip
            return sol.W_final

        Wj = jax.numpy.asarray(W0)
        flow = scheme_flow(system, scheme, solver, Wj, args.steps, engine="jax")
        recording = stepping.Recording(save_every=args.steps, last=args.steps)

        def traced(flow: Any = flow, Wj: Any = Wj, h: float = h, rec: Any = recording) -> Any:
            done, W, state = 0, Wj, flow.init(Wj)
            while done < args.steps:
                chunk = flow.step_many(W, done, h, args.steps - done, state, recording=rec)
                done, W, state = chunk.stop, chunk.W[-1], chunk.state
            return np.asarray(W)

        a, b = numba(), traced()  # compile, and check they agree
        # (roundoff grows along 2000 steps of a rotating body: a sanity check, not a test)
        assert np.abs(a - b).max() <= 1e-8 * np.abs(a).max()
        numba_t, jax_t = [np.inf, np.inf], [np.inf, np.inf]
        for _ in range(args.repeats):  # interleaved
            numba_t = list(map(min, numba_t, best(numba, 1)))
            jax_t = list(map(min, jax_t, best(traced, 1)))
        row = (
            f"| {label} | {args.steps / numba_t[0]:,.0f} | {args.steps / jax_t[0]:,.0f} | "
            f"{jax_t[0] / numba_t[0]:.2f} | {jax_t[1] / numba_t[1]:.2f} |"
        )
        lines.append(row)
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
