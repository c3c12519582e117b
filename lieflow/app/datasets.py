"""Trajectory files and sweeps as labelled arrays: :func:`open_run` and :func:`open_sweep`
give :class:`xarray.Dataset` objects (``pip install 'lieflow[sweep]'``).

Dimensions:

``time``
    saved states (every ``save_every``-th step and the last); coordinates ``time``
    (``t = k h``) and ``saved_step`` (``k``).
``step``
    every step ``k = 0..K`` of the per-step diagnostics; coordinates ``step`` and
    ``step_time``. ``iterations`` and ``residual`` of step 0 (the initial condition) are 0
    and NaN.
``ensemble``
    members of an ensemble run (``[initial] seeds`` or ``perturb``), labelled by their
    seeds; absent for a single initial condition.
``row``, ``col``
    matrix entries of the states ``W``.
``casimir``
    the Casimirs ``tr W^k``, labelled by ``k``.

Arrays are read from the files when they are used (lazily: opening a sweep of 100 runs
reads their headers only); ``.load()`` reads everything, ``chunks=`` gives dask arrays.
Only what a file's checkpoint covers is shown (steps a crashed run wrote after it are not).
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, LieflowError

__all__ = ["MANIFEST", "SWEEP_FORMAT", "ZARR_STORE", "open_run", "open_sweep", "write_zarr_run"]

#: A sweep's directory (``lieflow sweep``): its manifest, the trajectory files ``runs/<id>.h5``
#: and, with ``store = "zarr"``, the Zarr store (:data:`ZARR_STORE`). The manifest lists every
#: run (parameters, status, error, file) and names its format (:data:`SWEEP_FORMAT`).
MANIFEST = "manifest.json"
SWEEP_FORMAT = "lieflow-sweep"


def _xarray() -> Any:
    try:
        import xarray
    except ImportError as exc:
        raise InputError(
            f"labelled datasets need the 'xarray' package ({exc}). To fix: pip install "
            "'lieflow[sweep]'."
        ) from None
    return xarray


class _StoredRun:
    """What :func:`open_run` needs of one file, read once: header, valid lengths, shapes,
    where its arrays are (format version 1 or 2)."""

    def __init__(self, path: Path) -> None:
        from . import io

        h5py = io._h5py()
        self.path = path
        with io._open(path, "r") as f, io._Reading(path):
            layout = io._check_format(f, path)
            ck = io._read_checkpoint(f, path)
            io._check_lengths(f, ck.step, path, layout)
            self.attrs = io._header_attributes(f)
            self.k = ck.step
            self.paths = layout.paths
            #: file row of step k's iterations and residual: k + update_row0
            self.update_row0 = layout.update_row0
            saved = f[self.paths["saved_step"]][()]
            self.n_saved = int(np.searchsorted(saved, self.k, side="right"))
            self.saved_step = saved[: self.n_saved]
            self.t = f[self.paths["time"]][: self.n_saved]
            self.shapes = {
                name: tuple(obj.shape[1:])
                for name in ("W", *_DIAGNOSTICS)
                if isinstance(obj := f[self.paths[name]], h5py.Dataset)
            }
            self.dtype = f[self.paths["W"]].dtype
            self.labels = f["ensemble"][()] if layout.netcdf and "ensemble" in f else None
        #: the run's arrays in a sweep's Zarr store when read from there (:meth:`from_zarr`)
        self.group: Any = None
        self._finish()

    @classmethod
    def from_zarr(cls, group: Any, arrays: Mapping[str, Any], path: Path) -> _StoredRun:
        """A run as stored in a sweep's Zarr store (:func:`write_zarr_run`): its group and
        the group's ``arrays`` by name; ``path`` is its trajectory file (not read)."""
        self = cls.__new__(cls)
        self.path, self.group = path, arrays
        attrs = dict(group.attrs)
        self.k = int(attrs.pop(_STORED))
        saved = attrs.pop(_SAVED, None)  # the saved steps and times, when few
        self.attrs = attrs
        self.paths = {name: name for name in _ARRAYS}
        self.update_row0 = 0
        if saved is None:
            saved = (arrays["saved_step"][...], arrays["time"][...])
        # rows a writer appended after its last commit are not the run's (yet)
        n = int(np.searchsorted(np.asarray(saved[0]), self.k, side="right"))
        self.saved_step = np.asarray(saved[0][:n], dtype=np.int64)
        self.t = np.asarray(saved[1][:n], dtype=np.float64)
        self.n_saved = n
        self.shapes = {name: tuple(arrays[name].shape[1:]) for name in ("W", *_DIAGNOSTICS)}
        self.dtype = np.dtype(arrays["W"].dtype)
        self.labels = np.asarray(attrs.pop(_LABELS)) if _LABELS in attrs else None
        self._finish()
        return self

    def _finish(self) -> None:
        self.h = float(self.attrs["h"])
        w = self.shapes["W"]
        self.members = w[0] if len(w) == 3 else None
        self.seeds = (
            self.labels
            if self.labels is not None
            else _seeds(str(self.attrs.get("config", "")), self.members)
        )

    def rows(self, name: str) -> int:
        """Valid rows of a variable (up to the checkpoint; ``iterations`` and ``residual``
        counted from step 0)."""
        return self.n_saved if name == "W" else self.k + 1

    def offset(self, name: str) -> int:
        """How many leading steps the file has no row for (step 0 of the solver's columns
        in a version-1 file)."""
        return -self.update_row0 if name in ("iterations", "residual") else 0

    def block(self, name: str, start: int, stop: int) -> Any:
        """Rows ``start:stop`` of the file's (or the store's) array ``name``."""
        if self.group is not None:
            return np.asarray(self.group[name][start:stop])
        from . import io

        with io._open(self.path, "r") as f, io._Reading(self.path):
            return f[self.paths[name]][start:stop]

    def arrays(self) -> dict[str, Any]:
        """Every array of the run up to its checkpoint, step 0's solver columns included
        (0 iterations, NaN residual; a version-1 file has no row for them)."""
        out: dict[str, Any] = {"saved_step": self.saved_step, "time": self.t}
        for name in ("W", *_DIAGNOSTICS):
            offset = self.offset(name)
            data = self.block(name, 0, self.rows(name) - offset)
            if offset:
                head = np.full((offset, *data.shape[1:]), np.nan if name == "residual" else 0)
                data = np.concatenate([head.astype(data.dtype), data])
            out[name] = data
        if self.labels is not None:
            out["ensemble"] = self.labels
        return out


