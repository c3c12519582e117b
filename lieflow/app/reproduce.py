"""``lieflow reproduce``: rerun the paper's numerical experiments and compare with its tables.

The paper ("Efficient Implementation of high-order isospectral symplectic Runge–Kutta
schemes", section *Numerical experiments*) runs four integrators — 1s-SyDIRK (``midpoint``),
7s-SyDIRK (``sydirk7``), 2s-Gauss (``gauss2``) and 3s-Gauss (``gauss3``) — on

* the rigid body on so(3): N = 2000 steps, h = 0.1 and 0.01, random ``W0``, tolerance 1e-15;
* the periodic Toda lattice, n = 4, the paper's ``W0``: N = 1000, h = 0.1 and 0.01,
  tolerance 1e-14;
* the generalized rigid body on so(n), n = 10, 20, 50: N = 2000, h = 0.01, tolerance 1e-14;

28 runs. The paper states neither the rigid body's inertia nor the generalized rigid body's
``J`` nor its random ``W0``; lieflow's choices, all derived from one recorded seed ``s``:

* rigid body: principal moments (1, 2, 3), ``W0 = SO(3).random(seed=s)``;
* generalized rigid body on so(n): ``J_i`` uniform in [1, 2)
  (``GeneralizedRigidBody.random_inertia(n, seed=s)``), ``W0 = SO(n).random(seed=s + 1)``
  (i.i.d. standard normal entries, skew-symmetrised).

Every run uses ``FixedPoint(rtol=tol)`` — a relative test, SPEC §5 — with lieflow's default
warm starts; ``gauss2``/``gauss3`` use lieflow's default reduced stage form of the block
algorithm (SPEC §4.5: the same fixed point, fewer products). lieflow counts iterations as
updates performed, one more than the paper counts (SPEC §5); the report shows both.

Those defaults are not the paper's algorithm, so the Toda iteration table (Table 4) also
reruns the paper's algorithm itself (:func:`run_paper_algorithm`): the block form of SPEC
§4.3 for the Gauss schemes, cold starts (the ``h = 0`` guess every step) and the paper's
absolute stopping test ``||X_{k+1} - X_k||_F <= tol``; its counts are compared with the
published ones, and lieflow's defaults are shown in a separate, labelled column.
"""

from __future__ import annotations

import csv
import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import attrs
import numpy as np

from .. import compiled
from ..algebras import SO, Array
from ..engines import Engine
from ..errors import InputError
from ..integration import integrate
from ..schemes import get as get_scheme
from ..solution import Solution
from ..solvers.fixed_point import FixedPoint
from ..systems.base import IsospectralSystem
from ..systems.rigid_body import GeneralizedRigidBody, RigidBody
from ..systems.toda import PAPER_W0, PeriodicToda

__all__ = [
    "SCHEMES",
    "STUDIES",
    "Case",
    "Published",
    "ReproduceResult",
    "RunRecord",
    "machine_description",
    "paper_cases",
    "published",
    "reproduce",
    "reproduce_study",
    "run_case",
    "run_paper_algorithm",
]

#: The paper's integrators as lieflow scheme names, and the paper's names for them.
SCHEMES: tuple[tuple[str, str], ...] = (
    ("midpoint", "1s-SyDIRK"),
    ("sydirk7", "7s-SyDIRK"),
    ("gauss2", "2s-Gauss"),
    ("gauss3", "3s-Gauss"),
)
#: Schemes of the paper's iteration tables (7s-SyDIRK is left out there).
ITERATION_SCHEMES: tuple[str, ...] = ("midpoint", "gauss2", "gauss3")

_SYSTEM_TITLES: tuple[tuple[str, str], ...] = (
    ("rigid_body", "Rigid body"),
    ("toda", "Periodic Toda lattice"),
    ("generalized_rigid_body", "Generalized rigid body"),
)


def _scheme_label(name: str) -> str:
    return dict(SCHEMES)[name]


def _system_title(system: str) -> str:
    return dict(_SYSTEM_TITLES)[system]


@attrs.frozen
class Published:
    """The paper's numbers for one row of its tables.

    ``wall_time`` follows :data:`SCHEMES`; ``max_iterations`` follows
    :data:`ITERATION_SCHEMES` and uses the paper's count (updates minus one).
    """

    wall_time: tuple[float, float, float, float]
    max_iterations: tuple[int, int, int]


