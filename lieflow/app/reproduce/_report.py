"""What :func:`~lieflow.app.reproduce.reproduce` writes: the figures, ``results.csv`` and
``report.md`` (each table beside the paper's)."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

from ..reports import machine_description, md_table
from ._cases import (
    _SYSTEM_TITLES,
    _TABLES,
    ITERATION_SCHEMES,
    SCHEMES,
    CaseResult,
    _scheme_label,
    _system_title,
    published,
)


def _by_system(records: Sequence[CaseResult], system: str) -> list[CaseResult]:
    return [r for r in records if r.case.system == system]


def _case_labels(records: Sequence[CaseResult]) -> list[str]:
    labels: list[str] = []
    for r in records:
        if r.case.label not in labels:
            labels.append(r.case.label)
    return labels


def _lookup(records: Sequence[CaseResult], label: str, scheme: str) -> CaseResult:
    return next(r for r in records if r.case.label == label and r.scheme == scheme)


def _figures(records: Sequence[CaseResult], out: Path) -> list[Path]:
    from ..plotting import Curve, Panel, energy_figure

    paths = []
    for system, title in _SYSTEM_TITLES:
        recs = _by_system(records, system)
        if not recs:
            continue
        panels = []
        for label in _case_labels(recs):
            case = _lookup(recs, label, SCHEMES[0][0]).case
            curves = tuple(
                Curve(name, r.t[1:], r.energy_error[1:])
                for scheme, name in SCHEMES
                for r in (_lookup(recs, label, scheme),)
            )
            step = "" if label.startswith("h =") else f", h = {case.h:g}"
            panels.append(Panel(f"{title}: {label}{step}, N = {case.steps}", curves))
        paths.append(
            energy_figure(panels, out / f"{system}_energy.png", title=f"{title}: energy error")
        )
    return paths


_CSV_COLUMNS = (
    "system",
    "case",
    "scheme",
    "scheme_label",
    "n",
    "h",
    "steps",
    "tolerance",
    "seed",
    "wall_time_s",
    "paper_wall_time_s",
    "max_iterations",
    "max_iterations_paper_count",
    "paper_max_iterations",
    "mean_iterations",
    "max_energy_error",
    "max_casimir_drift",
    "spectrum_drift",
)


def _paper_numbers(r: CaseResult) -> tuple[float | None, int | None]:
    pub = published(r.case.system, r.case.label)
    if pub is None:
        return None, None
    names = [s for s, _ in SCHEMES]
    wall = pub.wall_time[names.index(r.scheme)]
    its = (
        pub.max_iterations[ITERATION_SCHEMES.index(r.scheme)]
        if r.scheme in ITERATION_SCHEMES
        else None
    )
    return wall, its


def _write_csv(records: Sequence[CaseResult], path: Path, seed: int) -> Path:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(_CSV_COLUMNS)
        for r in records:
            wall, its = _paper_numbers(r)
            writer.writerow(
                [
                    r.case.system,
                    r.case.label,
                    r.scheme,
                    _scheme_label(r.scheme),
                    r.case.n,
                    repr(r.case.h),
                    r.case.steps,
                    repr(r.case.tol),
                    seed,
                    f"{r.wall_time:.6f}",
                    "" if wall is None else f"{wall:.4f}",
                    r.max_iterations,
                    r.max_iterations - 1,
                    "" if its is None else its,
                    f"{r.mean_iterations:.4f}",
                    f"{r.max_energy_error:.6e}",
                    f"{r.max_casimir_drift:.6e}",
                    f"{r.spectrum_drift:.6e}",
                ]
            )
    return path


def _seconds(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.4f}"


def _time_table(recs: Sequence[CaseResult]) -> str:
    header = ["case"]
    for _, name in SCHEMES:
        header += [f"{name} lieflow", f"{name} paper"]
    rows = []
    for label in _case_labels(recs):
        row = [label]
        for scheme, _ in SCHEMES:
            r = _lookup(recs, label, scheme)
            row += [_seconds(r.wall_time), _seconds(_paper_numbers(r)[0])]
        rows.append(row)
    return md_table(header, rows)


def _count(r: CaseResult) -> str:
    """An iteration count as the paper counts it (updates in brackets)."""
    return f"{r.max_iterations - 1} ({r.max_iterations} updates)"


def _beside_paper(recs: Sequence[CaseResult], label: str) -> list[str]:
    """Each scheme's count for case ``label`` beside the published one."""
    cells = []
    for scheme in ITERATION_SCHEMES:
        r = _lookup(recs, label, scheme)
        paper = _paper_numbers(r)[1]
        cells += [_count(r), "n/a" if paper is None else str(paper)]
    return cells


