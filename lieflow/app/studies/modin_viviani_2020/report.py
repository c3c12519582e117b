"""The written results of ``lieflow reproduce modin-viviani-2020``: ``results.csv`` (one row
per run), ``results.nc`` (an :mod:`xarray` dataset on a ``gamma × seed`` grid, with every
run's vortex count along time) and ``report.md`` (the outcome table, the trend with each
detector setting, conservation, runs, time, machine)."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from .analysis import Analysis, RunResult
from .plan import ALTERNATIVES, STUDY, Plan

__all__ = ["write_csv", "write_dataset", "write_report"]


_CSV_COLUMNS = (
    "gamma",
    "seed",
    "status",
    "outcome",
    "outcome_share",
    *(f"outcome_smoothing{s:g}_threshold{t:g}" for s, t in ALTERNATIVES),
    "final_positive",
    "final_negative",
    "measured_gamma",
    "gamma_drift",
    "momentum_drift",
    "energy",
    "C2",
    "C3",
    "C4",
    "max_energy_error",
    "max_casimir_drift",
    "mean_iterations",
    "wall_time_s",
    "rotation",
    "file",
    "error",
)


def _csv_row(r: RunResult) -> list[str]:
    s = r.state
    final = r.final
    return [
        f"{s.gamma:g}",
        str(s.seed),
        r.status,
        str(r.outcome),
        f"{r.share:.3f}",
        *(str(a) for a in (r.alternatives or (-1,) * len(ALTERNATIVES))),
        str(final.positive if final is not None else -1),
        str(final.negative if final is not None else -1),
        f"{s.measured_gamma:.15g}",
        f"{r.gamma_drift:.3e}",
        f"{r.momentum_drift:.3e}",
        f"{s.energy:.15g}",
        *(f"{c:.15g}" for c in s.casimirs),
        f"{r.energy_error:.3e}",
        f"{r.casimir_drift:.3e}",
        f"{r.iterations:.2f}",
        f"{r.wall_time:.2f}",
        f"{s.rotation:.15g}",
        s.file,
        r.error.splitlines()[0] if r.error else "",
    ]


def write_csv(analysis: Analysis, path: Path) -> Path:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(_CSV_COLUMNS)
        for r in analysis.runs:
            writer.writerow(_csv_row(r))
    return path


def write_dataset(plan: Plan, analysis: Analysis, path: Path, seed: int) -> Path:
    """``results.nc``: the per-run results on a ``gamma × seed`` grid and the count along
    every run (``time``)."""
    import xarray as xr

    gammas = list(plan.gammas)
    seeds = list(range(seed, seed + plan.seeds))
    shape = (len(gammas), len(seeds))
    nt = len(analysis.time)

    def grid(get: Callable[[RunResult], Any], fill: Any, dtype: Any) -> np.ndarray:
        out = np.full(shape, fill, dtype=dtype)
        for r in analysis.runs:
            out[gammas.index(r.state.gamma), seeds.index(r.state.seed)] = get(r)
        return out

    def series(get: Callable[[RunResult], np.ndarray]) -> np.ndarray:
        out = np.full((*shape, nt), -1, dtype=np.int64)
        for r in analysis.runs:
            if r.complete:
                out[gammas.index(r.state.gamma), seeds.index(r.state.seed)] = get(r)
        return out

    dims = ("gamma", "seed")
    data = {
        "outcome": (dims, grid(lambda r: r.outcome, -1, np.int64)),
        "outcome_share": (dims, grid(lambda r: r.share, np.nan, float)),
        "count": ((*dims, "time"), series(lambda r: r.counts)),
        "positive": ((*dims, "time"), series(lambda r: r.positive)),
        "negative": ((*dims, "time"), series(lambda r: r.negative)),
        "measured_gamma": (dims, grid(lambda r: r.state.measured_gamma, np.nan, float)),
        "gamma_drift": (dims, grid(lambda r: r.gamma_drift, np.nan, float)),
        "momentum_drift": (dims, grid(lambda r: r.momentum_drift, np.nan, float)),
        "energy": (dims, grid(lambda r: r.state.energy, np.nan, float)),
        "max_energy_error": (dims, grid(lambda r: r.energy_error, np.nan, float)),
        "max_casimir_drift": (dims, grid(lambda r: r.casimir_drift, np.nan, float)),
        "rotation": (dims, grid(lambda r: r.state.rotation, np.nan, float)),
        "status": (dims, grid(lambda r: r.status, "missing", object).astype(str)),
    }
    casimirs = np.full((*shape, 3), np.nan)
    for r in analysis.runs:
        casimirs[gammas.index(r.state.gamma), seeds.index(r.state.seed)] = r.state.casimirs
    data["casimirs"] = ((*dims, "casimir"), casimirs)
    attrs_: dict[str, Any] = {
        "study": STUDY,
        "plan": json.dumps(attrs.asdict(plan)),
        "description": "outcome: most frequent number of coherent vortices over the last "
        f"{plan.settle:g} of each run (-1: run not complete)",
    }
    if analysis.trend is not None:
        attrs_["spearman_rho"] = analysis.trend.rho
        attrs_["spearman_rho_95"] = [analysis.trend.low, analysis.trend.high]
    ds = xr.Dataset(
        data,
        coords={"gamma": gammas, "seed": seeds, "time": analysis.time, "casimir": [2, 3, 4]},
        attrs=attrs_,
    )
    ds.to_netcdf(path, engine="h5netcdf")
    return path


def _outcome_table(plan: Plan, analysis: Analysis) -> str:
    from ...reports import md_table

    rows = []
    for g in plan.gammas:
        runs = [r for r in analysis.runs if r.state.gamma == g and r.complete]
        tally = [sum(r.outcome == k for r in runs) for k in (2, 3, 4)]
        other = len(runs) - sum(tally)
        mean = np.mean([r.outcome for r in runs]) if runs else math.nan
        rows.append([f"{g:.2f}", str(len(runs)), *map(str, tally), str(other), f"{mean:.2f}"])
    return md_table(["γ", "runs", "2", "3", "4", "other", "mean"], rows)


def _conservation_lines(analysis: Analysis) -> list[str]:
    done = [r for r in analysis.runs if r.complete]
    if not done:
        return ["No run completed."]

    def worst(get: Callable[[RunResult], float]) -> str:
        return f"{max(get(r) for r in done):.1e}"

    return [
        f"- largest Casimir drift `|ΔC_k| / ‖W₀‖^k` (k = 2, 3, 4), any step of any run: "
        f"**{worst(lambda r: r.casimir_drift)}**",
        f"- largest relative energy error: **{worst(lambda r: r.energy_error)}**",
        f"- largest change of `γ` along a run: {worst(lambda r: r.gamma_drift)}; of the "
        f"angular momentum, `‖ΔL‖/√C₂`: {worst(lambda r: r.momentum_drift)} (in the rotating "
        "frame the components of `L` across the axis are kept to O(h²), not to roundoff)",
        f"- fixed-point updates per step: {min(r.iterations for r in done):.1f}–"
        f"{max(r.iterations for r in done):.1f} on average per run",
    ]


def write_report(
    plan: Plan,
    analysis: Analysis,
    path: Path,
    *,
    seed: int,
    device: str,
    executor: str,
    timing: dict[str, float],
    figure: Path,
) -> Path:
    from ...reports import machine_description, md_table

    done = [r for r in analysis.runs if r.complete]
    failed = [r for r in analysis.runs if not r.complete]
    trend = analysis.trend
    lines = [
        f"# Modin & Viviani (2020) reproduced: `lieflow reproduce {STUDY}` ({plan.name})",
        "",
        "The long-time fate of 2D Euler on the sphere against `γ = ‖L‖/√C₂`: Zeitlin's model "
        f"at N = {plan.N}, isospectral midpoint (Cayley update), no dissipation, "
        f"h = {plan.h:g}, t = {plan.t_final:g} ({plan.steps} steps), {plan.runs} runs "
        f"({len(plan.gammas)} values of γ × {plan.seeds} seeds from seed {seed}), random "
        f"initial vorticity in degrees {plan.degrees[0]}–{plan.degrees[1]} plus the "
        "solid-body rotation that sets γ, rms vorticity 1. The outcome of a run is the most "
        f"frequent number of coherent vortices over its last {100 * plan.settle:.0f} % "
        f"(detector: heat-kernel low-pass σ = {plan.smoothing:g} rad, persistence ≥ "
        f"{plan.threshold:g} max|ω̄|).",
        "",
        f"![outcome against gamma]({figure.name})",
        "",
        "## Outcome against γ",
        "",
        _outcome_table(plan, analysis),
        "",
        "Trend (Spearman's rank correlation of γ and the outcome; the paper: fewer structures "
        "at larger γ, i.e. ρ < 0): "
        + (
            f"**{trend.describe()}**."
            if trend is not None
            else "not measurable (too few runs completed, or every run ended alike)."
        ),
        "",
        "The same with other detector settings (low-pass σ, persistence threshold):",
        "",
        md_table(
            ["σ (rad)", "threshold", "trend"],
            [
                [f"{s:g}", f"{t:g}", trend_.describe() if trend_ is not None else "n/a"]
                for (s, t), trend_ in zip(ALTERNATIVES, analysis.alternative_trends, strict=True)
            ],
        ),
        "",
        "## Conservation",
        "",
        *_conservation_lines(analysis),
        "",
        "## Runs",
        "",
        f"{len(done)} of {len(analysis.runs)} runs complete"
        + (f"; failed or incomplete: {len(failed)}" if failed else "")
        + ". Per-run numbers: `results.csv`; as an xarray dataset: `results.nc`; the "
        'trajectories: `lieflow.open_sweep("sweep")`.',
        "",
    ]
    for r in failed:
        lines.append(f"- γ = {r.state.gamma:g}, seed {r.state.seed}: {r.status} {r.error}")
    lines += [
        "## Time",
        "",
        f"- wall clock of the command: {timing['wall']:.0f} s (executor: {executor}, device: "
        f"{device})",
        f"- the runs' own wall clock, summed: {timing['runs']:.0f} s (one BLAS thread each)",
        f"- analysis (this process, CPU): {timing['analysis']:.1f} s",
        "",
        "## Machine",
        "",
        *(f"- {k}: {v}" for k, v in machine_description().items()),
        "",
    ]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path
