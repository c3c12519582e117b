"""Reading trajectory files: the states, the diagnostics, a system's extra diagnostics
and the checkpoint, each checked against the file's format and checksums, and every check a
resume makes before it touches a file (:func:`_verify_for_resume`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import attrs
import numpy as np

from ... import state_trees
from ...algebras import Array
from ...errors import LieflowError
from ...flows import WarmStart
from ..config import ConfigError, identity_changes
from ._format import (
    _DAMAGE,
    _DIGEST,
    _EXTRA,
    _HEADER_COPY,
    _LABELS,
    _LAYOUTS,
    _PER_STEP,
    _PER_UPDATE,
    _SCALARS,
    _SLOT_ATTRS,
    _STATE,
    _TINY,
    FORMAT,
    FORMAT_VERSION,
    _as_path,
    _h5py,
    _header_copy,
    _is_scale,
    _Layout,
    _plain,
    _where,
    checkpoint_digest,
)
from ._header import TrajectoryHeader
from ._lock import _RESUME_FIX, DamagedOutputError, _open, _Reading, salvage_fix

if TYPE_CHECKING:  # pragma: no cover
    import h5py


@attrs.frozen(eq=False)
class Checkpoint:
    """Where a run resumes (a :class:`lieflow.sinks.ResumePoint`): ``W`` after step ``step``
    and the flow's state then (what :meth:`lieflow.Flow.step` carries: a scheme's warm start,
    a splitting's tuple of them), stored leaf by leaf under ``warm/`` (:mod:`lieflow.state_trees`:
    ``leaves`` maps each leaf's path to its value)."""

    step: int
    t: float
    W: Array = attrs.field(repr=False)
    leaves: Mapping[str, Any] = attrs.field(repr=False)

    def state(self, template: Any) -> Any:
        """The flow's state, shaped like ``template`` (the flow's ``init(W0)``)."""
        return state_trees.rebuild(template, dict(self.leaves))

    @property
    def warm(self) -> WarmStart:
        """The state of a run of one scheme: its :class:`~lieflow.flows.WarmStart`, keeping
        as many solutions as the run did (``previous/0``, ``previous/1``, ... are stored,
        filled or not; older files store one ``previous`` array)."""
        kept = sum(1 for key in self.leaves if re.fullmatch(r"previous/\d+", key))
        state = self.state(WarmStart.keeping(kept + 1) if kept else WarmStart())
        return state if isinstance(state, WarmStart) else WarmStart()


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


def _check_format(f: h5py.File, path: Path) -> _Layout:
    """The layout of a lieflow trajectory file, or LieflowError for any other file (and
    DamagedOutputError for one whose header attributes do not read back)."""
    try:
        found = _plain(f.attrs.get("format"))
    except _DAMAGE as exc:
        raise _unreadable_header(path, exc) from None
    if found is None and _has_header_copy(f):  # ours, its attributes unreadable
        raise _unreadable_header(path, KeyError("format"))
    if found != FORMAT:
        raise LieflowError(
            f"{_where(path)} is not a lieflow trajectory file (no format = {FORMAT!r} "
            "attribute). To fix: pass a file written by `lieflow run`."
        )
    version = _plain(f.attrs.get("format_version", 1))
    layout = _LAYOUTS.get(version) if isinstance(version, int) else None
    if layout is None:
        raise LieflowError(
            f"{_where(path)} is a lieflow trajectory file of format version {version!r}, "
            f"which this lieflow cannot read (it reads versions 1 to {FORMAT_VERSION}). To "
            "fix: read it with the newer lieflow that wrote it (pip install -U lieflow)."
        )
    return layout


def format_version(path: Path | str) -> int:
    """The format version of a trajectory file (1: groups, no dimensions; 2: netCDF-4)."""
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        return _check_format(f, p).version


def _slot_items(slot: h5py.Group) -> dict[str, Any]:
    """Everything a checkpoint slot stores except step, t and the digest: datasets by path
    (arrays; dimension scales are not items) and the other values (version 1: one attribute
    each, ``"none"`` read back as ``None``; version 2: the JSON attribute ``scalars``)."""
    h5py = _h5py()
    items: dict[str, Any] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset) and not _is_scale(obj):
            items[name] = np.asarray(obj[()])

    slot.visititems(visit)
    for key, raw in slot.attrs.items():
        if key == _SCALARS:
            items.update(json.loads(_plain(raw)))
        elif key not in _SLOT_ATTRS:
            value = _plain(raw)
            items[key] = None if isinstance(value, str) and value == "none" else value
    return items


