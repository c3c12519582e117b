r"""The traced engine: the whole step — the scheme's map, ``B``, the stopping rule, the warm
start, the update and the projection — compiled once by ``jax.jit`` and run on the array's
device with no host round trip per update.

Nothing here restates the numerics. The program is the scheme's own :meth:`Scheme.step
<lieflow.schemes.Scheme.step>` on the system's own ``B`` and projection — the array-API
source the eager engine runs op by op on a device — traced with a
:class:`~lieflow.engines.traced_loops.TracedSolver` (the solver's iteration as a
``lax.while_loop``) and the warm start as fixed-shape arrays
(:mod:`lieflow.engines.traced_warm`). What the engine adds is how they run:

* a chunk of steps is one call: a ``lax.while_loop`` over the steps up to the next state the
  run needs (:class:`lieflow.stepping.Recording`: a save point, an extra diagnostic, the last
  step), with the energy and Casimirs of every step computed on the device when the run
  records diagnostics; the host sees the chunk's last state and a few numbers per step —
  one synchronisation per chunk;
* a step that does not converge ends the chunk before it; the stepping loop hands it to the eager
  engine (:meth:`TracedSchemeFlow.step` falls back to :meth:`SchemeFlow.step
  <lieflow.flows.SchemeFlow.step>`), which retries cold or raises the same
  :class:`~lieflow.errors.ConvergenceError` as every engine;
* arrays: JAX arrays in, JAX arrays out; NumPy arrays run on JAX's default device and come
  back as NumPy arrays (``engine="jax"``); CuPy and PyTorch arrays cross to JAX and back by
  DLPack, without a copy, where JAX runs on the same device.

Compiled programs are kept by the flow, per step size and warm-start depth (JAX keeps one
per shape and dtype): a flow reused for several runs compiles once.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from .. import chunks, stepping
from ..algebras import Array
from ..backends import is_numpy, namespace
from ..errors import InputError
from ..flows import SchemeFlow, StepStats
from ..warm_start import WarmStart
from . import traced_loops, traced_warm

__all__ = ["TracedSchemeFlow", "available", "jax_array", "plan"]


def available() -> bool:
    """Whether JAX can be imported."""
    try:
        import jax  # noqa: F401
    except ImportError:
        return False
    return True


def _jax() -> Any:
    """The ``jax`` module with double precision switched on (``jax_enable_x64``: lieflow's
    states are float64/complex128, and a traced loop counts in 64-bit integers) and, unless
    the user chose one, JAX's persistent compilation cache in :func:`cache_directory`."""
    try:
        import jax
    except ImportError as exc:
        raise InputError(
            "the traced engine needs JAX: pip install jax (with CUDA for a GPU: "
            "pip install 'jax[cuda12]'), or choose engine='numpy'"
        ) from exc
    jax.config.update("jax_enable_x64", True)
    if not getattr(jax.config, "jax_compilation_cache_dir", None):
        jax.config.update("jax_compilation_cache_dir", str(cache_directory()))
    return jax


def cache_directory() -> Path:
    """Where the traced engine's compiled programs are kept between processes (JAX's
    persistent compilation cache, keyed by the program itself: the same system, scheme,
    solver, step size, shape and dtype compile once per machine): ``$XDG_CACHE_HOME/
    lieflow/jax``, else ``~/.cache/lieflow/jax``. A cache directory the user set for JAX
    (``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``) is used as it is."""
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "lieflow" / "jax"


def jax_array(x: Any) -> Any:
    """``x`` as a JAX array: itself, a NumPy array copied to JAX's default device, any
    other library's array through DLPack (no copy where JAX runs on its device)."""
    jax = _jax()
    if isinstance(x, jax.Array):
        return x
    if is_numpy(x):
        return jax.numpy.asarray(x)
    return jax.dlpack.from_dlpack(x)