_DIAGNOSTICS = ("energy", "energy_error", "casimirs", "casimir_drift", "iterations", "residual")
_ARRAYS = ("saved_step", "time", "W", *_DIAGNOSTICS)
#: The Zarr store of a sweep (``lieflow sweep --store zarr``), in the sweep directory.
ZARR_STORE = "runs.zarr"
#: Attribute of a run's group in the store, written last: the steps it holds.
_STORED = "lieflow_stored_steps"
#: Attributes of a run's group: its saved steps and times (up to ``_SAVED_MAX`` of them;
#: JSON numbers round-trip exactly), its ensemble's labels.
_SAVED, _SAVED_MAX, _LABELS = "lieflow_saved", 10_000, "lieflow_ensemble"
#: Bytes per chunk of the store's arrays (along their first axis).
_CHUNK_BYTES = 8 << 20


def _seeds(config: str, members: int | None) -> Any:
    """The ensemble's labels: ``[initial] seeds`` if the configuration has them."""
    from .io import _ensemble_labels

    return None if members is None else _ensemble_labels(config, members)


def _fill(dtype: np.dtype[Any]) -> Any:
    if np.issubdtype(dtype, np.complexfloating):
        return complex(np.nan, np.nan)
    return np.nan if np.issubdtype(dtype, np.floating) else 0


