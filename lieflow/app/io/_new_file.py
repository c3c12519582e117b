"""What a new trajectory file holds before its first step (format version 2): the header
attributes, the dimensions and variables, step 0 and both checkpoint slots
(:func:`_initialise`, :func:`_lay_out`), and the rows of a system's extra diagnostics
(:func:`_append_extra`)."""

from __future__ import annotations

import datetime as _dt
import sys
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from ... import chunks
from ...algebras import Array
from ._format import (
    _EXTRA,
    _HEADER_COPY,
    FORMAT,
    FORMAT_VERSION,
    _attach,
    _batch_dims,
    _coordinate,
    _dimension,
    _growable,
    _h5py,
    _header_copy,
    _is_netcdf,
    _stored_dtype,
)
from ._header import TrajectoryHeader, environment
from ._slots import _checked, _write_slot

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

if TYPE_CHECKING:  # pragma: no cover
    import h5py


def _append_extra(f: h5py.File, rows: list[tuple[int, float, Mapping[str, Any]]]) -> None:
    """Append ``(step, t, {name: value})`` rows to ``/diagnostics/extra`` (datasets are
    created at the first row, shaped like its values; in a netCDF-4 file along the unlimited
    dimension ``sample``, an ensemble's member axis on ``ensemble``)."""
    if not rows:
        return
    netcdf = _is_netcdf(f)
    group = f.get(_EXTRA)
    if group is None:
        group = f.require_group(_EXTRA)
        if netcdf:
            _dimension(group, "sample", 0, unlimited=True)
    columns: dict[str, Array] = {
        "step": np.array([r[0] for r in rows], dtype=np.int64),
        "t": np.array([r[1] for r in rows], dtype=np.float64),
    }
    for name in rows[0][2]:
        columns[name] = np.stack([np.asarray(r[2][name]) for r in rows])
    for name, values in columns.items():
        if name not in group:
            dims = _extra_dims(f, group, name, values.shape[1:]) if netcdf else None
            _growable(group, name, values[0], values.dtype, dims)
        ds = group[name]
        n = ds.shape[0]
        ds.resize(n + len(values), axis=0)
        ds[n:] = values


def _extra_dims(f: h5py.File, group: h5py.Group, name: str, shape: tuple[int, ...]) -> list[Any]:
    """Dimensions of an extra diagnostic: ``sample``, then ``ensemble`` for an axis as long
    as the ensemble's first, then ``<name>_dim<i>`` of the group."""
    dims: list[Any] = [group["sample"]]
    members = f["ensemble"].shape[0] if "ensemble" in f else None
    for i, n in enumerate(shape):
        if i == 0 and n == members:
            dims.append(f["ensemble"])
        else:
            dims.append(_dimension(group, f"{name}_dim{i}", n))
    return dims


def _ensemble_labels(config: str, members: int) -> Array:
    """Labels of an ensemble's members: ``[initial] seeds`` of the configuration if it
    has one per member, else ``0..members-1``."""
    try:
        seeds = tomllib.loads(config).get("initial", {}).get("seeds") if config else None
    except (tomllib.TOMLDecodeError, AttributeError):
        seeds = None
    if isinstance(seeds, list) and len(seeds) == members:
        try:
            return np.asarray(seeds, dtype=np.int64)
        except (TypeError, ValueError, OverflowError):
            pass
    return np.arange(members, dtype=np.int64)


def _initialise(f: h5py.File, header: TrajectoryHeader) -> None:
    """Write a new file's header, dimensions, variables and step 0 (format version 2)."""
    system, W0 = header.system, np.asarray(header.W0)
    powers = [k for k in system.casimir_powers if k <= system.algebra.n]
    meta: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": header.config_text,
        "config_source": header.config_source,
        "identity": header.identity,
        "system": header.system_name,
        "scheme": header.scheme,
        "solver": header.solver,
        "h": header.h,
        "save_every": header.save_every,
        "requested_steps": header.requested_steps,
        "casimir_powers": np.asarray(powers, dtype=np.int64),
        "completed_steps": 0,
        "status": "running",
        "wall_time": 0.0,
        "failure": "",
        "resumes": 0,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        **environment(),
    }
    H0 = np.asarray(system.hamiltonian(W0), dtype=np.float64)
    C0 = np.asarray(system.casimirs(W0), dtype=np.float64)
    batch = W0.shape[:-2]
    labels = [
        _ensemble_labels(header.config_text, n) if len(batch) == 1 else np.arange(n) for n in batch
    ]
    casimir_labels = np.asarray(powers if len(powers) == C0.shape[-1] else
                                np.arange(C0.shape[-1]), dtype=np.int64)  # fmt: skip
    _lay_out(f, meta, W0, H0, C0, labels, casimir_labels)
    extra, _ = chunks.extra_hook(system, header.save_every)
    if extra is not None:
        _append_extra(f, [(0, 0.0, extra(W0))])