def _like(y: Any, like: Any) -> Any:
    """The JAX array ``y`` as an array of ``like``'s library (NumPy: a host copy)."""
    jax = _jax()
    if isinstance(like, jax.Array):
        return y
    if is_numpy(like):
        return np.asarray(y)
    return namespace(like).from_dlpack(y)


def _leaves_like(state: WarmStart, like: Any) -> WarmStart:
    """``state`` with its kept solutions as arrays of ``like``'s library."""
    return state.replaced([_like(x, like) for x in state.history()], int(state.trusted))


@attrs.frozen
class _Program:
    """A compiled chunk program and what its outputs hold: ``run(W, history, steps)``
    returns ``(W, history, done, iterations, residuals, solver index, energy, Casimirs,
    states)`` with buffers of ``length`` steps; ``names`` are the solvers an index refers
    to. ``states`` holds every step's state where the system's diagnostics do not trace
    (``holds_all``: the host computes them), else nothing (and, with ``diagnostics``, the
    energy and Casimirs hold every step's)."""

    run: Any
    length: int
    names: tuple[str, ...]
    diagnostics: bool
    holds_all: bool
    offsets: Any  # the shape and dtype of a step's solved offsets (the warm start's)


def _traces(f: Any, W: Any) -> bool:
    """Whether ``f(W)`` traces with JAX (a system's diagnostics written for NumPy only do
    not)."""
    jax = _jax()
    try:
        jax.eval_shape(f, jax.ShapeDtypeStruct(W.shape, W.dtype))
    except Exception:
        return False
    return True


def plan(system: Any, scheme: Any, solver: Any, W0: Any) -> str | None:
    """``None`` if the traced engine runs this case, else the reason it does not (checked
    by tracing one step, without compiling it)."""
    if not available():
        return "JAX is not installed (pip install jax)"
    reason = traced_loops.supported(solver)
    if reason is not None:
        return reason
    jax = _jax()
    W = jax_array(W0)
    try:
        jax.eval_shape(
            lambda W: _one_step(system, scheme, traced_loops.TracedSolver(solver), W, 0.5, None)[0],
            jax.ShapeDtypeStruct(W.shape, W.dtype),
        )
    except Exception as exc:  # a scheme or system whose code does not trace: named
        return (
            f"scheme {scheme.name!r} on {type(system).__name__} does not trace with JAX "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        )
    return None


def _one_step(
    system: Any, scheme: Any, solver: traced_loops.TracedSolver, W: Array, h: float, guess: Any
) -> tuple[Array, Any, Array, Array, Array, Array]:
    """One traced step: ``(W1, offsets, accepted, updates, last relative update, solver
    index)``; ``W1`` on the phase space (:meth:`~lieflow.IsospectralSystem.project`)."""
    res = scheme.step(W, h, system, solver, guess)
    W1 = system.project(res.W)
    xp = namespace(W1)
    accepted = xp.all(xp.isfinite(W1))
    for good, _ in solver.verdicts:
        accepted = accepted & good
    which = solver.verdicts[-1][1] if solver.verdicts else xp.asarray(0, dtype=xp.int64)
    return W1, res.warm, accepted, res.stats.iterations, res.stats.residual, which


