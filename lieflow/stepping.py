r"""The one stepping loop and the one consumer loop.

:func:`advance` yields :class:`~lieflow.chunks.Chunk`\ s of consecutive completed steps of
any :class:`~lieflow.flows.Flow`. :func:`run` consumes them for every caller —
:func:`lieflow.integrate`, ``lieflow run`` and ``lieflow sweep`` — and owns what happens
after a step: which states are saved, the diagnostics
(:class:`~lieflow.chunks.Diagnostics`, computed once per chunk, :mod:`lieflow.chunks`),
the monitor, the failure policy and the checkpoint cadence; it hands each chunk to
:class:`Sink`\ s that only store it (the protocol is defined here, by the loop that feeds
it; :mod:`lieflow.sinks` holds the sinks). A flow may advance many steps per call
(:class:`MultiStepFlow`, e.g. the compiled engine); a step it does not finish is then
taken by its plain :meth:`~lieflow.flows.Flow.step` from the last good state, so failures
read the same on every engine.

Time is ``t_k = k h``, computed from the step index, never accumulated.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from typing import Any, Literal, Protocol, runtime_checkable

import attrs
import numpy as np

from . import _signals
from .algebras import Array
from .backends import all_finite, is_numpy, to_numpy
from .chunks import Chunk, ChunkDiagnostics, DeferredDiagnostics, Diagnostics
from .errors import ConvergenceError, InputError
from .flows import Flow
from .steps import StepStats

__all__ = [
    "Cadence",
    "Ending",
    "Monitor",
    "MultiStepFlow",
    "Outcome",
    "Recording",
    "Sink",
    "advance",
    "batch_steps",
    "chunk_steps",
    "run",
]

#: At most this many steps per chunk of a multi-step flow (a progress tick each) ...
CHUNK_STEPS = 1024
#: ... and at most this many entries of saved states per chunk (8 MiB of float64).
CHUNK_ENTRIES = 1 << 20


def _mask(kept: bool) -> Array:
    mask = np.array([kept])
    mask.setflags(write=False)
    return mask


#: The keep masks of a one-step chunk (read-only): ``_ONE_STEP[kept]``.
_ONE_STEP = (_mask(False), _mask(True))


#: A chunk of steps taken one :meth:`~lieflow.flows.Flow.step` call each (:func:`advance`'s
#: ``batch``) holds at most this many entries of states ...
BATCH_ENTRIES = 4096
#: ... and at most this many steps: chunks are cut by step counts alone, never by a clock,
#: so a run's chunks (what its sinks see, where its checkpoints fall) are the same under any
#: load. Small states' steps take microseconds to a millisecond, so a chunk shares the
#: consumer's per-chunk work among many steps and still ends within tens of milliseconds.
BATCH_STEPS = 64


def batch_steps(W0: Array) -> int:
    """Steps per chunk of a flow stepped one :meth:`~lieflow.flows.Flow.step` call at a time
    (:func:`advance`'s ``batch``): :data:`BATCH_STEPS` for small states, fewer for larger
    ones (1 from :data:`BATCH_ENTRIES` entries on, where the per-chunk work of :func:`run`
    is a small part of a step)."""
    return max(1, min(BATCH_STEPS, BATCH_ENTRIES // max(1, math.prod(W0.shape))))


def chunk_steps(W0: Array) -> int:
    """Steps per chunk for states like ``W0``: :data:`CHUNK_STEPS`, fewer for large states
    so that a chunk holds at most :data:`CHUNK_ENTRIES` numbers."""
    return max(1, min(CHUNK_STEPS, CHUNK_ENTRIES // max(1, math.prod(W0.shape))))


@attrs.frozen
class Recording:
    """What the consumer (:func:`run`) needs of the steps, decided once per run: the states
    of step ``k`` where ``k % save_every == 0`` or ``k == last`` (saved) or
    ``k % extra_every == 0`` (the system's extra diagnostics, ``extra_every > 0``), and the
    energy and Casimirs of every step when ``diagnostics``. A flow whose states live on a
    device (:attr:`MultiStepFlow.holds_needed_states`) ends its chunks at the states needed
    and holds only those, so that nothing else crosses to the host."""

    save_every: int = 1
    last: int = 0
    extra_every: int = 0
    diagnostics: bool = False

    def needs_state(self, k: int) -> bool:
        """Whether the state after step ``k`` is saved or diagnosed."""
        extra = self.extra_every
        return k % self.save_every == 0 or k == self.last or bool(extra and k % extra == 0)

    def next_needed(self, k: int) -> int:
        """The first step after ``k`` whose state is needed (at most :attr:`last`)."""
        j = (k // self.save_every + 1) * self.save_every
        if self.extra_every:
            j = min(j, (k // self.extra_every + 1) * self.extra_every)
        return min(j, max(self.last, k + 1))

    def needed(self, index: Array) -> Array:
        """The boolean mask of :meth:`needs_state` over step indices ``index``."""
        mask = (index % self.save_every == 0) | (index == self.last)
        if self.extra_every:
            mask |= index % self.extra_every == 0
        return np.asarray(mask)


@runtime_checkable
class MultiStepFlow(Flow, Protocol):
    """A :class:`~lieflow.flows.Flow` that can also advance many steps per call.

    A flow that sets ``holds_needed_states = True`` (a device engine,
    :class:`lieflow.engines.traced.TracedSchemeFlow`) takes ``recording=`` (the run's
    :class:`Recording`) in :meth:`step_many`: :func:`advance` then ends its chunks at the
    states the recording needs, and the chunk holds those states only
    (:attr:`~lieflow.chunks.Chunk.held`), with the energy and Casimirs of every step when it
    asks for diagnostics (:attr:`~lieflow.chunks.Chunk.energy`,
    :attr:`~lieflow.chunks.Chunk.casimirs`)."""

    def step_many(self, W: Array, start: int, h: float, steps: int, state: Any) -> Chunk:
        """Up to ``steps`` steps from ``W`` after step ``start``. Fewer (possibly none) when
        a step was not accepted; the stepping loop then takes that step with :meth:`step`."""
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
    batch: int = 1,
    align: int = 0,
    recording: Recording | None = None,
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
    batch : int
        At most this many steps per chunk of a flow that is not a :class:`MultiStepFlow`
        (numpy states only): the steps are the same, one :meth:`~lieflow.flows.Flow.step`
        call each, and the consumer's work per chunk is shared by them. A step that fails, or a
        ``KeyboardInterrupt`` while stepping, first yields the chunk of the steps done
        before it.
    align : int
        Such chunks also end at the multiples of ``align`` (``0``: anywhere): :func:`run`
        passes ``save_every`` when its checkpoints fall at the saved states.
    recording : Recording, optional
        What the consumer needs of the steps (:func:`run` passes its own); a flow that
        holds only the states needed (:class:`MultiStepFlow`) ends its chunks at them.
        ``None``: every step's state is needed.

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
    needed = None  # a flow that holds only the states needed: the recording, and its chunks
    if many is not None and getattr(flow, "holds_needed_states", False) is True:
        needed = Recording(last=steps) if recording is None else recording
        size = CHUNK_STEPS
    if many is None and batch > 1 and steps - start > 1 and is_numpy(W0):
        yield from _batched(flow, W0, h, steps, start, state, batch, align)
        return
    # as in _batched: after the first step, step_from_phase_space (not after a chunk of
    # step_many, whose states the flow's own projection did not make)
    step = flow.step
    again = getattr(flow, "step_from_phase_space", None) if many is None else None
    while k < steps:
        if many is not None:
            # Chunks end at multiples of ``size`` counted from step 0, wherever the run
            # started, so a run resumed at a chunk end takes the same chunks as an
            # uninterrupted one (bit-for-bit resume).
            asked = min(size - k % size, steps - k)
            if needed is None:
                chunk = many(W, k, h, asked, state)
            else:  # up to the next state needed (a save point), which it holds
                asked = min(asked, needed.next_needed(k) - k)
                chunk = many(W, k, h, asked, state, recording=needed)
            if chunk.size:
                yield chunk
                W, k, state = chunk.W[-1], chunk.stop, chunk.state
            if chunk.size == asked:
                continue
        try:
            W, state, stats = step(W, k * h, h, state)
        except ConvergenceError as exc:
            raise exc.at(k + 1, k * h) from exc
        if again is not None:
            step = again
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


def _batched(
    flow: Flow, W: Array, h: float, steps: int, k: int, state: Any, batch: int, align: int
) -> Iterator[Chunk]:
    """:func:`advance` of a flow in chunks of up to ``batch`` steps (numpy states), each
    ending at a multiple of ``align`` if it reaches one."""
    shape, dtype = W.shape, W.dtype
    # after the first step, W is the flow's own last result, on its phase space: a flow
    # that can use that (SchemeFlow.step_from_phase_space: the same result, the final
    # projection skipped where it is the identity) is stepped by it from then on
    step, again = flow.step, getattr(flow, "step_from_phase_space", None)
    while k < steps:
        m = min(batch, steps - k, align - k % align) if align else min(batch, steps - k)
        Ws = np.empty((m, *shape), dtype)
        done: list[StepStats] = []
        # (steps done in this chunk, the last state, the flow's state after it), replaced by
        # one store once a step's results are in Ws and done: a Ctrl-C raised between two
        # statements (at any call) then never pairs one step's W with the next step's flow
        # state, which a checkpoint would keep (the resumed run's warm start one step ahead)
        progress = (0, W, state)
        try:
            while progress[0] < m:
                j, W, state = progress
                t = (k + j) * h
                try:
                    W_next, state_next, stats = step(W, t, h, state)
                except ConvergenceError as exc:
                    raise exc.at(k + j + 1, t) from exc
                if again is not None:
                    step = again
                if not all_finite(W_next):
                    _check_finite(W_next, stats.iterations, stats.solver, stats.residual, k + j, h)
                Ws[j] = W_next
                done.append(stats)
                progress = (j + 1, W_next, state_next)
        finally:  # the steps done reach the consumer, however the chunk ends
            j, W, state = progress
            if j:
                yield Chunk(
                    k,
                    h,
                    Ws[:j],
                    np.array([s.iterations for s in done[:j]], dtype=np.int64),
                    np.array([s.residual for s in done[:j]], dtype=np.float64),
                    tuple(s.solver for s in done[:j]),
                    state,
                )
        k += j


#: How a run ended: every step done, stopped by Ctrl-C (resumable), or a step failed.
Ending = Literal["complete", "interrupted", "failed"]


@runtime_checkable
class Sink(Protocol):
    """Receives a run's steps from :func:`lieflow.stepping.run`.

    The stepping loop calls :meth:`record` for every chunk of steps, in order; :meth:`checkpoint`
    at its checkpoint cadence and once at the end; :meth:`close` exactly once, however the
    run ends; :meth:`result` after that, for what the caller gets back.

    The stepping loop holds interrupts (:func:`lieflow._signals.deferred`) while it takes the last
    checkpoint and closes the sinks, so that a second Ctrl-C cannot split the two. A sink
    that keeps nothing outside the process may say so with a class attribute
    ``durable = False`` (:class:`~lieflow.sinks.MemorySink`); a run whose sinks all do skips
    that section (two signal-handler swaps per call). Without the attribute a sink is
    durable.
    """

    def record(self, chunk: Chunk, keep: Array, diagnostics: ChunkDiagnostics | None) -> None:
        """Store the chunk's steps: the states where ``keep`` is true (a boolean per step),
        its iterations, residuals and solvers, and its ``diagnostics`` (``None`` when the
        run computes none). May buffer; nothing recorded is final until :meth:`checkpoint`."""
        ...

    def checkpoint(self, *, keep_last: bool = False) -> None:
        """Make everything recorded durable, with a resume point at the last recorded step
        (its state and the chunk's flow state resume bit-for-bit). ``keep_last``: also save
        the last recorded state (a failed run keeps its last good state)."""
        ...

    def close(self, status: Ending, failure: ConvergenceError | None, wall_time: float) -> None:
        """The run ended with ``status`` (the error of a failed step in ``failure``) after
        ``wall_time`` seconds of stepping; release what the sink holds."""
        ...

    def result(self) -> Any:
        """What the run gives its caller (:func:`lieflow.integrate` returns it): a
        :class:`~lieflow.Solution` for the built-in sinks."""
        ...


@attrs.frozen
class Cadence:
    """When :func:`run` takes a checkpoint (the resume point of a file sink).

    With neither ``steps`` nor ``seconds``: after every chunk that holds a saved state.
    Otherwise after the first chunk (holding a saved state or not) that ends at least
    ``steps`` steps or ``seconds`` seconds after the last checkpoint, whichever comes first.
    A checkpoint is always taken when the run ends, however it ends (Ctrl-C included).
    """

    steps: int | None = None
    seconds: float | None = None

    def __attrs_post_init__(self) -> None:
        if self.steps is not None and (isinstance(self.steps, bool) or self.steps < 1):
            raise InputError(f"checkpoint steps must be a positive integer, got {self.steps!r}")
        seconds = self.seconds
        if seconds is not None and (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float, np.floating, np.integer))
            or not (math.isfinite(seconds) and seconds >= 0)
        ):
            raise InputError(
                f"checkpoint seconds must be >= 0 and finite, got {self.seconds!r}. To fix: "
                "pass a number of seconds, or None to checkpoint at every saved state (the "
                'configuration\'s checkpoint = "saves")'
            )

    @property
    def at_saves(self) -> bool:
        """Whether a checkpoint follows every chunk holding a saved state."""
        return self.steps is None and self.seconds is None


@attrs.frozen
class Outcome:
    """How :func:`run` ended.

    Attributes
    ----------
    status : {"complete", "interrupted", "failed"}
        Every step done, stopped by ``KeyboardInterrupt`` (the sinks hold every step
        recorded), or a step failed (they hold the steps before it).
    start, done : int
        The step the run started after, and the last step recorded.
    failure : ConvergenceError or None
        The error of the failed step.
    wall_time : float
        Seconds spent stepping.
    """

    status: Ending
    start: int
    done: int
    failure: ConvergenceError | None
    wall_time: float


def run(
    flow: Flow,
    W0: Array,
    h: float,
    steps: int,
    *,
    sinks: Sequence[Sink],
    diagnostics: Diagnostics | DeferredDiagnostics | None = None,
    save_every: int = 1,
    start: int = 0,
    state: Any = None,
    monitor: Monitor | None = None,
    checkpoint: Cadence = Cadence(),
    on_failure: str = "truncate",
    interrupts: _signals.Interrupts | None = None,
) -> Outcome:
    """Advance ``flow`` from ``W0`` (the state after step ``start``) up to step ``steps``,
    handing every chunk of steps to each of ``sinks``: the one consumer loop.

    Step ``k`` is saved where ``k % save_every == 0`` or ``k == steps`` (the keep mask each
    sink receives). ``diagnostics`` (computed once per chunk) go to every sink and the
    largest energy error to ``monitor``. Checkpoints follow ``checkpoint``
    (:class:`Cadence`) and come once more at the end; a failed step then also keeps the last
    good state. Every sink is closed, however the run ends.

    Parameters
    ----------
    flow, W0, h, steps, start, state
        As :func:`advance`.
    sinks : sequence of Sink
        Where the steps go.
    diagnostics : Diagnostics or DeferredDiagnostics, optional
        Energy, Casimirs and extra diagnostics relative to the run's initial state
        (deferred: those of the initial state are computed with the first chunk's).
    save_every : int
        Save every ``save_every``-th state (and the last).
    monitor : Monitor, optional
        Progress callbacks.
    checkpoint : Cadence
        When to make the recorded steps durable between the start and the end.
    on_failure : {"raise", "truncate"}
        A failed step raises its :class:`ConvergenceError` after the sinks are closed
        (``"raise"``), or is returned in :attr:`Outcome.failure` (``"truncate"``).
    interrupts : lieflow._signals.Interrupts, optional
        A Ctrl-C handler that has held interrupts while the sinks were set up: armed while
        stepping (a held interrupt is raised at the first step, so the sinks record
        "interrupted"), checked after every chunk (an interrupt Python swallowed in a
        finalizer still stops the run), held again while the sinks are closed.

    Returns
    -------
    Outcome
        How the run ended (``KeyboardInterrupt`` is caught: ``status == "interrupted"``).
    """
    status: Ending = "interrupted"
    failure: ConvergenceError | None = None
    done = start
    at_saves, every, seconds = checkpoint.at_saves, checkpoint.steps, checkpoint.seconds
    last_step, began = start, time.perf_counter()
    last_time = began
    try:
        if interrupts is not None:
            interrupts.arm()
        if monitor is not None:  # inside: Ctrl-C while a progress bar starts is an interrupt
            monitor.start(start, steps)
        # Chunks of several steps of a numpy flow (a monitor hears of each chunk, a Ctrl-C
        # is acted on after it) unless a checkpoint after every chunk is to see every step;
        # they end where a checkpoint every ``every`` steps falls due.
        batch = 1 if seconds == 0 else min(batch_steps(W0), every or BATCH_STEPS)
        extra = 0 if diagnostics is None or diagnostics.extra is None else diagnostics.extra_every
        recording = Recording(save_every, steps, extra, diagnostics is not None)
        for chunk in advance(flow, W0, h, steps, start=start, state=state, batch=batch,
                             align=save_every if at_saves else 0,
                             recording=recording):  # fmt: skip
            if not is_numpy(chunk.W):  # another array library: to the host, once per chunk
                chunk = attrs.evolve(chunk, W=to_numpy(chunk.W))
            if chunk.held is None and chunk.W.shape[0] == 1:  # one step: its mask in Python
                k = chunk.start + 1
                kept = k % save_every == 0 or k == steps
                keep = _ONE_STEP[kept]
            else:
                index = chunk.index
                keep = (index % save_every == 0) | (index == steps)
                kept = bool(keep.any())
            if diagnostics is None:
                diag = None
            elif isinstance(diagnostics, DeferredDiagnostics):
                diagnostics, diag = diagnostics.start(chunk)
            else:
                diag = diagnostics.of_chunk(chunk)
            for sink in sinks:
                sink.record(chunk, keep, diag)
            done = chunk.stop
            if at_saves:
                due = kept
            else:
                now = time.perf_counter()
                due = (every is not None and done - last_step >= every) or (
                    seconds is not None and now - last_time >= seconds
                )
            if due:
                for sink in sinks:
                    sink.checkpoint()
                last_step, last_time = done, time.perf_counter()
            if monitor is not None:
                err = None if diag is None else diag.max_energy_error
                monitor.advance(chunk.size, int(chunk.iterations.sum()), err)
            del chunk  # hold no chunk while the next one is computed
            if interrupts is not None:
                interrupts.check()
        status = "complete"
    except KeyboardInterrupt:
        status = "interrupted"
    except ConvergenceError as exc:
        status, failure = "failed", exc
    finally:
        if interrupts is not None:
            interrupts.disarm()
            interrupts.consume()  # the sinks record it below, or the run had finished
        wall = time.perf_counter() - began
        try:
            if monitor is not None:
                monitor.stop()
        finally:
            # Checkpoint what was computed (a failed run keeps its last state), then close.
            # With interrupts deferred, so a second Ctrl-C cannot split the two (where a
            # sink keeps something outside the process: Sink's ``durable``).
            if any(getattr(sink, "durable", True) for sink in sinks):
                with _signals.deferred():
                    _finish(sinks, status, failure, wall)
            else:
                _finish(sinks, status, failure, wall)
    if failure is not None and on_failure == "raise":
        raise failure
    return Outcome(status, start, done, failure, wall)


def _finish(
    sinks: Sequence[Sink], status: Ending, failure: ConvergenceError | None, wall: float
) -> None:
    """Checkpoint and close every sink; the first error is raised after all are closed."""
    error: BaseException | None = None
    for sink in sinks:
        try:
            try:
                sink.checkpoint(keep_last=status == "failed")
            finally:
                sink.close(status, failure, wall)
        except BaseException as exc:
            error = error or exc
    if error is not None:
        raise error
