"""The study as one call: :func:`reproduce_modin_viviani`."""

from __future__ import annotations

import time
from pathlib import Path

import attrs
import numpy as np

from ....errors import InputError, LieflowError
from .analysis import Analysis, analyse
from .plan import PLANS, STUDY, Log, Plan, _plugin, grid_text, initial_states


@attrs.frozen(eq=False)
class StudyResult:
    """What :func:`reproduce_modin_viviani` did.

    Attributes
    ----------
    directory : Path
    plan : Plan
    analysis : Analysis
    files : tuple of Path
        The figure, report, CSV and dataset.
    wall_time : float
    """

    directory: Path
    plan: Plan
    analysis: Analysis
    files: tuple[Path, ...]
    wall_time: float


def reproduce_modin_viviani(
    out_dir: Path | str = "lieflow-out",
    *,
    plan: Plan | str = "full",
    seed: int = 0,
    executor: str = "local",
    workers: int | None = None,
    scheduler: str | None = None,
    device: str = "cpu",
    log: Log | None = None,
) -> StudyResult:
    """Run (or resume) the study and write its figure, report and results.

    Parameters
    ----------
    out_dir : path
        Parent directory; the study writes ``OUT/modin-viviani-2020[-quick|-smoke]/``.
    plan : Plan or {"full", "quick", "smoke"}
    seed : int
        First seed of the random fields (and of the bootstrap).
    executor, workers, scheduler
        Where the runs go (:func:`lieflow.sweep`): ``"local"`` process pool of ``workers``
        processes, or ``"dask"`` (a new LocalCluster, or the cluster at ``scheduler``).
    device : str
        ``[run] device`` of every run (``"cpu"``, ``"cupy"``, ``"torch:cuda:0"``, ...).
    log : callable, optional
        Receives progress lines.

    Raises
    ------
    InputError
        Bad arguments, a missing plugin or extra, an output directory that cannot be
        written or holds another version's initial data.
    KeyboardInterrupt
        The sweep was interrupted (its runs resume on the next call).
    """
    from ...reports import output_dir
    from ...sweeps import SweepProgress, load_sweep, sweep

    if isinstance(plan, str):
        if plan not in PLANS:
            raise InputError(f"plan must be one of {', '.join(PLANS)}, got {plan!r}")
        plan = PLANS[plan]
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"reproduce {STUDY}: seed must be an integer >= 0, got {seed!r}")
    _plugin()
    start = time.perf_counter()
    suffix = "" if plan.name == "full" else f"-{plan.name}"
    out = output_dir(Path(out_dir) / f"{STUDY}{suffix}")
    states = initial_states(plan, int(seed), out)
    grid_path = out / "grid.toml"
    grid_path.write_text(grid_text(plan, states, device), encoding="utf-8")
    if log is not None:
        log(f"{STUDY} ({plan.name}): {plan.runs} runs of {plan.steps} steps, N = {plan.N}: {out}")
    grid = load_sweep(grid_path)
    swept = sweep(grid, executor, workers=workers, scheduler=scheduler,
                  monitor=SweepProgress() if log is not None else None)  # fmt: skip
    if swept.interrupted:
        raise KeyboardInterrupt
    cpu = time.process_time()
    analysis = analyse(plan, states, grid.directory, seed=int(seed), log=log)
    if not any(r.complete for r in analysis.runs):
        raise LieflowError(
            f"reproduce {STUDY}: no run completed (see {grid.manifest}). To fix: read the "
            "runs' errors there, then run the command again (complete runs are kept)"
        )
    from .figure import study_figure
    from .report import write_csv, write_dataset, write_report

    figure = study_figure(plan, analysis, out / "modin_viviani_2020.png")
    analysis_cpu = time.process_time() - cpu
    timing = {
        "wall": time.perf_counter() - start,
        "runs": float(sum(r.get("wall_time", 0.0) or 0.0 for r in swept.runs)),
        "analysis": analysis_cpu,
    }
    files = (
        figure,
        write_report(
            plan,
            analysis,
            out / "report.md",
            seed=int(seed),
            device=device,
            executor=executor,
            timing=timing,
            figure=figure,
        ),
        write_csv(analysis, out / "results.csv"),
        write_dataset(plan, analysis, out / "results.nc", int(seed)),
    )
    if log is not None and analysis.trend is not None:
        log(f"{STUDY}: {analysis.trend.describe()}")
    return StudyResult(out, plan, analysis, files, time.perf_counter() - start)
