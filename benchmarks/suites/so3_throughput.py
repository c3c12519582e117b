"""The so(3) rigid body: one long midpoint trajectory, and an ensemble advanced as a stack.

Rigid body with inertia (1, 2, 3) (``lieflow.app.reproduce.Case``), midpoint rule, h = 0.1,
FixedPoint rtol 1e-14, no diagnostics.
"""

from __future__ import annotations

import time

import numpy as np

from lieflow import SO
from lieflow.app.reproduce import Case

from ..config import BenchContext
from ..contenders import AsPublished, Contender
from ..measure import stats, step_memory, time_contenders, warm_up
from ..report import Section, Table, TargetCheck, mebibytes, rate, ratio, seconds
from ..timing import best_of

#: Issue 6: single-trajectory steps per second.
TARGET_STEPS = 200_000.0
#: Issue 6: ensemble trajectory-steps per second.
TARGET_ENSEMBLE = 1_000_000.0

H = 0.1
TOL = 1e-14


def _single(ctx: BenchContext) -> tuple[tuple[str, ...], TargetCheck]:
    cfg = ctx.config
    system, W0 = Case("rigid_body", "h = 0.1", 3, H, cfg.so3_steps, TOL).build(ctx.seed)
    default = ctx.lieflow("midpoint")
    engines = ctx.engine_runs("midpoint")
    paper, cold = AsPublished("midpoint"), ctx.lieflow("midpoint", warm_start=False)
    contenders: list[Contender] = [default, paper, cold, *engines]
    t = time_contenders(contenders, system, W0, H, cfg.so3_ratio_steps, cfg.repeats)
    base = t[default.label].median
    # The long run on the fastest configuration (the numpy path's rate is the short runs').
    fastest = min([default, *engines], key=lambda c: t[c.label].median)
    long_run = best_of(lambda: fastest.run(system, W0, H, cfg.so3_steps), 1)
    best_rate = cfg.so3_steps / long_run.median
    result = stats(t[default.label])
    row = (
        "single trajectory",
        f"{cfg.so3_ratio_steps:,} steps",
        rate(cfg.so3_ratio_steps / base) + " steps/s",
        seconds(base / cfg.so3_ratio_steps),
        f"{result.mean_iterations:.2f} / {result.max_iterations}",
        ratio(t[paper.label].median, base),
        ratio(t[cold.label].median, base),
        "—",
        mebibytes(step_memory(default, system, W0, H)),
        *[ratio(base, t[e.label].median) for e in engines],
    )
    met = best_rate >= TARGET_STEPS
    per_step = 1e6 / best_rate
    target = TargetCheck(
        target=f"so(3) midpoint, one trajectory, h = 0.1, rtol 1e-14: ≥ {TARGET_STEPS:,.0f} "
        "steps/s",
        measured=f"{best_rate:,.0f} steps/s over {cfg.so3_steps:,} steps ({fastest.label})",
        met=met,
        gap="" if met else f"{TARGET_STEPS / best_rate:.1f}× short",
        limit=(
            f"{per_step:.1f} µs per step for {result.mean_iterations:.1f} updates of 3×3 "
            "matrices"
            + (
                ": interpreter and numpy per-call overhead (~1 µs a call, ~30 ns of "
                "arithmetic per 3×3 product)"
                if fastest.engine in (None, "numpy")
                else ""
            )
        ),
    )
    return row, target


def _ensemble(ctx: BenchContext) -> tuple[tuple[str, ...], TargetCheck]:
    cfg = ctx.config
    system, _ = Case("rigid_body", "h = 0.1", 3, H, cfg.ensemble_steps, TOL).build(ctx.seed)
    stack = np.stack([SO(3).random(seed=ctx.seed + i) for i in range(cfg.ensemble_size)])
    default = ctx.lieflow("midpoint")
    engines = ctx.engine_runs("midpoint")
    batched = time_contenders(
        [default, *engines], system, stack, H, cfg.ensemble_steps, cfg.repeats
    )
    traj_steps = cfg.ensemble_size * cfg.ensemble_steps
    base = batched[default.label].median
    loop = best_of(
        lambda: [
            default.run(system, W, H, cfg.ensemble_steps) for W in stack[: cfg.ensemble_loop_size]
        ],
        cfg.repeats,
    )
    loop_per = loop.median / (cfg.ensemble_loop_size * cfg.ensemble_steps)
    result = stats(batched[default.label])
    row = (
        f"ensemble K = {cfg.ensemble_size:,}",
        f"{cfg.ensemble_steps} steps",
        rate(traj_steps / base) + " traj-steps/s",
        seconds(base / cfg.ensemble_steps),
        f"{result.mean_iterations:.2f} / {result.max_iterations}",
        "—",
        "—",
        ratio(loop_per, base / traj_steps),
        mebibytes(step_memory(default, system, stack, H)),
        *[ratio(base, batched[e.label].median) for e in engines],
    )
    best_label = min(batched, key=lambda k: batched[k].median)
    best_throughput = traj_steps / batched[best_label].median
    met = best_throughput >= TARGET_ENSEMBLE
    target = TargetCheck(
        target=f"so(3) ensemble as one (K, 3, 3) stack: ≥ {TARGET_ENSEMBLE:,.0f} "
        "trajectory-steps/s",
        measured=f"{best_throughput:,.0f} trajectory-steps/s (K = {cfg.ensemble_size:,}, "
        f"{best_label}; numpy batched {ratio(loop_per, base / traj_steps)} over one "
        "trajectory at a time)",
        met=met,
        gap="" if met else f"{TARGET_ENSEMBLE / best_throughput:.1f}× short",
        limit=(
            "a step iterates until the slowest trajectory converges "
            f"(up to {result.max_iterations} updates per step on the numpy path), and every "
            "numpy operation makes a pass over the whole (K, 3, 3) stack and a temporary"
        ),
    )
    return row, target


def run(ctx: BenchContext) -> Section:
    """Single trajectory and ensemble."""
    start = time.perf_counter()
    warm_up([ctx.lieflow("midpoint"), *ctx.engine_runs("midpoint"), AsPublished("midpoint")])
    single, t1 = _single(ctx)
    ensemble, t2 = _ensemble(ctx)
    header = [
        "run",
        "length",
        "throughput",
        "s/step",
        "updates/step mean / max",
        "× vs as published",
        "× vs warm starts off",
        "× vs one trajectory at a time",
        "peak MiB (1 step)",
    ]
    header += [f"× engine={e} vs {ctx.base_engine}" for e in ctx.engines]
    table = Table(
        tuple(header),
        (single, ensemble),
        caption="so(3) rigid body, midpoint, h = 0.1, rtol 1e-14 (ratios: how many times "
        "faster lieflow's default is than the baseline).",
    )
    notes = [
        f"The table's single-trajectory row: {ctx.config.so3_ratio_steps:,} steps, "
        f"interleaved, median of {ctx.config.repeats}, on the base engine; the target uses one "
        f"{ctx.config.so3_steps:,}-step run of the fastest configuration.",
        f"‘× vs one trajectory at a time’: {ctx.config.ensemble_loop_size} trajectories of "
        "the ensemble integrated separately, per trajectory-step.",
    ]
    return Section(
        title="so(3) rigid body: steps per second and ensembles",
        intro="The smallest system: cost is per-call overhead, not arithmetic.",
        tables=(table,),
        targets=(t1, t2),
        notes=tuple(notes),
        seconds=time.perf_counter() - start,
    )
