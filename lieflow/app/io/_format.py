"""The trajectory file's format: its name and version, the two layouts (version 1 groups,
version 2 netCDF-4 variables), the checkpoint digest, and the netCDF-4 dimension and
variable helpers (dimension scales, the committed complex type, chunked growable datasets).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import attrs
import numpy as np

from ...algebras import Array
from ...errors import InputError, LieflowError

if TYPE_CHECKING:  # pragma: no cover
    import h5py


FORMAT = "lieflow-trajectory"


#: The layout written: 2 (netCDF-4: variables at the root, named dimensions); files of
#: version 1 (groups /trajectory and /diagnostics, no dimensions) are read and resumed.
FORMAT_VERSION = 2


_TINY = float(np.finfo(float).tiny)


_PER_STEP = ("energy", "energy_error", "casimirs", "casimir_drift")


_PER_UPDATE = ("iterations", "residual")


#: Group of the optional per-sample diagnostics a system provides.
_EXTRA = "diagnostics/extra"


@attrs.frozen
class _Layout:
    """Where a format version keeps each array of a trajectory file.

    ``paths`` maps ``saved_step``, ``time``, ``W``, ``W0``, the per-step diagnostics and
    ``step`` (version 2 only) to dataset paths; ``update_row0`` is the row of step 0 in
    ``iterations`` and ``residual`` (-1 in version 1, which has no row for step 0).
    """

    version: int
    paths: Mapping[str, str]
    update_row0: int

    @property
    def netcdf(self) -> bool:
        """Whether the file follows netCDF-4 (named dimensions on every dataset)."""
        return self.version >= 2

    def update_rows(self, k: int) -> slice:
        """Rows of ``iterations`` / ``residual`` holding steps ``1..k``."""
        return slice(1 + self.update_row0, k + 1 + self.update_row0)


_NAMES = ("energy", "energy_error", "casimirs", "casimir_drift", "iterations", "residual")


_V1_PATHS = {"saved_step": "trajectory/step", "time": "trajectory/t", "W": "trajectory/W"}


_V2_PATHS = {"saved_step": "saved_step", "time": "time", "W": "W", "step": "step"}


_LAYOUTS = {
    1: _Layout(
        1,
        MappingProxyType(
            {**_V1_PATHS, "W0": "initial/W0", **{n: f"diagnostics/{n}" for n in _NAMES}}
        ),
        -1,
    ),
    2: _Layout(2, MappingProxyType({**_V2_PATHS, "W0": "initial/W0", **{n: n for n in _NAMES}}), 0),
}


#: Checkpoint slots store the flow's state leaf by leaf under ``warm/<path>`` (a scheme's
#: :class:`~lieflow.flows.WarmStart`: ``warm/last``, ``warm/previous/0``, ...,
#: ``warm/trusted``; files written before the deeper warm starts: ``warm/previous``).
_STATE = "warm"


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


_DIGEST = "sha256"


#: Errors h5py raises on a file whose bytes are damaged (a bad checksum, a broken B-tree).
_DAMAGE = (OSError, KeyError, RuntimeError, ValueError, TypeError, IndexError, AttributeError)


def _h5py() -> Any:
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is in the cli extra
        raise LieflowError(
            "HDF5 output needs the 'h5py' package. To fix: pip install 'lieflow[cli]'."
        ) from exc
    return h5py


def _where(path: Path) -> str:
    return repr(str(path))


def _as_path(path: object, what: str = "path") -> Path:
    """``path`` as a :class:`Path`, or :class:`InputError` for anything else."""
    if isinstance(path, (str, os.PathLike)) and str(path):
        return Path(path)
    raise InputError(
        f"{what} must be a file path (str or pathlib.Path), got {path!r}. To fix: pass the "
        "path of a file written by `lieflow run`."
    )


# -- checkpoint integrity -----------------------------------------------------------------


def _canonical(value: Any) -> tuple[bytes, memoryview]:
    """What identifies a checkpoint item (an array, a scalar, a string or ``None``): a
    header and, for an array, its contiguous data as a buffer (hashed where it lies, never
    copied: a checkpoint of a large state would otherwise allocate two more states)."""
    if value is None:
        return b"none", memoryview(b"")
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        return f"array:{a.dtype.str}:{a.shape}:".encode(), a.reshape(-1).view(np.uint8).data
    value = _plain(value)
    return f"{type(value).__name__}:{value!r}".encode(), memoryview(b"")


def checkpoint_digest(step: int, t: float, items: Mapping[str, Any]) -> str:
    """SHA-256 of a checkpoint: its step index, time and every item it stores.

    ``items`` maps the names stored in the checkpoint slot (``"W"``, ``"warm/last"``, ...)
    to their values; arrays are hashed with their dtype and shape, other values by type and
    ``repr`` (``None`` is stored as ``"none"``). The writer stores the digest in the slot's
    ``sha256`` attribute and every reader recomputes it from what it reads back.
    """
    h = hashlib.sha256(f"lieflow-checkpoint;step={int(step)};t={float(t).hex()};".encode())
    for key in sorted(items):
        head, data = _canonical(items[key])
        h.update(key.encode() + b"=" + (len(head) + data.nbytes).to_bytes(8, "little"))
        h.update(head)
        h.update(data)
    return h.hexdigest()


_SLOT_ATTRS = ("step", "t", _DIGEST)


#: Version 2 stores a slot's non-array items (``None``, booleans, numbers, strings) as one
#: JSON attribute, so that every attribute is a plain netCDF string or number.
_SCALARS = "scalars"


def _plain(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


#: Rows per chunk of the growing datasets: at most this many rows ...
CHUNK_ROWS = 128
#: ... and at most this many bytes (at least one row): a damaged chunk (one flipped bit,
#: the chunk a killed process was rewriting) costs at most 128 steps of one diagnostic, or
#: 4 KiB of saved states (one state, if larger); everything else of the file stays readable.
CHUNK_BYTES = 1 << 12


#: The root attributes a run changes (its length, status and time); every other one is
#: fixed when the file is created, and copied then (:func:`_header_copy`).
_MUTABLE = ("requested_steps", "completed_steps", "status", "wall_time", "failure", "resumes",
            "salvaged")  # fmt: skip

#: The attribute of ``initial/W0`` holding that copy: a fixed-length string, stored in the
#: dataset's object header, which HDF5 checksums and never moves (the root attributes are
#: rewritten at every resume, their values are not checksummed, and a file cut short can
#: lose them): :func:`lieflow.app.salvage.salvage` restores a root attribute from it.
_HEADER_COPY = "header"


def _header_copy(meta: Mapping[str, Any]) -> str:
    """JSON of the root attributes a run never changes (``meta``: the attributes as
    written; arrays as lists)."""
    fixed = {k: _plain(v) for k, v in meta.items() if k not in _MUTABLE and k != "_NCProperties"}
    return json.dumps(
        {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in fixed.items()},
        sort_keys=True,
    )


def _chunk_rows(row_bytes: int) -> int:
    return max(1, min(CHUNK_ROWS, CHUNK_BYTES // max(row_bytes, 1)))


def _growable(
    group: h5py.Group, name: str, row: Array, dtype: Any, dims: Sequence[Any] | None = None
) -> h5py.Dataset:
    """An empty dataset that grows along its first axis, one row shaped like ``row``;
    ``dims`` (netCDF-4 files): the dimension scales of its axes."""
    row = np.asarray(row)
    ds = group.create_dataset(
        name,
        shape=(0, *row.shape),
        maxshape=(None, *row.shape),
        dtype=_stored_dtype(group.file, dtype),
        chunks=(_chunk_rows(row.size * np.dtype(dtype).itemsize), *row.shape),
        fletcher32=True,
    )
    if dims is not None:
        _attach(ds, dims)
    return ds


# -- netCDF-4 ------------------------------------------------------------------------------
#
# A netCDF-4 file is an HDF5 file whose datasets are netCDF variables: every axis of every
# dataset has one HDF5 dimension scale (its netCDF dimension). A dimension with a coordinate
# variable is that variable, made a scale under its own name; one without is an empty
# dataset whose scale name says "not a variable" and its length. Each dimension carries a
# file-wide id (``_Netcdf4Dimid``). Complex numbers are stored as the committed compound
# type ``_PFNC_DOUBLE_COMPLEX_TYPE`` {r, i} (the nc-complex convention: h5py and h5netcdf
# read it as complex, netCDF-C as a compound, nc-complex and netCDF4-python as complex).


_NOT_A_VARIABLE = "This is a netCDF dimension but not a netCDF variable."


_DIMID = "_Netcdf4Dimid"


#: Coordinate variables of the fixed dimensions (labels of the ensemble and Casimirs).
_LABELS = ("ensemble", "casimir")


_COMPLEX_TYPES = {8: "_PFNC_FLOAT_COMPLEX_TYPE", 16: "_PFNC_DOUBLE_COMPLEX_TYPE"}


def _is_netcdf(f: h5py.File) -> bool:
    return _plain(f.attrs.get("format_version", 1)) >= 2


def _is_scale(ds: Any) -> bool:
    """Whether an HDF5 dataset is a dimension scale (a netCDF dimension): HDF5's own test
    (its ``CLASS`` attribute; ~20× faster than reading the attribute through h5py)."""
    h5py = _h5py()
    return isinstance(ds, h5py.Dataset) and bool(h5py.h5ds.is_scale(ds.id))


def _stored_dtype(f: h5py.File, dtype: Any) -> Any:
    """The HDF5 type of ``dtype`` in a netCDF-4 file: complex as the committed compound type
    of the nc-complex convention (created at its first use), anything else as it is."""
    dtype = np.dtype(dtype)
    if dtype.kind != "c" or not _is_netcdf(f):
        return dtype
    name = _COMPLEX_TYPES.get(dtype.itemsize)
    if name is None:  # pragma: no cover - no complex256 state in practice
        return dtype
    if name not in f:
        f[name] = dtype
    return f[name]


def _next_dimid(f: h5py.File) -> int:
    """One more than the largest dimension id in the file (through h5py's low-level API:
    3x faster than ``visititems``, which builds an object per item)."""
    h5py = _h5py()
    ids = [-1]
    key = _DIMID.encode()

    def visit(name: bytes, info: Any) -> None:
        if info.type == h5py.h5o.TYPE_DATASET and info.num_attrs:
            if h5py.h5a.exists(f.id, key, obj_name=name):
                attr = h5py.h5a.open(f.id, key, obj_name=name)
                value = np.zeros(attr.shape, dtype=attr.dtype)
                attr.read(value)
                ids.append(int(value))

    h5py.h5o.visit(f.id, visit, info=True)
    return max(ids) + 1


def _dimension(
    group: h5py.Group, name: str, size: int, *, unlimited: bool = False, dimid: int | None = None
) -> h5py.Dataset:
    """A netCDF dimension without coordinate variable (created if missing; one of another
    length, left by a process killed while it replaced a dataset, is replaced)."""
    if name in group:
        old = group[name]
        if unlimited or old.shape[0] == size:
            return old
        _detach_all(old)
        del group[name]
    kwargs: dict[str, Any] = {"maxshape": (None,), "chunks": (1024,)} if unlimited else {}
    ds = group.create_dataset(name, shape=(size,), dtype=">f4", **kwargs)
    ds.make_scale(f"{_NOT_A_VARIABLE}{size:10d}")
    ds.attrs[_DIMID] = np.int32(_next_dimid(group.file) if dimid is None else dimid)
    return ds


def _coordinate(ds: h5py.Dataset, dimid: int) -> h5py.Dataset:
    """Make a 1-D dataset the coordinate variable of the dimension of its name."""
    ds.make_scale(ds.name.rsplit("/", 1)[-1])
    ds.attrs[_DIMID] = np.int32(dimid)
    return ds


def _attach(ds: h5py.Dataset, dims: Sequence[Any]) -> None:
    """Attach one dimension scale to each axis of ``ds``."""
    for axis, scale in enumerate(dims):
        ds.dims[axis].attach_scale(scale)


def _detach_all(scale: h5py.Dataset) -> None:
    """Detach a dimension scale from every dataset still attached to it."""
    for ref, axis in list(scale.attrs.get("REFERENCE_LIST", [])):
        with contextlib.suppress(*_DAMAGE):
            scale.file[ref].dims[int(axis)].detach_scale(scale)


def _detach(ds: h5py.Dataset) -> None:
    """Detach every dimension scale of ``ds`` (before deleting it: no dangling references)."""
    for axis in range(ds.ndim):
        for scale in list(ds.dims[axis].values()):
            ds.dims[axis].detach_scale(scale)


def _state_dims(ndim: int) -> list[str]:
    """The dimensions of a state with ``ndim`` axes: (``ensemble``,) ``row``, ``col``."""
    return [*_batch_dims(ndim - 2), "row", "col"]


def _batch_dims(n: int) -> list[str]:
    """Names of ``n`` batch axes: ``ensemble`` (``ensemble_0``, ... if more than one)."""
    return ["ensemble"] if n == 1 else [f"ensemble_{i}" for i in range(n)]
