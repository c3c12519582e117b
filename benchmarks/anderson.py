"""Anderson acceleration against the plain fixed point (issue 38): time per step and per
update of ``FixedPoint(anderson=5)`` over ``FixedPoint()``, the numpy engine, in one process.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.anderson          # the grid below (~10 min)
    OPENBLAS_NUM_THREADS=1 python -m benchmarks.anderson --sizes 1024 --inv-h 128 --steps 1
    python -m benchmarks.anderson --sizes 256 --inv-h 32 --repeats 5    # one row

Euler–Zeitlin midpoint (``time="fluid"``) from the smooth rms-1 field of
``benchmarks.device.initial_state(N)``, ``rtol = 1e-13``, ``N = 64 … 512`` (1024 on request:
minutes per row on one thread) and ``h = 1/256 … 1/32``; then the so(10) generalized rigid
body (``h = 0.01``, ``0.1``) and the periodic Toda lattice (``h = 0.1``, ``0.5``). Each
row first takes one untimed plain step from the initial state, then runs ``--steps`` warm-
started steps from there with each solver, alternately, ``--repeats`` times: the best
process CPU time of each (a shared machine's wall clock counts other processes' time
slices; with one BLAS thread CPU time is the step's own). Ratios are Anderson over plain:
per step, and per update (CPU time inside the solver per fixed-point update: the step's
other work — commutator update, warm start — is the same for both and, divided by fewer
updates, would make an accelerated update look dearer than it is).

Targets (issue 38, one BLAS thread): ``N = 256``, ``h = 1/32``: a step ``≤ 0.5×`` plain's;
per update ``≤ 1.15×`` at ``N ≥ 256`` (rows where Anderson engages); no row slower per step
than ``1.10×``; ``N = 1024``, ``h = 1/128``: ``≤ 16`` updates per step.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Callable, Sequence
from typing import Any

import attrs
import numpy as np

import lieflow as lf
from lieflow.solvers import ImplicitProblem, SolveResult

#: The depth measured (the issue's window).
DEPTH = 5
RTOL = 1e-13

#: Issue 38's targets.
TARGET_STEP_256 = 0.5
TARGET_UPDATE = 1.15
TARGET_NEVER_SLOWER = 1.10
TARGET_UPDATES_1024 = 16


def _euler_zeitlin(N: int) -> tuple[Any, np.ndarray]:
    from .device import initial_state

    system = lf.systems.get("euler_zeitlin", N=N, time="fluid", diagnostics_every=0)
    return system, initial_state(N)


def _small(name: str) -> tuple[Any, np.ndarray]:
    system: Any = (
        lf.systems.GeneralizedRigidBody.random_inertia(10, seed=3)
        if name == "so(10)"
        else lf.systems.get("periodic_toda")
    )
    return system, system.random_state(seed=1)


@attrs.frozen
class Timed(lf.solvers.FixedPoint):
    """:class:`~lieflow.solvers.FixedPoint` adding the CPU seconds of its solves to
    ``seconds[0]``: the time of the updates alone (a step's other work, the commutator
    update, the diagnostics, is the same for both solvers and would otherwise be spread
    over fewer updates of the accelerated one)."""

    seconds: list[float] = attrs.field(factory=lambda: [0.0], kw_only=True, eq=False)

    def solve(self, problem: ImplicitProblem) -> SolveResult:
        start = time.process_time()
        res = super().solve(problem)
        self.seconds[0] += time.process_time() - start
        return res


def measure(
    make: Callable[[], tuple[Any, np.ndarray]], h: float, steps: int, repeats: int
) -> dict[str, float]:
    """Updates per step, best CPU seconds per step and per update (of the solves alone)
    of plain and Anderson iteration."""
    system, W0 = make()
    scheme = lf.schemes.get("midpoint")
    W1 = lf.integrate(system, scheme, W0, h=h, steps=1, engine="numpy").W_final
    depths = {"plain": 0, "anderson": DEPTH}
    best = dict.fromkeys(depths, np.inf)
    per_update = dict.fromkeys(depths, np.inf)
    updates = dict.fromkeys(depths, 0.0)
    for r in range(repeats):
        for name in depths if r % 2 == 0 else reversed(list(depths)):
            solver = Timed(rtol=RTOL, anderson=depths[name])
            start = time.process_time()
            sol = lf.integrate(system, scheme, W1, h=h, steps=steps, solver=solver,
                               engine="numpy", diagnostics=False)  # fmt: skip
            best[name] = min(best[name], (time.process_time() - start) / steps)
            updates[name] = float(sol.iterations.mean())
            total = updates[name] * steps
            per_update[name] = min(per_update[name], solver.seconds[0] / total)
    out = {"plain_updates": updates["plain"], "anderson_updates": updates["anderson"]}
    out["plain_step"] = best["plain"]
    out["step_ratio"] = best["anderson"] / best["plain"]
    out["update_ratio"] = per_update["anderson"] / per_update["plain"]
    return out


def _row(label: str, h: str, r: dict[str, float]) -> str:
    return (
        f"| {label} | {h} | {r['plain_updates']:.1f} | {r['anderson_updates']:.1f} | "
        f"{1e3 * r['plain_step']:.1f} | {r['step_ratio']:.2f} | {r['update_ratio']:.2f} |"
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.anderson", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 512])
    parser.add_argument("--inv-h", type=int, nargs="+", default=[256, 128, 64, 32],
                        help="1/h in fluid time")  # fmt: skip
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-small", action="store_true", help="skip so(10) and Toda")
    args = parser.parse_args(argv)
    print("| case | h | plain updates/step | Anderson updates/step | plain ms/step "
          "| step ratio | update ratio |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    cases: list[tuple[str, str, str, Callable[[], tuple[Any, np.ndarray]], float, int]] = []
    for N in args.sizes:
        for inv in args.inv_h:
            build = functools.partial(_euler_zeitlin, N)
            cases.append(
                (f"N={N}", f"Euler–Zeitlin N = {N}", f"1/{inv}", build, 1 / inv, args.steps)
            )
    if not args.no_small:
        for name, hs in (("so(10)", (0.01, 0.1)), ("Toda", (0.1, 0.5))):
            for h in hs:
                cases.append((name, name, f"{h:g}", functools.partial(_small, name), h, 200))
    rows: list[tuple[str, float, dict[str, float]]] = []
    for key, label, h_text, make, h, steps in cases:
        try:
            r = measure(make, h, steps, args.repeats)
        except lf.ConvergenceError as exc:
            print(f"| {label} | {h_text} | plain fails: {exc.reason} | | | | |", flush=True)
            continue
        rows.append((key, h, r))
        print(_row(label, h_text, r), flush=True)
    print()
    _targets(rows)
    return 0


def _targets(rows: list[tuple[str, float, dict[str, float]]]) -> None:
    """The issue's targets on the rows measured."""
    for label, h, r in rows:
        if label == "N=256" and h == 1 / 32:
            verdict = "met" if r["step_ratio"] <= TARGET_STEP_256 else "NOT met"
            print(f"- N = 256, h = 1/32: step ratio {r['step_ratio']:.2f} "
                  f"(target <= {TARGET_STEP_256}): {verdict}")  # fmt: skip
        if label == "N=1024" and h == 1 / 128:
            verdict = "met" if r["anderson_updates"] <= TARGET_UPDATES_1024 else "NOT met"
            print(f"- N = 1024, h = 1/128: {r['anderson_updates']:.1f} updates/step "
                  f"(target <= {TARGET_UPDATES_1024}): {verdict}")  # fmt: skip
    engaged = [
        (label, h, r)
        for label, h, r in rows
        if label.startswith("N=")
        and int(label[2:]) >= 256
        and r["anderson_updates"] < r["plain_updates"]
    ]
    if engaged:
        worst = max(r["update_ratio"] for _, _, r in engaged)
        verdict = "met" if worst <= TARGET_UPDATE else "NOT met"
        print(f"- per update at N >= 256 where Anderson engages: at most {worst:.2f}x "
              f"(target <= {TARGET_UPDATE}): {verdict}")  # fmt: skip
    worst = max(r["step_ratio"] for _, _, r in rows)
    verdict = "met" if worst <= TARGET_NEVER_SLOWER else "NOT met"
    print(f"- slowest row per step: {worst:.2f}x plain (target <= {TARGET_NEVER_SLOWER}): "
          f"{verdict}")  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
