"""The output on disk: free space kept in reserve (a full disk stops a run at its last
checkpoint before HDF5 could damage the file), a finished new file given its name at
once (replacing, or an exclusive create), and flushing to the disk itself (``fsync``)."""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..config import ConfigError
from ._format import (
    _where,
)
from ._lock import (
    _WRITE_ERRORS,
)

if TYPE_CHECKING:  # pragma: no cover
    import h5py


#: Free space kept in reserve on the output's disk: a write is not started unless this much
#: (plus what it writes) is free, because HDF5 interrupted by a full disk can leave the
#: file's superblock pointing past its end (measured: a resume on a full disk made the file
#: unopenable, "addr overflow"). Enough for the metadata and new chunks of a few commits.
_SPACE_MARGIN = 1 << 20


#: Free space enough to rewrite a file's status attributes (a full disk's last write).
_ATTRIBUTES_ROOM = 1 << 16


def _ensure_space(path: Path, nbytes: int = 0) -> None:
    """Raise ENOSPC (before anything is written) unless ``nbytes`` plus the margin are free
    on the disk holding ``path``."""
    try:
        st = os.statvfs(path.parent)
    except (OSError, AttributeError):  # pragma: no cover - no statvfs: HDF5 reports it
        return
    if st.f_bavail * st.f_frsize < nbytes + _SPACE_MARGIN:
        raise OSError(errno.ENOSPC, "No space left on device", str(path))


def _close_quietly(f: Any) -> None:
    """Close an h5py file whose writes failed (its close may fail too: the error is moot)."""
    with contextlib.suppress(*_WRITE_ERRORS, ValueError):
        f.close()


def _file_id(f: h5py.File) -> tuple[int, int]:
    """(device, inode) of the file HDF5 is writing."""
    try:
        st = os.fstat(int(f.id.get_vfd_handle()))
    except (OSError, TypeError, ValueError, AttributeError):  # pragma: no cover - other drivers
        st = os.stat(f.filename)
    return st.st_dev, st.st_ino


def _exists_error(out: Path, from_config: bool) -> ConfigError:
    """``out`` exists; the fix in the words of the caller (``lieflow run``'s flags, or
    :func:`lieflow.integrate`'s arguments)."""
    how = ("pass --resume to continue it, --force to replace it, or choose another output"
           if from_config else
           "pass resume=True to continue it, replace=True to replace it, or choose another "
           "out")  # fmt: skip
    return ConfigError(
        f"{_where(out)} already exists (another run may have created it since this one "
        f"started). To fix: {how}.",
        "[run] output",
    )


def _publish(tmp: Path, out: Path, replace: bool, from_config: bool) -> None:
    """Give the finished file ``tmp`` the name ``out``: atomically replacing an existing file
    if ``replace``, else only if ``out`` does not exist (a hard link is an atomic exclusive
    create; where links are not supported, an O_EXCL placeholder is replaced)."""
    if replace:
        os.replace(tmp, out)
        return
    try:
        os.link(tmp, out)
    except FileExistsError:
        raise _exists_error(out, from_config) from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
            raise
        try:
            os.close(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        except FileExistsError:
            raise _exists_error(out, from_config) from None
        os.replace(tmp, out)
    else:
        tmp.unlink()


def _sync(f: h5py.File) -> None:
    """Flush ``f`` and make it durable (``fsync``): a checkpoint survives a power loss."""
    f.flush()
    os.fsync(int(f.id.get_vfd_handle()))