class _Stacked:
    """A lazily read array over many files: ``lead`` dimensions of runs, then a dataset of
    each run's file padded to a common shape (missing runs and rows read as the fill).

    Each run's :meth:`_StoredRun.offset` shifts the first axis (``iterations`` of step ``k``
    is row ``k - 1`` of a version-1 file; rows before the offset read as ``head``); ``last``
    reads only each run's last valid row (the final state) and drops the first axis.
    """

    def __init__(
        self,
        runs: Sequence[_StoredRun | None],
        lead: tuple[int, ...],
        name: str,
        rows: int,
        rest: tuple[int, ...],
        dtype: Any,
        *,
        head: Any = 0,
        last: bool = False,
    ) -> None:
        self.runs, self.lead, self.name = list(runs), lead, name
        self.rows, self.rest, self.head, self.last = rows, rest, head, last
        self.dtype = np.dtype(dtype)
        self.shape = (*lead, *(() if last else (rows,)), *rest)
        self.fill = _fill(self.dtype)

    def variable(self, dims: Sequence[str]) -> Any:
        xr = _xarray()
        from xarray.core import indexing

        array = self

        base: Any = xr.backends.BackendArray

        class Backend(base):
            __slots__ = ()
            shape = array.shape
            dtype = array.dtype

            def __getitem__(self, key: Any) -> Any:
                return indexing.explicit_indexing_adapter(
                    key, array.shape, indexing.IndexingSupport.OUTER, array.read
                )

        return xr.Variable(tuple(dims), indexing.LazilyIndexedArray(Backend()))

    def read(self, key: tuple[Any, ...]) -> Any:
        idx = [np.arange(n)[k] for n, k in zip(self.shape, key, strict=True)]
        drop = [i for i, k in enumerate(key) if isinstance(k, (int, np.integer))]
        full = [np.atleast_1d(i) for i in idx]
        nl = len(self.lead)
        out = np.full(tuple(len(i) for i in full), self.fill, dtype=self.dtype)
        body = full[nl:]
        for combo in itertools.product(*(enumerate(ix) for ix in full[:nl])):
            pos = tuple(p for p, _ in combo)
            run = self.runs[
                int(np.ravel_multi_index(tuple(v for _, v in combo), self.lead)) if nl else 0
            ]
            if run is None:
                continue
            offset = run.offset(self.name)
            valid = run.rows(self.name) - offset  # rows of the file's dataset
            actual = run.shapes[self.name]
            target = out[pos] if nl else out
            if self.last:
                rows, trailing = np.array([valid - 1]), body
            else:
                rows, trailing = body[0] - offset, body[1:]
                if offset:
                    target[rows < 0] = self.head
            ok_rows = (rows >= 0) & (rows < valid)
            masks = [t < a for t, a in zip(trailing, actual, strict=True)]
            if not ok_rows.any() or not all(m.any() for m in masks):
                continue
            r = rows[ok_rows]
            block = run.block(self.name, int(r.min()), int(r.max()) + 1)
            inner = np.ix_(*(t[m] for t, m in zip(trailing, masks, strict=True)))
            sub = (slice(None), *inner)
            data = block[(r - r.min(),)][sub]
            place = np.ix_(*(np.flatnonzero(m) for m in masks))
            if self.last:
                target[place] = data[0]
            else:
                at = np.flatnonzero(ok_rows)[(...,) + (None,) * len(masks)]
                sub = (at, *place)
                target[sub] = data
        if drop:
            out = out.reshape(tuple(n for i, n in enumerate(out.shape) if i not in drop))
        return out


def _dims(info: _StoredRun, name: str) -> tuple[str, ...]:
    ens = ("ensemble",) if info.members is not None else ()
    if name == "W":
        return ("time", *ens, "row", "col")
    if name in ("casimirs", "casimir_drift"):
        return ("step", *ens, "casimir")
    if name in ("iterations", "residual"):
        return ("step",)
    return ("step", *ens)


def _variables(
    runs: Sequence[_StoredRun | None], lead: tuple[int, ...], lead_dims: Sequence[str]
) -> dict[str, Any]:
    """The lazily read data variables of runs arranged on ``lead`` (padded to the largest)."""
    ref = next(r for r in runs if r is not None)
    present = [r for r in runs if r is not None]
    out = {}
    for name in ("W", *_DIAGNOSTICS):
        rows = max(r.rows(name) for r in present)
        rest = tuple(max(s) for s in zip(*(r.shapes[name] for r in present), strict=True))
        ragged = len(present) < len(runs) or any(
            r.rows(name) != rows or r.shapes[name] != rest for r in present
        )
        dtype = (
            np.result_type(*(r.dtype for r in present))
            if name == "W"
            else (np.float64 if name != "iterations" or ragged else np.int64)
        )
        head = np.nan if name == "residual" else 0  # step 0 of a version-1 file
        dims = (*lead_dims, *_dims(ref, name))
        out[name] = _Stacked(runs, lead, name, rows, rest, dtype, head=head).variable(dims)
        if name == "W":
            final = _Stacked(runs, lead, name, rows, rest, dtype, last=True)
            out["W_final"] = final.variable((*lead_dims, *_dims(ref, name)[1:]))
    return out


