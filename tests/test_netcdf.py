"""Trajectory files are netCDF-4 (issue 16.4): plain ``xarray.open_dataset(path,
engine="h5netcdf")`` opens what ``lieflow run`` writes, with named dimensions, real and
complex states, ensembles; files of format version 1 are still read and resumed."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from helpers import needs_zeitlin, zeitlin_ensemble

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.config import build, load_config, parse_config
from lieflow.app.io import _format, _reader, _slots

xr = pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")

DATA = Path(__file__).parent / "data"

RIGID = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }

[initial]
random = true
seed = 3

[scheme]
name = "gauss2"

[solver]
name = "fixed_point"
params = { rtol = 1e-15 }

[run]
h = 0.1
steps = 60
save_every = 10
engine = "numpy"
"""

ZEITLIN = zeitlin_ensemble()

NAMES = ("energy", "energy_error", "casimirs", "casimir_drift")


def lieflow_run(tmp_path: Path, text: str, name: str) -> Path:
    """``lieflow run`` of ``text`` into ``tmp_path/name``."""
    config = tmp_path / f"{name}.toml"
    config.write_text(text, encoding="utf-8")
    out = tmp_path / f"{name}.h5"
    assert main(["run", str(config), "--no-progress", "--out", str(out)]) == 0
    return out


def v1_file(tmp_path: Path, name: str) -> Path:
    """A copy of a file written by lieflow with format version 1 (``tests/data``: made
    with the configurations above by the lieflow of commit b044ffd, gzipped)."""
    out = tmp_path / name
    with gzip.open(DATA / f"{name}.gz", "rb") as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return out


# -- what netCDF-C requires of an HDF5 file --------------------------------------------------


def _attr_ok(value: Any) -> bool:
    """An attribute netCDF can hold: a string, a number, or a 1-D array of numbers."""
    if isinstance(value, (str, bytes, np.bytes_, int, float, np.integer, np.floating)):
        return not isinstance(value, (bool, np.bool_))
    if isinstance(value, np.ndarray):
        return value.ndim <= 1 and value.dtype.kind in "iuf"
    return False


def assert_netcdf4(path: Path) -> None:
    """Every dataset is a netCDF dimension or variable (one dimension scale per axis, of
    the axis's length; variables sharing an unlimited dimension equally long), names have
    no '/', attributes are strings, numbers or 1-D numeric arrays, complex numbers use the
    committed type ``_PFNC_DOUBLE_COMPLEX_TYPE``."""
    problems: list[str] = []
    lengths: dict[str, set[int]] = {}
    with h5py.File(path, "r") as f:

        def visit(name: str, obj: Any) -> None:
            for key, value in obj.attrs.items():
                if key in ("DIMENSION_LIST", "REFERENCE_LIST", "CLASS", "NAME"):
                    continue
                if not _attr_ok(value):
                    problems.append(f"{name}: attribute {key} = {value!r}")
            if isinstance(obj, h5py.Datatype):
                if name != "_PFNC_DOUBLE_COMPLEX_TYPE":
                    problems.append(f"unexpected committed type {name}")
                return
            if not isinstance(obj, h5py.Dataset):
                return
            if obj.dtype.kind == "c" and not obj.id.get_type().committed():
                problems.append(f"{name}: complex without the committed nc-complex type")
            if obj.attrs.get("CLASS") == b"DIMENSION_SCALE":
                return
            for axis, n in enumerate(obj.shape):
                scales = list(obj.dims[axis].values())
                if len(scales) != 1:
                    problems.append(f"{name}: axis {axis} has {len(scales)} dimension scales")
                    continue
                scale = scales[0]
                if scale.maxshape == (None,):
                    lengths.setdefault(scale.name, set()).add(n)
                elif scale.shape[0] != n:
                    problems.append(f"{name}: axis {axis} is {n} long, {scale.name} is not")

        for key, value in f.attrs.items():
            if not _attr_ok(value):
                problems.append(f"/: attribute {key} = {value!r}")
        f.visititems(visit)
    ragged = {dim: sorted(n) for dim, n in lengths.items() if len(n) > 1}
    assert not problems and not ragged, (problems, ragged)


# -- version 2 ------------------------------------------------------------------------------


