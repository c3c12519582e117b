"""Who may touch an output file, and what is wrong with one: the exclusive output lock
(:class:`_OutputLock`), opening a file with a busy, damaged or missing file told apart
(:func:`_open`, :class:`_Reading`), and the errors for each (busy, damaged, disk full).
"""

from __future__ import annotations

import errno
import os
import re
import socket
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from ...errors import LieflowError
from ._format import _DAMAGE, _HDF5_SIGNATURE, _h5py, _where

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no advisory locks (see _OutputLock)
    fcntl = None  # type: ignore[assignment]

if TYPE_CHECKING:  # pragma: no cover
    import h5py


class OutputBusyError(LieflowError):
    """Another process is writing the output file (or holds its lock)."""


class DiskFullError(LieflowError):
    """The disk filled up while a trajectory file was written; the file keeps its last
    checkpoint, and the same command continues it once space is freed."""


#: What h5py raises when a write fails: OSError from a write, RuntimeError from a flush or
#: a close whose metadata cache could not be written.
_WRITE_ERRORS = (OSError, RuntimeError)


def _no_space(exc: BaseException) -> bool:
    """Whether ``exc`` (or what it was raised from) is a full disk or an exceeded quota."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        text = str(exc)
        if "No space left on device" in text or "errno = 28," in text or "quota" in text.lower():
            return True
        exc = exc.__cause__ or exc.__context__  # type: ignore[assignment]
    return False


def _disk_full(path: Path, steps: int | None = None) -> DiskFullError:
    kept = (
        f"the file keeps its last checkpoint (step {steps}); nothing before it is lost"
        if steps is not None
        else "nothing was changed or lost"
    )
    return DiskFullError(
        f"no space left on device writing {_where(path)}: {kept}. To fix: free space on that "
        "disk and run the same command again to continue (`lieflow run CONFIG --resume`, or "
        "integrate(..., out=..., resume=True))."
    )


class DamagedOutputError(LieflowError):
    """The output file's bytes are damaged: a checksum does not match, its structure is
    broken, or a process killed during a write left part of it unreadable."""


def _check_signature(path: Path, fix: str) -> None:
    """Refuse a path that is missing, a directory, empty or not HDF5, reading 8 bytes only
    (nothing is opened for writing, so a refused file is left exactly as it was)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(_HDF5_SIGNATURE))
    except FileNotFoundError:
        raise LieflowError(
            f"{_where(path)} does not exist. To fix: check the path, or run the configuration "
            "first."
        ) from None
    except IsADirectoryError:
        raise LieflowError(
            f"{_where(path)} is a directory, not a trajectory file. To fix: give the path of "
            "the .h5 file written by `lieflow run`."
        ) from None
    except OSError as exc:
        raise LieflowError(
            f"cannot read {_where(path)}: {exc.strerror or exc}. To fix: check the path and "
            "its permissions."
        ) from None
    if not head:
        raise LieflowError(
            f"{_where(path)} is empty (0 bytes), not a lieflow trajectory file (lieflow never "
            f"leaves an empty file: it writes under a temporary name first). To fix: {fix}."
        )
    if head != _HDF5_SIGNATURE:
        raise LieflowError(
            f"{_where(path)} is not an HDF5 file (it does not start with the HDF5 signature), "
            f"so it is not a lieflow trajectory file. To fix: {fix}."
        )


_READ_FIX = "check the path; give a file written by `lieflow run`"


_RESUME_FIX = (
    "check the path; to start a new run there instead, drop --resume and pass --force "
    "(which replaces the file)"
)


#: HDF5's chunk cache per open dataset, in bytes. None: the writer stores whole chunks (a state, a
#: checkpoint slot's arrays, a chunk of diagnostic rows per save) and reads whole datasets,
#: so a cache would only hold memory — HDF5 keeps a chunk-sized buffer for every dataset
#: it cached (measured: one state per open slot dataset, 12 of them with five-deep warm
#: starts, which took a streamed N = 512 run from 15 to 28 states of peak memory).
_CHUNK_CACHE_BYTES = 0


def _open(path: Path, mode: str, fix: str = _READ_FIX) -> h5py.File:
    h5py = _h5py()
    _check_signature(path, fix)
    try:
        return h5py.File(path, mode, rdcc_nbytes=_CHUNK_CACHE_BYTES)
    except FileNotFoundError:
        raise LieflowError(
            f"{_where(path)} does not exist. To fix: check the path, or run the configuration "
            "first."
        ) from None
    except OSError as exc:
        if _HDF5_LOCKED.search(str(exc)):
            raise OutputBusyError(
                f"cannot open {_where(path)}: another process has it open for writing "
                f"({exc}). To fix: wait until that run has finished, or stop it first."
            ) from None
        what = "truncated (shorter than HDF5 recorded)" if "truncated file" in str(exc) else (
            "damaged")  # fmt: skip
        raise DamagedOutputError(
            f"cannot open {_where(path)} as HDF5: the file is {what} ({exc}). To fix: "
            f"{salvage_fix(path)}; or {fix}."
        ) from None


