"""open_run / open_sweep (issue 16.4) and ensembles in one run (16.3), with real numbers."""

from __future__ import annotations

import concurrent.futures as cf
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import needs_zeitlin, zeitlin_ensemble

import lieflow as lf
from lieflow.app import io
from lieflow.app.config import ConfigError, build, parse_config
from lieflow.app.sweeps import SweepResult

xr = pytest.importorskip("xarray")

RIGID = """
[system]
name = "rigid_body"
params = {{ inertia = [1.0, 2.0, 3.0] }}

[initial]
random = true
{initial}

[scheme]
name = "{scheme}"

[run]
h = {h}
steps = {steps}
save_every = {save_every}
engine = "numpy"
"""


def rigid(initial: str = "seed = 0", scheme: str = "gauss2", h: float = 0.1, steps: int = 30,
          save_every: int = 7) -> str:  # fmt: skip
    return RIGID.format(initial=initial, scheme=scheme, h=h, steps=steps, save_every=save_every)


def run_file(tmp_path: Path, text: str, name: str = "run.h5") -> Path:
    setup = build(parse_config(text, base_dir=tmp_path), output=tmp_path / name)
    assert io.run(setup).status == "complete"
    return tmp_path / name


def test_open_run_round_trip_is_exact(tmp_path: Path) -> None:
    path = run_file(tmp_path, rigid())
    tr = io.read_trajectory(path)
    ds = lf.open_run(path)
    assert dict(ds.sizes) == {"time": 6, "row": 3, "col": 3, "step": 31, "casimir": 1}
    assert not ds.W.variable._in_memory  # read lazily
    np.testing.assert_array_equal(ds.W.values, tr.W)
    np.testing.assert_array_equal(ds.time.values, tr.t)
    np.testing.assert_array_equal(ds.saved_step.values, [0, 7, 14, 21, 28, 30])
    np.testing.assert_array_equal(ds.step_time.values, np.arange(31) * 0.1)
    for name in ("energy", "energy_error", "casimirs", "casimir_drift"):
        np.testing.assert_array_equal(ds[name].values, getattr(tr, name))
    np.testing.assert_array_equal(ds.iterations.values[1:], tr.iterations)
    np.testing.assert_array_equal(ds.residual.values[1:], tr.residual)
    assert ds.iterations.values[0] == 0 and np.isnan(ds.residual.values[0])
    assert ds.iterations.dtype == np.int64
    np.testing.assert_array_equal(ds.W_final.values, tr.W[-1])
    assert ds.attrs["config"] == tr.meta["config"] and ds.attrs["scheme"] == "gauss2"
    assert ds.attrs["status"] == "complete" and ds.attrs["h"] == 0.1
    # lazy indexing: slices, integers, arrays, negative steps
    np.testing.assert_array_equal(ds.W.isel(time=[0, 3, 5], row=1).values, tr.W[[0, 3, 5], 1])
    np.testing.assert_array_equal(ds.W.isel(time=slice(None, None, -2)).values, tr.W[::-2])
    np.testing.assert_array_equal(ds.energy_error.isel(step=-1).values, tr.energy_error[-1])
    np.testing.assert_array_equal(ds.W.sel(time=2.1).values, tr.W[3])
    dask_ds = lf.open_run(path, chunks={"step": 8})
    assert dask_ds.energy.chunks is not None
    np.testing.assert_array_equal(dask_ds.energy.values, tr.energy)


def test_ensemble_from_seeds_runs_as_one_batch(tmp_path: Path) -> None:
    seeds = [3, 1, 4, 5]
    path = run_file(tmp_path, rigid(f"seeds = {seeds}"))
    ds = lf.open_run(path)
    assert ds.W.dims == ("time", "ensemble", "row", "col")
    assert ds.energy_error.dims == ("step", "ensemble")
    assert ds.casimir_drift.dims == ("step", "ensemble", "casimir")
    np.testing.assert_array_equal(ds.ensemble.values, seeds)
    for seed in seeds:  # each member is the run of that seed alone (same solves to roundoff)
        alone = lf.open_run(run_file(tmp_path, rigid(f"seed = {seed}"), f"s{seed}.h5"))
        member = ds.sel(ensemble=seed)
        np.testing.assert_allclose(member.W.values, alone.W.values, rtol=0, atol=1e-13)
        np.testing.assert_allclose(member.energy.values, alone.energy.values, rtol=1e-13)
        assert float(member.energy_error.max()) < 1e-6
    # resume of an ensemble is bit for bit
    text = rigid(f"seeds = {seeds}")
    half = build(parse_config(text.replace("steps = 30", "steps = 13")), output=tmp_path / "r.h5")
    io.run(half)
    io.run(build(parse_config(text), output=tmp_path / "r.h5"), resume=True)
    resumed = lf.open_run(tmp_path / "r.h5")  # also keeps the state at step 13, where it stopped
    np.testing.assert_array_equal(resumed.energy.values, ds.energy.values)
    kept = resumed.W.sel(time=resumed.saved_step.isin(ds.saved_step.values))
    np.testing.assert_array_equal(kept.values, ds.W.values)