def _iteration_table(recs: Sequence[CaseResult]) -> str:
    header = ["case"]
    for scheme in ITERATION_SCHEMES:
        name = _scheme_label(scheme)
        header += [f"{name} lieflow", f"{name} paper"]
    rows = [[label, *_beside_paper(recs, label)] for label in _case_labels(recs)]
    return md_table(header, rows)


def _like_with_like_table(recs: Sequence[CaseResult], paper_algorithm: Sequence[CaseResult]) -> str:
    """Table 4: the paper's algorithm beside the published counts (paper's count, updates
    in brackets), then lieflow's defaults in separate, labelled columns."""
    header = ["case"]
    for scheme in ITERATION_SCHEMES:
        header += [f"{_scheme_label(scheme)} paper's algorithm", "paper"]
    header += [f"{_scheme_label(s)} lieflow defaults" for s in ITERATION_SCHEMES]
    rows = [
        [
            label,
            *_beside_paper(paper_algorithm, label),
            *(_count(_lookup(recs, label, s)) for s in ITERATION_SCHEMES),
        ]
        for label in _case_labels(recs)
    ]
    return md_table(header, rows)


def _conservation_table(records: Sequence[CaseResult]) -> str:
    header = [
        "system",
        "case",
        "scheme",
        "max energy error",
        "max Casimir drift",
        "spectrum drift",
        "mean updates/step",
    ]
    rows = [
        [
            _system_title(r.case.system),
            r.case.label,
            _scheme_label(r.scheme),
            f"{r.max_energy_error:.2e}",
            f"{r.max_casimir_drift:.2e}",
            f"{r.spectrum_drift:.2e}",
            f"{r.mean_iterations:.2f}",
        ]
        for r in records
    ]
    return md_table(header, rows)


_CAPTIONS = {
    1: "Wall time in seconds for each simulation of the rigid body.",
    2: (
        "Maximum number of fixed-point iterations per step (tolerance 1e-15), rigid body. "
        "lieflow's number is counted as the paper counts (updates - 1); updates in brackets."
    ),
    3: "Wall time in seconds for each simulation of the Toda lattice.",
    4: (
        "Maximum number of fixed-point iterations per step, Toda lattice, in the paper's "
        "count (updates - 1; updates in brackets). *Paper's algorithm*: what the paper ran "
        "— 1s-SyDIRK, and the block form of SPEC §4.3 for 2s/3s-Gauss — with cold starts "
        "and the paper's absolute test ||X_{k+1} - X_k|| <= 1e-14; it should match the "
        "published counts. *lieflow defaults*: the reduced stage form (SPEC §4.5), warm "
        "starts and the relative test rtol = 1e-14: a different, cheaper algorithm, not "
        "comparable with the published column."
    ),
    5: "Wall time in seconds for each simulation of the generalized rigid body.",
    6: (
        "Maximum number of fixed-point iterations per step (tolerance 1e-14), generalized "
        "rigid body (paper's count = updates - 1)."
    ),
}


