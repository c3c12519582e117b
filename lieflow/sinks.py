r"""Where a run's steps go: :class:`MemorySink` (a :class:`~lieflow.Solution`), the file
sinks found by suffix (:func:`open_sink`), and the :class:`Sink` protocol they follow (defined
by the loop that feeds them, :mod:`lieflow.stepping`, and importable from here).

:func:`lieflow.stepping.run` is the one consumer loop: it takes each
:class:`~lieflow.chunks.Chunk` of steps from :func:`lieflow.stepping.advance`, decides which
states are saved (every ``save_every``-th and the last), computes the diagnostics once
(:class:`~lieflow.chunks.ChunkDiagnostics`), and hands both to every sink. A sink only
stores: in memory (:class:`MemorySink`, this module), in an HDF5 trajectory file (the
application's ``TrajectorySink``, :mod:`lieflow.app.io`), or wherever a plugin writes.

A file format is found by its suffix in the plugin registry
(``registry.add_sink(".h5", factory)``, :meth:`lieflow.RegistryBuilder.add_sink`), so that
``integrate(out="run.h5")`` reaches the application's writer without the core importing the
application.

The stepping loop hands sinks chunks whose states are on the host already
(:func:`lieflow.stepping.run`
copies another library's states once per chunk); a flow's state held for a checkpoint may
still live on a device, and a sink copies it with :func:`to_host`.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, ClassVar, Protocol

import attrs
import numpy as np

from .algebras import Array
from .backends import to_numpy
from .chunks import Chunk, ChunkDiagnostics, DeferredDiagnostics, Diagnostics
from .errors import ConvergenceError, InputError
from .solution import Solution, Status
from .stepping import Ending, Sink  # the Sink protocol is the stepping loop's: what it feeds

__all__ = [
    "DEFAULT_SUFFIX",
    "Ending",
    "MemorySink",
    "ResumePoint",
    "RunInfo",
    "Sink",
    "SinkFactory",
    "describe",
    "open_sink",
    "run_identity",
    "to_host",
]


def to_host(x: Any) -> Array:
    """``x`` as a numpy array in host memory: the one device → host conversion of the sinks
    (:func:`lieflow.backends.to_numpy`: a no-op for numpy arrays, one copy for an array of
    another library)."""
    return to_numpy(x)


class ResumePoint(Protocol):
    """Where a resumable sink's stored run continues: the state ``W`` after step ``step``
    and the flow's state then."""

    @property
    def step(self) -> int: ...

    @property
    def W(self) -> Array: ...

    def state(self, template: Any) -> Any:
        """The flow's state, shaped like ``template`` (the flow's ``init(W)``)."""
        ...


@attrs.frozen(eq=False)
class RunInfo:
    """What a file sink records about a run besides its steps (its header).

    Attributes
    ----------
    system : IsospectralSystem
        The system (diagnostics, the resume checks).
    system_name, scheme, solver : str
        Registry names recorded with the run (``scheme``: the scheme's or flow's name).
    h : float
        Step size.
    save_every : int
        Every ``save_every``-th state is saved (and the last).
    requested_steps : int
        Steps asked for.
    identity : str
        JSON of everything that defines the trajectory except its length and location
        (:func:`run_identity`): a resume is refused unless the stored run's identity is the
        same.
    W0 : ndarray
        The initial condition.
    config_text, config_source : str
        The configuration the run was made from and where it came from (``lieflow run``;
        empty for :func:`lieflow.integrate`).
    """

    system: Any = attrs.field(repr=False)
    system_name: str
    scheme: str
    solver: str
    h: float
    save_every: int
    requested_steps: int
    identity: str = attrs.field(repr=False)
    W0: Array = attrs.field(repr=False)
    config_text: str = attrs.field(default="", repr=False)
    config_source: str = ""


def describe(obj: Any, depth: int = 0) -> Any:
    """A JSON-able description of ``obj`` for a run's identity: attrs classes field by
    field (``{"type": qualname, field: ...}``), arrays by dtype, shape and the first 16 hex
    digits of the SHA-256 of their bytes, numbers, strings, ``None`` and sequences as they
    are, anything else by ``repr`` (and by ``repr`` beyond six levels of nesting). A field
    whose metadata says ``identity=False`` (how a result is computed, not which: e.g.
    :attr:`FixedPoint.check_every <lieflow.solvers.FixedPoint>`) is left out."""
    if depth > 6:
        return repr(obj)
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        digest = hashlib.sha256(a.tobytes()).hexdigest()[:16]
        return f"array {a.dtype.str} {a.shape} sha256:{digest}"
    if isinstance(obj, (bool, int, float, str)) or obj is None:
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (tuple, list)):
        return [describe(x, depth + 1) for x in obj]
    if attrs.has(type(obj)):
        fields = {f.name: describe(getattr(obj, f.name), depth + 1)
                  for f in attrs.fields(type(obj))
                  if f.init and f.metadata.get("identity", True)}  # fmt: skip
        return {"type": type(obj).__qualname__, **fields}
    return repr(obj)