@needs_zeitlin
def test_ensemble_from_perturbations_and_complex_states(tmp_path: Path) -> None:
    text = zeitlin_ensemble()
    setup = build(parse_config(text), output=tmp_path / "ez.h5")
    system = setup.system
    base = system.random_state(2)
    expected = np.stack([base + 1e-3 * system.random_state(10 + k) for k in range(3)])
    np.testing.assert_allclose(setup.W0, expected, atol=1e-15)
    io.run(setup)
    ds = lf.open_run(tmp_path / "ez.h5")
    assert ds.W.dtype == np.complex128 and ds.W.shape == (4, 3, 4, 4)
    np.testing.assert_array_equal(ds.W.isel(time=0).values, setup.W0)
    np.testing.assert_array_equal(ds.ensemble.values, [0, 1, 2])
    assert float(ds.casimir_drift.max()) < 1e-10
    with pytest.raises(ConfigError, match="both seeds and perturb"):
        parse_config(text.replace("seed = 2", "seeds = [1, 2]"))


GRID = """
"scheme.name" = ["midpoint", "gauss2"]

[[sweep.zip]]
"run.h" = [0.1, 0.05, 0.025]
"run.steps" = [10, 20, 40]
"run.save_every" = [5, 10, 20]
"""


def make_sweep(tmp_path: Path, base: str, table: str) -> SweepResult:
    grid = tmp_path / "grid.toml"
    grid.write_text(base + "\n[sweep]\n" + table)
    with cf.ThreadPoolExecutor(2) as pool:
        return lf.sweep(grid, pool)


def test_open_sweep_labelled_axes_and_a_convergence_fit(tmp_path: Path) -> None:
    res = make_sweep(tmp_path, rigid(), GRID)
    assert res.ok
    ds = lf.open_sweep(tmp_path / "grid")
    assert ds.W.dims == ("scheme", "h", "time", "row", "col")
    assert list(ds.scheme.values) == ["midpoint", "gauss2"]
    np.testing.assert_array_equal(ds.h.values, [0.1, 0.05, 0.025])
    np.testing.assert_array_equal(ds.steps.values, [10, 20, 40])  # zipped: a coordinate on h
    assert ds.h.attrs["key"] == "run.h" and json.loads(ds.attrs["sweep_axes"])["h"] == [
        "run.h", "run.steps", "run.save_every"]  # fmt: skip
    assert ds.time.dims == ("time",)  # every run saved at t = 0, 0.5, 1: one time axis
    np.testing.assert_allclose(ds.time.values, [0.0, 0.5, 1.0])
    assert (ds.status == "complete").all() and ds.step.size == 41
    # each cell is its file
    for rec in res.runs:
        sel = {"scheme": rec["params"]["scheme.name"], "h": rec["params"]["run.h"]}
        tr = io.read_trajectory(res.directory / rec["output"])
        np.testing.assert_array_equal(ds.W.sel(sel).values, tr.W)
        k = tr.completed_steps
        np.testing.assert_array_equal(ds.energy_error.sel(sel).values[: k + 1], tr.energy_error)
        assert np.isnan(ds.energy_error.sel(sel).values[k + 1 :]).all()  # padded
        np.testing.assert_array_equal(ds.iterations.sel(sel).values[1 : k + 1], tr.iterations)
    # a convergence study without glue: final-state error against a fine reference
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    ref = lf.integrate(system, lf.schemes.get("gauss4"), system.random_state(0), h=0.005,
                       steps=200, engine="numpy").W_final  # fmt: skip
    err = np.sqrt(((ds.W_final - ref) ** 2).sum(("row", "col")))
    orders = {
        s: np.polyfit(np.log(ds.h), np.log(err.sel(scheme=s)), 1)[0] for s in ds.scheme.values
    }
    assert abs(orders["midpoint"] - 2) < 0.15 and abs(orders["gauss2"] - 4) < 0.3, orders