def _lay_out(
    f: h5py.File,
    meta: Mapping[str, Any],
    W0: Array,
    H0: Array,
    C0: Array,
    labels: list[Array],
    casimir_labels: Array,
) -> None:
    """Write the header attributes ``meta``, the dimensions, the variables and step 0 of a
    new file (format version 2): the initial state ``W0``, its energy ``H0`` and Casimirs
    ``C0``, the labels of its ensemble axes and of its Casimirs; both checkpoint slots hold
    ``W0`` at step 0. What :meth:`TrajectoryWriter.create` writes, and what
    :func:`lieflow.app.salvage.salvage` rebuilds a damaged file on."""
    for key, value in meta.items():
        f.attrs[key] = value
    h5py = _h5py()
    props = (
        f"version=2,lieflow={meta.get('lieflow_version', '')},"
        f"hdf5={h5py.version.hdf5_version},h5py={h5py.__version__}"
    )
    f.attrs["_NCProperties"] = np.array(props, dtype=h5py.string_dtype("ascii", len(props)))
    # dimensions: the two unlimited axes first (ids 0, 1), then the fixed ones
    time = _coordinate(_growable(f, "time", np.float64(0), np.float64), 0)
    step = _coordinate(_growable(f, "step", np.int64(0), np.int64), 1)
    dimid = 2
    ens = []
    for name, values in zip(_batch_dims(len(labels)), labels, strict=True):
        values = np.asarray(values, dtype=np.int64)
        ens.append(_coordinate(f.create_dataset(name, data=values, **_checked(values)), dimid))
        dimid += 1
    row = _dimension(f, "row", W0.shape[-2], dimid=dimid)
    col = _dimension(f, "col", W0.shape[-1], dimid=dimid + 1)
    casimir_labels = np.asarray(casimir_labels, dtype=np.int64)
    casimir = _coordinate(
        f.create_dataset("casimir", data=casimir_labels, **_checked(casimir_labels)), dimid + 2
    )
    state = [*ens, row, col]
    saved = _growable(f, "saved_step", np.int64(0), np.int64, [time])
    W = _growable(f, "W", W0, W0.dtype, [time, *state])
    variables = {
        "energy": _growable(f, "energy", H0, np.float64, [step, *ens]),
        "energy_error": _growable(f, "energy_error", H0, np.float64, [step, *ens]),
        "casimirs": _growable(f, "casimirs", C0, np.float64, [step, *ens, casimir]),
        "casimir_drift": _growable(f, "casimir_drift", C0, np.float64, [step, *ens, casimir]),
        "iterations": _growable(f, "iterations", np.int64(0), np.int64, [step]),
        "residual": _growable(f, "residual", np.float64(0), np.float64, [step]),
    }
    for name, text in _DESCRIPTIONS.items():
        f[name].attrs["long_name"] = text
    W.attrs["coordinates"] = "saved_step"
    initial = f.create_group("initial").create_dataset(
        "W0", data=W0, dtype=_stored_dtype(f, W0.dtype), **_checked(W0)
    )
    _attach(initial, state)
    initial.attrs[_HEADER_COPY] = np.bytes_(_header_copy(meta).encode())
    rows = {
        time: 0.0, step: 0, saved: 0, W: W0,
        variables["energy"]: H0, variables["energy_error"]: np.zeros_like(H0),
        variables["casimirs"]: C0, variables["casimir_drift"]: np.zeros_like(C0),
        variables["iterations"]: 0, variables["residual"]: np.nan,
    }  # fmt: skip
    for ds, value in rows.items():
        ds.resize(1, axis=0)
        ds[0] = value
    ck = f.create_group("checkpoint")
    for i in (0, 1):
        _write_slot(ck.create_group(f"slot{i}"), 0, 0.0, {"W": W0}, {})
    ck.attrs["current"] = 0


#: ``long_name`` of the variables of a netCDF-4 trajectory file.
_DESCRIPTIONS = {
    "time": "time t = k h of the saved states",
    "saved_step": "step index k of the saved states",
    "W": "saved states W_k",
    "step": "step index k of the per-step diagnostics",
    "energy": "energy (Hamiltonian) H(W_k)",
    "energy_error": "relative energy error |H(W_k) - H(W_0)| / |H(W_0)|",
    "casimirs": "Casimirs C_j(W_k) = tr W_k^j",
    "casimir_drift": "Casimir drift |C_j(W_k) - C_j(W_0)| / ||W_0||^j",
    "iterations": "solver updates of step k (0 at step 0)",
    "residual": "last relative update of step k's solve (NaN at step 0)",
    "casimir": "power j of the Casimir tr W^j",
}
