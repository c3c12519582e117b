"""The time of one fixed-point iteration: at large n against the matrix products it needs,
at small n (the Python and NumPy-call overhead) per update of a whole numpy-engine run.

At large n an iteration should cost what its ``n×n`` products cost (the BLAS bound): the
midpoint map needs 2 (``BM``, ``(BM)B``; ``MB = (BM)^T``), the reduced stage form ``3s``
(``G_j B_j^T``, ``P_j B_j``, ``G_j^T P_j``), the block form ``3s²``. The iteration is timed
through the scheme's :class:`~lieflow.solvers.ImplicitProblem` and ``FixedPoint.solve``
(stopping-rule norms included), the products with ``np.matmul(a, b, out=c)``.

At small n (issue 18) the products are negligible and what counts is everything around
them: ``lieflow.integrate(..., engine="numpy", diagnostics=False)`` divided by the
updates it took (warm starts, the step's update and projection and the stepping loop included).
Issue 27 measures that against :func:`plain_midpoint`, the same algorithm as a plain NumPy
loop, timed interleaved in the same process (target: at most 1.3× its time per update).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable

import attrs
import numpy as np

import lieflow as lf
from lieflow.app.reproduce import Case
from lieflow.schemes import BlockProblem, MidpointProblem, ReducedProblem
from lieflow.solvers import ImplicitProblem, SolveResult
from lieflow.tableaus import gauss

from ..config import BenchContext
from ..measure import stats
from ..report import Section, Table, TargetCheck, seconds
from ..timing import Timing, best_of, compare, peak_memory
from .rigid_body_scaling import grb_case

#: Issue 6: an iteration within this factor of its products.
TARGET_RATIO = 1.25

#: Issue 18: seconds per update of a numpy-engine so(3) midpoint run (4x below ~40 µs).
TARGET_SMALL = 8.5e-6

H = 0.01

#: Issue 27: a numpy-engine update within this factor of the plain loop's
#: (:func:`plain_midpoint`).
TARGET_PLAIN = 1.3

#: Small-n runs: (label, reproduce system, n, h, scheme) — the paper's cases.
SMALL_CASES: tuple[tuple[str, str, int, float, str], ...] = (
    ("so(3) rigid body", "rigid_body", 3, 0.1, "midpoint"),
    ("so(3) rigid body", "rigid_body", 3, 0.1, "gauss2"),
    ("so(10) generalized rigid body", "generalized_rigid_body", 10, 0.01, "midpoint"),
    ("so(10) generalized rigid body", "generalized_rigid_body", 10, 0.01, "gauss3"),
)


@attrs.frozen
class Formulation:
    """A fixed-point problem and how many products (and unknown matrices) it has."""

    label: str
    build: Callable[[lf.IsospectralSystem, np.ndarray], ImplicitProblem]
    products: int
    unknowns: int
    scheme: str


def formulations() -> tuple[Formulation, ...]:
    """Midpoint, gauss3 reduced form, gauss3 block form."""
    g3 = gauss(3)
    return (
        Formulation("midpoint", lambda s, W: MidpointProblem(s, W, H), 2, 1, "midpoint"),
        Formulation(
            "gauss3 reduced form", lambda s, W: ReducedProblem(s, W, H, g3), 9, 6, "gauss3"
        ),
        Formulation("gauss3 block form", lambda s, W: BlockProblem(s, W, H, g3), 27, 9, "gauss3"),
    )


def stats_of(timing: Timing[object]) -> SolveResult:
    """The solve result of a timing that must have succeeded."""
    value = timing.value
    assert isinstance(value, SolveResult)
    return value


@attrs.frozen
class IterationRow:
    """One ``(n, formulation)`` measurement."""

    n: int
    label: str
    iterations: int
    per_iteration: float
    products: float
    working_set: float
    unknowns: int
    fresh_output: bool
    engines: tuple[tuple[str, float], ...]

    @property
    def ratio(self) -> float:
        """Seconds per iteration over seconds of the products it needs."""
        return self.per_iteration / self.products


def measure(ctx: BenchContext, n: int, form: Formulation) -> IterationRow:
    """Time the solve and the products at size ``n``."""
    repeats = max(5, ctx.config.large_repeats)
    system, W0 = grb_case(n, 1).build(ctx.seed)
    problem = form.build(system, W0)
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, n, n))
    out = np.empty((n, n))

    def products() -> None:
        for _ in range(form.products):
            np.matmul(a, b, out=out)

    fns: dict[str, Callable[[], object]] = {
        "solve": lambda: solver.solve(problem),
        "products": products,
    }
    timed = compare(fns, repeats)
    solve = timed["solve"]
    its = stats_of(solve).iterations
    products_seconds = timed["products"].median
    working = peak_memory(lambda: solver.solve(problem)) / (W0.itemsize * n * n)
    fresh = not np.shares_memory(problem.map(problem.x0), problem.map(problem.x0))
    engines = []
    if form.label != "gauss3 block form":
        for run in ctx.engine_runs(form.scheme, n):
            e = run.engine or ""
            t = best_of(functools.partial(run.run, system, W0, H, 1), repeats)
            engines.append((e, t.median / int(stats(t).iterations.sum())))
    return IterationRow(
        n,
        form.label,
        its,
        solve.median / its,
        products_seconds,
        working,
        form.unknowns,
        fresh,
        tuple(engines),
    )


@attrs.frozen
class SmallRow:
    """One small-n numpy-engine run: its updates and seconds per update."""

    label: str
    scheme: str
    steps: int
    updates: int
    per_update: float


def measure_small(ctx: BenchContext, case: tuple[str, str, int, float, str]) -> SmallRow:
    """Time a whole numpy-engine run (``FixedPoint(rtol=1e-14)``, no diagnostics) and
    divide by its updates; median of the repeats."""
    label, name, n, h, scheme = case
    steps = 50 if ctx.config.quick else 2000
    system, W0 = Case(name, "", n, h, steps, 1e-14).build(ctx.seed)
    solver = lf.solvers.FixedPoint(rtol=1e-14)

    def once() -> lf.Solution:
        return lf.integrate(system, lf.schemes.get(scheme), W0, h, steps=steps, solver=solver,
                            engine="numpy", diagnostics=False)  # fmt: skip

    timing = best_of(once, max(3, ctx.config.repeats))
    sol = timing.value
    assert isinstance(sol, lf.Solution)
    updates = int(sol.iterations.sum())
    return SmallRow(label, scheme, steps, updates, timing.median / updates)


def small_n(ctx: BenchContext) -> tuple[Table, TargetCheck]:
    """The small-n table and its target (issue 18: so(3) midpoint ≤ 8.5 µs per update)."""
    rows = [measure_small(ctx, case) for case in SMALL_CASES]
    cells = tuple(
        (r.label, r.scheme, str(r.steps), f"{r.updates / r.steps:.2f}", seconds(r.per_update))
        for r in rows
    )
    table = Table(
        ("system", "scheme", "steps", "updates per step", "s/update"),
        cells,
        caption="Small n, numpy engine: a whole lieflow.integrate run (FixedPoint rtol 1e-14, "
        "warm starts, diagnostics=False) divided by its fixed-point updates.",
    )
    so3 = rows[0]
    met = so3.per_update <= TARGET_SMALL
    target = TargetCheck(
        target=f"small n (issue 18): so(3) midpoint, numpy engine, ≤ "
        f"{seconds(TARGET_SMALL)} per update",
        measured=", ".join(f"{r.label} {r.scheme}: {seconds(r.per_update)}" for r in rows),
        met=met,
        gap="" if met else f"{so3.per_update / TARGET_SMALL:.2f}x over",
        limit="NumPy call overhead (~0.3-1 µs a call on 3×3 arrays): ~15 calls per update "
        "(stage projection, B, two products, the combination, two norms), ~30 per step "
        "(warm-start extrapolation and its error check, the commutator update with its "
        "stage projection, the stepping loop's per-step chunk and finiteness check)",
    )
    return table, target


def plain_midpoint(
    S: np.ndarray, W0: np.ndarray, h: float, steps: int, rtol: float = 1e-14, patience: int = 6
) -> tuple[np.ndarray, int]:
    r"""The midpoint rule of a body with :math:`B(W) = S \odot W` as a plain NumPy loop:
    lieflow's numpy-engine algorithm with nothing around it (the baseline of issue 27).

    Per step, from the guess ``M = W + δ`` (``δ``: the previous step's solved offset
    ``M - W``, zero at first), the minimal-variable map (SPEC §4.1)

    .. math:: M \leftarrow W + q\,(BM - (BM)^T) + q^2\, BMB,\qquad B = S \odot M,
              \quad q = h/2,

    until the update meets ``||ΔM|| <= rtol ||M||`` (or sets no new minimum of the relative
    update for ``patience`` updates: roundoff), then ``W <- W + h (BM - (BM)^T)`` with
    ``B = S ⊙ M``. Returns the last state and the number of updates. Unlike lieflow it
    skips the stage projection (``B`` of the iterate itself, in the map and in the update;
    lieflow skips the projection of each new state on so(n) too, where it changes no bit),
    so its bits may differ from lieflow's in the last places.
    """
    q = 0.5 * h
    qq = q * q
    W = W0
    warm = np.zeros_like(W0)
    total = 0
    for _ in range(steps):
        M = W + warm
        best, best_at, k = math.inf, 0, 0
        while True:
            B = M * S
            BM = B @ M
            new = W + q * (BM - BM.T) + qq * (BM @ B)
            d = (new - M).ravel()
            f = new.ravel()
            step, size = math.sqrt(d.dot(d)), math.sqrt(f.dot(f))
            k += 1
            M = new
            if step <= rtol * size:
                break
            r = step / size
            if r < best:
                best, best_at = r, k
            elif k - best_at >= patience:
                break
        total += k
        warm = M - W
        B = M * S
        BM = B @ M
        W = W + h * (BM - BM.T)
    return W, total


@attrs.frozen
class PlainRow:
    """lieflow's numpy engine against :func:`plain_midpoint` on one body."""

    label: str
    steps: int
    updates: int
    plain_updates: int
    per_update: float
    plain_per_update: float

    @property
    def ratio(self) -> float:
        """lieflow's seconds per update over the plain loop's."""
        return self.per_update / self.plain_per_update


