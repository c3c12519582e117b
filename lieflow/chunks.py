r"""What the stepping loop hands on: :class:`Chunk`\ s of consecutive steps, and their
diagnostics, computed once per chunk for every sink.

:func:`lieflow.stepping.advance` yields chunks; :func:`lieflow.stepping.run` computes each
chunk's :class:`ChunkDiagnostics` with the run's :class:`Diagnostics` (energy error
``|η(W) − η(W0)| / |η(W0)|``, Casimir drift ``|C_j(W) − C_j(W0)| / ||W0||^{k_j}`` and the
system's own ``extra_diagnostics``) and hands both to the sinks (:mod:`lieflow.sinks`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import attrs
import numpy as np

from .algebras import Array
from .systems.base import IsospectralSystem

__all__ = ["Chunk", "ChunkDiagnostics", "DeferredDiagnostics", "Diagnostics", "extra_hook"]

#: The smallest positive normal float64: the floor of the energy error's denominator.
_TINY = float(np.finfo(float).tiny)


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
    held : ndarray of int, optional
        Which steps' states ``W`` holds (indices ``0 .. m-1`` into the chunk, increasing,
        the last step always among them); ``None`` (the default): every step's. A flow
        whose states live on a device holds only those its
        :class:`~lieflow.stepping.Recording` needs
        (:attr:`~lieflow.stepping.MultiStepFlow.holds_needed_states`), so that only they
        reach the host.
    energy, casimirs : ndarray, optional
        The Hamiltonian ``(m, *batch)`` and Casimirs ``(m, *batch, n_casimirs)`` of every
        step, where the flow computed them (on its device); ``None``: :class:`Diagnostics`
        computes them from ``W``.
    """

    start: int
    h: float
    W: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    residuals: Array = attrs.field(repr=False)
    solvers: tuple[str, ...]
    state: Any = attrs.field(repr=False)
    held: Array | None = attrs.field(default=None, kw_only=True, repr=False)
    energy: Array | None = attrs.field(default=None, kw_only=True, repr=False)
    casimirs: Array | None = attrs.field(default=None, kw_only=True, repr=False)

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

    def states(self, keep: Array) -> Array:
        """The states of the steps where the boolean mask ``keep`` (one entry per step) is
        true: ``W[keep]``, or the rows of the held steps among them (every step kept must
        be held: :class:`~lieflow.stepping.Recording` decides both)."""
        held = self.held
        if held is None:
            return self.W[keep]
        rows = keep[held]
        if int(np.count_nonzero(rows)) != int(np.count_nonzero(keep)):
            raise ValueError(
                f"steps {(self.index[keep]).tolist()} are kept, but the chunk holds the states "
                f"of steps {(self.index[held]).tolist()} only"
            )
        return self.W[rows]

    def state_at(self, j: int) -> Array:
        """The state after the chunk's ``j``-th step (``0 .. m-1``), which must be held."""
        held = self.held
        if held is None:
            return self.W[j]
        rows = np.flatnonzero(held == j)
        if not rows.size:
            raise ValueError(f"the chunk does not hold the state of step {self.start + 1 + j}")
        return self.W[int(rows[0])]


def _per_state(f: Any, W: Array) -> Array:
    """``f`` of each state in ``W`` (``(m, *batch, n, n)``): one vectorised call, or for a
    single state a call on that state."""
    if W.shape[0] == 1:
        return np.asarray(f(W[0]))[None]
    return np.asarray(f(W))


#: One sample of a system's own diagnostics: ``(step, t, {name: value})``.
ExtraRow = tuple[int, float, Mapping[str, Any]]


@attrs.frozen(eq=False)
class ChunkDiagnostics:
    """The diagnostics of a chunk's steps (computed once by :func:`~lieflow.stepping.run`,
    for every sink).

    Attributes
    ----------
    energy, casimirs : ndarray
        ``η(W_k)`` ``(m, *batch)`` and the Casimirs ``(m, *batch, n_casimirs)``.
    energy_error, casimir_drift : ndarray
        Their errors against the initial values (:class:`Diagnostics`).
    extra : tuple of (step, t, dict)
        Samples of ``system.extra_diagnostics`` at the chunk's steps that are multiples of
        :attr:`Diagnostics.extra_every`.
    """

    energy: Array = attrs.field(repr=False)
    casimirs: Array = attrs.field(repr=False)
    energy_error: Array = attrs.field(repr=False)
    casimir_drift: Array = attrs.field(repr=False)
    extra: tuple[ExtraRow, ...] = attrs.field(repr=False)

    @property
    def max_energy_error(self) -> float:
        """The largest relative energy error among the chunk's steps."""
        return float(np.max(self.energy_error))


def extra_hook(system: Any, save_every: int) -> tuple[Callable[[Array], Any] | None, int]:
    """``(system.extra_diagnostics or None, interval in steps)``: the interval is
    ``system.diagnostics_every`` (``None``: ``save_every``; ``0``: no extra diagnostics)."""
    every = getattr(system, "diagnostics_every", None)
    if every is not None and int(every) == 0:
        return None, 0
    return getattr(system, "extra_diagnostics", None), int(every) if every else save_every


