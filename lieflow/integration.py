"""The one entry point that runs many steps, :func:`integrate` (over the one consumer loop,
:func:`lieflow.stepping.run`, into a :class:`~lieflow.sinks.Sink`), and the step stream
:func:`iterate` (over the one stepping loop, :func:`lieflow.stepping.advance`)."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import ArrayLike

from . import stepping
from .algebras import Array
from .engines import Engine
from .errors import InputError
from .flows import Flow, SchemeFlow, StepStats, WarmStart
from .runs import DEFAULT_SOLVER, RunSpec, check_step_size, check_types, validated
from .schemes.base import Scheme
from .sinks import Sink, open_sink
from .solution import Solution
from .solvers.base import Solver
from .stepping import Monitor
from .systems.base import IsospectralSystem


@attrs.frozen
class Step:
    """One completed step of :func:`iterate`: step ``index`` took ``t - h`` to ``t``.

    ``warm`` is the flow's state after the step (the scheme's :class:`WarmStart`); with
    ``W`` and ``index`` it is all a checkpoint needs to resume bit-for-bit (:func:`iterate`
    with ``start`` and ``warm``). ``result`` is what the step cost.
    """

    index: int
    t: float
    W: Array = attrs.field(repr=False)
    result: StepStats
    warm: Any = attrs.field(repr=False)


def iterate(
    system: IsospectralSystem,
    scheme: Scheme,
    W0: ArrayLike,
    h: float,
    solver: Solver | None = None,
    *,
    start: int = 0,
    warm: WarmStart | None = None,
    warm_start: bool | int = True,
) -> Iterator[Step]:
    """Yield steps ``start + 1, start + 2, ...`` from ``W0``: an endless stream over
    :func:`lieflow.stepping.advance` of a :class:`SchemeFlow`.

    The arguments are checked as :func:`integrate` checks them, when ``iterate`` is called
    (not at the first step): ``h`` positive and finite, ``W0`` in the system's phase space,
    a system, a scheme and a solver instance (``FixedPoint()`` by default), ``start`` a
    non-negative step index.

    ``t`` is computed as ``index * h`` (never accumulated). ``warm`` seeds the first step's
    initial guess (pass the last :attr:`Step.warm` to resume a run bit-for-bit). A failed
    step raises :class:`ConvergenceError` carrying its index and time; a step whose result is
    not finite raises it too (reason ``"non_finite"``).

    Raises
    ------
    InputError
        A bad argument, named.
    """
    hf = check_step_size(h)
    solver = DEFAULT_SOLVER if solver is None else solver
    check_types(system, scheme, solver)
    if not isinstance(scheme, Scheme):
        raise InputError(
            f"iterate steps a Scheme, got {type(scheme).__name__}; step a Flow with "
            "lieflow.stepping.advance, or run it with lieflow.integrate"
        )
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or start < 0:
        raise InputError(f"start must be a non-negative step index, got {start!r}")
    W0a = validated(system, W0)
    flow = SchemeFlow(system, scheme, solver, warm_start)
    return _steps(flow, W0a, hf, int(start), warm)


def _steps(flow: Flow, W0: Array, h: float, start: int, warm: Any) -> Iterator[Step]:
    for chunk in stepping.advance(flow, W0, h, sys.maxsize, start=start, state=warm):
        yield Step(
            chunk.stop,
            chunk.stop * h,
            chunk.W[-1, ...],  # an index every array library takes
            StepStats(int(chunk.iterations[-1]), chunk.solvers[-1], float(chunk.residuals[-1])),
            chunk.state,
        )


def _progress_monitor(progress: bool | Monitor) -> Monitor | None:
    if progress is False:
        return None
    if progress is True:
        from .progress import ProgressBar

        return ProgressBar()
    if not all(callable(getattr(progress, m, None)) for m in ("start", "advance", "stop")):
        raise InputError(
            f"progress must be True, False or a Monitor (start, advance, stop), got {progress!r}"
        )
    return progress


def integrate(
    system: IsospectralSystem,
    scheme: Scheme | Flow,
    W0: ArrayLike,
    h: float,
    *,
    steps: int | None = None,
    t_final: float | None = None,
    solver: Solver | None = None,
    save_every: int = 1,
    diagnostics: bool = True,
    warm_start: bool | int = True,
    on_failure: Literal["raise", "truncate"] = "raise",
    progress: bool | Monitor = False,
    engine: Engine = "auto",
    out: str | os.PathLike[str] | Sink | None = None,
    resume: bool = False,
    replace: bool = False,
    checkpoint_seconds: float | None = 1.0,
    casimir_shift: float | Literal["auto"] = 0.0,
) -> Solution:
    """Integrate ``dW/dt = [B(W), W]`` from ``W0`` with a fixed step ``h``.

    Parameters
    ----------
    system : IsospectralSystem
        What to integrate (``lieflow.systems.get``): it validates ``W0`` and defines the
        diagnostics.
    scheme : Scheme or Flow
        How: a scheme (``lieflow.schemes.get``), run as a :class:`SchemeFlow` with
        ``solver``, ``warm_start`` and ``engine``; or any :class:`~lieflow.flows.Flow`,
        e.g. a :class:`~lieflow.flows.Splitting` of a scheme with dissipation (then
        ``solver``, ``warm_start`` and ``engine`` belong to its sub-flows and must be left
        at their defaults).
    W0 : array_like
        Initial condition in the system's algebra, shape ``(n, n)``; a stack of shape
        ``(..., n, n)`` is an ensemble advanced together.
    h : float
        Step size, positive.
    steps, t_final : int or float
        Number of steps, or final time (a whole number of steps).
    solver : Solver, optional
        Nonlinear solver; ``FixedPoint()`` (rtol 1e-14) by default.
    save_every : int
        Keep every ``save_every``-th state (the first and last are always kept). Memory:
        the saved states only, allocated once.
    diagnostics : bool
        Record the relative energy error and Casimir drift at every step.
    warm_start : bool or int
        Start each solve from a polynomial extrapolation of the previous steps' solutions
        (SPEC §5, :class:`~lieflow.flows.WarmStart`); an int is how many solutions to keep
        (``True``: :data:`~lieflow.flows.DEFAULT_DEPTH`).
    on_failure : {"raise", "truncate"}
        On a failed step raise :class:`ConvergenceError` (default) or return the steps done,
        with ``status = FAILED`` and the error in ``failure``.
    progress : bool or Monitor
        ``True`` shows a progress bar (needs ``rich``); a
        :class:`~lieflow.stepping.Monitor` receives the progress instead.
    engine : {"auto", "numpy", "compiled", "jax"}
        How a scheme's steps are computed (:mod:`lieflow.engines`). ``"numpy"``: the eager
        engine, one vectorised step at a time on the array's own library (any system,
        scheme, solver, dtype). ``"compiled"``: loops compiled with numba
        (``pip install 'lieflow[fast]'``) that advance many steps per call, for NumPy arrays
        of systems that supply a compiled ``B``
        (:meth:`~lieflow.IsospectralSystem.compiled_B`: the rigid bodies, the periodic Toda
        lattice, point vortices, Euler–Zeitlin, and any system with ``B(W) = S ⊙ W``),
        schemes with a compiled form (SyDIRK, reduced-form BlockGauss), float64 data or
        complex128 data on u(n)/su(N), and ``FixedPoint`` (or ``Auto``) solvers (see
        :mod:`lieflow.engines.compiled`). ``"jax"``: the traced engine
        (:mod:`lieflow.engines.traced`, ``pip install jax``): the whole step compiled by
        ``jax.jit`` and run on the array's device, a chunk of steps per call (NumPy arrays
        run on JAX's default device). Both run the same iterations and stopping rule, give
        results equal to roundoff, hand a step they cannot finish to the numpy path, and
        raise :class:`InputError` naming what is missing or not supported. ``"auto"``
        (default): for NumPy arrays the compiled loops where supported, numba is installed
        and they are faster (``n <= 128``, complex ``n <= 96``, and at least 1000
        trajectory-steps, see :func:`lieflow.engines.compiled.wins`: a function of the run alone, so
        the same run gives the same bits in any process), else numpy; for JAX arrays (and
        CuPy or PyTorch arrays on a GPU JAX runs on) the traced engine where it runs the
        case, else the eager engine.
    out : str, path or Sink, optional
        Stream the run into this trajectory file — the format ``lieflow run`` writes (the
        sink the plugin registry holds for the file's suffix, :func:`lieflow.sinks.open_sink`:
        the application's HDF5 writer for ``.h5`` and any suffix no other sink claims; read it
        with :func:`lieflow.open_run` or :func:`lieflow.app.io.read_trajectory`, plot it with
        ``lieflow plot``) — instead of keeping the states in memory: every ``save_every``-th
        state (and the last) goes to the file as the run proceeds, buffered and written in
        blocks at each checkpoint (``checkpoint_seconds``), and memory holds one chunk of
        steps (a few states) whatever the run's length. The returned :class:`Solution` then
        holds the initial and the last state only (``W``, ``t`` and ``saved_steps`` of length
        2), and the per-step diagnostics and iterations (a few numbers per step, read back
        from the file; they are recorded even with ``diagnostics=False``); ``solvers`` names
        the requested solver for every step. Or any :class:`~lieflow.sinks.Sink` object:
        ``integrate`` then returns its :meth:`~lieflow.sinks.Sink.result`. A file's directory must
        exist (it is not created).
    resume : bool
        With ``out``: continue the file from its last checkpoint (bit-for-bit the same as
        an uninterrupted run; ``steps`` may have grown) — it must have been written by the
        same system, scheme, solver, ``h``, ``save_every`` and ``W0``, else
        :class:`~lieflow.app.config.ConfigError` names what changed. Without an existing file
        the run starts afresh.
    replace : bool
        With ``out`` and no ``resume``: replace an existing file (otherwise an existing
        file is refused, so that a finished run is never overwritten by accident).
    checkpoint_seconds : float
        With ``out``: seconds between checkpoints — the resume point, written with the
        buffered states and diagnostics, flushed and fsync'd (a run killed outright loses at
        most this much work; Ctrl-C, a failed step or the end checkpoint everything). ``0``:
        after every chunk of steps; ``None``: after every chunk that holds a saved state
        (``lieflow run``'s ``[run] checkpoint = "saves"``; a numpy flow's chunks end at the
        saved states, so its checkpoints fall there).
    casimir_shift : float or "auto"
        Step the scheme on the Hamiltonian plus a Casimir, :math:`B(W) - cW`
        (:class:`~lieflow.systems.shifted.CasimirShifted`): the same flow, and an
        isospectral Lie–Poisson scheme of the same order, often far better conditioned.
        ``"auto"``: the least-squares :math:`c` of ``W0``
        (:func:`~lieflow.systems.shifted.casimir_shift`); ``0`` (default): the scheme as
        defined on ``system`` (the paper's). Diagnostics are always ``system``'s.

    Returns
    -------
    Solution
        Saved times and states, per-step iterations and solvers, the energy error and
        Casimir drift of every step, the status and the wall time.

    Raises
    ------
    InputError
        A bad argument (non-positive or non-numeric ``h``, ``W0`` outside the system's
        phase space, both or neither of ``steps`` and ``t_final``, ...).
    ConvergenceError
        A step failed to converge (with ``on_failure="raise"``); it names the step, the time,
        the solver's residual history and what to try.

    Examples
    --------
    >>> import lieflow as lf
    >>> body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    >>> sol = lf.integrate(body, lf.schemes.get("midpoint"), body.random_state(0),
    ...                    h=0.1, steps=100, save_every=50)
    >>> sol.t.tolist(), bool(sol.casimir_drift.max() < 1e-13)
    ([0.0, 5.0, 10.0], True)
    """
    if on_failure not in ("raise", "truncate"):
        raise InputError(f"on_failure must be 'raise' or 'truncate', got {on_failure!r}")
    if out is None and (resume or replace):
        raise InputError("resume and replace apply to a run streamed to a file: pass out=PATH")
    if resume and replace:
        raise InputError(
            "resume=True continues the file and replace=True starts it afresh: pass one of them"
        )
    if isinstance(out, type):
        raise InputError(
            f"out must be a file path or a Sink object, got the class {out.__name__}. To fix: "
            f"pass an instance (out={out.__name__}(...)), or leave out out= to keep the "
            "states in memory"
        )
    spec = RunSpec.build(system, scheme, W0, h, steps=steps, t_final=t_final, solver=solver,
                         save_every=save_every, diagnostics=diagnostics, warm_start=warm_start,
                         engine=engine, checkpoint_seconds=checkpoint_seconds,
                         casimir_shift=casimir_shift)  # fmt: skip
    monitor = _progress_monitor(progress)
    if out is None:
        sink: Sink = spec.memory_sink()
    elif isinstance(out, Sink):
        sink = out
    else:
        if isinstance(out, bytes) or not isinstance(out, (str, os.PathLike)) or not str(out):
            raise InputError(
                f"out must be a file path or a Sink (record, checkpoint, close, result), got "
                f"{out!r}"
            )
        sink = open_sink(Path(out).absolute(), spec.info(), resume=resume, replace=replace)
    outcome = spec.execute((sink,), monitor=monitor, on_failure=on_failure)
    if outcome.status == "interrupted":
        raise KeyboardInterrupt
    result: Solution = sink.result()
    return result
