"""What gets timed: lieflow configurations and the as-published baseline behind one interface.

A :class:`Contender` takes ``(system, W0, h, steps)`` and returns :class:`RunStats`. Engines
(``lieflow.integrate(..., engine=...)``, when the installed lieflow has that option) are one
more field of :class:`LieflowRun`, so comparing engines is one more contender per case.
"""

from __future__ import annotations

import inspect
from typing import Any, Literal, Protocol

import attrs
import numpy as np

import lieflow as lf
from lieflow import IsospectralSystem

from .paper_baseline import PaperScheme, PlainScheme, paper_integrate

#: The schemes of the paper as lieflow names.
PAPER_SCHEMES: tuple[str, ...] = ("midpoint", "gauss2", "gauss3", "sydirk7")


@attrs.frozen
class RunStats:
    """The outcome of one timed run.

    Attributes
    ----------
    steps : int
        Steps taken.
    iterations : ndarray
        Solver updates per step.
    W : ndarray
        States kept: the final state, or every state when the run was asked to keep them.
    """

    steps: int
    iterations: np.ndarray = attrs.field(repr=False)
    W: np.ndarray = attrs.field(repr=False)

    @property
    def mean_iterations(self) -> float:
        """Mean updates per step."""
        return float(np.mean(self.iterations))

    @property
    def max_iterations(self) -> int:
        """Most updates in one step."""
        return int(np.max(self.iterations))


class Contender(Protocol):
    """Anything :func:`benchmarks.timing.compare` can time on a case."""

    @property
    def label(self) -> str: ...

    def run(
        self, system: IsospectralSystem, W0: np.ndarray, h: float, steps: int, keep: bool = False
    ) -> RunStats: ...


def integrate_has_engine() -> bool:
    """Whether the installed :func:`lieflow.integrate` takes an ``engine=`` option."""
    return "engine" in inspect.signature(lf.integrate).parameters


def available_engines() -> tuple[str, ...]:
    """Engines that run a tiny midpoint problem (empty if ``engine=`` does not exist)."""
    if not integrate_has_engine():
        return ()
    system = lf.systems.get("rigid_body")
    W0 = system.algebra.random(seed=0)
    found = []
    for engine in ("numpy", "compiled", "auto"):
        try:
            lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2, engine=engine)
        except Exception:  # an engine that is unavailable (e.g. numba missing) is skipped
            continue
        found.append(engine)
    return tuple(found)


@attrs.frozen
class LieflowRun:
    """One configuration of :func:`lieflow.integrate`.

    Parameters
    ----------
    scheme : str
        Registered scheme name (``"gauss3"``).
    form : {"reduced", "block"}, optional
        Block-algorithm evaluation for Gauss schemes (``None``: the scheme's default).
    warm_start : bool
        ``integrate(..., warm_start=...)``.
    anderson : int
        ``FixedPoint(anderson=...)`` depth; 0 is the plain iteration.
    engine : str, optional
        ``integrate(..., engine=...)`` when that option exists; ``None`` leaves it out.
    rtol : float
        Fixed-point relative tolerance.
    """

    scheme: str
    form: Literal["reduced", "block"] | None = None
    warm_start: bool = True
    anderson: int = 0
    engine: str | None = None
    rtol: float = 1e-14

    @property
    def label(self) -> str:
        """A short description, e.g. ``gauss3 block form, cold``."""
        parts = [self.scheme]
        if self.form is not None:
            parts.append(f"{self.form} form")
        if not self.warm_start:
            parts.append("warm starts off")
        if self.anderson:
            parts.append(f"Anderson({self.anderson})")
        if self.engine is not None:
            parts.append(f"engine={self.engine}")
        return ", ".join(parts)

    def build_scheme(self) -> lf.Scheme:
        """The scheme object."""
        if self.form is None:
            return lf.schemes.get(self.scheme)
        return lf.schemes.get(self.scheme, form=self.form)

    def run(
        self, system: IsospectralSystem, W0: np.ndarray, h: float, steps: int, keep: bool = False
    ) -> RunStats:
        """Integrate without diagnostics (``keep``: save every state)."""
        extra: dict[str, Any] = {} if self.engine is None else {"engine": self.engine}
        sol = lf.integrate(
            system,
            self.build_scheme(),
            W0,
            h,
            steps=steps,
            solver=lf.solvers.FixedPoint(rtol=self.rtol, anderson=self.anderson),
            save_every=1 if keep else steps,
            diagnostics=False,
            warm_start=self.warm_start,
            **extra,
        )
        return RunStats(steps, sol.iterations, sol.W if keep else sol.W[-1])


@attrs.frozen
class AsPublished:
    """The paper's algorithm as published (:mod:`benchmarks.paper_baseline`) for a scheme."""

    scheme: str
    rtol: float = 1e-14

    @property
    def label(self) -> str:
        """``<scheme> as published``."""
        return f"{self.scheme} as published"

    def paper_scheme(self) -> PaperScheme:
        """The baseline's scheme: Gauss tableaus as one block equation, SyDIRKs composed."""
        tableau = lf.schemes.get(self.scheme).tableau
        composition = not self.scheme.startswith("gauss")
        return PaperScheme(tableau, composition=composition, rtol=self.rtol)

    def run(
        self, system: IsospectralSystem, W0: np.ndarray, h: float, steps: int, keep: bool = False
    ) -> RunStats:
        """Integrate with the dense as-published algorithm (``keep``: every state)."""
        scheme = self.paper_scheme()
        if not keep:
            res = paper_integrate(system, scheme, W0, h, steps)
            return RunStats(steps, res.iterations, res.W)
        states = [np.array(W0)]
        its = np.zeros(steps, dtype=np.int64)
        for k in range(steps):
            step = scheme.step(states[-1], h, system)
            states.append(step.W)
            its[k] = step.iterations
        return RunStats(steps, its, np.stack(states))


@attrs.frozen
class PlainReduced:
    """The reduced stage form as a plain numpy prototype (:class:`benchmarks.paper_baseline.
    PlainScheme`): lieflow's algorithm without lieflow's implementation."""

    scheme: str
    rtol: float = 1e-14

    @property
    def label(self) -> str:
        """``<scheme> plain numpy reduced``."""
        return f"{self.scheme} plain numpy reduced"

    def plain_scheme(self) -> PlainScheme:
        """Gauss tableaus as one stage system, SyDIRKs composed of midpoint steps."""
        tableau = lf.schemes.get(self.scheme).tableau
        return PlainScheme(tableau, composition=not self.scheme.startswith("gauss"), rtol=self.rtol)

    def run(
        self, system: IsospectralSystem, W0: np.ndarray, h: float, steps: int, keep: bool = False
    ) -> RunStats:
        """Integrate with the plain prototype (``keep``: every state)."""
        scheme = self.plain_scheme()
        states = [np.array(W0)]
        its = np.zeros(steps, dtype=np.int64)
        for k in range(steps):
            step = scheme.step(states[-1], h, system)
            states.append(step.W)
            if not keep:
                del states[0]
            its[k] = step.iterations
        return RunStats(steps, its, np.stack(states) if keep else states[-1])