def test_a_lieflow_run_file_opens_with_plain_xarray(tmp_path: Path) -> None:
    path = lieflow_run(tmp_path, RIGID.replace("seed = 3", "seeds = [3, 1]"), "rigid")
    assert io.format_version(path) == 2
    assert_netcdf4(path)
    tr = io.read_trajectory(path)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds.W.dims == ("time", "ensemble", "row", "col")
        assert dict(ds.sizes) == {"time": 7, "ensemble": 2, "row": 3, "col": 3, "step": 61,
                                  "casimir": 1}  # fmt: skip
        assert ds.energy_error.dims == ("step", "ensemble")
        assert ds.casimir_drift.dims == ("step", "ensemble", "casimir")
        assert ds.iterations.dims == ds.residual.dims == ("step",)
        np.testing.assert_array_equal(ds.W.values, tr.W)
        np.testing.assert_array_equal(ds.time.values, tr.t)
        np.testing.assert_array_equal(ds.saved_step.values, tr.step)
        assert "saved_step" in ds.coords
        np.testing.assert_array_equal(ds.step.values, np.arange(61))
        np.testing.assert_array_equal(ds.ensemble.values, [3, 1])  # the seeds
        np.testing.assert_array_equal(ds.casimir.values, [2])
        for name in NAMES:
            np.testing.assert_array_equal(ds[name].values, getattr(tr, name))
        np.testing.assert_array_equal(ds.iterations.values[1:], tr.iterations)
        np.testing.assert_array_equal(ds.residual.values[1:], tr.residual)
        assert ds.iterations.values[0] == 0 and np.isnan(ds.residual.values[0])
        assert ds.attrs["status"] == "complete" and ds.attrs["h"] == 0.1
        assert ds.attrs["config"] == tr.meta["config"]
        # open_run gives the same arrays under the same names
        run = lf.open_run(path)
        for name in ("W", *NAMES, "iterations", "residual"):
            assert run[name].dims == ds[name].dims
            np.testing.assert_array_equal(run[name].values, ds[name].values)
    with xr.open_dataset(path, engine="h5netcdf", group="initial") as initial:
        np.testing.assert_array_equal(initial.W0.values, tr.W[0])
    tree = xr.open_datatree(path, engine="h5netcdf")  # every group, no phony dimensions
    slot = tree[f"checkpoint/slot{int(tree['checkpoint'].attrs['current'])}"]
    np.testing.assert_array_equal(slot["W"].values, tr.checkpoint.W)
    assert slot.attrs["step"] == 60
    assert "_NCProperties" not in tr.meta


@needs_zeitlin
def test_complex_ensemble_states_and_extra_diagnostics(tmp_path: Path) -> None:
    """Euler-Zeitlin: complex states in the nc-complex compound type, read as complex."""
    path = lieflow_run(tmp_path, ZEITLIN, "ez")
    assert_netcdf4(path)
    tr = io.read_trajectory(path)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds.W.dtype == np.complex128 and ds.W.dims == ("time", "ensemble", "row", "col")
        np.testing.assert_array_equal(ds.W.values, tr.W)
        np.testing.assert_array_equal(ds.ensemble.values, [0, 1, 2])
        for name in NAMES:
            np.testing.assert_array_equal(ds[name].values, getattr(tr, name))
    extra = io.read_extra(path)
    with xr.open_dataset(path, engine="h5netcdf", group="diagnostics/extra") as ex:
        assert ex.energy_spectrum.dims[:2] == ("sample", "ensemble")
        assert set(extra) == set(ex.data_vars)
        for name, values in extra.items():
            np.testing.assert_array_equal(ex[name].values, values)
    run = lf.open_run(path)
    assert run.W.dtype == np.complex128
    np.testing.assert_array_equal(run.W.values, tr.W)


def test_interrupted_and_resumed_files_stay_netcdf4(tmp_path: Path) -> None:
    """A save cut off half-way (rows past the checkpoint) is truncated on resume and the
    file is a valid netCDF-4 file again, bit for bit the uninterrupted run."""
    config = tmp_path / "run.toml"
    config.write_text(RIGID, encoding="utf-8")
    reference = io.run(build(load_config(config), output=tmp_path / "ref.h5")).path
    setup = build(load_config(config), output=tmp_path / "cut.h5")

    class Stop:
        def start(self, done: int, total: int) -> None:
            self.done = done

        def advance(self, steps: int, iterations: int, err: float | None) -> None:
            self.done += steps
            if self.done >= 23:
                raise KeyboardInterrupt

        def stop(self) -> None:
            pass

    io.run(setup, monitor=Stop())
    assert_netcdf4(setup.output)
    with h5py.File(setup.output, "r+") as f:
        for name in ("step", "energy", "iterations"):
            f[name].resize(f[name].shape[0] + 3, axis=0)
    io.run(setup, resume=True)
    assert_netcdf4(setup.output)
    a, b = io.read_trajectory(setup.output), io.read_trajectory(reference)
    for name in ("step", "t", "W", *NAMES, "iterations", "residual"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    with (
        xr.open_dataset(setup.output, engine="h5netcdf") as x,
        xr.open_dataset(reference, engine="h5netcdf") as y,
    ):
        xr.testing.assert_identical(x.drop_attrs(), y.drop_attrs())


def test_integrate_out_writes_netcdf4(tmp_path: Path) -> None:
    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W0 = np.stack([body.random_state(0), body.random_state(1)])
    sol = lf.integrate(body, lf.schemes.get("midpoint"), W0, 0.1, steps=15, save_every=5,
                       out=tmp_path / "sol.h5", engine="numpy")  # fmt: skip
    assert_netcdf4(tmp_path / "sol.h5")
    with xr.open_dataset(tmp_path / "sol.h5", engine="h5netcdf") as ds:
        np.testing.assert_array_equal(ds.ensemble.values, [0, 1])
        np.testing.assert_array_equal(ds.W.values[-1], sol.W_final)


# -- version 1 ------------------------------------------------------------------------------


def assert_close_runs(a: io.Trajectory, b: io.Trajectory) -> None:
    """The same run to roundoff (a file of an older lieflow against this one's, whose
    solvers may take other numbers of iterations)."""
    assert a.completed_steps == b.completed_steps
    assert a.iterations.shape == b.iterations.shape
    for name in ("step", "t", "W", *NAMES):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-14)


