r"""The one stepping loop: advance any :class:`~lieflow.flows.Flow` in chunks.

:func:`advance` yields :class:`Chunk`\ s of consecutive completed steps; whoever consumes
them — :func:`lieflow.integrate` (memory: a :class:`~lieflow.Solution`) or
:func:`lieflow.app.io.run` (an HDF5 trajectory written as the run goes) — records them through
the same :class:`Diagnostics`. A flow may advance many steps per call
(:class:`MultiStepFlow`, e.g. the compiled engine); a step it does not finish is then taken
by its plain :meth:`~lieflow.flows.Flow.step` from the last good state, so failures read
the same on every engine.

Time is ``t_k = k h``, computed from the step index, never accumulated.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Protocol, runtime_checkable

import attrs
import numpy as np

from .algebras import Array
from .backends import all_finite
from .errors import ConvergenceError
from .flows import Flow
from .systems.base import IsospectralSystem

__all__ = ["Chunk", "Diagnostics", "Monitor", "MultiStepFlow", "advance", "chunk_steps"]

#: At most this many steps per chunk of a multi-step flow (a progress tick each) ...
CHUNK_STEPS = 1024
#: ... and at most this many entries of saved states per chunk (8 MiB of float64).
CHUNK_ENTRIES = 1 << 20


def chunk_steps(W0: Array) -> int:
    """Steps per chunk for states like ``W0``: :data:`CHUNK_STEPS`, fewer for large states
    so that a chunk holds at most :data:`CHUNK_ENTRIES` numbers."""
    return max(1, min(CHUNK_STEPS, CHUNK_ENTRIES // max(1, W0.size)))


@attrs.frozen(eq=False)
class Chunk:
    """Steps ``start + 1 .. start + m`` of a run (``m = len(W)``).

    Attributes
    ----------
    start : int
        Index of the step before the chunk.
    h : float
        Step size.
    W : ndarray
        The states after each step, ``(m, *batch, n, n)``.
    iterations : ndarray
        Solver updates per step, ``(m,)``.
    residuals : ndarray
        Last relative update of each step's solve, ``(m,)``.
    solvers : tuple of str
        The solver that finished each step.
    state : tree of arrays
        The flow's state after the last step: with ``W[-1]`` and :attr:`stop`, all a
        checkpoint needs to resume bit-for-bit.
    """

    start: int
    h: float
    W: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    residuals: Array = attrs.field(repr=False)
    solvers: tuple[str, ...]
    state: Any = attrs.field(repr=False)

    @property
    def size(self) -> int:
        """Number of steps ``m``."""
        return int(self.iterations.shape[0])

    @property
    def stop(self) -> int:
        """Index of the chunk's last step."""
        return self.start + self.size

    @property
    def index(self) -> Array:
        """Step indices ``start + 1 .. stop``."""
        return np.arange(self.start + 1, self.stop + 1)

    @property
    def t(self) -> Array:
        """Times ``k h`` of the chunk's steps."""
        return self.index * self.h


@runtime_checkable
class MultiStepFlow(Flow, Protocol):
    """A :class:`~lieflow.flows.Flow` that can also advance many steps per call."""

    def step_many(self, W: Array, start: int, h: float, steps: int, state: Any) -> Chunk:
        """Up to ``steps`` steps from ``W`` after step ``start``. Fewer (possibly none) when
        a step was not accepted; the driver then takes that step with :meth:`step`."""
        ...


class Monitor(Protocol):
    """Receives progress while a run proceeds (a progress bar, a log, a test hook)."""

    def start(self, done: int, total: int) -> None:
        """Called once before stepping; ``done`` steps exist already (a resumed run)."""
        ...

    def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
        """``steps`` more steps were recorded, taking ``iterations`` solver updates; the
        largest relative energy error among them (``None`` when not computed)."""
        ...

    def stop(self) -> None:
        """Called once when stepping ends, however it ends."""
        ...


def _check_finite(
    W: Array, iterations: int, solver: str, residual: float, k: int, h: float
) -> None:
    if not all_finite(W):
        raise ConvergenceError(
            "non_finite",
            solver=solver,
            iterations=iterations,
            residuals=(residual,),
            step=k + 1,
            t=k * h,
        )