def _read_checkpoint(f: h5py.File, path: Path | None = None) -> Checkpoint:
    """The current checkpoint, its SHA-256 verified (files written before lieflow stored
    digests have none and are read as they are)."""
    where = _where(Path(f.filename) if path is None else path)
    group = f["checkpoint"]
    slot_id = int(group.attrs["current"])
    if slot_id not in (0, 1):
        raise LieflowError(
            f"{where} is damaged: its checkpoint pointer is {slot_id}, not 0 or 1. To fix: "
            f"{salvage_fix(Path(f.filename))}; or run the configuration again (--force)."
        )
    slot = group[f"slot{slot_id}"]
    step, t = int(slot.attrs["step"]), float(slot.attrs["t"])
    items = _slot_items(slot)
    stored = slot.attrs.get(_DIGEST)
    if stored is not None and _plain(stored) != checkpoint_digest(step, t, items):
        raise LieflowError(
            f"{where} is damaged: the checkpoint at step {step} does not match its SHA-256 "
            "checksum (its bytes changed on disk after lieflow wrote them), so continuing "
            "from it would silently continue a wrong state. To fix: "
            f"{salvage_fix(Path(f.filename))}; or restore the file from a backup, or run the "
            "configuration again from the start (--force)."
        )
    if "W" not in items:
        raise LieflowError(f"{where} is damaged: its checkpoint has no state W.")
    leaves = {
        key[len(_STATE) + 1 :]: value
        for key, value in items.items()
        if key == _STATE or key.startswith(f"{_STATE}/")
    }
    return Checkpoint(step, t, items["W"], MappingProxyType(leaves))


def _check_lengths(f: h5py.File, k: int, path: Path, layout: _Layout) -> None:
    """The diagnostics reach the checkpoint at step ``k`` (rows after it are dropped later)."""
    at = layout.paths
    per_step = [f[at[n]].shape[0] for n in (*_PER_STEP, *(("step",) if "step" in at else ()))]
    if min(per_step) < k + 1 or f[at["iterations"]].shape[0] < k + 1 + layout.update_row0:
        raise LieflowError(
            f"{_where(path)} is damaged: its diagnostics end before its checkpoint at step "
            f"{k}. To fix: {salvage_fix(Path(f.filename))}; or start the run again without "
            "--resume (use --force)."
        )


def _check_invariants(
    f: h5py.File, ck: Checkpoint, system: Any, path: Path, layout: _Layout
) -> None:
    """The checkpointed state reproduces the energy and Casimirs recorded for its step."""
    k = ck.step
    at = layout.paths
    H, C = system.hamiltonian(ck.W), system.casimirs(ck.W)
    H_rec, C_rec, H0 = f[at["energy"]][k], f[at["casimirs"]][k], f[at["energy"]][0]
    scale_H = np.maximum(np.maximum(np.abs(H_rec), np.abs(H0)), _TINY)
    scale_C = system.casimir_scale(f[at["W0"]][()])
    bad = []
    if np.shape(H) != np.shape(H_rec) or not np.all(np.abs(H - H_rec) <= 1e-10 * scale_H):
        bad.append(f"energy {np.max(H)!r} (recorded {np.max(H_rec)!r})")
    if np.shape(C) != np.shape(C_rec) or not np.all(np.abs(C - C_rec) <= 1e-10 * scale_C):
        bad.append("Casimirs")
    if bad:
        raise LieflowError(
            f"{_where(path)} is damaged: the state checkpointed at step {k} does not reproduce "
            f"the invariants recorded for that step ({', '.join(bad)}), so continuing from it "
            "would continue a wrong state. To fix: restore the file from a backup, or run the "
            "configuration again from the start (--force)."
        )


def _check_coordinates(f: h5py.File, k: int, path: Path, layout: _Layout) -> None:
    """Version 2: read the coordinate variables a reader does not otherwise read (so that
    their Fletcher-32 checksums are verified) and check the step axis counts ``0..k``."""
    if not layout.netcdf:
        return
    steps = f[layout.paths["step"]][: k + 1]
    for name in _LABELS:
        if name in f:
            f[name][()]
    if not np.array_equal(steps, np.arange(k + 1)):
        raise LieflowError(
            f"{_where(path)} is damaged: its step coordinate is not 0..{k}. To fix: restore "
            "it from a backup, or run the configuration again (--force)."
        )