def run_identity(
    *, system: Any, scheme: Any, solver: Any, h: float, save_every: int, **more: Any
) -> str:
    """The identity of a run (:attr:`RunInfo.identity`): JSON, keys sorted, of everything
    that defines its trajectory except its length and location. Two runs with the same
    identity and initial condition compute the same steps, so one may resume the other's
    file (with more steps); the one definition for :func:`lieflow.integrate` (``out=``)
    and ``lieflow run`` / ``lieflow sweep``.

    Parameters
    ----------
    system, scheme, solver : object or mapping
        What steps: the objects (``integrate``: each :func:`describe`-d), or their
        descriptions as mappings (``lieflow run``: the configuration's ``name`` and
        ``params``), stored as they are.
    h : float
        Step size.
    save_every : int
        Save cadence (it decides which states the file holds).
    **more
        What else changes the steps (``warm_start``, ``splitting``, ``casimir_shift``),
        each described the same way; ``None`` leaves the key out, so files written before
        a key existed keep their identity.

    Returns
    -------
    str
        ``json.dumps`` of ``{"system", "scheme", "solver", "h", "save_every", **more}``
        with sorted keys (values it cannot encode as their ``str``).
    """
    parts = {"system": system, "scheme": scheme, "solver": solver, "h": h,
             "save_every": save_every}  # fmt: skip
    parts.update((k, v) for k, v in more.items() if v is not None)
    described = {k: v if isinstance(v, Mapping) else describe(v) for k, v in parts.items()}
    return json.dumps(described, sort_keys=True, default=str)


#: ``factory(path, run, resume=..., replace=...) -> Sink``: a file format's sink, registered
#: for a suffix; with ``resume`` it continues an existing file, and has a ``start``
#: (:class:`ResumePoint`, ``None`` for a new file).
SinkFactory = Callable[..., Sink]


#: The suffix whose sink writes a path that no registered sink claims by its suffix (the
#: trajectory format of ``lieflow run``, which takes any file name).
DEFAULT_SUFFIX = ".h5"


def open_sink(
    path: Path, run: RunInfo, *, resume: bool, replace: bool, make_directory: bool = False
) -> Sink:
    """The sink the registry holds for ``path``'s suffix (for another suffix, or none, the
    one for :data:`DEFAULT_SUFFIX`), opened for ``run``; ``make_directory``: a missing
    directory of ``path`` is created (``lieflow run``), else refused (a library call creates
    no directory its caller did not ask for).

    Raises
    ------
    InputError
        No installed plugin writes such files.
    """
    from .plugins import default_registry

    formats = default_registry().sinks
    entry = formats.get(path.suffix.lower()) or formats.get(DEFAULT_SUFFIX)
    if entry is None:
        known = ", ".join(sorted(formats)) or "none"
        raise InputError(
            f"no sink is registered to write {str(path)!r} (registered suffixes: {known}). "
            "To fix: reinstall lieflow so that its entry points are registered "
            "(pip install -e .; the application registers '.h5'), or pass a Sink object"
        )
    options = {"make_directory": True} if make_directory else {}  # (older factories: none)
    sink: Sink = entry.factory(path, run, resume=resume, replace=replace, **options)
    return sink


