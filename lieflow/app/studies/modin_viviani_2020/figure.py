"""The figure of ``lieflow reproduce modin-viviani-2020`` (one PNG, nine panels):

* outcome (number of coherent vortices at the end) against ``γ``, every run, with the mean per
  ``γ`` and the rank correlation;
* the count along every run (runs sorted by ``γ``), the detector applied to every saved state;
* the last state of a typical 2-, 3- and 4-vortex run, with the detected centres;
* relative energy error and Casimir drift of every run against time;
* the "staircase": the coarse-grained (low-passed) vorticity sorted against the area it
  covers, first and last state of the 4-vortex runs (its fine-grained counterpart, the
  eigenvalues of ``-iW``, is a Casimir and does not move).

matplotlib's object-oriented API with the Agg canvas, as in :mod:`lieflow.app.plotting`.
"""

from __future__ import annotations

__all__ = ["study_figure"]

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .analysis import Analysis, RunResult
    from .plan import Plan

#: Values below this (exact zeros: conservation to roundoff) are drawn at it on log axes.
FLOOR = 1e-17


def _typical(runs: list[RunResult], outcome: int) -> RunResult | None:
    """The run with ``outcome`` that holds it for the largest share of its window (the
    smallest γ on a tie)."""
    chosen = [r for r in runs if r.complete and r.outcome == outcome]
    if not chosen:
        return None
    return max(chosen, key=lambda r: (r.share, -r.state.gamma))


def _outcome_panel(ax: Any, plan: Plan, analysis: Analysis) -> None:
    done = [r for r in analysis.runs if r.complete]
    seeds = sorted({r.state.seed for r in done})
    width = 0.6 * (min(np.diff(plan.gammas)) if len(plan.gammas) > 1 else 0.1)
    for r in done:
        k = seeds.index(r.state.seed)
        offset = (k - (len(seeds) - 1) / 2) * width / max(1, len(seeds))
        ax.scatter(r.state.gamma + offset, r.outcome, s=30, color="C0", alpha=0.7)
    means = [
        (g, np.mean([r.outcome for r in done if r.state.gamma == g]))
        for g in plan.gammas
        if any(r.state.gamma == g for r in done)
    ]
    if means:
        ax.plot(*zip(*means, strict=True), color="k", marker="_", markersize=14, label="mean")
    ax.set_xlabel("γ = ‖L‖ / √C₂")
    ax.set_ylabel("coherent vortices at the end")
    ax.set_yticks(range(0, 7))
    ax.set_ylim(0.5, 6.5)
    ax.grid(True, alpha=0.3)
    trend = analysis.trend
    title = f"outcome against γ ({len(done)} runs, N = {plan.N}, t = {plan.t_final:g})"
    ax.set_title(title + ("\n" + trend.describe() if trend is not None else ""), fontsize=10)
    ax.legend(loc="upper right")


def _counts_panel(ax: Any, analysis: Analysis) -> None:
    from matplotlib.colors import BoundaryNorm, ListedColormap

    done = sorted(
        (r for r in analysis.runs if r.complete), key=lambda r: (r.state.gamma, r.state.seed)
    )
    if not done or analysis.time.size == 0:
        ax.set_axis_off()
        return
    image = np.stack([np.clip(r.counts, 0, 7) for r in done])
    cmap = ListedColormap(["#ffffff", "#bbbbbb", "#d62728", "#ff7f0e", "#1f77b4", "#9467bd",
                           "#8c564b", "#444444"])  # fmt: skip
    norm = BoundaryNorm(np.arange(-0.5, 8.5), cmap.N)
    t = analysis.time
    img = ax.imshow(image, aspect="auto", interpolation="nearest", cmap=cmap, norm=norm,
                    extent=(t[0], t[-1], len(done) - 0.5, -0.5))  # fmt: skip
    ticks = [i for i, r in enumerate(done) if i == 0 or r.state.gamma != done[i - 1].state.gamma]
    ax.set_yticks(ticks, [f"{done[i].state.gamma:g}" for i in ticks], fontsize=7)
    ax.set_ylabel("run (γ)")
    ax.set_xlabel("t")
    ax.set_title("coherent vortices along every run", fontsize=10)
    bar = ax.figure.colorbar(img, ax=ax, ticks=range(8), fraction=0.05)
    bar.ax.set_yticklabels(["0", "1", "2", "3", "4", "5", "6", "≥7"], fontsize=7)