def measure_plain(ctx: BenchContext, case: tuple[str, str, int, float, str]) -> PlainRow:
    """Time lieflow's numpy engine (midpoint, ``FixedPoint(rtol=1e-14)``, warm start from
    the last solution: ``warm_start=1``, no diagnostics) and :func:`plain_midpoint` on the
    same body, interleaved; median seconds per update of each."""
    label, name, n, h, _ = case
    steps = 50 if ctx.config.quick else 2000
    system, W0 = Case(name, "", n, h, steps, 1e-14).build(ctx.seed)
    S = np.asarray(system.hadamard_factor)
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    scheme = lf.schemes.get("midpoint")

    def lieflow() -> object:
        return lf.integrate(system, scheme, W0, h, steps=steps, solver=solver, engine="numpy",
                            diagnostics=False, warm_start=1)  # fmt: skip

    fns: dict[str, Callable[[], object]] = {
        "lieflow": lieflow,
        "plain": lambda: plain_midpoint(S, W0, h, steps),
    }
    timed = compare(fns, max(5, 3 * ctx.config.repeats))
    sol = timed["lieflow"].value
    assert isinstance(sol, lf.Solution)
    plain = timed["plain"].value
    assert isinstance(plain, tuple)
    updates, plain_updates = int(sol.iterations.sum()), int(plain[1])
    return PlainRow(
        label,
        steps,
        updates,
        plain_updates,
        timed["lieflow"].median / updates,
        timed["plain"].median / plain_updates,
    )


