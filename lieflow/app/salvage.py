"""Salvage a damaged trajectory file: cut it back to its last verified checkpoint.

A trajectory file (:mod:`lieflow.app.io`) whose bytes were damaged on disk — a process killed
while HDF5 rewrote a chunk, a file truncated by a full disk or a bad copy, flipped bits —
is refused by ``lieflow run --resume`` and by every reader. :func:`salvage` (``lieflow
salvage FILE``) keeps what is still verified and makes the file resumable again:

1. Every dataset is read back chunk by chunk (each chunk's Fletcher-32 checksum verified)
   to find how many of its leading rows are intact. A file shorter than HDF5 recorded
   (truncated) is first padded with zeros to its recorded length, so that its intact
   beginning can be read (the padding fails every checksum it covers).
2. The restart point is a step ``k`` such that every row of steps ``0..k`` is intact: the
   later of the two checkpoint slots whose SHA-256 digest matches (the run then continues
   bit for bit as if never stopped; at most two saves' worth of steps are recomputed), or,
   only if neither is usable, the latest intact saved state (the run continues from it with
   a cold solver start: its later steps agree with an uninterrupted run to the solver's
   tolerance, not bit for bit).
3. Everything after step ``k`` is dropped, the checkpoint is set to ``k`` and the file is
   marked ``interrupted``; ``lieflow run CONFIG --resume`` then continues it.

The work is done on a copy: the damaged original is kept as ``FILE.damaged`` (or
``FILE.damaged.1``, ...) and the salvaged copy takes its name only when it is complete, so a
salvage that fails leaves the file as it was.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ..errors import LieflowError
from .io._format import (
    _DAMAGE,
    _EXTRA,
    _LABELS,
    _PER_STEP,
    _PER_UPDATE,
    _as_path,
    _h5py,
    _Layout,
    _plain,
    _where,
    checkpoint_digest,
)
from .io._lock import DamagedOutputError, _check_signature, _OutputLock
from .io._reader import (
    _check_format,
    _check_kept,
    _check_spare,
    _opened,
    _readable_rows,
    _slot_items,
)
from .io._writer import _renew_spare, _truncate, _write_slot

__all__ = ["SalvageReport", "salvage"]

_FIX = "give a file written by `lieflow run` or `lieflow.integrate(out=...)`"

#: Salvage writes next to the file: its lock, the salvaged copy, the damaged original's name.
_WRITABLE_FIX = (
    "salvage writes in the file's directory (a lock, the salvaged copy, the backup): make it "
    "writable, or copy the file to a directory you can write to and salvage the copy"
)


@attrs.frozen
class SalvageReport:
    """What :func:`salvage` kept.

    Attributes
    ----------
    path : Path
        The salvaged file (resumable with ``lieflow run CONFIG --resume``).
    backup : Path or None
        The damaged original, kept unchanged (None: the file verified, nothing was done).
    recorded_steps : int
        Steps the damaged file claimed (its ``completed_steps``; -1 if unreadable).
    kept_steps : int
        Steps kept: the restart point ``k``.
    bit_for_bit : bool
        Whether the restart point is a verified checkpoint (a resume continues bit for bit)
        rather than a saved state (a resume restarts the solver cold).
    """

    path: Path
    backup: Path | None
    recorded_steps: int
    kept_steps: int
    bit_for_bit: bool

    def describe(self) -> str:
        """One line for the command line."""
        if self.backup is None:
            return (
                f"{str(self.path)!r} verifies (every row and its checkpoints read back "
                f"intact, {self.kept_steps} steps): nothing to salvage, the file is unchanged"
            )
        how = (
            "from its last verified checkpoint: --resume continues bit for bit"
            if self.bit_for_bit
            else "from its last verified saved state (no verified checkpoint there): "
            "--resume restarts the solver cold, so later steps agree with an uninterrupted "
            "run to the solver's tolerance, not bit for bit"
        )
        claimed = f" of {self.recorded_steps}" if self.recorded_steps >= 0 else ""
        return (
            f"salvaged {str(self.path)!r}: kept steps 0..{self.kept_steps}{claimed}, {how}; "
            f"the damaged original is {str(self.backup)!r}"
        )


def salvage(path: Path | str) -> SalvageReport:
    """Cut a damaged trajectory file back to its last verified restart point (module doc).

    Parameters
    ----------
    path : Path or str
        The trajectory file. It is locked like a run's output, so a file another run is
        writing is refused (:class:`~lieflow.app.io.OutputBusyError`).

    Returns
    -------
    SalvageReport
        What was kept; the original is kept as ``report.backup``.

    Raises
    ------
    LieflowError
        Not a lieflow trajectory file, or nothing of it can be read (not even its header and
        initial condition): then only a new run (``--force``) helps.
    """
    p = _as_path(path)
    _check_signature(p, _FIX)
    lock = _OutputLock.acquire(p, _WRITABLE_FIX)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.salvage")
    try:
        intact = _intact_steps(p)
        if intact is not None:
            return SalvageReport(p, None, intact, intact, True)
        shutil.copyfile(p, tmp)
        _pad_truncated(tmp)
        recorded, kept, exact = _cut_back(tmp, p)
        backup = _free_name(p.with_name(f"{p.name}.damaged"))
        try:
            os.link(p, backup)
        except OSError:  # no hard links here: a copy
            shutil.copyfile(p, backup)
        os.replace(tmp, p)
    except OSError as exc:
        raise LieflowError(
            f"cannot salvage {_where(p)}: {exc.strerror or exc}. To fix: salvage needs as much "
            f"free space as the file; {_WRITABLE_FIX}."
        ) from None
    finally:
        tmp.unlink(missing_ok=True)
        lock.release()
    return SalvageReport(p, backup, recorded, kept, exact)


def _intact_steps(path: Path) -> int | None:
    """The steps of a file that passes every check of a resume (nothing to salvage), else
    None."""
    try:
        with _opened(path) as (f, ck, layout):
            _check_kept(f, ck.step, path, layout)
            _check_spare(f, path)
            return ck.step
    except LieflowError:
        return None


def _free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2``, ... whichever does not exist."""
    candidate, i = path, 0
    while os.path.lexists(candidate):
        i += 1
        candidate = path.with_name(f"{path.name}.{i}")
    return candidate