@attrs.frozen(eq=False)
class TracedSchemeFlow(SchemeFlow):
    """A :class:`~lieflow.flows.SchemeFlow` whose steps a program compiled by ``jax.jit``
    takes, a chunk per call (:meth:`step_many`; the module docstring says how). Build it
    with :func:`lieflow.engines.scheme_flow` (``engine="jax"``, or ``"auto"`` for arrays
    of a device library)."""

    #: chunks end at the states a run needs, and hold only those (lieflow.stepping.advance)
    holds_needed_states = True
    _programs: dict[tuple[Any, ...], _Program] = attrs.field(init=False, factory=dict, repr=False)
    #: the warm start the last chunk returned and the arrays it was made of (reused when
    #: the next chunk starts from it: no conversion per chunk)
    _carried: list[tuple[WarmStart, traced_warm.History]] = attrs.field(
        init=False, factory=list, repr=False
    )

    def step(
        self, W: Array, t: float, h: float, state: WarmStart | None
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """One step: a chunk of one step of the compiled program, so that the flow stays
        compiled where it is stepped alone (a :class:`~lieflow.flows.Splitting`); a step it
        does not accept is taken by the eager engine from the same state."""
        chunk = self.step_many(W, 0, h, 1, state)
        if not chunk.size:
            return SchemeFlow.step(self, W, t, h, state)
        stats = StepStats(int(chunk.iterations[0]), chunk.solvers[0], float(chunk.residuals[0]))
        return chunk.W[-1], chunk.state, stats

    def step_from_phase_space(
        self, W: Array, t: float, h: float, state: WarmStart | None
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """:meth:`step` (the compiled program always projects: one pass of its own)."""
        return self.step(W, t, h, state)

    def step_many(
        self,
        W: Array,
        start: int,
        h: float,
        steps: int,
        state: WarmStart | None,
        recording: stepping.Recording | None = None,
    ) -> chunks.Chunk:
        """Up to ``steps`` steps after step ``start`` (fewer if one is not accepted), the
        chunk holding the last state only, with each step's energy and Casimirs when
        ``recording`` asks for diagnostics."""
        jax = _jax()
        diagnostics = recording is not None and recording.diagnostics
        Wj = jax_array(W)
        depth = 0 if state is None else state.depth
        program = self._program(float(h), diagnostics, depth, Wj)
        history = None if state is None else self._history(state, program)
        # committed to the state's device, as the program's outputs are: the inputs of the
        # first call then look like those of the next ones (no second compilation)
        device = next(iter(Wj.devices()))
        Wj, history = jax.device_put((Wj, history), device)
        parts: list[Any] = []
        held: list[Any] = []
        done, filled = 0, (0, 0)
        while done < steps:
            ask = min(program.length, steps - done)
            Wj, last, history, rows, count, *buffers, states = program.run(Wj, history, ask)
            # the one synchronisation of the call: the counts and the per-step numbers
            counts = (count,) if history is None else (count, history.count, history.trusted)
            fetched = jax.device_get((counts, buffers))
            taken = int(fetched[0][0])
            parts.append([b[:taken] for b in fetched[1]])
            if program.holds_all:
                held.append(states[:taken])
            if taken and history is not None:
                filled = (int(fetched[0][1]), int(fetched[0][2]))
            done += taken
            if taken < ask:
                break
        iterations, residuals, which, energy, casimirs = (
            np.concatenate([p[i] for p in parts]) for i in range(5)
        )
        new = state
        if state is not None and done:
            assert history is not None
            new = _leaves_like(state.replaced(list(rows[: filled[0]]), filled[1]), W)
            self._carried.clear()  # the next chunk, given ``new``, starts from ``history``
            self._carried.append((new, history))
        if program.holds_all:  # every state, the diagnostics the host's
            W_out = _like(jax.numpy.concatenate(held) if len(held) > 1 else held[0], W)
            kept = None
        else:  # the last state only, the diagnostics the device's
            W_out = _like(last, W) if done else _like(last, W)[:0]
            kept = np.array([done - 1]) if done else np.zeros(0, dtype=np.int64)
        on_device = program.diagnostics and not program.holds_all
        return chunks.Chunk(
            start,
            h,
            W_out,
            iterations.astype(np.int64),
            residuals.astype(np.float64),
            tuple(program.names[int(i)] for i in which),
            new,
            held=kept,
            energy=energy if on_device else None,
            casimirs=casimirs if on_device else None,
        )

    def _history(self, state: WarmStart, program: _Program) -> traced_warm.History:
        """``state`` as the arrays the program carries: those the last chunk ended with
        when ``state`` is the warm start it returned, else converted."""
        for returned, history in self._carried:
            if returned is state:
                return history
        shape = program.offsets
        return traced_warm.from_warm_start(state, tuple(shape.shape), shape.dtype, _jax().numpy)

    def _program(self, h: float, diagnostics: bool, depth: int, W: Any) -> _Program:
        """The compiled chunk program for step size ``h`` (built on first use, kept)."""
        key = (h, diagnostics, depth)
        made = self._programs.get(key)
        if made is None:
            made = self._programs[key] = self._build(h, diagnostics, depth, W)
        return made

    def _build(self, h: float, diagnostics: bool, depth: int, W: Any) -> _Program:
        jax = _jax()
        jnp, lax = jax.numpy, jax.lax
        system, scheme, solver = self.system, self.scheme, self.solver
        names = traced_loops.TracedSolver(solver).names
        batch = tuple(W.shape[:-2])
        if diagnostics and _traces(lambda W: (system.hamiltonian(W), system.casimirs(W)), W):
            holds_all = False
            casimirs = jax.eval_shape(system.casimirs, jax.ShapeDtypeStruct(W.shape, W.dtype))
            per_step = math.prod(batch) * (1 + math.prod(casimirs.shape[len(batch) :]))
        else:  # no diagnostics, or the host computes them from every state
            holds_all, diagnostics = diagnostics, False
            casimirs = jax.ShapeDtypeStruct((*batch, 0), jnp.float64)
            per_step = math.prod(W.shape) if holds_all else 1
        length = max(1, min(stepping.CHUNK_STEPS, stepping.CHUNK_ENTRIES // max(per_step, 1)))
        stored = (length, *W.shape) if holds_all else (0, *W.shape)
        offsets = jax.eval_shape(
            lambda W: _one_step(system, scheme, traced_loops.TracedSolver(solver), W, h, None)[1],
            jax.ShapeDtypeStruct(W.shape, W.dtype),
        )

        def run(W: Any, history: traced_warm.History | None, steps: Any) -> tuple[Any, ...]:
            buffers = (
                jnp.zeros(length, jnp.int64),
                jnp.zeros(length, jnp.float64),
                jnp.zeros(length, jnp.int64),
                jnp.zeros((length, *batch), jnp.float64),
                jnp.zeros((length, *casimirs.shape), jnp.float64),
                jnp.zeros(stored, W.dtype),
            )

            def body(carry: tuple[Any, ...]) -> tuple[Any, ...]:
                j, _, W, history, buffers = carry
                traced = traced_loops.TracedSolver(solver)
                guess = None if history is None else traced_warm.predict(history, jnp)
                W1, offsets, accepted, updates, residual, which = _one_step(
                    system, scheme, traced, W, h, guess
                )
                its, res, whiches, energy, cas, states = buffers
                if holds_all:
                    states = states.at[j].set(W1)
                its = its.at[j].set(updates)
                res = res.at[j].set(residual)
                whiches = whiches.at[j].set(which)
                if diagnostics:
                    energy = energy.at[j].set(jnp.real(system.hamiltonian(W1)))
                    cas = cas.at[j].set(jnp.real(system.casimirs(W1)))
                W = jnp.where(accepted, W1, W)
                if history is not None:
                    moved = traced_warm.advance(history, offsets, jnp)
                    history = jax.tree_util.tree_map(
                        lambda a, b: jnp.where(accepted, a, b), moved, history
                    )
                j = jnp.where(accepted, j + 1, j)
                return j, ~accepted, W, history, (its, res, whiches, energy, cas, states)

            start = (jnp.asarray(0, jnp.int64), jnp.asarray(False), W, history, buffers)
            j, _, W, history, buffers = lax.while_loop(
                lambda c: (c[0] < steps) & ~c[1], body, start
            )
            # the history's rows as separate outputs too (a warm start's leaves: no
            # slicing on the host), and W with the chunk's step axis
            rows = () if history is None else tuple(history.history[i] for i in range(depth))
            return (W, W[None], history, rows, j, *buffers)

        return _Program(jax.jit(run), length, names, diagnostics, holds_all, offsets)
