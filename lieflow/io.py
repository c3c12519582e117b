"""HDF5 trajectory files: a writer that saves as the run proceeds, a reader, and resume.

File layout (format ``lieflow-trajectory``, format version 1)::

    /                         attributes: lieflow version, the configuration's full text and
                              identity, system / scheme / solver, h, save_every, requested
                              and completed steps, status, wall time, platform and versions
    /initial/W0               the initial condition
    /trajectory/step, t, W    saved states (every save_every-th step and the last)
    /diagnostics/energy       eta(W_k), k = 0..K            (one row per step, K = completed)
    /diagnostics/energy_error |eta(W_k) - eta(W_0)| / |eta(W_0)|
    /diagnostics/casimirs     Casimirs C_j(W_k), shape (K + 1, n_casimirs)
    /diagnostics/casimir_drift  |C_j(W_k) - C_j(W_0)| / ||W_0||^{k_j}
    /diagnostics/iterations   solver updates of steps 1..K
    /diagnostics/residual     last relative update of each step's solve
    /checkpoint/slot0, slot1  (W, warm) at a step, written alternately; the root group's
                              "current" attribute names the valid one and is set last

All datasets are chunked and resizable. Per-step diagnostics are buffered between saves; at
every save the buffers are appended, the state is checkpointed (step index, ``W`` and the
scheme's ``warm`` start) and the file is flushed. A run stopped at any moment — Ctrl-C, a
kill, a power cut after the last flush — therefore leaves a readable file whose checkpoint is
consistent, and :func:`run` with ``resume=True`` truncates whatever was written after the
checkpoint and continues bit-for-bit as if never stopped (same states, same diagnostics).
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol

import attrs
import numpy as np

from .algebras import Array
from .config import ConfigError, RunSetup
from .errors import ConvergenceError, LieflowError
from .integrate import Step, WarmStart, iterate

if TYPE_CHECKING:  # pragma: no cover
    import h5py

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "Checkpoint",
    "Monitor",
    "RunSummary",
    "Trajectory",
    "TrajectoryWriter",
    "environment",
    "read_checkpoint",
    "read_trajectory",
    "run",
]

FORMAT = "lieflow-trajectory"
FORMAT_VERSION = 1
_TINY = float(np.finfo(float).tiny)
_PER_STEP = ("energy", "energy_error", "casimirs", "casimir_drift")
_PER_UPDATE = ("iterations", "residual")


def _h5py() -> Any:
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is in the cli extra
        raise LieflowError(
            "HDF5 output needs the 'h5py' package. To fix: pip install 'lieflow[cli]'."
        ) from exc
    return h5py


def environment() -> dict[str, str]:
    """Versions and platform recorded in every output (lieflow, Python, numpy, scipy, h5py)."""
    import scipy

    from . import __version__

    info = {
        "lieflow_version": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }
    try:
        import h5py

        info["h5py"] = h5py.__version__
        info["hdf5"] = h5py.version.hdf5_version
    except ImportError:  # pragma: no cover
        pass
    return info


@attrs.frozen(eq=False)
class Checkpoint:
    """A resumable state: ``W`` after step ``step`` and the warm-start state of
    :func:`lieflow.iterate` (its default before the first step)."""

    step: int
    t: float
    W: Array = attrs.field(repr=False)
    warm: WarmStart = attrs.field(repr=False)


@attrs.frozen(eq=False)
class Trajectory:
    """The contents of a trajectory file (:func:`read_trajectory`).

    Attributes
    ----------
    path : Path
        The file.
    meta : Mapping
        Root attributes (configuration text, versions, status, ...).
    step, t, W : ndarray
        Saved states: step indices, times and states.
    energy, energy_error, casimirs, casimir_drift : ndarray
        Per-step diagnostics for steps ``0..completed_steps``.
    iterations, residual : ndarray
        Per-step solver updates and last relative update, steps ``1..completed_steps``.
    checkpoint : Checkpoint
        The last checkpoint.
    """

    path: Path
    meta: Mapping[str, Any] = attrs.field(repr=False)
    step: Array = attrs.field(repr=False)
    t: Array = attrs.field(repr=False)
    W: Array = attrs.field(repr=False)
    energy: Array = attrs.field(repr=False)
    energy_error: Array = attrs.field(repr=False)
    casimirs: Array = attrs.field(repr=False)
    casimir_drift: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    residual: Array = attrs.field(repr=False)
    checkpoint: Checkpoint

    @property
    def h(self) -> float:
        """Step size."""
        return float(self.meta["h"])

    @property
    def status(self) -> str:
        """``"running"`` (or killed), ``"interrupted"``, ``"failed"`` or ``"complete"``."""
        return str(self.meta["status"])

    @property
    def completed_steps(self) -> int:
        """Steps recorded (the checkpoint's step index)."""
        return self.checkpoint.step

    @property
    def step_times(self) -> Array:
        """Times ``k h`` of the per-step diagnostics, ``k = 0..completed_steps``."""
        return np.arange(self.completed_steps + 1) * self.h


def _open(path: Path, mode: str) -> h5py.File:
    h5py = _h5py()
    try:
        return h5py.File(path, mode)
    except FileNotFoundError:
        raise LieflowError(
            f"{str(path)!r} does not exist. To fix: check the path, or run the configuration first."
        ) from None
    except OSError as exc:
        raise LieflowError(
            f"cannot open {str(path)!r} as HDF5 ({exc}). To fix: check that it is a lieflow "
            "trajectory file and that no other process is writing it."
        ) from None


def _check_format(f: h5py.File, path: Path) -> None:
    if f.attrs.get("format") != FORMAT:
        raise LieflowError(
            f"{str(path)!r} is not a lieflow trajectory file (no format = {FORMAT!r} "
            "attribute). To fix: pass a file written by `lieflow run`."
        )


def _read_checkpoint(f: h5py.File) -> Checkpoint:
    slot = f["checkpoint"][f"slot{int(f['checkpoint'].attrs['current'])}"]
    return Checkpoint(
        int(slot.attrs["step"]), float(slot.attrs["t"]), slot["W"][()], _read_warm(slot)
    )


def _read_warm(slot: h5py.Group) -> WarmStart:
    """Rebuild the :class:`WarmStart` a checkpoint stored field by field: arrays as datasets
    ``warm/<field>``, other values as attributes (``"none"`` for ``None``); a field not
    stored (step 0) keeps its default."""
    values: dict[str, Any] = {}
    for field in attrs.fields(WarmStart):
        key = f"warm/{field.name}"
        if key in slot:
            values[field.name] = slot[key][()]
        elif key in slot.attrs:
            value = _plain(slot.attrs[key])
            values[field.name] = None if value == "none" else value
    return WarmStart(**values)


def read_checkpoint(path: Path | str) -> Checkpoint:
    """The last checkpoint of a trajectory file."""
    p = Path(path)
    with _open(p, "r") as f:
        _check_format(f, p)
        return _read_checkpoint(f)


def read_trajectory(path: Path | str) -> Trajectory:
    """Read a trajectory file, up to its last checkpoint (anything after it is ignored).

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, or not a lieflow trajectory.
    """
    p = Path(path)
    with _open(p, "r") as f:
        _check_format(f, p)
        ck = _read_checkpoint(f)
        k = ck.step
        saved = f["trajectory/step"][()]
        n_saved = int(np.searchsorted(saved, k, side="right"))
        d = f["diagnostics"]
        return Trajectory(
            path=p,
            meta=MappingProxyType({key: _plain(v) for key, v in f.attrs.items()}),
            step=saved[:n_saved],
            t=f["trajectory/t"][:n_saved],
            W=f["trajectory/W"][:n_saved],
            energy=d["energy"][: k + 1],
            energy_error=d["energy_error"][: k + 1],
            casimirs=d["casimirs"][: k + 1],
            casimir_drift=d["casimir_drift"][: k + 1],
            iterations=d["iterations"][:k],
            residual=d["residual"][:k],
            checkpoint=ck,
        )


def _plain(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _chunk_rows(row_bytes: int, target: int = 1 << 16) -> int:
    return max(1, min(1024, target // max(row_bytes, 1)))


def _growable(group: h5py.Group, name: str, row: Array, dtype: Any) -> None:
    row = np.asarray(row)
    group.create_dataset(
        name,
        shape=(0, *row.shape),
        maxshape=(None, *row.shape),
        dtype=dtype,
        chunks=(_chunk_rows(row.size * np.dtype(dtype).itemsize), *row.shape),
    )


class TrajectoryWriter:
    """Appends a run to an open trajectory file.

    Create one with :meth:`create` (a new file) or :meth:`reopen` (resume). Feed every step
    to :meth:`add`; call :meth:`save` at save points (it appends the buffered diagnostics,
    optionally the state, writes a checkpoint and flushes) and :meth:`close` at the end.
    Writes go to explicit positions, so a :meth:`save` interrupted half-way can simply be
    repeated.
    """

    def __init__(self, f: h5py.File, setup: RunSetup) -> None:
        self._f = f
        self._system = setup.system
        diag = f["diagnostics"]
        self._H0 = diag["energy"][0]
        self._C0 = diag["casimirs"][0]
        self._cscale = setup.system.casimir_scale(f["initial/W0"][()])
        # h5py path lookups cost tens of microseconds each: keep the handles
        self._diag = {name: diag[name] for name in (*_PER_STEP, *_PER_UPDATE)}
        self._traj = {name: f["trajectory"][name] for name in ("step", "t", "W")}
        self._ck = f["checkpoint"]
        self._slots = [self._ck["slot0"], self._ck["slot1"]]
        self._slot_data: list[dict[str, Any]] = [{}, {}]
        self._n_diag = self._diag["iterations"].shape[0] + 1  # rows committed (steps 0..K)
        self._n_saved = self._traj["step"].shape[0]
        self._buffer: list[tuple[Array, Array, int, float]] = []
        self._slot = int(self._ck.attrs["current"])
        self._step = int(self._slots[self._slot].attrs["step"])  # the checkpoint's step
        self._max_error = float(np.max(self._diag["energy_error"][: self._n_diag]))

    @property
    def path(self) -> Path:
        """The file being written."""
        return Path(self._f.filename)

    @property
    def max_energy_error(self) -> float:
        """Largest relative energy error recorded so far (buffered steps included)."""
        return self._max_error

    # -- creation --------------------------------------------------------------------------

    @classmethod
    def create(cls, setup: RunSetup) -> TrajectoryWriter:
        """Create ``setup.output`` holding the header and step 0.

        The file is written under a temporary name in the same directory and renamed when
        complete, so a failure leaves no partial file; an existing file is replaced.
        """
        h5py = _h5py()
        out = setup.output
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
        try:
            with h5py.File(tmp, "w") as f:
                _initialise(f, setup)
            os.replace(tmp, out)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return cls(_open(out, "r+"), setup)

    @classmethod
    def reopen(cls, setup: RunSetup) -> tuple[TrajectoryWriter, Checkpoint]:
        """Open ``setup.output`` to resume: check it belongs to this configuration, truncate
        everything written after its last checkpoint and return that checkpoint."""
        path = setup.output
        f = _open(path, "r+")
        try:
            _check_format(f, path)
            if f.attrs["identity"] != setup.config.identity():
                raise ConfigError(
                    f"--resume: {str(path)!r} was written by a different configuration "
                    f"(stored: {f.attrs['identity']}; now: {setup.config.identity()}). To fix: "
                    "restore the configuration it was started with (only [run] steps may "
                    "change), or write to a new output file.",
                    "--resume",
                )
            if not np.array_equal(f["initial/W0"][()], setup.W0):
                raise ConfigError(
                    f"--resume: {str(path)!r} starts from a different initial condition than "
                    f"[initial] in {setup.config.source}. To fix: restore the [initial] section "
                    "it was started with, or write to a new output file.",
                    "--resume",
                )
            ck = _read_checkpoint(f)
            _truncate(f, ck.step)
            f.attrs["resumes"] = int(f.attrs.get("resumes", 0)) + 1
            f.attrs["requested_steps"] = setup.config.run.steps
            f.flush()
        except BaseException:
            f.close()
            raise
        return cls(f, setup), ck

    # -- writing ---------------------------------------------------------------------------

    def _energy_error(self, H: Array) -> Array:
        """``|H - H0| / |H0|`` (as :attr:`lieflow.Solution.energy_error`)."""
        return np.abs(H - self._H0) / np.maximum(np.abs(self._H0), _TINY)

    def add(self, step: Step) -> float:
        """Buffer the diagnostics of ``step``; return its relative energy error."""
        W = step.W
        H = self._system.hamiltonian(W)
        C = self._system.casimirs(W)
        err = float(np.max(self._energy_error(H)))
        self._max_error = max(self._max_error, err)
        self._buffer.append((H, C, step.result.iterations, step.result.residual))
        return err

    def save(self, step: Step, *, state: bool) -> None:
        """Append the buffered diagnostics (up to ``step``), the state if ``state``, write a
        checkpoint at ``step`` and flush."""
        f, buf = self._f, self._buffer
        n0, n1 = self._n_diag, self._n_diag + len(buf)
        if n1 - 1 != step.index:
            raise LieflowError(  # pragma: no cover - internal consistency
                f"internal error: {len(buf)} buffered steps do not end at step {step.index}"
            )
        if buf:
            H = np.asarray([b[0] for b in buf])
            C = np.asarray([b[1] for b in buf])
            columns = {
                "energy": H,
                "energy_error": self._energy_error(H),
                "casimirs": C,
                "casimir_drift": np.abs(C - self._C0) / self._cscale,
                "iterations": np.asarray([b[2] for b in buf], dtype=np.int64),
                "residual": np.asarray([b[3] for b in buf], dtype=float),
            }
            for name, values in columns.items():
                start = n0 if name in _PER_STEP else n0 - 1
                ds = self._diag[name]
                ds.resize(start + len(values), axis=0)
                ds[start:] = values
        n_saved = self._n_saved
        if state:
            for name, value in (("step", step.index), ("t", step.t), ("W", step.W)):
                ds = self._traj[name]
                ds.resize(n_saved + 1, axis=0)
                ds[n_saved] = value
            n_saved += 1
        self._checkpoint(step.index, step.t, step.W, step.warm)
        f.flush()
        self._n_diag, self._n_saved = n1, n_saved
        buf.clear()

    def _checkpoint(self, index: int, t: float, W: Array, warm: WarmStart) -> None:
        slot_id = 1 - self._slot
        slot, cache = self._slots[slot_id], self._slot_data[slot_id]
        _put(slot, "W", W, cache)
        for field in attrs.fields(WarmStart):
            value = getattr(warm, field.name)
            key = f"warm/{field.name}"
            if isinstance(value, np.ndarray):
                _put(slot, key, value, cache)
                continue
            if key in slot:
                cache.pop(key, None)
                del slot[key]
            slot.attrs[key] = "none" if value is None else value
        slot.attrs["step"] = index
        slot.attrs["t"] = t
        self._f.flush()
        self._ck.attrs["current"] = slot_id  # the commit point
        self._slot, self._step = slot_id, index

    def close(self, status: str, wall_time: float, failure: str = "") -> None:
        """Record the final status and the time spent, and close the file."""
        f = self._f
        try:
            f.attrs["completed_steps"] = self._step
            f.attrs["status"] = status
            f.attrs["wall_time"] = float(f.attrs.get("wall_time", 0.0)) + wall_time
            f.attrs["failure"] = failure
            f.flush()
        finally:
            f.close()


def _put(group: h5py.Group, name: str, value: Array, cache: dict[str, Any]) -> None:
    """Write ``value`` to dataset ``name`` of ``group`` in place (``cache`` keeps handles)."""
    value = np.asarray(value)
    ds = cache.get(name)
    if ds is None and name in group:
        ds = cache[name] = group[name]
    if ds is not None and (ds.shape != value.shape or ds.dtype != value.dtype):
        del group[name]
        ds = None
    if ds is None:
        cache[name] = group.create_dataset(name, data=value)
    else:
        ds[...] = value


def _initialise(f: h5py.File, setup: RunSetup) -> None:
    cfg, system, W0 = setup.config, setup.system, setup.W0
    meta: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": cfg.text,
        "config_source": cfg.source,
        "identity": cfg.identity(),
        "system": cfg.system.name,
        "scheme": cfg.scheme.name,
        "solver": cfg.solver.name,
        "h": cfg.run.h,
        "save_every": cfg.run.save_every,
        "requested_steps": cfg.run.steps,
        "casimir_powers": [k for k in system.casimir_powers if k <= system.algebra.n],
        "completed_steps": 0,
        "status": "running",
        "wall_time": 0.0,
        "failure": "",
        "resumes": 0,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        **environment(),
    }
    for key, value in meta.items():
        f.attrs[key] = value
    f.create_group("initial").create_dataset("W0", data=W0)
    H0 = system.hamiltonian(W0)
    C0 = system.casimirs(W0)
    tr = f.create_group("trajectory")
    _growable(tr, "step", np.int64(0), np.int64)
    _growable(tr, "t", np.float64(0), np.float64)
    _growable(tr, "W", W0, W0.dtype)
    d = f.create_group("diagnostics")
    _growable(d, "energy", H0, np.float64)
    _growable(d, "energy_error", H0, np.float64)
    _growable(d, "casimirs", C0, np.float64)
    _growable(d, "casimir_drift", C0, np.float64)
    _growable(d, "iterations", np.int64(0), np.int64)
    _growable(d, "residual", np.float64(0), np.float64)
    for name, value in (
        ("energy", H0),
        ("energy_error", np.zeros_like(H0)),
        ("casimirs", C0),
        ("casimir_drift", np.zeros_like(C0)),
    ):
        d[name].resize(1, axis=0)
        d[name][0] = value
    for name, value in (("step", 0), ("t", 0.0), ("W", W0)):
        tr[name].resize(1, axis=0)
        tr[name][0] = value
    ck = f.create_group("checkpoint")
    for i in (0, 1):
        slot = ck.create_group(f"slot{i}")
        slot.create_dataset("W", data=W0)
        slot.attrs["step"] = 0
        slot.attrs["t"] = 0.0
    ck.attrs["current"] = 0


def _truncate(f: h5py.File, k: int) -> None:
    """Drop every row written after step ``k`` (a save the process did not finish)."""
    d = f["diagnostics"]
    for name in _PER_STEP:
        if d[name].shape[0] > k + 1:
            d[name].resize(k + 1, axis=0)
    for name in _PER_UPDATE:
        if d[name].shape[0] > k:
            d[name].resize(k, axis=0)
    if min(d[n].shape[0] for n in _PER_STEP) != k + 1 or d["iterations"].shape[0] != k:
        raise LieflowError(
            f"{f.filename!r} is damaged: its diagnostics end before its checkpoint at step "
            f"{k}. To fix: start the run again without --resume (use --force)."
        )
    tr = f["trajectory"]
    n = int(np.searchsorted(tr["step"][()], k, side="right"))
    for name in ("step", "t", "W"):
        tr[name].resize(n, axis=0)
    f.attrs["completed_steps"] = k


class Monitor(Protocol):
    """Receives progress while :func:`run` proceeds (a progress bar, or a test hook)."""

    def start(self, done: int, total: int) -> None:
        """Called once before stepping; ``done`` steps exist already (resume)."""
        ...

    def advance(self, step: Step, energy_error: float) -> None:
        """Called after each step is recorded (and saved, at save points)."""
        ...

    def stop(self) -> None:
        """Called once when stepping ends, however it ends."""
        ...


@attrs.frozen
class RunSummary:
    """How :func:`run` ended.

    Attributes
    ----------
    path : Path
        The trajectory file.
    status : str
        ``"complete"``, ``"interrupted"`` (Ctrl-C; resumable) or ``"failed"``.
    completed_steps, requested_steps : int
        Steps in the file and steps asked for.
    new_steps : int
        Steps computed by this call.
    wall_time : float
        Seconds this call spent stepping.
    max_energy_error : float
        Largest relative energy error in the file.
    failure : str
        The error message of a failed run.
    """

    path: Path
    status: str
    completed_steps: int
    requested_steps: int
    new_steps: int
    wall_time: float
    max_energy_error: float
    failure: str = ""


def run(
    setup: RunSetup,
    *,
    resume: bool = False,
    monitor: Monitor | None = None,
) -> RunSummary:
    """Integrate ``setup`` and write the trajectory to ``setup.output`` as it proceeds.

    Parameters
    ----------
    setup : RunSetup
        A validated run (:func:`lieflow.config.build`).
    resume : bool
        Continue the existing file from its last checkpoint (bit-for-bit the same as an
        uninterrupted run; ``[run] steps`` may have grown). Without an existing file the run
        starts afresh. Without ``resume`` an existing file is replaced.
    monitor : Monitor, optional
        Progress callbacks.

    Returns
    -------
    RunSummary
        ``status == "interrupted"`` after Ctrl-C (the file holds every step done).

    Raises
    ------
    ConfigError
        ``resume`` on a file of another configuration.
    LieflowError
        A step failed to converge (the file holds the steps before it, status "failed").
    """
    cfg = setup.config.run
    if resume and setup.output.exists():
        writer, ck = TrajectoryWriter.reopen(setup)
        W, warm, done = ck.W, ck.warm, ck.step
    else:
        writer = TrajectoryWriter.create(setup)
        W, warm, done = setup.W0, None, 0
    target = cfg.steps
    if done >= target:
        writer.close("complete", 0.0)
        return RunSummary(setup.output, "complete", done, target, 0, 0.0, writer.max_energy_error)

    def save_point(index: int) -> bool:
        return index % cfg.save_every == 0 or index == target

    status, failure, last = "running", "", None
    last_saved = done
    start = time.perf_counter()
    if monitor is not None:
        monitor.start(done, target)
    try:
        stream = iterate(setup.system, setup.scheme, W, cfg.h, setup.solver, start=done, warm=warm)
        for step in stream:
            last = step
            err = writer.add(step)
            if save_point(step.index):
                writer.save(step, state=True)
                last_saved = step.index
            if monitor is not None:
                monitor.advance(step, err)
            if step.index == target:
                status = "complete"
                break
    except KeyboardInterrupt:
        status = "interrupted"
    except ConvergenceError as exc:
        status, failure = "failed", str(exc)
    finally:
        wall = time.perf_counter() - start
        if monitor is not None:
            monitor.stop()
        try:
            if last is not None and last.index != last_saved:
                # Checkpoint what was computed (this also completes a save that was itself
                # interrupted: writes go to fixed positions). A failed run keeps its last state.
                state = save_point(last.index) or status == "failed"
                writer.save(last, state=state)
        finally:
            writer.close(status if status != "running" else "interrupted", wall, failure)
    completed = done if last is None else last.index
    summary = RunSummary(
        setup.output,
        status,
        completed,
        target,
        completed - done,
        wall,
        writer.max_energy_error,
        failure,
    )
    if status == "failed":
        raise LieflowError(
            f"{failure} The {completed} steps before the failure are saved in "
            f"{str(setup.output)!r} (status 'failed')."
        )
    return summary