#: Why lieflow's numpy engine costs more per update than the plain loop (measured).
PLAIN_LIMIT = (
    "per update lieflow's map and stopping test cost what the loop's update and "
    "its two norms do (CPU time, measured alone: so(3) 4.4 + 1.0 µs against ~6.3; "
    "so(10) 4.7 + 2.1 against ~6.7); the gap is per step, ~16 µs against the loop's ~3 "
    "(so(3) 53 against 44 µs a step, so(10) 46 against 30): the commutator update with "
    "its stage projection (~4.8 µs; the loop skips the projection), the warm start's "
    "prediction and bookkeeping (~3.3 µs), the solve's guess, stopping test and result "
    "(~2 µs), the step's problem (~1.3 µs), and the step's, flow's and stepping loop's "
    "results, chunk and finiteness check (~4 µs). The new state is not projected again "
    "on so(n) (SchemeFlow.step_from_phase_space: an exactly skew state stays exactly "
    "skew under the commutator update). so(10), 4 updates a step, needs ~6 µs less per "
    "step for 1.3×"
)


def _plain_target(rows: list[PlainRow], text: str) -> TargetCheck:
    """The verdict of :data:`TARGET_PLAIN` on ``rows``."""
    same = all(r.updates == r.plain_updates for r in rows)
    worst = max(rows, key=lambda r: r.ratio)
    met = worst.ratio <= TARGET_PLAIN and same
    return TargetCheck(
        target=text,
        measured=", ".join(f"{r.label}: {r.ratio:.2f}×" for r in rows)
        + ("" if same else " (the two took different numbers of updates)"),
        met=met,
        gap="" if met else f"worst {worst.ratio:.2f}× ({worst.label})",
        limit=PLAIN_LIMIT,
    )