#: HDF5's own message when another process holds its lock on the file: the only open
#: error that means "busy" (a truncated file's message names ``sblock``, not a lock).
_HDF5_LOCKED = re.compile(r"unable to lock file", re.IGNORECASE)


def salvage_fix(path: Path) -> str:
    """The fix offered for a damaged trajectory file: :func:`lieflow.app.salvage.salvage`."""
    return (
        f"`lieflow salvage {path}` keeps every row that reads back and repairs what has a "
        "copy (the damaged original is kept next to it), then continue it with --resume"
    )


def _damaged(path: Path, exc: BaseException) -> DamagedOutputError:
    return DamagedOutputError(
        f"{_where(path)} is damaged: reading it failed ({type(exc).__name__}: {exc}). Its "
        "bytes were changed on disk (a checksum did not match, e.g. after a process was "
        "killed while it wrote, or its structure is broken). "
        f"To fix: {salvage_fix(path)}; or restore it from a backup, or run the configuration "
        "again (--force)."
    )


class _Reading:
    """``with _Reading(path):`` turns h5py's errors on a damaged file into one LieflowError."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        return None

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: Any
    ) -> Literal[False]:
        if exc is None or isinstance(exc, LieflowError) or not isinstance(exc, _DAMAGE):
            return False
        if _no_space(exc):
            raise _disk_full(self.path) from None
        raise _damaged(self.path, exc) from None


# -- one writer per output file ------------------------------------------------------------


#: What to do when an output's file or lock cannot be created.
_OUTPUT_FIX = (
    "choose an output path in a directory you can write to (not under /proc, /sys or /dev)"
)


def _cannot_create(path: Path, exc: OSError) -> LieflowError:
    return LieflowError(
        f"cannot create {_where(path)}: {exc.strerror or exc}. To fix: {_OUTPUT_FIX}."
    )


def _cannot_lock(path: Path, exc: OSError, fix: str) -> LieflowError:
    """The lock of ``path`` (a file beside it) cannot be created or taken."""
    return LieflowError(
        f"cannot lock {_where(path)} (its lock file beside it): {exc.strerror or exc}. To "
        f"fix: {fix}."
    )


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


class _OutputLock:
    """An exclusive advisory lock on an output path, held for a whole run.

    The lock is ``flock`` on a sidecar file ``.<name>.lock`` in the output's directory
    (HDF5 takes its own locks on the data file itself, and those are released whenever the
    library closes it), holding the owner's pid and host. :meth:`release` removes the
    sidecar while still holding the lock; the kernel releases it when the process dies, however
    it dies, so a leftover sidecar never blocks a later run. A process that locked a
    sidecar its previous holder had just removed notices (the path no longer names the file
    it locked) and tries again. Without ``fcntl`` (Windows) there is no lock.
    """

    def __init__(self, path: Path, fd: int | None) -> None:
        self.path = path
        self._fd = fd

    @classmethod
    def acquire(cls, output: Path, fix: str = _OUTPUT_FIX) -> _OutputLock:
        """Lock ``output`` (``fix``: what to do if its lock cannot be created there)."""
        real = Path(os.path.realpath(output))  # one lock whatever symlink names the file
        lock_path = real.with_name(f".{real.name}.lock")
        if fcntl is None:  # pragma: no cover - not POSIX
            return cls(lock_path, None)
        for _ in range(100):
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            except OSError as exc:
                raise _cannot_lock(output, exc, fix) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                if isinstance(exc, BlockingIOError):
                    raise OutputBusyError(
                        f"{_where(output)} is being written by another lieflow run ({holder}); "
                        "two runs writing one file would lose one of the results, so this "
                        "one is refused (--force and --resume too). To fix: wait until that "
                        "run has finished or stop it, or write to another output (--out)."
                    ) from None
                raise _cannot_lock(output, exc, fix) from None
            if _same_file(fd, lock_path):
                os.ftruncate(fd, 0)
                os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
                return cls(lock_path, fd)
            os.close(fd)  # its previous holder removed it after we opened it: try again
        raise OutputBusyError(  # pragma: no cover - needs 100 lost races in a row
            f"could not lock {_where(output)}: other processes keep taking its lock. To fix: "
            "make sure one run at a time writes this file."
        )

    def release(self) -> None:
        """Remove the sidecar and release the lock (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if _same_file(fd, self.path):
                os.unlink(self.path)
        except OSError:  # pragma: no cover - the directory became read-only
            pass
        finally:
            os.close(fd)