def _readable_rows(ds: h5py.Dataset, rows: int | None = None) -> int:
    """How many of the first ``rows`` rows of ``ds`` (default: all) read back, every chunk's
    Fletcher-32 checksum verified and every chunk there in HDF5's chunk index (a damaged
    index entry makes a chunk read as zeros, silently): read chunk by chunk, so memory holds
    one chunk."""
    n = ds.shape[0] if rows is None else min(rows, ds.shape[0])
    if not ds.shape:
        try:
            ds[()]
        except _DAMAGE:
            return 0
        return 1
    size = (ds.chunks or (max(n, 1),))[0]
    for start in range(0, n, size):
        try:
            if ds.chunks:
                _chunk_at(ds, start)  # in the index, or it would read as zeros
            ds[start : min(start + size, n)]
        except _DAMAGE:
            return start
    return n


def _chunk_at(ds: h5py.Dataset, row: int) -> bytes:
    """The stored bytes of the chunk of ``ds`` holding ``row``, found in HDF5's chunk index
    as a read finds it: raises if the index has lost it (a flipped bit in a B-tree key:
    a plain read then returns the fill value, zeros, without an error)."""
    first = row // ds.chunks[0] * ds.chunks[0]
    return bytes(ds.id.read_direct_chunk((first,) + (0,) * (ds.ndim - 1))[1])


def _kept_rows(f: h5py.File, k: int, layout: _Layout) -> dict[str, tuple[h5py.Dataset, int]]:
    """Every dataset a file that ends at step ``k`` keeps, with the rows it keeps of it."""
    at = layout.paths
    rows: dict[str, tuple[h5py.Dataset, int]] = {}
    for name in (*_PER_STEP, *(("step",) if "step" in at else ())):
        rows[at[name]] = (f[at[name]], k + 1)
    for name in _PER_UPDATE:
        rows[at[name]] = (f[at[name]], k + 1 + layout.update_row0)
    n_saved = int(np.searchsorted(f[at["saved_step"]][()], k, side="right"))
    for name in ("saved_step", "time", "W"):
        rows[at[name]] = (f[at[name]], n_saved)
    rows[at["W0"]] = (f[at["W0"]], f[at["W0"]].shape[0] if f[at["W0"]].shape else 1)
    for name in _LABELS:
        if name in f:
            rows[name] = (f[name], f[name].shape[0])
    group = f.get(_EXTRA)
    if group is not None:
        n_extra = int(np.searchsorted(group["step"][()], k, side="right"))
        for ds in group.values():
            if not _is_scale(ds):
                rows[ds.name] = (ds, n_extra)
    return rows


def _check_kept(f: h5py.File, k: int, path: Path, layout: _Layout) -> None:
    """Read back every row a resume keeps (steps ``0..k``), so that a file whose data was
    damaged on disk is refused before it is continued, not reported ``complete``."""
    for name, (ds, rows) in _kept_rows(f, k, layout).items():
        good = _readable_rows(ds, rows)
        if good < rows:
            raise DamagedOutputError(
                f"{_where(path)} is damaged: {name!r} does not read back from row {good} on (a "
                "chunk fails its checksum or is lost from HDF5's chunk index; the file keeps "
                f"{rows} rows of it up to its checkpoint at step {k}; its bytes "
                "changed on disk, e.g. after a process was killed while it wrote). To fix: "
                f"{salvage_fix(path)}; or run the configuration again (--force)."
            )


def _has_header_copy(f: h5py.File) -> bool:
    """Whether ``initial/W0`` holds the copy of a trajectory file's header attributes."""
    try:
        return f["initial/W0"].attrs.get(_HEADER_COPY) is not None
    except _DAMAGE:
        return False


def _unreadable_header(path: Path, exc: BaseException) -> DamagedOutputError:
    return DamagedOutputError(
        f"{_where(path)} is damaged: its header attributes do not read back "
        f"({type(exc).__name__}: {exc}). To fix: {salvage_fix(path)}; or run the "
        "configuration again (--force)."
    )


