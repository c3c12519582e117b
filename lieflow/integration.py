"""The one entry point that runs many steps, :func:`integrate` (over the one consumer loop,
:func:`lieflow.driver.run`, into a :class:`~lieflow.sinks.Sink`), and the step stream
:func:`iterate` (over the one stepping loop, :func:`lieflow.driver.advance`)."""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import ArrayLike

from . import driver
from .algebras import Array
from .backends import from_host, is_foreign_array, is_numpy, to_numpy
from .driver import DeferredDiagnostics, Diagnostics, Monitor
from .engines import Engine, scheme_flow
from .errors import InputError
from .flows import Flow, SchemeFlow, StepStats, WarmStart
from .schemes.base import Scheme
from .sinks import MemorySink, RunInfo, Sink, open_sink, run_identity
from .solution import Solution
from .solvers.base import Solver
from .solvers.fixed_point import FixedPoint
from .systems.base import IsospectralSystem
from .systems.shifted import CasimirShifted, shifted

#: The checkpoint cadence of ``checkpoint_seconds=1.0`` (the default), built once (a frozen
#: value: its validators cost ~1 µs a call).
DEFAULT_CADENCE = driver.Cadence(seconds=1.0)

#: The solver of a run that names none: ``FixedPoint()`` (a frozen value, built once: its
#: stopping rule's validators cost 6 µs a call).
DEFAULT_SOLVER = FixedPoint()


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


def check_step_size(h: float) -> float:
    """Return ``h`` as a float, or raise :class:`InputError` unless it is positive and finite."""
    if isinstance(h, (str, bytes, bool)):
        raise InputError(f"step size h must be a real number, got {h!r}")
    try:
        hf = float(h)
    except (TypeError, ValueError):
        raise InputError(f"step size h must be a real number, got {h!r}") from None
    if not math.isfinite(hf) or hf <= 0:
        raise InputError(f"step size h must be positive and finite, got {h!r}")
    return hf


def _not_a_class(value: object, what: str) -> None:
    """Refuse a class passed where an instance is expected (``solver=FixedPoint``)."""
    if isinstance(value, type):
        raise InputError(
            f"{what} must be an instance, got the class {value.__name__}; "
            f"pass an instance: {value.__name__}()"
        )


def _check_types(system: object, scheme: object, solver: object) -> None:
    _not_a_class(system, "system")
    _not_a_class(scheme, "scheme")
    _not_a_class(solver, "solver")
    if not isinstance(system, IsospectralSystem):
        raise InputError(
            f"system must be an IsospectralSystem, got {type(system).__name__}; "
            "use lieflow.systems.get(name, ...) or subclass IsospectralSystem"
        )
    if not isinstance(scheme, Scheme) and isinstance(scheme, Flow):
        return  # a flow carries its own solvers (Scheme first: a protocol check is slow)
    if not isinstance(scheme, Scheme):
        raise InputError(
            f"scheme must be a Scheme or a Flow, got {type(scheme).__name__}; "
            "use lieflow.schemes.get(name)"
        )
    if not (hasattr(solver, "name") and callable(getattr(solver, "solve", None))):
        raise InputError(
            f"solver must implement the Solver protocol (name, solve), got {type(solver).__name__}"
        )


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
    :func:`lieflow.driver.advance` of a :class:`SchemeFlow`.

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
    _check_types(system, scheme, solver)
    if not isinstance(scheme, Scheme):
        raise InputError(
            f"iterate steps a Scheme, got {type(scheme).__name__}; step a Flow with "
            "lieflow.driver.advance, or run it with lieflow.integrate"
        )
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or start < 0:
        raise InputError(f"start must be a non-negative step index, got {start!r}")
    W0a = _validated(system, W0)
    flow = SchemeFlow(system, scheme, solver, warm_start)
    return _steps(flow, W0a, hf, int(start), warm)


def _steps(flow: Flow, W0: Array, h: float, start: int, warm: Any) -> Iterator[Step]:
    for chunk in driver.advance(flow, W0, h, sys.maxsize, start=start, state=warm):
        yield Step(
            chunk.stop,
            chunk.stop * h,
            chunk.W[-1, ...],  # an index every array library takes
            StepStats(int(chunk.iterations[-1]), chunk.solvers[-1], float(chunk.residuals[-1])),
            chunk.state,
        )


#: The most steps a run may ask for (indices and times stay exact in 64-bit integers).
MAX_STEPS = 2**53