@needs_zeitlin
def test_version_1_files_are_read(tmp_path: Path) -> None:
    old = v1_file(tmp_path, "v1_zeitlin_ensemble.h5")
    assert io.format_version(old) == 1
    new = lieflow_run(tmp_path, ZEITLIN, "ez")
    a, b = io.read_trajectory(old), io.read_trajectory(new)
    assert a.meta["format_version"] == 1 and b.meta["format_version"] == 2
    assert a.W.dtype == np.complex128 and a.W.shape == b.W.shape == (4, 3, 4, 4)
    assert_close_runs(a, b)
    xa, xb = io.read_extra(old), io.read_extra(new)
    assert set(xa) == set(xb) and len(xa["step"]) == 4
    run = lf.open_run(old)  # the same dataset as from a version-2 file
    assert run.sizes == lf.open_run(new).sizes
    np.testing.assert_array_equal(run.W.values, a.W)
    np.testing.assert_array_equal(run.ensemble.values, [0, 1, 2])
    for name in NAMES:
        np.testing.assert_array_equal(run[name].values, getattr(a, name))
    np.testing.assert_array_equal(run.iterations.values[1:], a.iterations)
    assert run.iterations.values[0] == 0 and np.isnan(run.residual.values[0])
    assert io.read_diagnostics(old).iterations.shape == (12,)


def test_a_version_1_file_resumes_bit_for_bit_in_its_own_layout(tmp_path: Path) -> None:
    config = tmp_path / "run.toml"
    config.write_text(RIGID, encoding="utf-8")
    whole, split = v1_file(tmp_path, "v1_rigid_interrupted.h5"), tmp_path / "split.h5"
    shutil.copy(whole, split)
    assert io.read_checkpoint(whole).step == 37
    summary = io.run(build(load_config(config), output=whole), resume=True)
    assert summary.new_steps == 23 and summary.status == "complete"
    half = RIGID.replace("steps = 60", "steps = 45")
    io.run(build(parse_config(half), output=split), resume=True)
    io.run(build(load_config(config), output=split), resume=True)
    for path in (whole, split):
        assert io.format_version(path) == 1  # continued as it was written
        with h5py.File(path, "r") as f:
            assert "trajectory" in f and "W" not in f
    a, b = io.read_trajectory(whole), io.read_trajectory(split)
    for name in (*NAMES, "iterations", "residual"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert list(a.step) == [0, 10, 20, 30, 40, 50, 60]
    assert list(b.step) == [0, 10, 20, 30, 40, 45, 50, 60]  # also where it stopped
    np.testing.assert_array_equal(a.W, b.W[np.isin(b.step, a.step)])
    reference = io.run(build(load_config(config), output=tmp_path / "ref.h5")).path
    assert_close_runs(a, io.read_trajectory(reference))
    run = lf.open_run(whole)
    np.testing.assert_array_equal(run.iterations.values[1:], a.iterations)


def test_a_newer_format_is_refused(tmp_path: Path) -> None:
    path = io.run(build(parse_config(RIGID.replace("steps = 60", "steps = 3")),
                        output=tmp_path / "x.h5")).path  # fmt: skip
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 3
    with pytest.raises(lf.LieflowError, match=r"format version 3.*reads versions 1 to 2"):
        io.read_trajectory(path)
    with pytest.raises(lf.LieflowError, match="format version 3"):
        lf.open_run(path)


def test_a_slot_follows_state_trees_that_change_shape(tmp_path: Path) -> None:
    """Leaves that become trees and back (a state of another shape after a resume by
    another lieflow), arrays that change size, a dimension left by a killed writer: the
    slot holds exactly the items written (its digest matches) and stays netCDF-4."""
    path = io.run(build(parse_config(RIGID.replace("steps = 60", "steps = 2")),
                        output=tmp_path / "x.h5")).path  # fmt: skip
    W = io.read_checkpoint(path).W
    states = [
        {"W": W, "warm/a": np.ones(3), "warm/flag": True},
        {"W": W, "warm/a/b": np.ones((2, 2)), "warm/a/c": None, "warm/flag": False},
        {"W": W, "warm/a": np.arange(5.0), "warm/n": 3},
        {"W": W, "warm/a": np.arange(4.0) + 1j},
    ]
    with h5py.File(path, "r+") as f:
        slot, cache = f["checkpoint/slot0"], {}
        for k, items in enumerate(states):
            if k == 3:  # a dimension of another length that a killed writer left behind
                _slots._drop(slot, "warm/a")
                _format._dimension(slot["warm"], "a_dim0", 9)
                cache.clear()
            _slots._write_slot(slot, k, 0.1 * k, items, cache)
            stored = _reader._slot_items(slot)
            assert sorted(stored) == sorted(items)
            assert io.checkpoint_digest(k, 0.1 * k, stored) == slot.attrs["sha256"]
    assert_netcdf4(path)