def _check_attributes(f: h5py.File, path: Path) -> None:
    """Every header attribute reads back: a resume rewrites them as it closes the file, so
    one that does not (a flipped byte in the header) used to fail only after the resumed
    steps were written, leaving the file marked complete and unreadable."""
    try:
        meta = _header_attributes(f)
        raw = f["initial/W0"].attrs.get(_HEADER_COPY)
        copy = None if raw is None else json.loads(_plain(raw))
    except (*_DAMAGE, json.JSONDecodeError) as exc:
        raise _unreadable_header(path, exc) from None
    now = json.loads(_header_copy(meta))
    differ = [] if copy is None else sorted(k for k in now.keys() | copy.keys()
                                            if now.get(k) != copy.get(k))  # fmt: skip
    if differ:
        raise DamagedOutputError(
            f"{_where(path)} is damaged: its header attributes {', '.join(differ)} differ "
            f"from their copy written with the file (their bytes changed on disk). To fix: "
            f"{salvage_fix(path)}; or run the configuration again (--force)."
        )


def _visit_structure(group: h5py.Group) -> None:
    """Open every object under ``group`` and its attributes (their headers), not reading any
    dataset's data: what writing over them needs intact (data is overwritten whole)."""

    def visit(_: str, obj: Any) -> None:
        dict(obj.attrs)

    dict(group.attrs)
    group.visititems(visit)


def _check_spare(f: h5py.File, path: Path) -> None:
    """The spare checkpoint slot, where the next checkpoint goes, has an intact structure
    (a damaged one would fail that write half-way; damaged *data* there is harmless, as
    the next checkpoint overwrites it whole)."""
    group = f["checkpoint"]
    name = f"slot{1 - int(group.attrs['current'])}"
    try:
        _visit_structure(group[name])
    except _DAMAGE as exc:
        raise DamagedOutputError(
            f"{_where(path)} is damaged: its spare checkpoint slot {name!r}, where the next "
            f"checkpoint goes, does not read back ({type(exc).__name__}: {exc}). To fix: "
            f"{salvage_fix(path)}; or run the configuration again (--force)."
        ) from None


@contextmanager
def _opened(path: Path | str) -> Iterator[tuple[h5py.File, Checkpoint, _Layout]]:
    """A trajectory file open for reading, with its verified checkpoint and its layout;
    every reader's checks (format, checksums, diagnostics reaching the checkpoint) done
    once here."""
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        layout = _check_format(f, p)
        ck = _read_checkpoint(f, p)
        _check_lengths(f, ck.step, p, layout)
        _check_coordinates(f, ck.step, p, layout)
        yield f, ck, layout


def read_checkpoint(path: Path | str) -> Checkpoint:
    """The last checkpoint of a trajectory file (its SHA-256 checksum verified).

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, not a lieflow trajectory, or damaged.
    """
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        _check_format(f, p)
        return _read_checkpoint(f, p)


#: Root attributes that belong to the file format, not to the run (netCDF's provenance).
_HIDDEN_ATTRS = ("_NCProperties",)


def _header_attributes(f: h5py.File) -> dict[str, Any]:
    """The root attributes: the run's header (netCDF's own attributes left out)."""
    return {key: _plain(v) for key, v in f.attrs.items() if key not in _HIDDEN_ATTRS}


def read_trajectory(path: Path | str) -> Trajectory:
    """Read a trajectory file, up to its last checkpoint (anything after it is ignored).

    Every dataset lieflow writes carries HDF5's Fletcher-32 chunk checksums and the
    checkpoint a SHA-256 digest, so a file whose bytes changed on disk is refused rather
    than read as wrong numbers (files from lieflow versions before 0.2 have neither).
    Files of both format versions are read (see the module's docstring).

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, not a lieflow trajectory, or damaged.
    """
    with _opened(path) as (f, ck, layout):
        k = ck.step
        at = layout.paths
        saved = f[at["saved_step"]][()]
        n_saved = int(np.searchsorted(saved, k, side="right"))
        updates = layout.update_rows(k)
        return Trajectory(
            path=_as_path(path),
            meta=MappingProxyType(_header_attributes(f)),
            step=saved[:n_saved],
            t=f[at["time"]][:n_saved],
            W=f[at["W"]][:n_saved],
            energy=f[at["energy"]][: k + 1],
            energy_error=f[at["energy_error"]][: k + 1],
            casimirs=f[at["casimirs"]][: k + 1],
            casimir_drift=f[at["casimir_drift"]][: k + 1],
            iterations=f[at["iterations"]][updates],
            residual=f[at["residual"]][updates],
            checkpoint=ck,
        )


