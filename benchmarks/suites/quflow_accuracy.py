"""Euler–Zeitlin against quflow's ``isomp`` at equal accuracy (issue 27 item 4).

quflow (Modin's reference Euler–Zeitlin code, ``pip install quflow``) is an optional external
contender: the section says it is skipped when ``import quflow`` fails and then reports
lieflow's side alone. Nothing of quflow is copied here; its ``isomp`` (the isospectral
midpoint rule by fixed-point iteration, its default tolerance ``sqrt(eps) h/ħ ‖W‖∞``) is
called as users call it.

Both codes integrate the same matrix ``W0`` (``lieflow_zeitlin.random_vorticity``, built by
lieflow, so quflow's ``shc2mat`` basis is never used) in the same convention,
``Ẇ = [Δ⁻¹W, W]/ħ`` in fluid time (docs/euler-zeitlin.md, "The time unit"). The error of a
run is ``‖W(T) − W_ref(T)‖_F / ‖W_ref(T)‖_F`` against Gauss-4 at a small step, rtol 1e-14.
Time-to-accuracy at an error level is interpolated on the log–log work–precision frontier
(:func:`scipy_work_precision.time_to_reach`; its ``energy_error`` field carries the state
error here). lieflow's curves: the midpoint rule and Gauss-4 (4 stages, order 8) with the
commutator update at rtol 1e-14 and the conjugation update at rtol 1e-8, and Gauss-2 (order
4) with the conjugation update; then Gauss-2 and Gauss-4 with the conjugation update at rtol
1e-8 and ``casimir_shift="auto"`` (the same flow stepped on ``B(W) - c⋆W``, an isospectral
Lie–Poisson scheme of the same order: the setting ``docs/choosing.md`` recommends trying
first). All runs are timed interleaved in one process, median round.

Both sides run as a user comparing final states would: quflow's ``isomp`` computes no
diagnostics and returns the last state only, so lieflow runs with ``diagnostics=False`` and
``save_every=steps`` (the first and the last state kept). :data:`RECOMMENDED` is the one
configuration the docs recommend for 1e-4 … 1e-6, chosen once for every level and both sizes;
its own time to each level is reported beside the frontier's.

The floor of a midpoint step with ``u`` fixed-point updates is ``u (2 GEMM + B) + GEMM + B``
(each term the best time of that operation alone on the same state, as in
``benchmarks/floor.py``); quflow's iteration does the same products.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from typing import Any, Literal

import attrs
import numpy as np

import lieflow as lf
from lieflow import tableaus
from lieflow.schemes import BlockGauss, SyDIRK

from ..config import BenchContext
from ..floor import best
from ..report import Section, Table, TargetCheck, seconds
from ..timing import compare
from .scipy_work_precision import Point, time_to_reach

#: Error levels of the time-to-accuracy comparison (relative Frobenius error at T).
LEVELS = (1e-4, 1e-5, 1e-6)

#: Target of issue 27: quflow's time / lieflow's time at every level.
TARGET = 1.5

#: rtol of the conjugation ("accuracy") runs.
ACCURACY_RTOL = 1e-8

#: The configuration recommended for errors 1e-4 … 1e-6 (docs/conjugation.md): Gauss-2
#: (order 4), conjugation update at :data:`ACCURACY_RTOL`, Casimir shift ``"auto"``.
RECOMMENDED = f"lieflow gauss2 conjugation+shift rtol {ACCURACY_RTOL:g}"


@attrs.frozen
class Setup:
    """Size, final time, steps per curve and timing rounds of one run of the suite."""

    N: int
    T: float
    midpoint_steps: tuple[int, ...]
    gauss_steps: tuple[int, ...]
    gauss2_steps: tuple[int, ...]
    reference_steps: int
    repeats: int
    shifted_gauss2_steps: tuple[int, ...]
    shifted_gauss_steps: tuple[int, ...]


def setups(quick: bool) -> tuple[Setup, ...]:
    """N = 64 over T = 1/2 and N = 128 over T = 1/4 of fluid time (quick: N = 16, T = 1/8,
    one round)."""
    if quick:
        return (Setup(16, 0.125, (8, 16, 32), (1, 2), (1, 2), 8, 1, (1, 2), (1,)),)
    midpoint = (32, 64, 128, 256, 512, 1024)
    # N = 128 over T = 1/4: fixed point diverges for gauss4 at h = 1/4 there, and quflow
    # needs > 1024 steps for 1e-6 over T = 1/2. Fixed point stalls for gauss2 at h = 1/4
    # (with the Casimir shift it converges there).
    return (Setup(64, 0.5, midpoint, (2, 4, 8, 16), (4, 8, 16), 64, 5, (2, 3, 4, 6, 8, 12),
                  (1, 2, 3, 4)),
            Setup(128, 0.25, midpoint, (2, 4, 8, 16), (4, 8, 16), 32, 3, (2, 3, 4, 6, 8, 12),
                  (1, 2, 3)))  # fmt: skip


def quflow_isomp() -> Callable[..., Any] | None:
    """quflow's ``isomp``, or ``None`` when quflow is not installed."""
    try:
        import quflow
    except ImportError:
        return None
    fn: Callable[..., Any] = quflow.isomp
    return fn


