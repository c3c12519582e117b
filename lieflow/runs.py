r"""One run, decided once: :class:`RunSpec` — the one front door behind
:func:`lieflow.integrate` and ``lieflow run`` / ``lieflow sweep``.

A run is validated and set up in one place, :meth:`RunSpec.build`, whoever asks:

* its arguments checked (step size, number of steps or final time, save cadence, the
  system, scheme and solver, ``W0`` in the system's phase space);
* its **device** decided once: ``W0`` is placed there (:func:`lieflow.backends.place`; an
  array of another library stays where it is) before anything is written, so a device that
  is not there is refused with no file left behind;
* its **flow** built once, for the state as placed (:func:`lieflow.engines.scheme_flow`:
  the engine is chosen for that device), with the Casimir shift, and wrapped by the caller's
  ``compose`` (``lieflow run``'s ``[splitting]``);
* its **cadences** fixed: the states kept (``save_every``), the checkpoints
  (:class:`~lieflow.stepping.Cadence`), the diagnostics.

:meth:`RunSpec.execute` then runs it into sinks — a :class:`~lieflow.sinks.MemorySink`
(:meth:`RunSpec.memory_sink`), a trajectory file opened through
:func:`lieflow.sinks.open_sink` with :meth:`RunSpec.info`, any other
:class:`~lieflow.sinks.Sink` — through the one consumer loop (:func:`lieflow.stepping.run`).
**Resume** is decided there once too: a sink that continues a stored run has a ``start``
(:class:`~lieflow.sinks.ResumePoint`), whose state and warm start :meth:`execute` moves to
the run's device.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import ArrayLike

from . import _signals, state_trees, stepping
from .algebras import Array
from .backends import from_host, is_foreign_array, is_numpy, place, to_numpy
from .chunks import DeferredDiagnostics, Diagnostics
from .engines import Engine, scheme_flow
from .errors import InputError
from .flows import Flow
from .schemes.base import Scheme
from .sinks import MemorySink, RunInfo, Sink, run_identity
from .solvers.base import Solver
from .solvers.fixed_point import FixedPoint
from .stepping import Monitor, Outcome
from .systems.base import IsospectralSystem
from .systems.shifted import CasimirShifted, shifted

__all__ = ["DEFAULT_SOLVER", "MAX_STEPS", "RunSpec", "check_step_size", "resolve_steps"]

#: The solver of a run that names none: ``FixedPoint()`` (a frozen value, built once: its
#: stopping rule's validators cost 6 µs a call).
DEFAULT_SOLVER = FixedPoint()

#: The checkpoint cadence of ``checkpoint_seconds=1.0`` (the default), built once (a frozen
#: value: its validators cost ~1 µs a call).
DEFAULT_CADENCE = stepping.Cadence(seconds=1.0)

#: The most steps a run may ask for (indices and times stay exact in 64-bit integers).
MAX_STEPS = 2**53

#: A run whose saved states need more than this fraction of the available memory is refused.
MEMORY_FRACTION = 0.5
#: Saved states up to this many bytes are never checked against the available memory.
_SMALL_RUN = 1 << 26


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


def resolve_steps(h: float, steps: int | None, t_final: float | None) -> int:
    """The number of steps of a run given ``steps`` or ``t_final`` (exactly one), checked."""
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


def _check_save_every(save_every: int) -> int:
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
    return int(save_every)


def _not_a_class(value: object, what: str) -> None:
    """Refuse a class passed where an instance is expected (``solver=FixedPoint``)."""
    if isinstance(value, type):
        raise InputError(
            f"{what} must be an instance, got the class {value.__name__}; "
            f"pass an instance: {value.__name__}()"
        )


def check_types(system: object, scheme: object, solver: object) -> None:
    """Refuse a system that is not an :class:`~lieflow.IsospectralSystem`, a scheme that is
    neither a :class:`~lieflow.Scheme` nor a :class:`~lieflow.flows.Flow`, and a solver
    without ``name`` and ``solve`` (``None``: none needed), naming what to pass."""
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


def validated(system: IsospectralSystem, W0: ArrayLike) -> Array:
    """``W0`` checked to lie in ``system``'s phase space (an array of another library is
    checked through a host copy, and returned as it came)."""
    if is_foreign_array(W0):  # an array of another library (lieflow.backends)
        return from_host(validated(system, to_numpy(W0)), W0)
    W0a = system.validate(W0)
    if W0a.size == 0:
        raise InputError(
            f"W0 is an empty stack of states (shape {W0a.shape}); pass at least one n x n state"
        )
    return W0a


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


def check_memory(nbytes: int, steps: int, save_every: int) -> None:
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


def _cadence(seconds: float | None) -> stepping.Cadence:
    """The checkpoint cadence of ``seconds`` (``None``: at every chunk holding a saved
    state)."""
    if type(seconds) is float and seconds == 1.0:
        return DEFAULT_CADENCE
    return stepping.Cadence(seconds=seconds)


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


@attrs.frozen(eq=False)
class RunSpec:
    """A run, validated and set up once (module docstring); build it with :meth:`build`.

    Attributes
    ----------
    system : IsospectralSystem
        The system whose diagnostics the run records (the flow may step a Casimir-shifted
        form of it).
    flow : Flow
        What steps: a scheme's flow on the engine chosen for :attr:`W0_device`, or the
        caller's flow.
    W0, W0_device : array
        The initial state on the host (NumPy, validated), and where the run starts it:
        the same array on the CPU, its copy on :attr:`device`, or the caller's own array
        of another library.
    h : float
        Step size.
    steps : int
        Index of the last step.
    save_every : int
        Every ``save_every``-th state is saved (and the last).
    diagnostics : bool
        Whether the energy and Casimirs of every step are recorded (a file records them
        whatever this says).
    checkpoint : Cadence
        When the sinks make what they recorded durable (the resume point).
    device : str
        Where the run lives: ``"cpu"``, a device name (:func:`lieflow.backends.place`), or
        ``"array"`` (``W0`` came as an array of another library and stays on its device).
    identity : str or None
        What defines the trajectory besides its length and location
        (:func:`lieflow.sinks.run_identity`): a file resumes only a run of the same identity.
        ``None``: described from :attr:`described` when a sink asks (:meth:`info`), not on
        every call (a description costs about as much as a small step).
    names : tuple of str, or None
        The names a file records (system, scheme, solver: the registry's); ``None``: looked
        up when a sink asks.
    described : dict
        The objects and settings :func:`~lieflow.sinks.run_identity` describes (scheme,
        solver, ``h``, ``save_every``, ``warm_start``, the Casimir shift).
    """

    system: IsospectralSystem
    flow: Flow
    W0: Array = attrs.field(repr=False)
    W0_device: Array = attrs.field(repr=False)
    h: float
    steps: int
    save_every: int = 1
    diagnostics: bool = True
    checkpoint: stepping.Cadence = DEFAULT_CADENCE
    device: str = "cpu"
    identity: str | None = attrs.field(default=None, repr=False)
    names: tuple[str, str, str] | None = None
    described: dict[str, Any] = attrs.field(factory=dict, repr=False)

    @classmethod
    def build(
        cls,
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
        engine: Engine = "auto",
        checkpoint_seconds: float | None = 1.0,
        casimir_shift: float | Literal["auto"] = 0.0,
        device: str | None = None,
        compose: Callable[[Flow], Flow] | None = None,
        identity: str | None = None,
        names: tuple[str, str, str] | None = None,
    ) -> RunSpec:
        """Validate a run and set it up (the module docstring says what is decided here).

        The arguments are :func:`lieflow.integrate`'s; besides them, ``device`` places
        ``W0`` on a device before anything else (``None``: where ``W0`` is), ``compose``
        wraps the scheme's flow (``lieflow run``'s ``[splitting]`` around it), and
        ``identity`` and ``names`` (system, scheme, solver) are those a configuration
        gives; by default they are described from the objects.

        Raises
        ------
        InputError
            A bad argument, named; a device that is not there.
        """
        h = check_step_size(h)
        n_steps = resolve_steps(h, steps, t_final)
        save_every = _check_save_every(save_every)
        is_flow = not isinstance(scheme, Scheme) and isinstance(scheme, Flow)
        if is_flow:
            if solver is not None or not warm_start or engine != "auto" or _nonzero(casimir_shift):
                raise InputError(
                    "solver, warm_start, engine and casimir_shift configure a Scheme; a Flow "
                    "carries its own (set them on its SchemeFlow parts)"
                )
            check_types(system, scheme, None)
        else:
            solver = DEFAULT_SOLVER if solver is None else solver
            check_types(system, scheme, solver)
        cadence = _cadence(checkpoint_seconds)
        W0_checked = validated(system, W0)
        W0_host = to_numpy(W0_checked)
        if device is None:
            where, W0_device = ("cpu" if is_numpy(W0_checked) else "array"), W0_checked
        else:  # the one placement: a device that is not there is refused here
            where, W0_device = device, (W0_host if device == "cpu" else place(W0_host, device))
        if is_flow:
            flow: Flow = scheme  # type: ignore[assignment]
            shift = None
        else:
            stepped = shifted(system, W0_host, casimir_shift)
            assert solver is not None
            flow = scheme_flow(stepped, scheme, solver, W0_device, n_steps,  # type: ignore[arg-type]
                               engine=engine, warm_start=warm_start)  # fmt: skip
            shift = stepped.c if isinstance(stepped, CasimirShifted) else None
        if compose is not None:
            flow = compose(flow)
        described = dict(system=system, scheme=scheme, solver=solver, h=h, save_every=save_every,
                         warm_start=warm_start, casimir_shift=shift)  # fmt: skip
        return cls(system, flow, W0_host, W0_device, h, n_steps, save_every, diagnostics,
                   cadence, where, identity, names, described)  # fmt: skip

    def info(self, **more: Any) -> RunInfo:
        """What a file sink records about the run besides its steps
        (:class:`~lieflow.sinks.RunInfo`); ``more``: the fields of a sink's own header
        (``lieflow run``'s configuration text and source, ...)."""
        names = self.names
        if names is None:
            solver = self.described.get("solver")
            solver_name = (
                "" if solver is None else str(getattr(solver, "name", type(solver).__name__))
            )
            names = (_system_name(self.system), self.flow.name, solver_name)
        identity = run_identity(**self.described) if self.identity is None else self.identity
        return RunInfo(
            system=self.system,
            system_name=names[0],
            scheme=names[1],
            solver=names[2],
            h=self.h,
            save_every=self.save_every,
            requested_steps=self.steps,
            identity=identity,
            W0=self.W0,
            **more,
        )

    def memory_sink(self) -> MemorySink:
        """A :class:`~lieflow.sinks.MemorySink` for this run (its saved states must fit in
        memory: checked here)."""
        check_memory(MemorySink.saved_states(self.steps, self.save_every) * self.W0.nbytes,
                     self.steps, self.save_every)  # fmt: skip
        return MemorySink(self.system, self.flow.name, self.h, self.W0, self.steps,
                          self.save_every, self._diagnostics(durable=False))  # fmt: skip

    def _diagnostics(self, *, durable: bool) -> Diagnostics | DeferredDiagnostics | None:
        """The run's diagnostics: always where a sink keeps them outside the process (a
        file records every step's); else only if asked, and then computed with the first
        chunk's (one batch)."""
        if durable:
            return Diagnostics.of(self.system, self.W0, save_every=self.save_every)
        if not self.diagnostics:
            return None
        return Diagnostics.deferred(self.system, self.W0, save_every=self.save_every)

    def execute(
        self,
        sinks: Sequence[Sink],
        *,
        monitor: Monitor | None = None,
        on_failure: Literal["raise", "truncate"] = "truncate",
        interrupts: _signals.Interrupts | None = None,
    ) -> Outcome:
        """Run into ``sinks`` (:func:`lieflow.stepping.run`), from the resume point of the
        first sink if it continues a stored run (its state and warm start placed where the
        run lives), else from :attr:`W0_device`. Every sink is closed, however the run
        ends; a sink that fails to give its resume point is closed first (resumable)."""
        W, start, state = self.W0_device, 0, None
        point = getattr(sinks[0], "start", None) if sinks else None
        if point is not None:
            try:
                start, W_host = point.step, point.W
                state = point.state(self.flow.init(W_host))
                if self.device != "cpu":  # placed once, where the run lives
                    like = self.W0_device
                    W = from_host(np.asarray(W_host), like)
                    state = state_trees.map_leaves(
                        lambda x: from_host(x, like) if isinstance(x, np.ndarray) else x, state
                    )
                else:
                    W = W_host
            except BaseException:  # the sinks hold their files: release them, resumable
                for sink in sinks:
                    sink.close("interrupted", None, 0.0)
                raise
        durable = any(getattr(sink, "durable", True) for sink in sinks)
        return stepping.run(self.flow, W, self.h, self.steps, sinks=sinks,
                          diagnostics=self._diagnostics(durable=durable),
                          save_every=self.save_every, start=start, state=state,
                          monitor=monitor, checkpoint=self.checkpoint,
                          on_failure=on_failure, interrupts=interrupts)  # fmt: skip