@attrs.frozen(eq=False)
class TrajectoryDiagnostics:
    """A trajectory file without its saved states (:func:`read_diagnostics`).

    Attributes
    ----------
    completed_steps : int
        The checkpoint's step index ``K``.
    W0, W : ndarray
        The initial state and the checkpointed state after step ``K``.
    energy_error, casimir_drift : ndarray
        Per-step diagnostics, steps ``0..K``.
    iterations : ndarray
        Solver updates of steps ``1..K``.
    """

    completed_steps: int
    W0: Array = attrs.field(repr=False)
    W: Array = attrs.field(repr=False)
    energy_error: Array = attrs.field(repr=False)
    casimir_drift: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)


def read_diagnostics(path: Path | str) -> TrajectoryDiagnostics:
    """The per-step diagnostics, the initial and the last checkpointed state of a trajectory
    file — everything but the saved states, so it fits in memory whatever the run's length.

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, not a lieflow trajectory, or damaged.
    """
    with _opened(path) as (f, ck, layout):
        k = ck.step
        at = layout.paths
        return TrajectoryDiagnostics(
            completed_steps=k,
            W0=f[at["W0"]][()],
            W=np.asarray(ck.W),
            energy_error=f[at["energy_error"]][: k + 1],
            casimir_drift=f[at["casimir_drift"]][: k + 1],
            iterations=f[at["iterations"]][layout.update_rows(k)],
        )


def read_extra(path: Path | str) -> dict[str, Array]:
    """The system's own diagnostics in a trajectory file (``/diagnostics/extra``): ``step``,
    ``t`` and one array per name, one row per sample up to the last checkpoint; empty if the
    system provides none (no ``extra_diagnostics`` method)."""
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        _check_format(f, p)
        k = _read_checkpoint(f, p).step
        group = f.get(_EXTRA)
        if group is None:
            return {}
        n = int(np.searchsorted(group["step"][()], k, side="right"))
        return {name: ds[:n] for name, ds in group.items() if not _is_scale(ds)}


def _verify_for_resume(header: TrajectoryHeader) -> Checkpoint:
    """Every check of a resume, on the file opened read-only: a refused file is not touched."""
    path = header.output
    from_config = bool(header.config_source)
    with _open(path, "r", _RESUME_FIX) as f, _Reading(path):
        layout = _check_format(f, path)
        _check_attributes(f, path)
        stored, now = str(_plain(f.attrs["identity"])), header.identity
        if stored != now:
            changed = "; ".join(identity_changes(stored, now)) or f"{stored} -> {now}"
            raise ConfigError(
                f"--resume: {_where(path)} was written by a different configuration; changed: "
                f"{changed}. To fix: "
                + (
                    "restore the configuration it was started with (only [run] steps or "
                    "t_final and output may change)"
                    if from_config
                    else "call integrate with the arguments it was started with (only steps "
                    "or t_final may change)"
                )
                + ", or write to a new output file.",
                "--resume",
            )
        if not np.array_equal(f[layout.paths["W0"]][()], header.W0):
            given = f"[initial] in {header.config_source}" if from_config else "W0"
            raise ConfigError(
                f"--resume: {_where(path)} starts from a different initial condition than "
                f"{given}. To fix: restore the initial condition it was started with, or "
                "write to a new output file.",
                "--resume",
            )
        ck = _read_checkpoint(f, path)
        _check_lengths(f, ck.step, path, layout)
        _check_coordinates(f, ck.step, path, layout)
        _check_invariants(f, ck, header.system, path, layout)
        _check_kept(f, ck.step, path, layout)
        _check_spare(f, path)
        if ck.step > header.requested_steps:
            raise ConfigError(
                f"--resume: {_where(path)} already holds {ck.step} steps, more than the "
                f"{header.requested_steps} asked for ([run] steps / t_final); resuming never "
                f"shortens a file. To fix: ask for at least {ck.step} steps to continue it, or "
                f"read its first {header.requested_steps} steps from the file as it is.",
                "[run] steps",
            )
    return ck