@attrs.frozen
class Curve:
    """One code and configuration: its runs by step count."""

    label: str
    steps: tuple[int, ...]
    run: Callable[[int], Callable[[], tuple[np.ndarray, float]]]


def lieflow_curve(
    system: lf.IsospectralSystem, W0: np.ndarray, T: float, label: str, scheme: lf.Scheme,
    rtol: float, steps: tuple[int, ...], shift: float | Literal["auto"] = 0.0,
) -> Curve:  # fmt: skip
    """lieflow runs: final state and mean updates per step (no diagnostics, the first and
    the last state kept, as quflow's ``isomp`` returns the last state only)."""
    solver = lf.solvers.FixedPoint(rtol=rtol)

    def make(n: int) -> Callable[[], tuple[np.ndarray, float]]:
        def go() -> tuple[np.ndarray, float]:
            sol = lf.integrate(
                system, scheme, W0, h=T / n, steps=n, solver=solver, diagnostics=False,
                save_every=n, casimir_shift=shift,
            )  # fmt: skip
            return sol.W[-1], float(np.mean(sol.iterations))

        return go

    return Curve(label, steps, make)


def quflow_curve(
    isomp: Callable[..., Any], W0: np.ndarray, T: float, steps: tuple[int, ...]
) -> Curve:
    """quflow ``isomp`` runs at its default tolerance: final state and iterations per step."""

    def make(n: int) -> Callable[[], tuple[np.ndarray, float]]:
        def go() -> tuple[np.ndarray, float]:
            stats: dict[str, float] = {"iterations": 0.0}
            W = isomp(W0.copy(), T / n, steps=n, stats=stats)
            return W, float(stats["iterations"])

        return go

    return Curve("quflow isomp (tol auto)", steps, make)


@contextlib.contextmanager
def one_numba_thread() -> Iterator[None]:
    """numba's parallel loops on one thread while timing (BLAS runs on one thread too).

    quflow's kernels are ``prange`` loops: with two numba thread pools in one process on a
    shared 2-core machine, its steps measured 4–15× slower than alone, which would measure
    the machine, not the code.
    """
    try:
        import numba
    except ImportError:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


def relative_error(W: np.ndarray, ref: np.ndarray) -> float:
    """``‖W − ref‖_F / ‖ref‖_F``."""
    return float(np.linalg.norm(W - ref) / np.linalg.norm(ref))


def floor_per_update(system: lf.IsospectralSystem, W: np.ndarray) -> tuple[float, float]:
    """Best seconds of one complex GEMM and of one ``B`` on ``W``."""
    out = np.empty_like(W)
    gemm = best(lambda: np.matmul(W, W, out=out), 15, time.perf_counter)
    B = best(lambda: system.B(W), 15, time.perf_counter)
    return gemm, B


@attrs.frozen
class SizeResult:
    """The tables, target and notes of one size."""

    tables: tuple[Table, ...]
    target: TargetCheck
    notes: tuple[str, ...]


