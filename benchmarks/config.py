"""Problem sizes and repeat counts of the full and the quick benchmark runs."""

from __future__ import annotations

from typing import Any

import attrs

from .contenders import LieflowRun


@attrs.frozen
class BenchConfig:
    """Sizes of every benchmark; :func:`full` and :func:`quick` are the two presets.

    Attributes
    ----------
    quick : bool
        Tiny sizes (the test suite's mode).
    repeats : int
        Rounds of interleaved timing (median round reported) for small and medium cases.
    large_repeats : int
        Rounds for large cases (n >= 256).
    reproduce_step_divisor : int
        Divide the reproduction suite's step counts by this (1 = the paper's runs).
    reproduce_quick : bool
        Use ``lieflow.app.reproduce.paper_cases(quick=True)``.
    reproduce_baseline_steps : int
        Steps of each reproduction cell rerun against the as-published baseline.
    grb_sizes : tuple of int
        Generalized rigid body sizes.
    paper_max_n : int
        Largest ``n`` for which the dense as-published baseline is run.
    so3_steps, so3_ratio_steps : int
        Single so(3) trajectory: steps of the rate run, and of the baseline comparison.
    ensemble_size, ensemble_steps, ensemble_loop_size : int
        so(3) ensemble: trajectories, steps, and trajectories run one at a time as baseline.
    iteration_sizes : tuple of int
        Sizes of the per-iteration cost benchmark.
    zeitlin_sizes : tuple of int
        Euler–Zeitlin sizes ``N``.
    zeitlin_paper_max_n : int
        Largest ``N`` for the as-published baseline (complex dense products are slow).
    wp_n : int
        Work–precision: generalized rigid body size.
    wp_time : float
        Work–precision: final time.
    wp_steps : tuple of int
        Work–precision: step counts (``h = wp_time / steps``).
    compiled_max_n : int
        Largest ``n`` at which ``engine="compiled"`` is timed (its loop products are far
        slower than BLAS at large ``n``).
    """

    quick: bool
    repeats: int
    large_repeats: int
    reproduce_step_divisor: int
    reproduce_quick: bool
    reproduce_baseline_steps: int
    grb_sizes: tuple[int, ...]
    paper_max_n: int
    so3_steps: int
    so3_ratio_steps: int
    ensemble_size: int
    ensemble_steps: int
    ensemble_loop_size: int
    iteration_sizes: tuple[int, ...]
    zeitlin_sizes: tuple[int, ...]
    zeitlin_paper_max_n: int
    wp_n: int
    wp_time: float
    wp_steps: tuple[int, ...]
    compiled_max_n: int = 128

    def grb_steps(self, n: int) -> int:
        """Steps per timed run of the generalized rigid body at size ``n``."""
        if self.quick:
            return 3
        return 20 if n <= 64 else 5 if n <= 128 else 2

    def grb_repeats(self, n: int) -> int:
        """Timing rounds at size ``n``."""
        return self.repeats if n < 256 else self.large_repeats


def full() -> BenchConfig:
    """The documented run (about 15 minutes on two cores)."""
    return BenchConfig(
        quick=False,
        repeats=3,
        large_repeats=1,
        reproduce_step_divisor=1,
        reproduce_quick=False,
        reproduce_baseline_steps=100,
        grb_sizes=(50, 128, 256, 512),
        paper_max_n=256,
        so3_steps=100_000,
        so3_ratio_steps=5_000,
        ensemble_size=10_000,
        ensemble_steps=20,
        ensemble_loop_size=50,
        iteration_sizes=(256, 512),
        zeitlin_sizes=(64, 128, 256, 512),
        zeitlin_paper_max_n=128,
        wp_n=50,
        wp_time=1.0,
        wp_steps=(5, 10, 20, 40, 80),
    )


def quick() -> BenchConfig:
    """Tiny sizes: every table and cell, in seconds (used by the tests)."""
    return BenchConfig(
        quick=True,
        repeats=1,
        large_repeats=1,
        reproduce_step_divisor=20,
        reproduce_quick=True,
        reproduce_baseline_steps=3,
        grb_sizes=(6, 12),
        paper_max_n=12,
        so3_steps=200,
        so3_ratio_steps=50,
        ensemble_size=64,
        ensemble_steps=3,
        ensemble_loop_size=4,
        iteration_sizes=(24,),
        zeitlin_sizes=(8,),
        zeitlin_paper_max_n=8,
        wp_n=6,
        wp_time=0.2,
        wp_steps=(4, 8),
    )


@attrs.frozen
class BenchContext:
    """What every benchmark receives: the sizes, the engines to compare and where figures go.

    Attributes
    ----------
    config : BenchConfig
        Sizes and repeats.
    engines : tuple of str
        Values of ``lieflow.integrate(..., engine=...)`` compared against ``base_engine``
        (empty when the installed lieflow has no ``engine`` option).
    base_engine : str or None
        The engine of the lever comparisons (``"numpy"``; ``None``: no ``engine`` option).
    img_dir : str
        Directory for figures (created by the benchmark that writes one).
    img_prefix : str
        How the markdown page refers to ``img_dir`` (relative to the page).
    seed : int
        Seed of the random initial conditions (``lieflow.app.reproduce.Case.build``).
    """

    config: BenchConfig
    engines: tuple[str, ...] = ()
    base_engine: str | None = None
    img_dir: str = "docs/img"
    img_prefix: str = "img"
    seed: int = 0

    def lieflow(self, scheme: str, **options: Any) -> LieflowRun:
        """A lieflow configuration on the base engine (``options``: other fields)."""
        return LieflowRun(scheme, engine=options.pop("engine", self.base_engine), **options)

    def engine_runs(self, scheme: str, n: int = 0) -> list[LieflowRun]:
        """The default configuration on every compared engine (``compiled`` only up to
        ``config.compiled_max_n``)."""
        return [
            LieflowRun(scheme, engine=e)
            for e in self.engines
            if e != "compiled" or n <= self.config.compiled_max_n
        ]