def _resolve_steps(h: float, steps: int | None, t_final: float | None) -> int:
    if (steps is None) == (t_final is None):
        raise InputError("give exactly one of steps=N or t_final=T")
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise InputError(f"steps must be a positive integer, got {steps!r}")
        if steps > MAX_STEPS:
            raise InputError(f"steps = {steps} is too many to count; use fewer steps or a larger h")
        return int(steps)
    assert t_final is not None
    if not (math.isfinite(t_final) and t_final > 0):
        raise InputError(f"t_final must be positive and finite, got {t_final!r}")
    n = round(t_final / h)
    if n > MAX_STEPS:
        raise InputError(f"t_final / h = {t_final / h:.3g} steps is too many to count")
    if n < 1 or abs(n * h - t_final) > 1e-9 * t_final:
        raise InputError(
            f"t_final = {t_final} is not a whole number of steps of h = {h}; "
            "choose h = t_final / N or pass steps=N"
        )
    return n


def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (``MemAvailable``), if known."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


#: A run whose saved states need more than this fraction of the available memory is refused.
MEMORY_FRACTION = 0.5
#: Saved states up to this many bytes are never checked against the available memory.
_SMALL_RUN = 1 << 26


def _check_memory(nbytes: int, steps: int, save_every: int) -> None:
    """Refuse (before anything runs) a run whose saved states would not fit in memory."""
    if nbytes <= _SMALL_RUN:
        return  # not worth reading /proc/meminfo (16 µs, a tenth of a short compiled run)
    available = _available_memory()
    if available is None or nbytes <= MEMORY_FRACTION * available:
        return
    fit = max(1, math.ceil(nbytes / (MEMORY_FRACTION * available) * save_every))
    raise InputError(
        f"the saved states of this run need {nbytes / 2**30:.1f} GiB, more than half of the "
        f"{available / 2**30:.1f} GiB of memory available. To fix: stream the run to a "
        'trajectory file with integrate(..., out="run.h5") or `lieflow run` (they keep '
        "only one chunk of steps in memory; read the file with lieflow.app.io.read_trajectory), "
        "or save fewer "
        f"states (save_every={fit} or more)"
    )


def _validated(system: IsospectralSystem, W0: ArrayLike) -> Array:
    if is_foreign_array(W0):  # an array of another library (lieflow.backends)
        return from_host(_validated(system, to_numpy(W0)), W0)
    W0a = system.validate(W0)
    if W0a.size == 0:
        raise InputError(
            f"W0 is an empty stack of states (shape {W0a.shape}); pass at least one n x n state"
        )
    return W0a


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


def _system_name(system: IsospectralSystem) -> str:
    """The registry name of ``system``'s class (what ``lieflow plot`` looks up), else the
    class name."""
    from .plugins import default_registry

    for name, entry in default_registry().systems.items():
        if getattr(entry, "factory", None) is type(system):
            return str(name)
    return type(system).__name__


def _nonzero(casimir_shift: object) -> bool:
    return isinstance(casimir_shift, str) or casimir_shift != 0


def _casimir_shift(flow: Flow) -> float | None:
    """The Casimir shift ``c`` a scheme is stepped with (part of a file's identity: a
    resume with another shift is refused), else None (files without one keep their
    identity)."""
    stepped = getattr(flow, "system", None)
    return stepped.c if isinstance(stepped, CasimirShifted) else None


