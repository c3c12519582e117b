"""The paper's experiments: its integrators and published tables (:data:`SCHEMES`,
:func:`published`), the cases (:class:`Case`, :func:`paper_cases`) and one run of a case
(:func:`run_case`, :func:`run_paper_algorithm`) measured as a :class:`CaseResult`."""

from __future__ import annotations

import attrs
import numpy as np

from ...algebras import SO, Array
from ...engines import Engine, compiled
from ...errors import InputError
from ...integration import integrate
from ...schemes import get as get_scheme
from ...solution import Solution
from ...solvers.fixed_point import FixedPoint
from ...systems.base import IsospectralSystem
from ...systems.rigid_body import GeneralizedRigidBody, RigidBody
from ...systems.toda import PAPER_W0, PeriodicToda

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
class CaseResult:
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
    def from_solution(cls, case: Case, scheme: str, sol: Solution) -> CaseResult:
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


def run_case(case: Case, scheme: str, seed: int) -> CaseResult:
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
    return CaseResult.from_solution(case, scheme, sol)


def run_paper_algorithm(case: Case, scheme: str, seed: int) -> CaseResult:
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
    return CaseResult.from_solution(case, scheme, sol)


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