def measure(ctx: BenchContext, s: Setup, isomp: Callable[..., Any] | None) -> SizeResult:
    """Every curve at one size: errors, times, floor ratios and time to accuracy."""
    import lieflow_zeitlin as lz

    system = lf.systems.get("euler_zeitlin", N=s.N, time="fluid")
    W0 = lz.random_vorticity(s.N, degree=8, seed=ctx.seed)
    g4 = tableaus.gauss(4)
    ref_sol = lf.integrate(
        system, BlockGauss(g4), W0, h=s.T / s.reference_steps, steps=s.reference_steps,
        solver=lf.solvers.FixedPoint(rtol=1e-14), diagnostics=False,
    )  # fmt: skip
    ref = ref_sol.W[-1]
    midpoint = "lieflow midpoint commutator rtol 1e-14"
    curves = [
        lieflow_curve(system, W0, s.T, midpoint, SyDIRK(), 1e-14, s.midpoint_steps),
        lieflow_curve(system, W0, s.T, f"lieflow midpoint conjugation rtol {ACCURACY_RTOL:g}",
                      SyDIRK(update="conjugation"), ACCURACY_RTOL, s.midpoint_steps),
        lieflow_curve(system, W0, s.T, "lieflow gauss4 commutator rtol 1e-14", BlockGauss(g4),
                      1e-14, s.gauss_steps),
        lieflow_curve(system, W0, s.T, f"lieflow gauss4 conjugation rtol {ACCURACY_RTOL:g}",
                      BlockGauss(g4, update="conjugation"), ACCURACY_RTOL, s.gauss_steps),
        lieflow_curve(system, W0, s.T, f"lieflow gauss2 conjugation rtol {ACCURACY_RTOL:g}",
                      BlockGauss(tableaus.gauss(2), update="conjugation"), ACCURACY_RTOL,
                      s.gauss2_steps),
        lieflow_curve(system, W0, s.T, RECOMMENDED,
                      BlockGauss(tableaus.gauss(2), update="conjugation"), ACCURACY_RTOL,
                      s.shifted_gauss2_steps, "auto"),
        lieflow_curve(system, W0, s.T, f"lieflow gauss4 conjugation+shift rtol {ACCURACY_RTOL:g}",
                      BlockGauss(g4, update="conjugation"), ACCURACY_RTOL,
                      s.shifted_gauss_steps, "auto"),
    ]  # fmt: skip
    if isomp is not None:
        isomp(W0.copy(), s.T, steps=1)  # numba compiles on the first call: not timed
        curves.append(quflow_curve(isomp, W0, s.T, s.midpoint_steps))
    runs = {f"{c.label}|{n}": c.run(n) for c in curves for n in c.steps}
    with one_numba_thread():
        timed = compare(runs, s.repeats)
    gemm, B = floor_per_update(system, ref)
    rows, points = [], []
    finals: dict[str, np.ndarray] = {}
    for key, t in timed.items():
        label, n = key.rsplit("|", 1)
        if t.result is None:
            rows.append((label, n, "n/a", "n/a", "n/a", t.error or "", "—"))
            continue
        W, updates = t.result
        finals[key] = W
        err = relative_error(W, ref)
        side = "quflow" if label.startswith("quflow") else "lieflow"
        points.append(Point(side, label, n, t.median, err, 0.0, f"{updates:.2f}"))
        steps = int(n)
        floor = updates * (2 * gemm + B) + gemm + B
        midpoint_rule = "midpoint" in label or side == "quflow"
        rows.append((label, n, f"{err:.2e}", seconds(t.median), f"{updates:.2f}",
                     seconds(t.median / steps),
                     f"{t.median / steps / floor:.2f}" if midpoint_rule else "—"))  # fmt: skip
    table = Table(
        ("code / configuration", "steps", "error at T", "seconds", "updates/step",
         "s/step", "× its floor"),
        tuple(rows),
        caption=f'Euler–Zeitlin N = {s.N}, time="fluid", T = {s.T:g}, W0 = '
        f"lieflow_zeitlin.random_vorticity({s.N}, degree=8, seed={ctx.seed}); error: relative "
        f"Frobenius vs gauss4 at {s.reference_steps} steps, rtol 1e-14; median of {s.repeats} "
        "interleaved rounds; floor of a midpoint step = u (2 GEMM + B) + GEMM + B, "
        f"GEMM = {seconds(gemm)}, B = {seconds(B)} (best of 15).",
    )  # fmt: skip
    lie = [p for p in points if p.side == "lieflow"]
    quf = [p for p in points if p.side == "quflow"]
    rec = [p for p in lie if p.curve == RECOMMENDED]
    level_rows, ratios = [], []
    for level in LEVELS:
        a, b = time_to_reach(lie, level), time_to_reach(quf, level)
        c = time_to_reach(rec, level)
        r = None if a is None or b is None else b[0] / a[0]
        rc = None if c is None or b is None else b[0] / c[0]
        ratios.append(r)
        level_rows.append((
            f"{level:.0e}",
            "—" if a is None else f"{seconds(a[0])} ({a[1].curve}, {a[1].param} steps)",
            "—" if b is None else seconds(b[0]),
            "—" if r is None else f"{r:.2f}×",
            "—" if c is None else seconds(c[0]),
            "—" if rc is None else f"{rc:.2f}×",
        ))  # fmt: skip
    levels = Table(
        ("error", "lieflow best", "quflow isomp", "quflow / lieflow",
         "recommended alone", "quflow / recommended"),
        tuple(level_rows),
        caption=f"N = {s.N}: seconds to reach the error at T, interpolated on the log–log "
        "frontier of each side's runs; 'recommended alone': the curve "
        f"'{RECOMMENDED}' by itself (one configuration for every level).",
    )  # fmt: skip
    goal = f"Euler–Zeitlin N = {s.N} ≥ {TARGET}× quflow's time-to-accuracy at 1e-4…1e-6"
    notes: list[str] = []
    if isomp is None:
        target = TargetCheck(
            target=goal,
            measured="nothing: quflow is not installed (`pip install quflow`); lieflow's side only",
            met=None,
        )
    else:
        known = [r for r in ratios if r is not None]
        worst = min(known) if len(known) == len(LEVELS) else None
        met = None if worst is None else worst >= TARGET
        target = TargetCheck(
            target=goal,
            measured=", ".join("n/a" if r is None else f"{r:.2f}×" for r in ratios),
            met=met,
            gap="" if met or worst is None else f"worst {worst:.2f}×",
        )
        same = [
            relative_error(finals[f"quflow isomp (tol auto)|{n}"], finals[f"{midpoint}|{n}"])
            for n in s.midpoint_steps
            if f"quflow isomp (tol auto)|{n}" in finals and f"{midpoint}|{n}" in finals
        ]
        if same:
            notes.append(
                f"Convention check, N = {s.N}: quflow isomp and lieflow midpoint (rtol 1e-14) "
                f"at equal steps differ by ≤ {max(same):.1e} relative — the size of quflow's "
                "default tolerance (√eps·h/ħ·‖W‖∞), far below their common step error."
            )
    return SizeResult((table, levels), target, tuple(notes))


def run(ctx: BenchContext) -> Section:
    """The work–precision curves, time-to-accuracy ratios and the floor (or a skip note)."""
    start = time.perf_counter()
    title = "Euler–Zeitlin against quflow at equal accuracy"
    try:
        import lieflow_zeitlin  # noqa: F401
    except ImportError:
        return Section(
            title=title,
            intro="Skipped: the `lieflow-zeitlin` plugin is not installed.",
            seconds=time.perf_counter() - start,
        )
    isomp = quflow_isomp()
    results = [measure(ctx, s, isomp) for s in setups(ctx.config.quick)]
    intro = (
        "**quflow skipped**: `import quflow` failed (it is an optional external contender, "
        "`pip install quflow`); lieflow's side only."
        if isomp is None
        else "quflow's `isomp` (its default tolerance) and lieflow from the same W0 in the "
        "same convention (Ẇ = [Δ⁻¹W, W]/ħ, fluid time); numba and BLAS on one thread."
    )
    return Section(
        title=title,
        intro=intro,
        tables=tuple(t for r in results for t in r.tables),
        targets=tuple(r.target for r in results),
        notes=tuple(n for r in results for n in r.notes),
        seconds=time.perf_counter() - start,
    )