def against_plain(ctx: BenchContext) -> tuple[Table, tuple[TargetCheck, ...]]:
    """The midpoint rows of :data:`SMALL_CASES` against the plain loop; target (issue 27):
    ≤ 1.3× its seconds per update."""
    rows = [measure_plain(ctx, c) for c in SMALL_CASES if c[4] == "midpoint"]
    cells = tuple(
        (
            r.label,
            f"{r.updates / r.steps:.2f} / {r.plain_updates / r.steps:.2f}",
            seconds(r.per_update),
            seconds(r.plain_per_update),
            f"{r.ratio:.2f}",
        )
        for r in rows
    )
    table = Table(
        (
            "system",
            "updates per step (lieflow / plain)",
            "lieflow s/update",
            "plain loop s/update",
            "ratio",
        ),
        cells,
        caption="Midpoint rule, FixedPoint rtol 1e-14, warm start from the last step's "
        "solution: lieflow.integrate(engine='numpy', warm_start=1, diagnostics=False) "
        "against the same algorithm as a plain NumPy loop (plain_midpoint), timed "
        "alternately, median of each.",
    )
    so3 = [r for r in rows if r.label.startswith("so(3)")]
    rest = [r for r in rows if not r.label.startswith("so(3)")]
    targets = (
        _plain_target(so3, "small n (issue 27, stated for so(3)): a numpy-engine update ≤ "
                      f"{TARGET_PLAIN}× a plain NumPy loop of the same algorithm"),
        _plain_target(rest, f"the same on so(10) ≤ {TARGET_PLAIN}×"),
    )  # fmt: skip
    return table, targets