def advance(
    flow: Flow,
    W0: Array,
    h: float,
    steps: int,
    *,
    start: int = 0,
    state: Any = None,
) -> Iterator[Chunk]:
    """Advance ``flow`` from ``W0`` (the state after step ``start``) up to step ``steps``.

    Parameters
    ----------
    flow : Flow
        What to advance (a :class:`MultiStepFlow` is advanced a chunk per call).
    W0 : ndarray
        The (validated) state after step ``start``.
    h : float
        Step size.
    steps : int
        Index of the last step to take.
    start : int
        Index of the step ``W0`` follows (0 for a new run; a checkpoint's to resume).
    state : tree of arrays, optional
        The flow's state after step ``start`` (a checkpoint's, to resume bit-for-bit);
        ``flow.init(W0)`` by default.

    Yields
    ------
    Chunk
        Consecutive completed steps, in order.

    Raises
    ------
    ConvergenceError
        A step failed (or produced a non-finite state), with its index and time; the
        chunks before it have been yielded.
    """
    W, k = W0, start
    state = flow.init(W0) if state is None else state
    # a MultiStepFlow (by its method: runtime protocol checks cost ~30 µs a call)
    many = getattr(flow, "step_many", None)
    many = many if callable(many) else None
    size = chunk_steps(W0)
    while k < steps:
        if many is not None:
            # Chunks end at multiples of ``size`` counted from step 0, wherever the run
            # started, so a run resumed at a chunk end takes the same chunks as an
            # uninterrupted one (bit-for-bit resume).
            asked = min(size - k % size, steps - k)
            chunk = many(W, k, h, asked, state)
            if chunk.size:
                yield chunk
                W, k, state = chunk.W[-1], chunk.stop, chunk.state
            if chunk.size == asked:
                continue
        try:
            W, state, stats = flow.step(W, k * h, h, state)
        except ConvergenceError as exc:
            raise exc.at(k + 1, k * h) from exc
        _check_finite(W, stats.iterations, stats.solver, stats.residual, k, h)
        yield Chunk(
            k,
            h,
            W[None, ...],
            np.array([stats.iterations], dtype=np.int64),
            np.array([stats.residual]),
            (stats.solver,),
            state,
        )
        k += 1


def _per_state(f: Any, W: Array) -> Array:
    """``f`` of each state in ``W`` (``(m, *batch, n, n)``): one vectorised call, or for a
    single state a call on that state."""
    if W.shape[0] == 1:
        return np.asarray(f(W[0]))[None]
    return np.asarray(f(W))


@attrs.frozen(eq=False)
class Diagnostics:
    """Energy and Casimirs of states, and their errors against the initial values.

    ``energy_error = |η(W) − η(W0)| / |η(W0)|`` and
    ``casimir_drift = |C_j(W) − C_j(W0)| / ||W0||^{k_j}``
    (:meth:`~lieflow.IsospectralSystem.casimir_scale`). Build it with :meth:`of`.
    """

    system: IsospectralSystem
    H0: Array = attrs.field(repr=False)
    C0: Array = attrs.field(repr=False)
    scale: Array = attrs.field(repr=False)

    @classmethod
    def of(cls, system: IsospectralSystem, W0: Array) -> Diagnostics:
        """Diagnostics relative to the initial state ``W0``."""
        return cls(system, np.asarray(system.hamiltonian(W0)), np.asarray(system.casimirs(W0)),
                   np.asarray(system.casimir_scale(W0)))  # fmt: skip

    def energy(self, W: Array) -> Array:
        """``η`` of each state of a stack ``(m, *batch, n, n)``."""
        return _per_state(self.system.hamiltonian, W)

    def casimirs(self, W: Array) -> Array:
        """Casimirs of each state of a stack ``(m, *batch, n, n)``."""
        return _per_state(self.system.casimirs, W)

    def energy_error(self, H: Array) -> Array:
        """Relative energy error of energies ``H``."""
        H0 = self.H0.astype(float, copy=False)
        return np.abs(np.asarray(H, dtype=float) - H0) / np.maximum(
            np.abs(H0), np.finfo(float).tiny
        )

    def casimir_drift(self, C: Array) -> Array:
        """Casimir drift of Casimirs ``C``."""
        return np.abs(C - self.C0) / self.scale
