"""Rerunning the paper's experiments (:func:`reproduce`) or a published study
(:func:`reproduce_study`, :data:`STUDIES`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import attrs
import numpy as np

from ...errors import InputError
from ..reports import output_dir
from ._cases import (
    ITERATION_SCHEMES,
    SCHEMES,
    CaseResult,
    paper_cases,
    run_case,
    run_paper_algorithm,
    warm_up,
)
from ._report import _figures, _write_csv, _write_report


@attrs.frozen(eq=False)
class ReproduceResult:
    """What :func:`reproduce` did: every run and the files it wrote."""

    out_dir: Path
    records: tuple[CaseResult, ...]
    files: tuple[Path, ...]
    seed: int
    quick: bool
    total_time: float
    #: the paper's algorithm (:func:`run_paper_algorithm`) on the Toda cases, for Table 4
    paper_algorithm: tuple[CaseResult, ...] = ()


def reproduce(
    out_dir: Path | str = "lieflow-out",
    *,
    quick: bool = False,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
) -> ReproduceResult:
    """Rerun the paper's experiments and write figures, ``report.md`` and ``results.csv``.

    Parameters
    ----------
    out_dir : path
        Output directory (created).
    quick : bool
        10x fewer steps and the generalized rigid body at n = 10 only (seconds, not minutes).
    seed : int
        Seed of the random initial conditions and inertias (recorded in the outputs).
    log : callable, optional
        Receives one line per finished run.

    Returns
    -------
    ReproduceResult

    Raises
    ------
    InputError
        ``seed`` is not a non-negative integer, or ``out_dir`` cannot be a directory (an
        existing file, or a place that cannot be written); checked before any run.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(
            f"reproduce: seed must be a non-negative integer, got {seed!r}. To fix: pass "
            "--seed 0 (or another integer >= 0)"
        )
    seed = int(seed)
    out = output_dir(out_dir)
    cases = paper_cases(quick)
    total = len(cases) * len(SCHEMES)
    start = time.perf_counter()
    warm_up(seed)
    records: list[CaseResult] = []
    for case in cases:
        for scheme, label in SCHEMES:
            rec = run_case(case, scheme, seed)
            records.append(rec)
            if log is not None:
                log(
                    f"[{len(records):2d}/{total}] {case.system:<22} {case.label:<8} "
                    f"{label:<9} {rec.wall_time:8.3f} s  max {rec.max_iterations:3d} updates  "
                    f"max energy error {rec.max_energy_error:.2e}"
                )
    paper_runs = tuple(
        run_paper_algorithm(case, scheme, seed)
        for case in cases
        if case.system == "toda"
        for scheme in ITERATION_SCHEMES
    )
    total_time = time.perf_counter() - start
    files = [*_figures(records, out)]
    files.append(_write_csv(records, out / "results.csv", seed))
    files.append(
        _write_report(
            records,
            out / "report.md",
            seed=seed,
            quick=quick,
            total_time=total_time,
            paper_algorithm=paper_runs,
        )
    )
    return ReproduceResult(out, tuple(records), tuple(files), seed, quick, total_time, paper_runs)


#: What ``lieflow reproduce STUDY`` can rerun: the paper's experiments (``"paper"``, the
#: default, :func:`reproduce`) and published studies built on lieflow's public API, the
#: sweep machinery and the plugins (:mod:`lieflow.app.studies`).
STUDIES: dict[str, str] = {
    "paper": "the paper's experiments: rigid body, Toda lattice, generalized rigid body "
    "(Tables 1-6)",
    "modin-viviani-2020": "Modin & Viviani (J. Fluid Mech. 2020): 2, 3 or 4 coherent vortices "
    "of 2D Euler on the sphere against gamma = |L|/sqrt(C2) (plugin lieflow-zeitlin, "
    "lieflow[sweep])",
}


def reproduce_study(
    study: str,
    out_dir: Path | str = "lieflow-out",
    *,
    quick: bool = False,
    smoke: bool = False,
    seed: int = 0,
    executor: str = "local",
    workers: int | None = None,
    scheduler: str | None = None,
    device: str = "cpu",
    log: Callable[[str], None] | None = None,
) -> tuple[Path, ...]:
    """Rerun ``study`` (a key of :data:`STUDIES`) and return the files it wrote.

    ``quick`` is the laptop variant, ``smoke`` a toy-sized run of the whole pipeline
    (seconds; studies with sweeps only); ``executor``, ``workers``, ``scheduler`` and
    ``device`` place the runs of a study that sweeps (:func:`lieflow.sweep`, ``[run]
    device``); the paper's experiments run in this process and take none of them.

    Raises
    ------
    InputError
        An unknown study, or options the study does not take.
    """
    if study not in STUDIES:
        raise InputError(
            f"reproduce: unknown study {study!r}. To fix: give one of "
            + ", ".join(STUDIES)
            + " (`lieflow reproduce --help` says what each reruns)"
        )
    if study == "paper":
        given = [
            name
            for name, value, default in (
                ("--smoke", smoke, False),
                ("--executor", executor, "local"),
                ("--workers", workers, None),
                ("--scheduler", scheduler, None),
                ("--device", device, "cpu"),
            )
            if value != default
        ]
        if given:
            raise InputError(
                f"reproduce: {', '.join(given)} apply to the studies that run sweeps, not to "
                "the paper's experiments (which run in this process). To fix: leave them out, "
                "or name a study, e.g. `lieflow reproduce modin-viviani-2020 --quick`"
            )
        return reproduce(out_dir, quick=quick, seed=seed, log=log).files
    if quick and smoke:
        raise InputError("reproduce: give --quick or --smoke, not both")
    from ..studies.modin_viviani_2020 import reproduce_modin_viviani

    plan = "smoke" if smoke else "quick" if quick else "full"
    result = reproduce_modin_viviani(out_dir, plan=plan, seed=seed, executor=executor,
                                     workers=workers, scheduler=scheduler, device=device,
                                     log=log)  # fmt: skip
    return result.files