def run(ctx: BenchContext) -> Section:
    """Every size and formulation; target: ratio ≤ 1.25 at n ≥ 256; and the small-n runs."""
    start = time.perf_counter()
    rows = [measure(ctx, n, f) for n in ctx.config.iteration_sizes for f in formulations()]
    header = [
        "n",
        "formulation",
        "updates",
        "s/iteration",
        "products needed (s)",
        "iteration / products",
        "peak working set (n×n matrices; unknown)",
    ]
    header += [f"engine={e} s/iteration (per step)" for e in ctx.engines]
    cells = []
    for r in rows:
        cell = [
            str(r.n),
            r.label,
            str(r.iterations),
            seconds(r.per_iteration),
            seconds(r.products),
            f"{r.ratio:.2f}",
            f"{r.working_set:.1f} ({r.unknowns})",
        ]
        engine_cells = {e: seconds(sec) for e, sec in r.engines}
        cell += [engine_cells.get(e, "—") for e in ctx.engines]
        cells.append(tuple(cell))
    table = Table(
        tuple(header),
        tuple(cells),
        caption="Generalized rigid body, h = 0.01, one cold solve at rtol 1e-14: time per "
        "fixed-point iteration vs the matrix products it needs (preallocated np.matmul).",
    )
    big = [r for r in rows if r.n >= 256 and r.label != "gauss3 block form"] or [
        r for r in rows if r.label != "gauss3 block form"
    ]
    worst = max(big, key=lambda r: r.ratio)
    met = worst.ratio <= TARGET_RATIO
    over = [r for r in big if r.ratio > TARGET_RATIO]
    target = TargetCheck(
        target=f"large n (≥ 256): time per fixed-point iteration ≤ {TARGET_RATIO}× the time "
        "of the products it needs",
        measured=", ".join(f"{r.label} n = {r.n}: {r.ratio:.2f}" for r in big)
        + ("" if big[0].n >= 256 else " (quick sizes)"),
        met=met,
        gap="" if met else f"worst {worst.ratio:.2f} ({worst.label}, n = {worst.n})",
        limit=(
            "the products dominate; the rest is elementwise passes over n×n arrays "
            "(the stage projection and B(W), the combination with h and h², two norms per "
            "iteration) and the fresh arrays of B and of the map's result"
            if not met or over
            else "the products dominate; elementwise passes and norms are a small fraction"
        ),
    )
    alloc_max = max(r.working_set - r.unknowns for r in rows)
    fresh = any(r.fresh_output for r in rows)
    alloc = TargetCheck(
        target="no allocation per iteration (large n)",
        measured=("every map() call returns a new array" if fresh else "map() reuses buffers")
        + f"; peak working set up to {alloc_max:.1f} n×n matrices beyond the unknown",
        met=not fresh,
        gap=""
        if not fresh
        else "the midpoint and reduced maps write their products into scratch kept for the "
        "step, but B(W) and the map's result are fresh arrays every iteration (the block form "
        "also allocates every product)",
        limit="the ImplicitProblem protocol returns a new array from map(), and a system's B "
        "returns a new array; removing those would take an out= argument in both protocols "
        "(scratch for the products gained 1.06–1.11× on gauss3 at n = 128–512)",
    )
    notes = [
        "s/iteration: one cold FixedPoint.solve divided by its updates; the products: the "
        "same number of n×n matmuls into a preallocated output; the two timed alternately, "
        f"median of {max(5, ctx.config.large_repeats)} each.",
        "Peak working set: tracemalloc peak of the solve over the size of one n×n matrix; "
        "the number in brackets is the size of the unknown itself.",
    ]
    small_table, small_target = small_n(ctx)
    plain_table, plain_targets = against_plain(ctx)
    return Section(
        title="Large n: cost of one iteration vs its matrix products; small n: overhead",
        intro="Is the fixed-point iteration at the BLAS bound? And at small n, how much "
        "does everything around the products cost?",
        tables=(table, small_table, plain_table),
        targets=(target, alloc, small_target, *plain_targets),
        notes=tuple(notes),
        seconds=time.perf_counter() - start,
    )