_ATTR_SKIP = ("casimir_powers",)


def _attrs(info: _StoredRun) -> dict[str, Any]:
    return {k: v for k, v in info.attrs.items() if k not in _ATTR_SKIP}


def open_run(path: Path | str, *, chunks: Mapping[str, int] | str | None = None) -> Any:
    """A trajectory file as an :class:`xarray.Dataset` (read lazily).

    Parameters
    ----------
    path : path
        A file written by ``lieflow run``, ``lieflow sweep`` or :func:`lieflow.app.io.run`.
    chunks : mapping or "auto", optional
        Give dask arrays of these chunks (``Dataset.chunk``) instead of lazy numpy ones.

    Returns
    -------
    xarray.Dataset
        Variables ``W`` (``time``, [``ensemble``], ``row``, ``col``), ``W_final``,
        ``energy``, ``energy_error`` (``step``, [``ensemble``]), ``casimirs``,
        ``casimir_drift`` (``step``, [``ensemble``], ``casimir``), ``iterations`` and
        ``residual`` (``step``); the file's header (configuration text, identity, system,
        scheme, solver, h, status, versions...) in ``attrs``. Complex states stay complex.

    Raises
    ------
    LieflowError
        The file is missing, not a trajectory, or damaged (checksums are verified).
    """
    from .io import _as_path

    xr = _xarray()
    info = _StoredRun(_as_path(path))
    ds = xr.Dataset(_variables([info], (), ()), coords=_coords(info), attrs=_attrs(info))
    return ds.chunk(chunks) if chunks is not None else ds


def _coords(info: _StoredRun) -> dict[str, Any]:
    k = np.arange(info.k + 1)
    coords: dict[str, Any] = {
        "time": ("time", info.t),
        "saved_step": ("time", info.saved_step),
        "step": ("step", k),
        "step_time": ("step", k * info.h),
        "casimir": ("casimir", np.asarray(info.attrs.get("casimir_powers", []), dtype=int)),
    }
    if info.members is not None:
        coords["ensemble"] = ("ensemble", info.seeds)
    return coords


def _zarr() -> Any:
    try:
        import zarr
    except ImportError as exc:
        raise InputError(
            f"the sweep's Zarr store needs the 'zarr' package, version 3 ({exc}). To fix: "
            "pip install 'lieflow[sweep]' (with Python 3.11 or newer)."
        ) from None
    return zarr


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value.item() if isinstance(value, np.generic) else value


