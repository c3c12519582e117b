"""Checkpoint slots: the state and the flow's state at a step written in place, leaf by leaf,
with HDF5 checksums and the slot's SHA-256 digest (:func:`_write_slot`); what a slot no
longer holds deleted with the dimensions only it used."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from ...algebras import Array
from ._format import (
    _DIGEST,
    _SCALARS,
    _SLOT_ATTRS,
    _attach,
    _detach,
    _dimension,
    _h5py,
    _is_netcdf,
    _is_scale,
    _plain,
    _state_dims,
    _stored_dtype,
    checkpoint_digest,
)

if TYPE_CHECKING:  # pragma: no cover
    import h5py


def _write_slot(
    slot: h5py.Group, index: int, t: float, items: Mapping[str, Any], cache: dict[str, Any]
) -> None:
    """Store ``items`` in a checkpoint slot (arrays as datasets; other values as attributes,
    ``None`` as ``"none"``, in version 1, as the JSON attribute ``scalars`` in version 2),
    then its step, time and :func:`checkpoint_digest`."""
    netcdf = _is_netcdf(slot.file)
    if cache.get("") != sorted(items):  # other leaves than this slot's last write here
        _prune(slot, set(items))
        cache.clear()
        cache[""] = sorted(items)
    scalars: dict[str, Any] = {}
    for key, value in items.items():
        if isinstance(value, np.ndarray):
            if key in slot.attrs:  # it was None (an attribute) at this slot's last write
                del slot.attrs[key]
            _put(slot, key, value, cache)
            continue
        if key in slot:
            cache.pop(key, None)
            _drop(slot, key)
        if netcdf:
            scalars[key] = _plain(value)
        else:
            slot.attrs[key] = "none" if value is None else value
    if netcdf:
        slot.attrs[_SCALARS] = json.dumps(scalars, sort_keys=True)
    slot.attrs["step"] = index
    slot.attrs["t"] = t
    slot.attrs[_DIGEST] = checkpoint_digest(index, t, items)


def _checked(value: Array) -> dict[str, Any]:
    """Dataset options for HDF5's Fletcher-32 checksum on the whole array (one chunk);
    an empty or scalar array cannot be chunked and goes without."""
    value = np.asarray(value)
    return {"chunks": value.shape, "fletcher32": True} if value.size and value.ndim else {}


def _put(group: h5py.Group, name: str, value: Array, cache: dict[str, Any]) -> None:
    """Write ``value`` to dataset ``name`` of ``group`` in place (``cache`` keeps handles)."""
    value = np.asarray(value)
    ds = cache.get(name)
    if ds is None and name in group:
        ds = cache[name] = group[name]
    if ds is not None and (ds.shape != value.shape or ds.dtype != value.dtype):
        cache.pop(name)
        _drop(group, name)
        ds = None
    if ds is None:
        ds = cache[name] = _create(group, name, value)
    else:
        ds[...] = value


def _create(group: h5py.Group, name: str, value: Array) -> h5py.Dataset:
    """A dataset holding ``value`` with its checksum; in a netCDF-4 file with dimensions: a
    state (shaped like W0) on the file's (``ensemble``,) ``row``, ``col``, anything else on
    dimensions ``<name>_dim<i>`` of its own group."""
    f = group.file
    ds = group.create_dataset(
        name, data=value, dtype=_stored_dtype(f, value.dtype), **_checked(value)
    )
    if _is_netcdf(f) and value.ndim:
        if name.rsplit("/", 1)[-1] in ("W", "W0") and value.shape == _state_shape(f):
            _attach(ds, [f[d] for d in _state_dims(value.ndim)])
        else:
            base = name.rsplit("/", 1)[-1]
            _attach(ds, [_dimension(ds.parent, f"{base}_dim{i}", n) for i, n in
                         enumerate(value.shape)])  # fmt: skip
    return ds


def _prune(slot: h5py.Group, keep: set[str]) -> None:
    """Delete what a checkpoint slot holds besides the items ``keep`` (the leaves of a flow
    state of another shape: a resume by a lieflow whose scheme keeps other state), so that
    the slot holds exactly the items its digest covers."""
    h5py = _h5py()
    stale: list[str] = []

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset) and not _is_scale(obj) and name not in keep:
            stale.append(name)

    slot.visititems(visit)
    for name in stale:
        if name in slot:
            _drop(slot, name)
    for key in list(slot.attrs):
        if key not in (*_SLOT_ATTRS, _SCALARS) and key not in keep:
            del slot.attrs[key]
    for key in keep:  # a group where a leaf goes (or a leaf where a group goes)
        parts = key.split("/")
        for i in range(1, len(parts) + 1):
            sub = "/".join(parts[:i])
            obj = slot.get(sub)
            if obj is None:
                break
            if isinstance(obj, h5py.Group) != (i < len(parts)):
                _drop(slot, sub)
                break


def _drop(group: h5py.Group, name: str) -> None:
    """Delete dataset (or group) ``name`` of ``group`` and the dimensions only it used."""
    h5py = _h5py()
    obj = group[name]
    parent, base = obj.parent, name.rsplit("/", 1)[-1]
    if _is_netcdf(group.file):
        inner = [obj] if isinstance(obj, h5py.Dataset) else []
        if isinstance(obj, h5py.Group):
            obj.visititems(lambda _, o: inner.append(o) if isinstance(o, h5py.Dataset) else None)
        for ds in inner:
            _detach(ds)
    del group[name]
    for i in range(8):
        dim = f"{base}_dim{i}"
        if dim in parent and _is_scale(parent[dim]):
            del parent[dim]


def _state_shape(f: h5py.File) -> tuple[int, ...]:
    """The shape of one state of a netCDF-4 file (from its dimensions)."""
    ens = [f[d].shape[0] for d in ("ensemble", *(f"ensemble_{i}" for i in range(8))) if d in f]
    return (*ens, f["row"].shape[0], f["col"].shape[0])