def test_open_sweep_stacked_ragged_and_failed_runs(tmp_path: Path) -> None:
    table = '"run.steps" = [10, 25]\n"solver.params.max_iter" = [100, 1]'
    res = make_sweep(tmp_path, rigid() + '\n[solver]\nname = "fixed_point"\n', table)
    assert [r["status"] for r in res.runs] == ["complete", "failed", "complete", "failed"]
    ds = lf.open_sweep(res.manifest)
    assert ds.W.dims == ("steps", "max_iter", "time", "row", "col")
    assert "t" in ds.coords and ds.t.dims == ("steps", "max_iter", "time")  # ragged time
    ok = ds.sel(steps=25, max_iter=100)
    tr = io.read_trajectory(res.directory / res.runs[2]["output"])
    np.testing.assert_array_equal(ok.W.values, tr.W)
    np.testing.assert_array_equal(ok.t.values, tr.t)
    short = ds.sel(steps=10, max_iter=100)
    assert np.isnan(
        short.W.values[len(io.read_trajectory(res.directory / res.runs[0]["output"]).W) :]
    ).all()
    failed = ds.sel(steps=25, max_iter=1)
    assert failed.status.item() == "failed" and "did not converge" in failed.error.item()
    assert failed.completed_steps.item() == 0
    assert np.isnan(failed.energy_error.values[1:]).all()
    lazy = lf.open_sweep(res.directory, chunks={"step": 10})  # dask arrays
    assert lazy.energy_error.chunks is not None
    np.testing.assert_array_equal(lazy.energy_error.values, ds.energy_error.values)
    stacked = lf.open_sweep(res.directory, stack=True)
    assert stacked.W.dims == ("run", "time", "row", "col")
    assert list(stacked.steps.values) == [10, 10, 25, 25]
    assert list(stacked.run.values) == [r["id"] for r in res.runs]
    np.testing.assert_array_equal(stacked.W.isel(run=2).values, tr.W)
    assert res.open().sizes == ds.sizes


def test_open_sweep_of_ensembles_and_list_valued_axes(tmp_path: Path) -> None:
    table = '"system.params.inertia" = [[1.0, 2.0, 3.0], [1.0, 1.5, 4.0]]'
    res = make_sweep(tmp_path, rigid("seeds = [0, 1]"), table)
    ds = lf.open_sweep(tmp_path / "grid")
    assert ds.W.dims == ("inertia", "time", "ensemble", "row", "col")
    assert list(ds.inertia.values) == ["[1.0, 2.0, 3.0]", "[1.0, 1.5, 4.0]"]
    for j, rec in enumerate(res.runs):
        tr = io.read_trajectory(res.directory / rec["output"])
        np.testing.assert_array_equal(ds.W.isel(inertia=j).values, tr.W)
    assert ds.energy_error.isel(inertia=1, ensemble=1).max() < 1e-6


def test_open_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(lf.LieflowError, match="does not exist"):
        lf.open_sweep(tmp_path)
    (tmp_path / "manifest.json").write_text('{"format": "other"}')
    with pytest.raises(lf.LieflowError, match="not a lieflow sweep manifest"):
        lf.open_sweep(tmp_path)
    (tmp_path / "x.h5").write_bytes(b"not hdf5")
    with pytest.raises(lf.LieflowError, match="not an HDF5 file"):
        lf.open_run(tmp_path / "x.h5")
    monkeypatch.setitem(sys.modules, "xarray", None)
    with pytest.raises(lf.InputError, match=r"lieflow\[sweep\]"):
        lf.open_run(tmp_path / "x.h5")


def test_a_solution_as_a_dataset_matches_the_file_of_the_same_run(tmp_path: Path) -> None:
    path = run_file(tmp_path, rigid("seeds = [0, 1]"))
    setup = build(parse_config(rigid("seeds = [0, 1]")), output=tmp_path / "unused.h5")
    sol = lf.integrate(setup.system, setup.scheme, setup.W0, h=0.1, steps=30, save_every=7,
                       solver=setup.solver, engine="numpy")  # fmt: skip
    mem, disk = sol.to_xarray(), lf.open_run(path)
    assert mem.W.dims == disk.W.dims and mem.energy_error.dims == disk.energy_error.dims
    for name in ("W", "W_final", "energy_error", "casimir_drift", "iterations"):
        np.testing.assert_allclose(mem[name].values, disk[name].values, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(mem.time.values, disk.time.values)
    np.testing.assert_array_equal(mem.saved_step.values, disk.saved_step.values)
    assert mem.attrs["status"] == "success" and mem.attrs["completed_steps"] == 30


def test_every_checkpoint_reads_back_whatever_the_save_cadence(tmp_path: Path) -> None:
    """A flow-state leaf that is None at one checkpoint of a slot and an array at its next
    (the solver's warm start) used to leave a stale attribute that made the file read as
    damaged (steps = 5, save_every = 1 did); every cadence now reads back and resumes."""
    table = '"run.steps" = [1, 2, 3, 5, 7]\n"run.save_every" = [1, 2, 3]'
    res = make_sweep(tmp_path, rigid(), table)
    assert res.ok
    for rec in res.runs:
        path = res.directory / rec["output"]
        assert io.read_trajectory(path).completed_steps == rec["params"]["run.steps"]
        assert lf.open_run(path).W_final.shape == (3, 3)


def test_solution_to_xarray_holds_the_solution() -> None:
    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    sol = lf.integrate(body, lf.schemes.get("midpoint"), body.random_state(0), 0.1, steps=10)
    ds = sol.to_xarray()
    assert np.array_equal(ds["W"].values, sol.W)
    assert np.array_equal(ds["energy_error"].values, sol.energy_error)
