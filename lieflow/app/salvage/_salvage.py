""":func:`salvage`: lock the damaged file, rebuild it next to itself, keep the original as
``FILE.damaged`` and put the new file in its place (a file that verifies is left as it is);
and what it returns, :class:`SalvageReport`."""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

import attrs

from ...errors import LieflowError
from ..io._format import _DAMAGE, _as_path, _where
from ..io._lock import _check_signature, _OutputLock
from ..io._reader import _check_attributes, _check_kept, _check_spare, _opened
from ._plan import _Plan
from ._reading import _source
from ._rebuild import _rebuild


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
    lost : tuple of str
        What of steps ``0..k`` did not read back (rows left as holes, saved states left out,
        attributes without a copy), one line each.
    repaired : tuple of str
        What was damaged and restored from a copy, one line each.
    """

    path: Path
    backup: Path | None
    recorded_steps: int
    kept_steps: int
    bit_for_bit: bool
    lost: tuple[str, ...] = ()
    repaired: tuple[str, ...] = ()

    def describe(self) -> str:
        """What was kept, lost and repaired, for the command line."""
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
        lines = [
            f"salvaged {str(self.path)!r}: kept steps 0..{self.kept_steps}{claimed}, {how}; "
            f"the damaged original is {str(self.backup)!r}"
        ]
        lines += [f"  lost: {line}" for line in self.lost]
        lines += [f"  repaired: {line}" for line in self.repaired]
        if not self.lost:
            lines.append("  every row of those steps read back intact")
        return "\n".join(lines)


_FIX = "give a file written by `lieflow run` or `lieflow.integrate(out=...)`"


#: Salvage writes next to the file: its lock, the salvaged copy, the damaged original's name.
_WRITABLE_FIX = (
    "salvage writes in the file's directory (a lock, the salvaged copy, the backup): make it "
    "writable, or copy the file to a directory you can write to and salvage the copy"
)


def salvage(path: Path | str) -> SalvageReport:
    """Rebuild a damaged trajectory file from what reads back (module doc).

    Parameters
    ----------
    path : Path or str
        The trajectory file. It is locked like a run's output, so a file another run is
        writing is refused (:class:`~lieflow.app.io.OutputBusyError`).

    Returns
    -------
    SalvageReport
        What was kept, lost and repaired; the original is kept as ``report.backup``.

    Raises
    ------
    LieflowError
        Not a lieflow trajectory file, or not even its step 0 (the initial condition, its
        energy and Casimirs) reads back: then only a new run (``--force``) helps.
    """
    p = _as_path(path)
    _check_signature(p, _FIX)
    lock = _OutputLock.acquire(p, _WRITABLE_FIX)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.salvage")
    try:
        intact = _intact_steps(p)
        if intact is not None:
            return SalvageReport(p, None, intact, intact, True)
        with _source(p) as (src, end):
            plan = _Plan.of(src, end, p)
            lost = _rebuild(src, end, plan, tmp)
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
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        lock.release()
    return SalvageReport(p, backup, plan.recorded, plan.k, plan.exact, lost, plan.repaired)


def _intact_steps(path: Path) -> int | None:
    """The steps of a file that passes every check of a resume (nothing to salvage), else
    None."""
    try:
        with _opened(path) as (f, ck, layout):
            _check_attributes(f, path)
            _check_kept(f, ck.step, path, layout)
            _check_spare(f, path)
            return ck.step
    except (LieflowError, *_DAMAGE):
        return None


def _free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2``, ... whichever does not exist."""
    candidate, i = path, 0
    while os.path.lexists(candidate):
        i += 1
        candidate = path.with_name(f"{path.name}.{i}")
    return candidate