def _file_sink(
    system: IsospectralSystem,
    scheme: Scheme | Flow,
    flow: Flow,
    solver: Solver | None,
    W0: Array,
    h: float,
    n_steps: int,
    *,
    save_every: int,
    warm_start: bool | int,
    out: str | os.PathLike[str],
    resume: bool,
    replace: bool,
) -> Sink:
    """``integrate(..., out=path)``: the sink registered for the path's suffix (the
    application's HDF5 trajectory writer for ``.h5``), opened for this run."""
    if isinstance(out, bytes) or not isinstance(out, (str, os.PathLike)) or not str(out):
        raise InputError(
            f"out must be a file path or a Sink (record, checkpoint, close, result), got {out!r}"
        )
    identity = run_identity(system=system, scheme=scheme, solver=solver, h=h,
                            save_every=save_every, warm_start=warm_start,
                            casimir_shift=_casimir_shift(flow))  # fmt: skip
    info = RunInfo(
        system=system,
        system_name=_system_name(system),
        scheme=flow.name,
        solver="" if solver is None else str(getattr(solver, "name", type(solver).__name__)),
        h=h,
        save_every=save_every,
        requested_steps=n_steps,
        identity=identity,
        W0=W0,
    )
    return open_sink(Path(out).absolute(), info, resume=resume, replace=replace)


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
        :class:`~lieflow.driver.Monitor` receives the progress instead.
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
        :mod:`lieflow.compiled`). ``"jax"``: the traced engine
        (:mod:`lieflow.engines.traced`, ``pip install jax``): the whole step compiled by
        ``jax.jit`` and run on the array's device, a chunk of steps per call (NumPy arrays
        run on JAX's default device). Both run the same iterations and stopping rule, give
        results equal to roundoff, hand a step they cannot finish to the numpy path, and
        raise :class:`InputError` naming what is missing or not supported. ``"auto"``
        (default): for NumPy arrays the compiled loops where supported, numba is installed
        and they are faster (``n <= 128``, complex ``n <= 96``, and at least 1000
        trajectory-steps, see :func:`lieflow.compiled.wins`: a function of the run alone, so
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
        (``lieflow run``'s ``[run] checkpoint = "saves"``).
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
    h = check_step_size(h)
    n_steps = _resolve_steps(h, steps, t_final)
    if (
        isinstance(save_every, bool)
        or not isinstance(save_every, (int, np.integer))
        or save_every < 1
    ):
        raise InputError(f"save_every must be a positive integer, got {save_every!r}")
    if save_every > MAX_STEPS:  # files store it as a 64-bit integer
        raise InputError(
            f"save_every = {save_every} is more than {MAX_STEPS} (2**53) steps. To fix: pass "
            "save_every=steps to keep the first and last states only"
        )
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
    if not isinstance(scheme, Scheme) and isinstance(scheme, Flow):
        if solver is not None or not warm_start or engine != "auto" or _nonzero(casimir_shift):
            raise InputError(
                "solver, warm_start, engine and casimir_shift configure a Scheme; a Flow "
                "carries its own (set them on its SchemeFlow parts)"
            )
        _check_types(system, scheme, None)
        W0a = _validated(system, W0)
        flow: Flow = scheme
    else:
        solver = DEFAULT_SOLVER if solver is None else solver
        _check_types(system, scheme, solver)
        W0a = _validated(system, W0)
        flow = scheme_flow(shifted(system, W0a, casimir_shift), scheme, solver, W0a, n_steps,
                           engine=engine, warm_start=warm_start)  # fmt: skip

    if out is not None and not is_numpy(W0a):
        raise InputError(
            "a run on arrays of another library (lieflow.backends) is kept in memory: its "
            "states reach the host a chunk at a time; streaming it to a file (out=) is not "
            "supported yet. To fix: leave out out=, or pass W0 as a numpy array"
        )
    monitor = _progress_monitor(progress)
    W0_device, W0a = W0a, to_numpy(W0a)  # states reach the host at the sinks, a chunk at a time
    cadence = (
        DEFAULT_CADENCE
        if type(checkpoint_seconds) is float and checkpoint_seconds == 1.0
        else driver.Cadence(seconds=checkpoint_seconds)
    )
    start, state = 0, None
    diag: Diagnostics | DeferredDiagnostics | None
    if out is None:
        _check_memory(MemorySink.saved_states(n_steps, save_every) * W0a.nbytes, n_steps,
                      save_every)  # fmt: skip
        # W0's diagnostics are computed with the first chunk's, in one batch
        diag = Diagnostics.deferred(system, W0a, save_every=save_every) if diagnostics else None
        sink: Sink = MemorySink(system, flow.name, h, W0a, n_steps, save_every, diag)
    else:
        # a file records every step's diagnostics, whatever ``diagnostics`` says
        diag = Diagnostics.of(system, W0a, save_every=save_every)
        if isinstance(out, Sink):
            sink = out
        else:
            sink = _file_sink(system, scheme, flow, solver, W0a, h, n_steps,
                              save_every=save_every, warm_start=warm_start, out=out,
                              resume=resume, replace=replace)  # fmt: skip
        point = getattr(sink, "start", None)
        if point is not None:
            try:
                start, W0a = point.step, point.W
                state = point.state(flow.init(W0a))
            except BaseException:  # the sink holds its file: release it, resumable
                sink.close("interrupted", None, 0.0)
                raise
    if start:  # resumed from a file (numpy arrays only): the checkpoint's state
        W0_device = W0a
    outcome = driver.run(flow, W0_device, h, n_steps, sinks=(sink,), diagnostics=diag,
                         save_every=save_every, start=start, state=state, monitor=monitor,
                         checkpoint=cadence, on_failure=on_failure)  # fmt: skip
    if outcome.status == "interrupted":
        raise KeyboardInterrupt
    result: Solution = sink.result()
    return result