#: Tables 1–6 of the paper, by (system, case).
_PUBLISHED: tuple[tuple[str, str, Published], ...] = (
    ("rigid_body", "h = 0.1", Published((0.8473, 6.0511, 3.1222, 4.0645), (8, 11, 10))),
    ("rigid_body", "h = 0.01", Published((0.6170, 4.7073, 2.4780, 4.1032), (5, 6, 6))),
    ("toda", "h = 0.1", Published((0.9575, 6.0116, 2.0907, 2.8484), (23, 17, 16))),
    ("toda", "h = 0.01", Published((0.4197, 2.7707, 1.1158, 1.5020), (8, 8, 8))),
    (
        "generalized_rigid_body",
        "n = 10",
        Published((1.2789, 8.8158, 3.7640, 5.6305), (15, 11, 11)),
    ),
    (
        "generalized_rigid_body",
        "n = 20",
        Published((1.4853, 10.1409, 7.2950, 14.3572), (11, 14, 13)),
    ),
    (
        "generalized_rigid_body",
        "n = 50",
        Published((9.0200, 68.1599, 57.1546, 112.5086), (21, 24, 21)),
    ),
)

#: The paper's table numbers and captions: (system, wall-time table, iteration table).
_TABLES: tuple[tuple[str, int, int], ...] = (
    ("rigid_body", 1, 2),
    ("toda", 3, 4),
    ("generalized_rigid_body", 5, 6),
)


def published(system: str, case: str) -> Published | None:
    """The paper's numbers for ``(system, case)``, e.g. ``("toda", "h = 0.1")``."""
    for s, c, numbers in _PUBLISHED:
        if (s, c) == (system, case):
            return numbers
    return None


@attrs.frozen
class Case:
    """One experiment of the paper: a system, a step size and a number of steps.

    Attributes
    ----------
    system : str
        ``"rigid_body"``, ``"toda"`` or ``"generalized_rigid_body"``.
    label : str
        The row label of the paper's tables (``"h = 0.1"``, ``"n = 20"``).
    n : int
        Matrix size.
    h : float
        Step size.
    steps : int
        Number of steps.
    tol : float
        Relative tolerance of the fixed-point iteration.
    """

    system: str
    label: str
    n: int
    h: float
    steps: int
    tol: float

    def build(self, seed: int) -> tuple[IsospectralSystem, Array]:
        """The system and initial condition (see the module docstring for the choices)."""
        if self.system == "rigid_body":
            rb = RigidBody((1.0, 2.0, 3.0))
            return rb, SO(3).random(seed=seed)
        if self.system == "toda":
            return PeriodicToda(4), PAPER_W0.copy()
        grb = GeneralizedRigidBody.random_inertia(self.n, seed=seed)
        return grb, SO(self.n).random(seed=seed + 1)