def _write_report(
    records: Sequence[CaseResult],
    path: Path,
    *,
    seed: int,
    quick: bool,
    total_time: float,
    paper_algorithm: Sequence[CaseResult] = (),
) -> Path:
    from ... import __version__

    machine = machine_description()
    lines = [
        "# lieflow reproduction of the paper's numerical experiments",
        "",
        f"lieflow {__version__}; {len(records)} runs in {total_time:.1f} s "
        f"({sum(r.wall_time for r in records):.1f} s in the timed stepping loops; the rest "
        "is the untimed warm-up, numba's first compilation included, and the bookkeeping)"
        + (" (**--quick**: 10x fewer steps, generalized rigid body n = 10 only)" if quick else "")
        + ".",
        "",
    ]
    if quick:
        lines += [
            "Quick mode: the published numbers are for the full runs (10x more steps), so "
            "wall times are not comparable; iteration counts roughly are.",
            "",
        ]
    lines += [
        "## Setup",
        "",
        f"- Seed: **{seed}**. Rigid body: inertia (1, 2, 3), W0 = SO(3).random(seed={seed}). "
        f"Generalized rigid body on so(n): J_i ~ U[1, 2) from "
        f"GeneralizedRigidBody.random_inertia(n, seed={seed}), W0 = SO(n).random(seed={seed + 1})"
        ". Toda: n = 4, the paper's W0 (eigenvalues ±1, ±√5).",
        "- Schemes: 1s-SyDIRK = `midpoint`, 7s-SyDIRK = `sydirk7` (Yoshida's 7-stage "
        "composition), 2s-Gauss = `gauss2`, 3s-Gauss = `gauss3` (block algorithm, lieflow's "
        "reduced stage form, SPEC §4.5).",
        "- Solver: `FixedPoint(rtol=tol)` — a relative stopping test (SPEC §5) — with warm "
        "starts; tol = 1e-15 (rigid body), 1e-14 (Toda, generalized rigid body).",
        "- Wall time: lieflow.integrate's stepping loop, per-step energy and Casimir "
        "evaluation included; one run each, after an untimed warm-up. The paper's machine is "
        "unknown, so compare ratios between schemes rather than absolute times.",
        "- Figures: relative energy error per step on log axes; exact zeros (energy "
        "conserved to the last bit, common for the Toda lattice) are drawn at 1e-17.",
        "- Iterations: lieflow counts updates performed; the paper counts one fewer (SPEC §5, "
        "e.g. its Toda 23/17/16 are 24/18/17 updates). Tables 2, 4 and 6 show lieflow's "
        "number in the paper's count, with the updates in brackets. Table 4 also reruns "
        "the paper's algorithm (block form, cold starts, absolute test 1e-14) to compare "
        "like with like; lieflow's defaults are in their own columns there.",
        "",
        "## Machine",
        "",
    ]
    lines += [f"- {key}: {value}" for key, value in machine.items()]
    lines.append("")
    for system, t_time, t_iter in _TABLES:
        recs = _by_system(records, system)
        if not recs:
            continue
        title = _system_title(system)
        lines += [
            f"## {title}",
            "",
            f"![{title} energy error]({system}_energy.png)",
            "",
            f"**Table {t_time}.** {_CAPTIONS[t_time]}",
            "",
            _time_table(recs),
            "",
            f"**Table {t_iter}.** {_CAPTIONS[t_iter]}",
            "",
            _like_with_like_table(recs, _by_system(paper_algorithm, system))
            if system == "toda" and _by_system(paper_algorithm, system)
            else _iteration_table(recs),
            "",
        ]
    lines += [
        "## Conservation (every run)",
        "",
        "Relative energy error max_k |eta(W_k) - eta(W_0)| / |eta(W_0)|, Casimir drift "
        "|C(W_k) - C(W_0)| / ||W_0||^k, eigenvalue drift relative to the largest |eigenvalue|.",
        "",
        _conservation_table(records),
        "",
    ]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path