def _snapshot_panel(ax: Any, run: RunResult | None, outcome: int, smoothing: float) -> None:
    from lieflow_zeitlin import low_pass
    from lieflow_zeitlin.plotting import plot_vorticity

    if run is None:
        ax.text(0.5, 0.5, f"no run ended with {outcome} vortices", ha="center", va="center",
                transform=ax.transAxes)  # fmt: skip
        ax.set_axis_off()
        return
    plot_vorticity(ax, low_pass(run.W_final, smoothing), projection="equirectangular")
    for v in run.final.vortices:
        lon = (v.lon + 180.0) % 360.0 - 180.0
        ax.plot(lon, v.lat, marker="+" if v.sign > 0 else "x", color="k", markersize=12,
                markeredgewidth=2)  # fmt: skip
    ax.set_title(
        f"{outcome} vortices: γ = {run.state.gamma:g}, seed {run.state.seed} (outcome in "
        f"{100 * run.share:.0f} % of the window)\nlast state, low-passed (σ = {smoothing:g})",
        fontsize=9,
    )


def _drift_panel(ax: Any, analysis: Analysis, key: str, title: str) -> None:
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    gammas = [r.state.gamma for r in analysis.runs]
    top = max(gammas) or 1.0
    files = list(analysis.drift["files"])
    t = analysis.drift["step_time"]
    stride = max(1, t.size // 2000)
    for r in analysis.runs:
        if not r.complete:
            continue
        y = analysis.drift[key][files.index(r.state.file)]
        ax.semilogy(t[1::stride], np.maximum(y[1::stride], FLOOR), color=cmap(r.state.gamma / top),
                    linewidth=0.6, alpha=0.7)  # fmt: skip
    ax.set_xlabel("t")
    ax.set_title(title + " (colour: γ)", fontsize=10)
    ax.grid(True, which="major", alpha=0.3)


def _staircase_panel(ax: Any, plan: Plan, analysis: Analysis) -> None:
    runs = [r for r in analysis.runs if r.complete and r.outcome == 4]
    ax.set_title(
        f"staircase: 4-vortex runs ({len(runs)}), coarse-grained (σ = "
        f"{plan.staircase_smoothing:g})",
        fontsize=10,
    )
    if not runs:
        ax.text(0.5, 0.5, "no 4-vortex run", ha="center", va="center", transform=ax.transAxes)
        return
    n = runs[0].staircase.shape[-1]
    area = (np.arange(n) + 0.5) / n
    for k, r in enumerate(runs):
        first, last = r.staircase
        ax.plot(area, first, color="0.6", linewidth=0.6, linestyle="--",
                label="t = 0" if k == 0 else None)  # fmt: skip
        ax.plot(area, last, color=f"C{k % 10}", linewidth=1.0,
                label="last state" if k == 0 else None)  # fmt: skip
    levels = runs[0].levels
    ax.plot((np.arange(levels.size) + 0.5) / levels.size, levels, "k.", markersize=3,
            label="levels of -iW (conserved), one run")  # fmt: skip
    ax.set_xlabel("area fraction (sorted)")
    ax.set_ylabel("vorticity")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def study_figure(plan: Plan, analysis: Analysis, path: Path) -> Path:
    """Write the study's figure to ``path`` (PNG) and return it."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(16, 13), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 3, height_ratios=(1.1, 1.0, 1.0))
    _outcome_panel(fig.add_subplot(grid[0, :2]), plan, analysis)
    _counts_panel(fig.add_subplot(grid[0, 2]), analysis)
    for col, outcome in enumerate((2, 3, 4)):
        run = _typical(list(analysis.runs), outcome)
        _snapshot_panel(fig.add_subplot(grid[1, col]), run, outcome, plan.smoothing)
    ax = fig.add_subplot(grid[2, 0])
    _drift_panel(ax, analysis, "energy_error", "relative energy error")
    ax = fig.add_subplot(grid[2, 1])
    _drift_panel(ax, analysis, "casimir_drift", "Casimir drift max_k |ΔC_k| / ‖W₀‖^k")
    _staircase_panel(fig.add_subplot(grid[2, 2]), plan, analysis)
    fig.suptitle(
        f"Modin & Viviani (2020) with lieflow: Euler–Zeitlin N = {plan.N}, isospectral midpoint, "
        f"h = {plan.h:g}, {plan.runs} runs",
        fontsize=12,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    return path