def paper_cases(quick: bool = False) -> tuple[Case, ...]:
    """The paper's seven cases (28 runs with four schemes); ``quick``: 10x fewer steps and
    the generalized rigid body at n = 10 only."""
    div = 10 if quick else 1
    cases = [Case("rigid_body", f"h = {h:g}", 3, h, 2000 // div, 1e-15) for h in (0.1, 0.01)]
    cases += [Case("toda", f"h = {h:g}", 4, h, 1000 // div, 1e-14) for h in (0.1, 0.01)]
    cases += [
        Case("generalized_rigid_body", f"n = {n}", n, 0.01, 2000 // div, 1e-14)
        for n in ((10,) if quick else (10, 20, 50))
    ]
    return tuple(cases)


@attrs.frozen(eq=False)
class RunRecord:
    """Measurements of one run.

    Attributes
    ----------
    case : Case
        The experiment.
    scheme : str
        lieflow scheme name.
    wall_time : float
        Seconds of :func:`lieflow.integrate`'s stepping loop (per-step energy and Casimir
        evaluation included).
    max_iterations, mean_iterations : int, float
        Solver updates per step (summed over sub-steps for 7s-SyDIRK).
    max_energy_error : float
        ``max_k |eta(W_k) - eta(W_0)| / |eta(W_0)|`` (:attr:`Solution.energy_error`).
    max_casimir_drift : float
        Largest relative Casimir drift over steps and Casimirs.
    spectrum_drift : float
        Largest relative eigenvalue drift over the saved states (every ``steps/20``).
    t, energy_error : ndarray
        Per-step times and relative energy errors (for the figures).
    """

    case: Case
    scheme: str
    wall_time: float
    max_iterations: int
    mean_iterations: float
    max_energy_error: float
    max_casimir_drift: float
    spectrum_drift: float
    t: Array = attrs.field(repr=False)
    energy_error: Array = attrs.field(repr=False)

    @classmethod
    def from_solution(cls, case: Case, scheme: str, sol: Solution) -> RunRecord:
        """Summarise a :class:`Solution`."""
        assert sol.energy_error is not None and sol.casimir_drift is not None
        return cls(
            case=case,
            scheme=scheme,
            wall_time=sol.wall_time,
            max_iterations=int(sol.iterations.max()),
            mean_iterations=float(sol.iterations.mean()),
            max_energy_error=float(sol.energy_error.max()),
            max_casimir_drift=float(sol.casimir_drift.max()),
            spectrum_drift=float(np.max(sol.spectrum_drift())),
            t=np.arange(sol.n_steps + 1) * sol.h,
            energy_error=sol.energy_error,
        )


def run_case(case: Case, scheme: str, seed: int) -> RunRecord:
    """Run ``scheme`` on ``case`` (fixed point with relative tolerance ``case.tol``)."""
    system, W0 = case.build(seed)
    sol = integrate(
        system,
        get_scheme(scheme),
        W0,
        case.h,
        steps=case.steps,
        solver=FixedPoint(rtol=case.tol),
        save_every=max(1, case.steps // 20),
    )
    return RunRecord.from_solution(case, scheme, sol)


def run_paper_algorithm(case: Case, scheme: str, seed: int) -> RunRecord:
    """Run the paper's own algorithm for ``scheme`` on ``case``: the block form (SPEC §4.3)
    for ``gauss2``/``gauss3`` (SyDIRK schemes are the paper's minimal-variable form
    already), cold starts, and the absolute stopping test ``||X_{k+1} - X_k||_F <=
    case.tol`` (``FixedPoint(rtol=0, atol=tol)``). For like-with-like iteration counts
    (Table 4); lieflow's defaults are :func:`run_case`."""
    system, W0 = case.build(seed)
    built = get_scheme(scheme)
    if scheme.startswith("gauss"):
        built = get_scheme(scheme, form="block")
    sol = integrate(
        system,
        built,
        W0,
        case.h,
        steps=case.steps,
        solver=FixedPoint(rtol=0.0, atol=case.tol),
        warm_start=False,
        save_every=max(1, case.steps // 20),
        engine="numpy",
    )
    return RunRecord.from_solution(case, scheme, sol)


def warm_up(seed: int) -> None:
    """A few untimed steps of every scheme on each engine the timed runs may use, so the
    first timed run pays no first-call costs (numba's compilation or cache load included)."""
    case = Case("rigid_body", "warm-up", 3, 0.1, 3, 1e-15)
    system, W0 = case.build(seed)
    engines: list[Engine] = ["numpy", "compiled"] if compiled.available() else ["numpy"]
    for scheme, _ in SCHEMES:
        for engine in engines:
            solver = FixedPoint(rtol=case.tol)
            try:
                integrate(
                    system, get_scheme(scheme), W0, case.h, steps=3, solver=solver, engine=engine
                )
            except InputError:  # numba is there but does not import: auto will use numpy
                pass


def machine_description() -> dict[str, str]:
    """Platform, CPU count, Python, numpy/scipy versions and the BLAS numpy was built with."""
    from .io import environment

    info = environment()
    info["processor"] = platform.processor() or platform.machine()
    info["cpu_count"] = str(os.cpu_count())
    try:
        config = np.show_config(mode="dicts")  # numpy >= 1.25
        blas = config["Build Dependencies"]["blas"]
        info["blas"] = f"{blas.get('name', '?')} {blas.get('version', '')}".strip()
    except Exception:  # pragma: no cover - older numpy or unusual builds
        info["blas"] = "unknown"
    threads = [
        f"{var}={os.environ[var]}"
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
        if var in os.environ
    ]
    info["blas_threads"] = ", ".join(threads) or "default"
    return info


@attrs.frozen(eq=False)
class ReproduceResult:
    """What :func:`reproduce` did: every run and the files it wrote."""

    out_dir: Path
    records: tuple[RunRecord, ...]
    files: tuple[Path, ...]
    seed: int
    quick: bool
    total_time: float
    #: the paper's algorithm (:func:`run_paper_algorithm`) on the Toda cases, for Table 4
    paper_algorithm: tuple[RunRecord, ...] = ()


def _output_dir(out_dir: Path | str) -> Path:
    """Create the output directory, or raise :class:`InputError` saying why it cannot be."""
    out = Path(out_dir).expanduser()
    for parent in (out, *out.parents):
        if parent.exists():
            if not parent.is_dir():
                raise InputError(
                    f"reproduce: output directory {str(out)!r}: {str(parent)!r} is a file, not "
                    "a directory. To fix: give a directory with --out (it is created if "
                    "missing)"
                )
            break
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".lieflow-write-test-{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        raise InputError(
            f"reproduce: cannot write to {str(out)!r}: {exc.strerror or exc}. To fix: give a "
            "directory you can write to with --out"
        ) from None
    return out


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
    out = _output_dir(out_dir)
    cases = paper_cases(quick)
    total = len(cases) * len(SCHEMES)
    start = time.perf_counter()
    warm_up(seed)
    records: list[RunRecord] = []
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


def _by_system(records: Sequence[RunRecord], system: str) -> list[RunRecord]:
    return [r for r in records if r.case.system == system]


def _case_labels(records: Sequence[RunRecord]) -> list[str]:
    labels: list[str] = []
    for r in records:
        if r.case.label not in labels:
            labels.append(r.case.label)
    return labels


def _lookup(records: Sequence[RunRecord], label: str, scheme: str) -> RunRecord:
    return next(r for r in records if r.case.label == label and r.scheme == scheme)


def _figures(records: Sequence[RunRecord], out: Path) -> list[Path]:
    from .plotting import Curve, Panel, energy_figure

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


def _paper_numbers(r: RunRecord) -> tuple[float | None, int | None]:
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


def _write_csv(records: Sequence[RunRecord], path: Path, seed: int) -> Path:
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


def _md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _seconds(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.4f}"


def _time_table(recs: Sequence[RunRecord]) -> str:
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
    return _md_table(header, rows)


def _count(r: RunRecord) -> str:
    """An iteration count as the paper counts it (updates in brackets)."""
    return f"{r.max_iterations - 1} ({r.max_iterations} updates)"


def _beside_paper(recs: Sequence[RunRecord], label: str) -> list[str]:
    """Each scheme's count for case ``label`` beside the published one."""
    cells = []
    for scheme in ITERATION_SCHEMES:
        r = _lookup(recs, label, scheme)
        paper = _paper_numbers(r)[1]
        cells += [_count(r), "n/a" if paper is None else str(paper)]
    return cells


def _iteration_table(recs: Sequence[RunRecord]) -> str:
    header = ["case"]
    for scheme in ITERATION_SCHEMES:
        name = _scheme_label(scheme)
        header += [f"{name} lieflow", f"{name} paper"]
    rows = [[label, *_beside_paper(recs, label)] for label in _case_labels(recs)]
    return _md_table(header, rows)


def _like_with_like_table(recs: Sequence[RunRecord], paper_algorithm: Sequence[RunRecord]) -> str:
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
    return _md_table(header, rows)


def _conservation_table(records: Sequence[RunRecord]) -> str:
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
    return _md_table(header, rows)


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
    records: Sequence[RunRecord],
    path: Path,
    *,
    seed: int,
    quick: bool,
    total_time: float,
    paper_algorithm: Sequence[RunRecord] = (),
) -> Path:
    from .. import __version__

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
    from .studies.modin_viviani_2020 import reproduce_modin_viviani

    plan = "smoke" if smoke else "quick" if quick else "full"
    result = reproduce_modin_viviani(out_dir, plan=plan, seed=seed, executor=executor,
                                     workers=workers, scheduler=scheduler, device=device,
                                     log=log)  # fmt: skip
    return result.files