def _pad_truncated(path: Path) -> None:
    """Extend a file shorter than the length HDF5 recorded in it with zeros to that length
    (HDF5 refuses to open it otherwise; the zeros fail every checksum they cover)."""
    h5py = _h5py()
    try:
        h5py.File(path, "r").close()
    except OSError as exc:
        found = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", str(exc))
        if found is None or int(found.group(2)) <= int(found.group(1)):
            return  # not truncated: _cut_back reports what is wrong
        os.truncate(path, int(found.group(2)))


def _cut_back(tmp: Path, original: Path) -> tuple[int, int, bool]:
    """Cut the copy ``tmp`` back to its restart point: (steps recorded, kept, bit for bit)."""
    h5py = _h5py()
    try:
        f = h5py.File(tmp, "r+")
    except OSError as exc:
        raise _lost(original, exc) from None
    try:
        try:
            layout = _check_format(f, original)
            recorded = int(_plain(f.attrs.get("completed_steps", -1)))
            k, slot_id, W = _restart_point(f, layout, original)
            group = f["checkpoint"]
            if W is not None:  # a saved state: written to a slot, with no solver state
                slot_id = 1 - int(group.attrs["current"]) if int(group.attrs["current"]) in (
                    0, 1) else 0  # fmt: skip
                t = k * float(f.attrs["h"])
                _write_slot(group[f"slot{slot_id}"], k, t, {"W": W}, {})
            group.attrs["current"] = slot_id
            _truncate(f, k, layout)
            _renew_spare(f)  # the slot given up (if damaged) is where the next one goes
            f.attrs["status"] = "interrupted"
            f.attrs["salvaged"] = (
                f"cut back from step {recorded} to step {k} by `lieflow salvage` "
                + ("(a verified checkpoint)" if W is None else "(a saved state: cold restart)")
            )
            f.flush()
        finally:
            f.close()
    except LieflowError:
        raise
    except _DAMAGE as exc:
        raise _lost(original, exc) from None
    return recorded, k, W is None


def _lost(path: Path, exc: BaseException) -> DamagedOutputError:
    return DamagedOutputError(
        f"{_where(path)} cannot be salvaged: its HDF5 structure (not only its data) is "
        f"damaged ({type(exc).__name__}: {exc}), so no step of it can be verified. To fix: "
        "restore it from a backup, or run the configuration again from the start (--force)."
    )


def _restart_point(f: Any, layout: _Layout, path: Path) -> tuple[int, int, Any]:
    """A step ``k`` whose rows ``0..k`` are all intact and that has a verified state (the
    latest verified checkpoint slot, else the latest saved state): ``(k, slot id, None)``
    for a checkpoint slot, ``(k, -1, W_k)`` for a saved state (step 0: the initial
    condition)."""
    at = layout.paths
    limit = np.inf
    for name in (*_PER_STEP, *(("step",) if "step" in at else ())):
        limit = min(limit, _readable_rows(f[at[name]]) - 1)
    for name in _PER_UPDATE:
        limit = min(limit, _readable_rows(f[at[name]]) - 1 - layout.update_row0)
    for name in _LABELS:
        if name in f and _readable_rows(f[name]) < f[name].shape[0]:
            limit = -1
    if _readable_rows(f[at["W0"]]) < (f[at["W0"]].shape[0] if f[at["W0"]].shape else 1):
        limit = -1
    saved_ok = min(_readable_rows(f[at[n]]) for n in ("saved_step", "time", "W"))
    saved = f[at["saved_step"]][:saved_ok]
    if saved_ok < f[at["saved_step"]].shape[0]:  # a state after saved[-1] is unverified
        limit = min(limit, int(saved[-1]) if saved.size else -1)
    group = f.get(_EXTRA)
    if group is not None:
        ok = min(_readable_rows(ds) for ds in group.values())
        if ok < group["step"].shape[0]:
            steps = group["step"][:ok]
            limit = min(limit, int(steps[-1]) if steps.size else 0)
    if limit < 0:
        raise DamagedOutputError(
            f"{_where(path)} cannot be salvaged: not even its first step (the initial "
            "condition and its diagnostics) reads back intact. To fix: restore it from a "
            "backup, or run the configuration again from the start (--force)."
        )
    slots: list[tuple[int, int]] = []
    for i in (0, 1):
        try:
            slot = f["checkpoint"][f"slot{i}"]
            step, t = int(slot.attrs["step"]), float(slot.attrs["t"])
            items = _slot_items(slot)
            digest = _plain(slot.attrs.get("sha256"))
        except _DAMAGE:
            continue
        if "W" in items and digest == checkpoint_digest(step, t, items) and step <= limit:
            slots.append((step, i))
    best_slot = max(slots, default=(-1, -1))
    usable = saved[saved <= limit]
    if best_slot[0] >= 0:  # recomputing up to two saves' steps beats a cold restart
        return best_slot[0], best_slot[1], None
    if usable.size:
        return int(usable[-1]), -1, f[at["W"]][usable.size - 1]
    return 0, -1, f[at["W0"]][()]