@attrs.define(eq=False)
class MemorySink:
    """Keeps a run in memory and builds its :class:`~lieflow.Solution`.

    Saved states go into one array allocated up front (``1 + steps // save_every`` states,
    plus the last), so memory is the saved states only; per-step iterations, solvers and
    diagnostics are kept for every step.

    Parameters
    ----------
    system : IsospectralSystem
        The system (stored on the :class:`~lieflow.Solution`).
    scheme : str
        The scheme's or flow's name.
    h : float
        Step size.
    W0 : ndarray
        The initial state (saved as step 0).
    steps : int
        Steps asked for.
    save_every : int
        Every ``save_every``-th state is saved (and the last): sizes the saved-state array.
    diagnostics : Diagnostics or DeferredDiagnostics, optional
        The run's diagnostics (:func:`lieflow.stepping.run` passes each chunk's to
        :meth:`record`; the per-step arrays, zero at step 0, are allocated at the first);
        ``None``: the solution has none.
    """

    #: Keeps nothing outside the process: no interrupts held while it closes (:class:`Sink`).
    durable: ClassVar[bool] = False
    system: Any
    scheme: str
    h: float
    W0: Array
    steps: int
    save_every: int = 1
    diagnostics: Diagnostics | DeferredDiagnostics | None = None
    _W: Array = attrs.field(init=False, repr=False)
    _k: Array = attrs.field(init=False, repr=False)
    _kept: int = attrs.field(init=False, default=1)
    _pending: bool = attrs.field(init=False, default=False)
    _iterations: Array = attrs.field(init=False, repr=False)
    _solvers: list[str] = attrs.field(init=False, factory=list, repr=False)
    _err: Array | None = attrs.field(init=False, default=None, repr=False)
    _drift: Array | None = attrs.field(init=False, default=None, repr=False)
    _extra: list[tuple[int, float, Mapping[str, Any]]] = attrs.field(init=False, factory=list)
    _done: int = attrs.field(init=False, default=0)
    _solution: Solution | None = attrs.field(init=False, default=None, repr=False)

    @staticmethod
    def saved_states(steps: int, save_every: int) -> int:
        """Slots for saved states: the initial one, every ``save_every``-th, and the last."""
        return 2 + steps // save_every

    def __attrs_post_init__(self) -> None:
        W0 = to_host(self.W0)
        n = self.saved_states(self.steps, self.save_every)
        self._W = np.empty((n, *W0.shape), dtype=W0.dtype)
        self._k = np.zeros(n, dtype=np.int64)
        self._W[0] = W0
        self._iterations = np.zeros(self.steps, dtype=np.int64)
        diag = self.diagnostics
        if diag is not None and diag.extra is not None:
            self._extra.append((0, 0.0, diag.extra(W0)))

    def _allocate(self, H0: tuple[int, ...], C0: tuple[int, ...]) -> None:
        """The per-step energy errors and Casimir drifts (zero at step 0), for energies of
        shape ``H0`` and Casimirs of shape ``C0``."""
        self._err = np.zeros((self.steps + 1, *H0))
        self._drift = np.zeros((self.steps + 1, *C0))

    def record(self, chunk: Chunk, keep: Array, diagnostics: ChunkDiagnostics | None) -> None:
        """Keep the chunk's saved states, iterations, solvers and diagnostics."""
        a, b = chunk.start, chunk.stop
        self._iterations[a:b] = to_host(chunk.iterations)
        self._solvers.extend(chunk.solvers)
        if diagnostics is not None and self.diagnostics is not None:
            if self._err is None or self._drift is None:
                self._allocate(diagnostics.energy.shape[1:], diagnostics.casimirs.shape[1:])
                assert self._err is not None and self._drift is not None
            self._err[a + 1 : b + 1] = diagnostics.energy_error
            self._drift[a + 1 : b + 1] = diagnostics.casimir_drift
            self._extra.extend(diagnostics.extra)
        n = self._kept
        index = keep.nonzero()[0]  # keep is 1-D (np.flatnonzero's wrapper costs ~1 µs)
        # every state kept (a one-step chunk, save_every=1): the chunk itself, no gathered copy
        if chunk.held is None:
            kept = chunk.W if index.size == keep.size else chunk.W[index]
        else:  # a chunk that holds some states only (a device flow's)
            kept = chunk.states(keep)
        self._W[n : n + index.size] = to_host(kept)
        self._k[n : n + index.size] = index + (a + 1)  # the step indices kept
        n += index.size
        self._kept = n
        # the last state computed so far is always at hand, in the spare slot after the kept
        self._pending = self._k[n - 1] != b
        if self._pending:
            self._W[n], self._k[n] = to_host(chunk.W[-1]), b
        self._done = b

    def checkpoint(self, *, keep_last: bool = False) -> None:
        """Nothing to make durable; ``keep_last`` saves the last recorded state."""
        if keep_last and self._pending:
            self._kept += 1
            self._pending = False

    def close(self, status: Ending, failure: ConvergenceError | None, wall_time: float) -> None:
        """Build the :class:`~lieflow.Solution` (the last state is always saved)."""
        self.checkpoint(keep_last=True)
        done, n = self._done, self._kept
        diag = self.diagnostics
        if diag is not None and self._err is None:  # no chunk was recorded
            # (deferred diagnostics, which no chunk started, give the initial state's)
            deferred = getattr(diag, "initial", None)
            initial: Any = deferred() if callable(deferred) else diag
            self._allocate(np.shape(initial.H0), np.shape(initial.C0))
        extra: dict[str, Array] = {}
        if self._extra:
            extra["step"] = np.array([e[0] for e in self._extra], dtype=np.int64)
            extra["t"] = np.array([e[1] for e in self._extra])
            for name in self._extra[0][2]:
                extra[name] = np.stack([to_host(e[2][name]) for e in self._extra])
        self._solution = Solution(
            system=self.system,
            scheme=self.scheme,
            h=self.h,
            t=self._k[:n] * self.h,
            W=self._W[:n],
            saved_steps=self._k[:n].copy(),
            iterations=self._iterations[:done],
            solvers=tuple(self._solvers),
            energy_error=None if self._err is None else self._err[: done + 1],
            casimir_drift=None if self._drift is None else self._drift[: done + 1],
            status=Status.SUCCESS if status == "complete" else Status.FAILED,
            failure=failure,
            wall_time=wall_time,
            extra=extra,
        )

    def result(self) -> Solution:
        """The :class:`~lieflow.Solution` (after :meth:`close`)."""
        if self._solution is None:
            raise InputError("MemorySink.result() before the run was closed")
        return self._solution