@attrs.frozen(eq=False)
class Diagnostics:
    """Energy and Casimirs of states, and their errors against the initial values.

    ``energy_error = |η(W) − η(W0)| / |η(W0)|`` and
    ``casimir_drift = |C_j(W) − C_j(W0)| / ||W0||^{k_j}``
    (:meth:`~lieflow.IsospectralSystem.casimir_scale`); and the system's own
    ``extra_diagnostics(W)`` (if it has them) every :attr:`extra_every` steps. Build it with
    :meth:`of`.
    """

    system: IsospectralSystem
    H0: Array = attrs.field(repr=False)
    C0: Array = attrs.field(repr=False)
    scale: Array = attrs.field(repr=False)
    extra: Callable[[Array], Any] | None = attrs.field(default=None, repr=False)
    extra_every: int = 0

    @classmethod
    def of(cls, system: IsospectralSystem, W0: Array, *, save_every: int = 1) -> Diagnostics:
        """Diagnostics relative to the initial state ``W0`` (extra diagnostics every
        ``system.diagnostics_every`` steps, by default every ``save_every``)."""
        extra, every = extra_hook(system, save_every)
        return cls(system, np.asarray(system.hamiltonian(W0)), np.asarray(system.casimirs(W0)),
                   np.asarray(system.casimir_scale(W0)), extra, every)  # fmt: skip

    @classmethod
    def deferred(
        cls, system: IsospectralSystem, W0: Array, *, save_every: int = 1
    ) -> DeferredDiagnostics:
        """What :meth:`of` gives, computed by :func:`~lieflow.stepping.run` together with the
        diagnostics of the first chunk (:class:`DeferredDiagnostics`)."""
        extra, every = extra_hook(system, save_every)
        return DeferredDiagnostics(system, W0, save_every, extra, every)

    def energy(self, W: Array) -> Array:
        """``η`` of each state of a stack ``(m, *batch, n, n)``."""
        return _per_state(self.system.hamiltonian, W)

    def casimirs(self, W: Array) -> Array:
        """Casimirs of each state of a stack ``(m, *batch, n, n)``."""
        return _per_state(self.system.casimirs, W)

    def energy_error(self, H: Array) -> Array:
        """Relative energy error of energies ``H``."""
        H0 = self.H0
        if not (type(H) is np.ndarray and H.dtype.char == "d"):
            H = np.asarray(H, dtype=float)
        if H0.ndim == 0:  # one trajectory: the denominator a Python float (the same value)
            h0 = float(H0)
            return np.abs(H - h0) / max(abs(h0), _TINY)
        H0 = H0.astype(float, copy=False)
        return np.abs(H - H0) / np.maximum(np.abs(H0), _TINY)

    def casimir_drift(self, C: Array) -> Array:
        """Casimir drift of Casimirs ``C``."""
        return np.abs(C - self.C0) / self.scale

    def of_chunk(self, chunk: Chunk) -> ChunkDiagnostics:
        """The diagnostics of ``chunk``'s steps (its own energy and Casimirs where its flow
        computed them)."""
        if chunk.energy is not None and chunk.casimirs is not None:
            return self._of(chunk, np.asarray(chunk.energy), np.asarray(chunk.casimirs))
        if chunk.held is not None:
            raise ValueError(
                "the chunk holds some of its states only and no energies: its flow computes "
                "diagnostics when stepping.run is given them (Recording.diagnostics)"
            )
        return self._of(chunk, self.energy(chunk.W), self.casimirs(chunk.W))

    def _of(self, chunk: Chunk, H: Array, C: Array) -> ChunkDiagnostics:
        """:meth:`of_chunk` given the energies ``H`` and Casimirs ``C`` of its states."""
        rows: tuple[ExtraRow, ...] = ()
        if self.extra is not None:
            at = np.flatnonzero(chunk.index % self.extra_every == 0).tolist()
            rows = tuple((int(chunk.index[j]), float(chunk.t[j]), self.extra(chunk.state_at(j)))
                         for j in at)  # fmt: skip
        return ChunkDiagnostics(H, C, self.energy_error(H), self.casimir_drift(C), rows)


@attrs.frozen(eq=False)
class DeferredDiagnostics:
    """:class:`Diagnostics` relative to ``W0``, computed together with the first chunk's
    (:meth:`start`): the energy and Casimirs of ``W0`` and of the chunk's states in one
    call each on the stack of them, instead of one call for ``W0`` before the run and one
    for the chunk (half the calls of a short run, whose cost is these calls' overhead).
    :func:`~lieflow.stepping.run` starts them at its first chunk;
    :class:`~lieflow.sinks.MemorySink` takes them as it takes :class:`Diagnostics`. Build it
    with :meth:`Diagnostics.deferred`.
    """

    system: IsospectralSystem
    W0: Array = attrs.field(repr=False)
    save_every: int = 1
    extra: Callable[[Array], Any] | None = attrs.field(default=None, repr=False)
    extra_every: int = 0

    def start(self, chunk: Chunk) -> tuple[Diagnostics, ChunkDiagnostics]:
        """The run's :class:`Diagnostics` and those of its first ``chunk``."""
        system, W0 = self.system, self.W0
        if chunk.energy is not None and chunk.casimirs is not None:  # the flow's own
            H = np.concatenate((np.asarray(system.hamiltonian(W0))[None], chunk.energy))
            C = np.concatenate((np.asarray(system.casimirs(W0))[None], chunk.casimirs))
        else:
            X = np.concatenate((W0[None], chunk.W))
            H, C = np.asarray(system.hamiltonian(X)), np.asarray(system.casimirs(X))
        diag = Diagnostics(system, np.asarray(H[0]), C[0], np.asarray(system.casimir_scale(W0)),
                           self.extra, self.extra_every)  # fmt: skip
        return diag, diag._of(chunk, H[1:], C[1:])

    def initial(self) -> Diagnostics:
        """The run's :class:`Diagnostics` before any chunk (a run whose first step failed)."""
        return Diagnostics.of(self.system, self.W0, save_every=self.save_every)
