r"""The step contract: what steps (:class:`Flow`) and what a step reports (:class:`StepStats`).

One signature from the scheme to the stepping loop, ``step(W, t, h, state) -> (W, state, stats)``:
a :class:`Flow` advances a state ``W`` from time ``t`` by ``h``, carrying a state tree of its
own (a warm start); the stepping loop (:mod:`lieflow.stepping`) and the engines
(:mod:`lieflow.engines`) call it, or its many-step form (``step_many(W, start, h, steps,
state)``, :class:`lieflow.stepping.MultiStepFlow`); a scheme's step
(:meth:`Scheme.step <lieflow.schemes.Scheme.step>`) is the same with what a
:class:`~lieflow.flows.SchemeFlow` binds — the system and the solver — in place of the time
(a scheme is autonomous). Every step reports its cost as :class:`StepStats`.

This module sits at the bottom of the core's layers (it imports nothing of lieflow but the
array type), so that schemes, flows, engines and the stepping loop all speak it;
:mod:`lieflow.flows` is where users find both names.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import attrs

from .algebras import Array

__all__ = ["Flow", "StepStats"]


@attrs.frozen
class StepStats:
    """What one step cost: of a scheme (:attr:`lieflow.schemes.StepResult.stats`) or of any
    flow (:meth:`Flow.step`).

    Attributes
    ----------
    iterations : int
        Nonlinear-solver updates (summed over the sub-steps of a composition; 0 for an
        explicit or exact flow).
    solver : str
        Name of the solver that finished the (last implicit sub-)step; ``""`` if none.
    residual : float
        The largest last relative update of the step's solves (0 if none).
    """

    iterations: int = 0
    solver: str = ""
    residual: float = 0.0


@runtime_checkable
class Flow(Protocol):
    """One step of an evolution ``W(t) -> W(t + h)``, with state carried between steps."""

    @property
    def name(self) -> str:
        """A short name (used in files and reports)."""
        ...

    def init(self, W0: Array) -> Any:
        """The state before the first step from ``W0`` (a tree of arrays, or ``None``)."""
        ...

    def step(self, W: Array, t: float, h: float, state: Any) -> tuple[Array, Any, StepStats]:
        """Advance ``W`` from time ``t`` by ``h``; return the new ``W``, state and stats."""
        ...
