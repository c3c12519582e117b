"""The analysis of the study's runs: the coherent-vortex count along every run and its
outcome (:func:`analyse`), and the trend of the outcome with ``γ`` (:func:`rank_trend`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ....errors import InputError
from .plan import ALTERNATIVES, InitialState, Log, Plan, _plugin


@attrs.frozen
class Trend:
    """Spearman's rank correlation between ``γ`` and the outcome, with its uncertainty.

    Attributes
    ----------
    rho : float
        Spearman's ``ρ`` over the runs (negative: fewer structures at larger ``γ``).
    low, high : float
        The 95 % bootstrap interval (percentiles of ``ρ`` over ``resamples`` resamplings of
        the runs with replacement).
    p_value : float
        Two-sided p-value of ``ρ = 0`` (scipy's t approximation).
    runs : int
    resamples : int
    """

    rho: float
    low: float
    high: float
    p_value: float
    runs: int
    resamples: int

    def describe(self) -> str:
        """``ρ = -0.93 [-0.95, -0.86] (95 % bootstrap, n = 32, p = 4e-14)``."""
        return (
            f"ρ = {self.rho:+.2f} [{self.low:+.2f}, {self.high:+.2f}] (95 % bootstrap, "
            f"n = {self.runs}, p = {self.p_value:.1g})"
        )


def _spearman_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Spearman's ``ρ`` of each row pair of ``x`` and ``y`` (shape ``(m, n)``): the Pearson
    correlation of their ranks (ties averaged); NaN for a row without variation."""
    from scipy.stats import rankdata

    rx, ry = rankdata(x, axis=-1), rankdata(y, axis=-1)
    rx -= rx.mean(axis=-1, keepdims=True)
    ry -= ry.mean(axis=-1, keepdims=True)
    norm = np.sqrt((rx * rx).sum(axis=-1) * (ry * ry).sum(axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray((rx * ry).sum(axis=-1) / norm)


def rank_trend(
    gammas: Sequence[float], outcomes: Sequence[float], seed: int = 0, resamples: int = 2000
) -> Trend:
    """Spearman's ``ρ`` between ``gammas`` and ``outcomes`` and its bootstrap interval
    (the runs resampled with replacement ``resamples`` times; resamples without variation
    in either variable are left out).

    Raises
    ------
    InputError
        Fewer than 3 runs, or no variation in either.
    """
    from scipy.stats import spearmanr

    g = np.asarray(gammas, dtype=float)
    o = np.asarray(outcomes, dtype=float)
    keep = np.isfinite(g) & np.isfinite(o)
    g, o = g[keep], o[keep]
    if g.size < 3 or np.ptp(g) == 0 or np.ptp(o) == 0:
        raise InputError(
            f"the rank correlation needs at least 3 runs with varying gamma and outcome, got "
            f"{g.size} runs (outcomes {sorted(set(o.tolist()))})"
        )
    rho, p = spearmanr(g, o)
    draws = np.random.default_rng(seed).integers(0, g.size, size=(resamples, g.size))
    values = _spearman_rows(g[draws], o[draws])
    low, high = np.percentile(values[np.isfinite(values)], [2.5, 97.5])
    return Trend(float(rho), float(low), float(high), float(p), int(g.size), resamples)


@attrs.frozen(eq=False)
class RunResult:
    """What the analysis found in one run.

    Attributes
    ----------
    state : InitialState
    status : str
        The sweep's status of the run (``"complete"``, ``"failed"``, ...).
    error : str
    counts, positive, negative : ndarray
        Coherent vortices (all, positive, negative) at every saved state.
    outcome : int
        Most frequent count over the last ``settle`` fraction of the run (-1 if the run did
        not complete).
    share : float
        Fraction of that window with the outcome's count.
    alternatives : tuple of int
        The outcome with the detector settings of :data:`ALTERNATIVES`.
    final : VortexCensus or None
        The vortices of the last state.
    W_final : ndarray or None
        The last state.
    staircase : ndarray
        The coarse-grained vorticity (low-pass ``staircase_smoothing``) at the detector's
        points, sorted (each point stands for the area ``4π/n``), first and last state
        ``(2, n)``.
    levels : ndarray
        The fine-grained vorticity levels (eigenvalues of ``-iW``, a Casimir of the run)
        of the last state.
    gamma_drift, momentum_drift : float
        Largest ``|γ(t) - γ(0)|`` and ``‖L(t) - L(0)‖/√C₂`` over the saved states.
    energy_error, casimir_drift : float
        Largest relative energy error and Casimir drift (``|ΔC_k|/‖W_0‖^k``, k = 2, 3, 4)
        over every step.
    iterations : float
        Mean fixed-point updates per step.
    wall_time : float
        Seconds the run took (its worker's wall clock).
    """

    state: InitialState
    status: str
    error: str
    counts: np.ndarray = attrs.field(repr=False)
    positive: np.ndarray = attrs.field(repr=False)
    negative: np.ndarray = attrs.field(repr=False)
    outcome: int
    share: float
    alternatives: tuple[int, ...]
    final: Any = attrs.field(repr=False)
    W_final: Any = attrs.field(repr=False)
    staircase: np.ndarray = attrs.field(repr=False)
    levels: np.ndarray = attrs.field(repr=False)
    gamma_drift: float
    momentum_drift: float
    energy_error: float
    casimir_drift: float
    iterations: float
    wall_time: float

    @property
    def complete(self) -> bool:
        """Whether the run completed (and has an outcome)."""
        return self.status == "complete"


@attrs.frozen(eq=False)
class Analysis:
    """Every run's result, the trend, and the data the figure needs.

    Attributes
    ----------
    runs : tuple of RunResult
    time : ndarray
        Times of the saved states.
    trend : Trend or None
        ``None`` when too few runs completed (or all ended alike).
    alternative_trends : tuple of (Trend or None)
        The trend with each setting of :data:`ALTERNATIVES`.
    drift : dict
        ``step_time``, ``energy_error`` (runs × steps) and ``casimir_drift`` (runs × steps,
        the largest over k) for the figure.
    """

    runs: tuple[RunResult, ...]
    time: np.ndarray = attrs.field(repr=False)
    trend: Trend | None
    alternative_trends: tuple[Trend | None, ...]
    drift: dict[str, np.ndarray] = attrs.field(repr=False)


def _mode(values: np.ndarray) -> tuple[int, float]:
    """Most frequent value (the smaller on a tie) and its share."""
    if values.size == 0:
        return -1, math.nan
    uniq, count = np.unique(values, return_counts=True)
    k = int(np.argmax(count))
    return int(uniq[k]), float(count[k] / values.size)


def _trend_or_none(gammas: list[float], outcomes: list[int], seed: int) -> Trend | None:
    try:
        return rank_trend(gammas, outcomes, seed=seed)
    except InputError:
        return None


def analyse(
    plan: Plan,
    states: Sequence[InitialState],
    sweep_dir: Path,
    seed: int = 0,
    log: Log | None = None,
) -> Analysis:
    """Apply the detector along every run of the study's sweep and measure the trend."""
    from ...datasets import open_sweep

    lz = _plugin()
    ds = open_sweep(sweep_dir)
    axis = "file"
    files = [str(f) for f in ds[axis].values]
    detector = lz.VortexDetector(plan.N, smoothing=plan.smoothing, threshold=plan.threshold)
    others = [lz.VortexDetector(plan.N, smoothing=s, threshold=t) for s, t in ALTERNATIVES]
    coarse = lz.VortexDetector(plan.N, smoothing=plan.staircase_smoothing)
    time_values = np.asarray(ds["time"].values if "time" in ds.coords else [], dtype=float)
    window = time_values >= (1 - plan.settle) * plan.t_final - 1e-9 * plan.t_final
    energy = np.asarray(ds["energy_error"].values, dtype=float)
    casimir = np.nanmax(np.asarray(ds["casimir_drift"].values, dtype=float), axis=-1)
    iterations = np.asarray(ds["iterations"].values, dtype=float)[:, 1:]
    status, error, wall = (ds[k].values for k in ("status", "error", "wall_time"))
    results = []
    for state in states:
        i = files.index(state.file)
        W = ds["W"].isel({axis: i}).values if status[i] == "complete" else None
        if W is None or not np.all(np.isfinite(W)):
            results.append(_missing(state, str(status[i]), str(error[i]), coarse.points))
            continue
        values = detector.filtered(W)
        censuses = [detector.census_of_field(v) for v in values]
        counts = np.array([c.count for c in censuses])
        outcome, share = _mode(counts[window])
        alternatives = tuple(
            _mode(np.array([d.census_of_field(v).count for v in d.filtered(W[window])]))[0]
            for d in others
        )
        L = lz.angular_momentum(W)
        root_c2 = math.sqrt(state.casimirs[0] * 4 * math.pi / plan.N)
        gammas = lz.gamma(W)
        results.append(
            RunResult(
                state=state,
                status=str(status[i]),
                error="",
                counts=counts,
                positive=np.array([c.positive for c in censuses]),
                negative=np.array([c.negative for c in censuses]),
                outcome=outcome,
                share=share,
                alternatives=alternatives,
                final=censuses[-1],
                W_final=W[-1],
                staircase=np.sort(coarse.filtered(W[[0, -1]]), axis=-1),
                levels=lz.vorticity_levels(W[-1]),
                gamma_drift=float(np.max(np.abs(gammas - gammas[0]))),
                momentum_drift=float(np.max(np.linalg.norm(L - L[0], axis=-1)) / root_c2),
                energy_error=float(np.nanmax(energy[i])),
                casimir_drift=float(np.nanmax(casimir[i])),
                iterations=float(np.nanmean(iterations[i])),
                wall_time=float(wall[i]),
            )
        )
        if log is not None:
            log(
                f"  gamma = {state.gamma:.3f}, seed {state.seed}: {outcome} vortices "
                f"({100 * share:.0f} % of the last {100 * plan.settle:.0f} %), counts "
                + "".join(str(min(c, 9)) for c in counts[:: max(1, len(counts) // 40)])
            )
    done = [r for r in results if r.complete]
    g = [r.state.gamma for r in done]
    trend = _trend_or_none(g, [r.outcome for r in done], seed)
    alternative_trends = tuple(
        _trend_or_none(g, [r.alternatives[k] for r in done], seed) for k in range(len(others))
    )
    drift = {
        "step_time": np.asarray(ds["step"].values, dtype=float) * plan.h,
        "energy_error": energy,
        "casimir_drift": casimir,
        "files": np.asarray(files, dtype=object),
    }
    return Analysis(tuple(results), time_values, trend, alternative_trends, drift)


def _missing(state: InitialState, status: str, error: str, points: int) -> RunResult:
    nan = math.nan
    none = np.zeros(0, dtype=int)
    stairs = np.full((2, points), nan)
    return RunResult(state, status, error, none, none, none, -1, nan, (), None, None, stairs,
                     np.zeros(0), nan, nan, nan, nan, nan, nan)  # fmt: skip