def write_zarr_run(path: Path | str, store: Path | str, name: str) -> int:
    """Write the run of trajectory file ``path`` into group ``name`` of the Zarr store
    ``store`` (replacing what the group held), up to the file's checkpoint.

    The group holds the arrays of the file's root (``saved_step``, ``time``, ``W``, the
    per-step diagnostics with step 0's ``iterations`` and ``residual``, ``ensemble``),
    chunked along their first axis, and the file's header as attributes; the attribute
    ``lieflow_stored_steps`` (the steps held) is written last, so a group a writer left
    half-written is never read. Only the group's own keys are written: processes writing
    different groups of one store never write the same object.

    Returns
    -------
    int
        The steps written (the file's checkpoint).
    """
    zarr = _zarr()
    info = _StoredRun(Path(path))
    attrs = {key: _jsonable(value) for key, value in info.attrs.items()}
    group = zarr.open_group(str(Path(store) / name), mode="w", attributes=attrs)
    for key, value in info.arrays().items():
        value = np.asarray(value)
        rows = max(1, min(len(value), _CHUNK_BYTES // max(1, value[:1].nbytes)))
        array = group.create_array(
            key, shape=value.shape, dtype=value.dtype, chunks=(rows, *value.shape[1:])
        )
        array[...] = value
    done: dict[str, Any] = {_STORED: info.k}
    if info.labels is not None:
        done[_LABELS] = info.labels.tolist()
    if info.n_saved <= _SAVED_MAX:
        done[_SAVED] = [info.saved_step.tolist(), info.t.tolist()]
    group.attrs.update(done)  # one write, the last
    return info.k


def _store_members(root: Path) -> dict[str, Any] | None:
    """Every group and array of the sweep's Zarr store by path (one read of its
    consolidated metadata), or None (no store, no zarr, unreadable)."""
    path = root / ZARR_STORE
    if not path.is_dir():
        return None
    try:
        import zarr

        return dict(zarr.open_group(str(path), mode="r").members(max_depth=None))
    except Exception:  # no zarr 3 here, or not a Zarr group: read the files
        return None


def _stored_run(
    store: Mapping[str, Any] | None, record: Mapping[str, Any], path: Path
) -> _StoredRun | None:
    """A run from the store if it holds the run as the manifest records it (same steps
    and status), else None (the file is read instead)."""
    if store is None:
        return None
    try:
        run = record["id"]
        group = store.get(run)
        if group is None or group.attrs.get(_STORED) != record.get("completed_steps"):
            return None
        if group.attrs.get("status") != record.get("status"):
            return None
        arrays = {name: store[f"{run}/{name}"] for name in _ARRAYS}
        return _StoredRun.from_zarr(group, arrays, path)
    except Exception:
        return None


def _manifest(path: Path | str) -> tuple[Path, dict[str, Any]]:
    p = Path(path)
    if p.is_dir():
        p = p / MANIFEST
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise LieflowError(
            f"{str(p)!r} does not exist. To fix: give a sweep directory (or its "
            f"{MANIFEST}) written by `lieflow sweep`."
        ) from None
    except (OSError, ValueError) as exc:
        raise LieflowError(f"cannot read the sweep manifest {str(p)!r}: {exc}.") from None
    if not isinstance(data, dict) or data.get("format") != SWEEP_FORMAT:
        raise LieflowError(
            f"{str(p)!r} is not a lieflow sweep manifest (no format = {SWEEP_FORMAT!r}). "
            "To fix: give the directory written by `lieflow sweep`."
        )
    return p, data


def _label_values(values: Sequence[Any]) -> np.ndarray[Any, Any]:
    """Axis labels: the values, or their JSON text when they are lists or tables."""
    if all(isinstance(v, (bool, int, float, str)) for v in values):
        return np.asarray(values)
    return np.asarray([json.dumps(v, sort_keys=True) for v in values])


def open_sweep(
    manifest_or_dir: Path | str,
    *,
    stack: bool = False,
    chunks: Mapping[str, int] | str | None = None,
) -> Any:
    """A sweep's runs as one :class:`xarray.Dataset`, one dimension per axis of the grid.

    Parameters
    ----------
    manifest_or_dir : path
        The sweep directory or its ``manifest.json``.
    stack : bool
        One ``run`` dimension (with every swept key as a coordinate along it) instead of a
        dimension per axis.
    chunks : mapping or "auto", optional
        Give dask arrays (``Dataset.chunk``).

    Returns
    -------
    xarray.Dataset
        The variables of :func:`open_run` with the axes in front (``scheme``, ``h``...; a
        zipped group's other keys are coordinates along its axis; ``attrs["sweep_axes"]``
        maps dimension names to keys), padded with NaN where runs differ in length or
        size (the ``time`` coordinate is then ``t`` over the axes and ``time``), plus per
        run ``status``, ``error``, ``completed_steps``, ``requested_steps``, ``wall_time``,
        ``max_energy_error``, ``step_size`` and ``config``. A run without a readable file (failed
        before its first step, not run yet) is all NaN with its status.
    """
    xr = _xarray()
    path, data = _manifest(manifest_or_dir)
    root = path.parent.absolute()
    axes = data["axes"]
    lead = tuple(len(a["values"][0]) for a in axes)
    lead_dims = [a["name"] for a in axes]
    records = {tuple(r["index"]): r for r in data["runs"]}
    order = list(itertools.product(*(range(n) for n in lead)))
    store = _store_members(root)
    infos: list[_StoredRun | None] = []
    for index in order:
        rec = records.get(index)
        info = None if rec is None else _stored_run(store, rec, root / rec["output"])
        if info is None and rec is not None and os.path.exists(root / rec["output"]):
            try:
                info = _StoredRun(root / rec["output"])
            except LieflowError:
                info = None  # damaged or being written: shown as missing, with its status
        infos.append(info)
    present = [i for i in infos if i is not None]
    dims_stacked = ["run"] if stack else lead_dims
    lead_shape = (len(order),) if stack else lead
    variables: dict[str, Any] = {}
    coords: dict[str, Any] = {}
    if present:
        variables = _variables(infos, lead_shape, dims_stacked)
        ref = present[0]
        same_t = all(
            i.n_saved == ref.n_saved and np.array_equal(i.t, ref.t) for i in present
        ) and len(present) == len(infos)
        rows_t = max(i.n_saved for i in present)
        if same_t:
            coords["time"] = ("time", ref.t)
            coords["saved_step"] = ("time", ref.saved_step)
        else:
            t = np.full((len(infos), rows_t), np.nan)
            for j, i in enumerate(infos):
                if i is not None:
                    t[j, : i.n_saved] = i.t
            coords["t"] = ((*dims_stacked, "time"), t.reshape(*lead_shape, rows_t))
        k = max(i.k for i in present)
        coords["step"] = ("step", np.arange(k + 1))
        coords["casimir"] = (
            "casimir",
            np.asarray(
                max((i.attrs.get("casimir_powers", []) for i in present), key=len), dtype=int
            ),
        )
        if ref.members is not None:
            coords["ensemble"] = ("ensemble", ref.seeds)

    def per_run(get: Any, dtype: Any, fill: Any) -> Any:
        out = np.full(len(order), fill, dtype=dtype)
        for j, index in enumerate(order):
            rec = records.get(index)
            if rec is not None:
                value = get(rec, infos[j])
                out[j] = fill if value is None else value
        return (dims_stacked, out.reshape(lead_shape))

    variables["status"] = per_run(lambda r, i: r["status"], object, "missing")
    variables["error"] = per_run(lambda r, i: r.get("error", ""), object, "")
    for name in ("completed_steps", "requested_steps", "attempts"):
        variables[name] = per_run(lambda r, i, n=name: r.get(n), np.int64, 0)
    for name in ("wall_time", "max_energy_error"):
        variables[name] = per_run(lambda r, i, n=name: r.get(n), np.float64, np.nan)
    variables["step_size"] = per_run(lambda r, i: None if i is None else i.h, np.float64, np.nan)
    variables["config"] = per_run(
        lambda r, i: None if i is None else str(i.attrs.get("config", "")), object, ""
    )
    variables["output"] = per_run(lambda r, i: str(root / r["output"]), object, "")
    # axis coordinates
    for a, name in zip(axes, lead_dims, strict=True):
        keys, values = a["keys"], a["values"]
        for j, (key, vals) in enumerate(zip(keys, values, strict=True)):
            cname = name if j == 0 else _coord_name(key, coords, lead_dims)
            labels = _label_values(vals)
            if stack:
                pos = lead_dims.index(name)
                coords[cname] = ("run", labels[[ix[pos] for ix in order]], {"key": key})
            else:
                coords[cname] = (name, labels, {"key": key})
    attrs = {
        "sweep_directory": str(root),
        "grid_source": data.get("grid_source", ""),
        "grid": data.get("grid", ""),
        "sweep_axes": json.dumps({a["name"]: a["keys"] for a in axes}),
        "lieflow_version": data.get("lieflow_version", ""),
        "runs_from_store": sum(i is not None and i.group is not None for i in infos),
    }
    ds = xr.Dataset(variables, coords=coords, attrs=attrs)
    if stack:
        ids = [records[ix]["id"] if ix in records else "" for ix in order]
        ds = ds.assign_coords(run=("run", ids))
    return ds.chunk(chunks) if chunks is not None else ds


def _coord_name(key: str, taken: Mapping[str, Any], dims: Sequence[str]) -> str:
    short = key.split(".")[-1]
    return key if short in taken or short in dims or short in _DIAGNOSTICS else short
