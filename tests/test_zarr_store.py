"""A sweep's Zarr store (issue 16.4): ``lieflow.sweep(..., store="zarr")`` /
``lieflow sweep --store zarr`` writes every run into one store, each worker its own runs;
``lieflow.open_sweep`` reads it and gives the dataset the trajectory files give."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import needs_zeitlin, zeitlin_ensemble

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.datasets import ZARR_STORE, open_sweep

xr = pytest.importorskip("xarray")
zarr = pytest.importorskip("zarr", minversion="3")

BASE = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }

[initial]
random = true
seeds = [0, 5]

[scheme]
name = "gauss2"

[solver]
name = "fixed_point"

[run]
h = 0.1
steps = 20
save_every = 10
engine = "numpy"
"""

GRID = """
"scheme.name" = ["midpoint", "gauss2"]

[[sweep.zip]]
"run.steps" = [12, 30]
"solver.params.max_iter" = [100, 1]
"""


def write_grid(tmp_path: Path, base: str = BASE, table: str = GRID) -> Path:
    path = tmp_path / "grid.toml"
    path.write_text(base + "\n[sweep]\n" + table)
    return path


def from_files(directory: Path) -> object:
    """The dataset of the trajectory files alone (the store moved aside)."""
    aside = directory.parent / "aside.zarr"
    shutil.move(directory / ZARR_STORE, aside)
    try:
        return open_sweep(directory).load()
    finally:
        shutil.move(aside, directory / ZARR_STORE)


def assert_same(a: object, b: object) -> None:
    xr.testing.assert_identical(a.drop_attrs(), b.drop_attrs())  # type: ignore[attr-defined]


def test_a_process_pool_sweep_writes_one_store_that_opens_as_the_files(tmp_path: Path) -> None:
    res = lf.sweep(write_grid(tmp_path), workers=2, store="zarr")
    assert [r["status"] for r in res.runs] == ["complete", "failed", "complete", "failed"]
    assert len({r["pid"] for r in res.runs}) >= 1 and not any("store_error" in r for r in res.runs)
    store = res.directory / ZARR_STORE
    root = zarr.open_group(str(store), mode="r")
    assert sorted(root.group_keys()) == sorted(r["id"] for r in res.runs)
    for rec in res.runs:  # each run's group holds its file, up to the checkpoint
        group = root[rec["id"]]
        tr = io.read_trajectory(res.directory / rec["output"])
        np.testing.assert_array_equal(group["W"][...], tr.W)
        np.testing.assert_array_equal(group["iterations"][1:], tr.iterations)
        assert group.attrs["status"] == rec["status"] and group.attrs["config"] == tr.meta["config"]
    ds = open_sweep(res.directory)
    assert ds.attrs["runs_from_store"] == 4
    assert ds.W.dims == ("scheme", "steps", "time", "ensemble", "row", "col")
    files = from_files(res.directory)
    assert files.attrs["runs_from_store"] == 0
    assert_same(ds.load(), files)
    stacked = open_sweep(res.directory, stack=True)
    assert stacked.attrs["runs_from_store"] == 4
    np.testing.assert_array_equal(stacked.W.isel(run=0).values, files.W.isel(scheme=0, steps=0))


def test_rerun_skips_and_fills_the_store_and_stale_groups_are_not_read(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, table='"scheme.name" = ["midpoint", "gauss2"]')
    first = lf.sweep(grid, workers=2)  # no store yet
    assert first.ok and not (first.directory / ZARR_STORE).exists()
    again = lf.sweep(grid, workers=2, store="zarr")  # complete runs: skipped, stored here
    assert again.skipped == 2
    assert open_sweep(again.directory).attrs["runs_from_store"] == 2
    # a longer run: its group (20 steps) is stale until its worker rewrites it (30 steps)
    longer = grid.read_text().replace("steps = 20", "steps = 30")
    grid.write_text(longer)
    manifest = json.loads((again.directory / "manifest.json").read_text())
    assert {r["completed_steps"] for r in manifest["runs"]} == {20}
    res = lf.sweep(grid, workers=2, store="zarr")
    assert res.ok and res.skipped == 0
    ds = open_sweep(res.directory)
    assert ds.attrs["runs_from_store"] == 2 and ds.step.size == 31
    assert_same(ds.load(), from_files(res.directory))
    # a group the manifest does not match (another step count) is read from the file
    group = zarr.open_group(str(res.directory / ZARR_STORE / res.runs[0]["id"]), mode="r+")
    group.attrs["lieflow_stored_steps"] = 7
    with pytest.warns(UserWarning, match="Consolidated metadata"):
        zarr.consolidate_metadata(str(res.directory / ZARR_STORE))
    assert open_sweep(res.directory).attrs["runs_from_store"] == 1


def test_lieflow_sweep_store_option_and_bad_stores(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, table='"run.h" = [0.1, 0.05]')
    assert main(["sweep", str(grid), "--workers", "2", "--store", "zarr", "--no-progress"]) == 0
    assert open_sweep(tmp_path / "grid").attrs["runs_from_store"] == 2
    with pytest.raises(lf.InputError, match="store must be one of 'zarr' or None"):
        lf.sweep(grid, store="parquet")


def test_lieflow_sweep_refuses_an_unknown_store(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    grid = write_grid(tmp_path, table='"run.h" = [0.1, 0.05]')
    assert main(["sweep", str(grid), "--store", "parquet"]) == 2
    assert "invalid choice: 'parquet' (choose from 'zarr')" in capsys.readouterr().err


@needs_zeitlin
def test_complex_ensemble_runs_in_the_store(tmp_path: Path) -> None:
    base = zeitlin_ensemble(members=2, steps=6, save_every=3)
    res = lf.sweep(write_grid(tmp_path, base, '"run.h" = [0.01, 0.02]'), workers=2,
                   store="zarr")  # fmt: skip
    assert res.ok
    ds = open_sweep(res.directory)
    assert ds.attrs["runs_from_store"] == 2 and ds.W.dtype == np.complex128
    assert_same(ds.load(), from_files(res.directory))


def _old_store(directory: Path, runs: list[dict[str, object]], to: Path) -> Path:
    """A copy of the sweep ``directory`` whose store is written the old way: each run's
    finished file copied into it by ``write_zarr_run``."""
    from lieflow.app.datasets import write_zarr_run

    shutil.copytree(directory, to)
    shutil.rmtree(to / ZARR_STORE)
    zarr.open_group(str(to / ZARR_STORE), mode="w")
    for rec in runs:
        write_zarr_run(to / str(rec["output"]), to / ZARR_STORE, str(rec["id"]))
    with pytest.warns(UserWarning, match="Consolidated metadata"):
        zarr.consolidate_metadata(str(to / ZARR_STORE))
    return to


def test_workers_write_the_store_as_they_step_bit_for_bit_the_old_copy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import concurrent.futures as cf

    from lieflow.app import datasets

    def no_copy(*args: object, **kwargs: object) -> int:
        raise AssertionError("a run's file was copied into the store")

    monkeypatch.setattr(datasets, "write_zarr_run", no_copy)
    table = '"scheme.name" = ["midpoint", "gauss2"]\n"solver.params.max_iter" = [100, 1]'
    grid = write_grid(tmp_path, table=table)  # two complete, two failed (last state kept)
    with cf.ThreadPoolExecutor(2) as pool:
        first = lf.sweep(grid, executor=pool, store="zarr")
    assert [r["status"] for r in first.runs] == ["complete", "failed", "complete", "failed"]
    assert not any("store_error" in r for r in first.runs)
    # longer runs: resumed from their files' checkpoints, their groups continued
    grid.write_text(grid.read_text().replace("steps = 20", "steps = 35"))
    with cf.ThreadPoolExecutor(2) as pool:
        res = lf.sweep(grid, executor=pool, store="zarr")
    assert [r.get("new_steps") for r in res.runs] == [15, None, 15, None]
    assert not any("store_error" in r for r in res.runs)
    monkeypatch.undo()
    old = _old_store(res.directory, res.runs, tmp_path / "old")
    new_root = zarr.open_group(str(res.directory / ZARR_STORE), mode="r")
    old_root = zarr.open_group(str(old / ZARR_STORE), mode="r")
    for rec in res.runs:
        new, was = new_root[rec["id"]], old_root[rec["id"]]
        assert dict(new.attrs) == dict(was.attrs)
        assert sorted(new.array_keys()) == sorted(was.array_keys())
        for key in was.array_keys():
            a, b = new[key][...], was[key][...]
            assert a.dtype == b.dtype and a.shape == b.shape, key
            np.testing.assert_array_equal(a, b, strict=True)
    ds, expected = open_sweep(res.directory).load(), open_sweep(old).load()
    assert ds.attrs["runs_from_store"] == expected.attrs["runs_from_store"] == 4
    drop = ("sweep_directory",)
    xr.testing.assert_identical(
        ds.drop_vars("output")
        .drop_attrs()
        .assign_attrs({k: v for k, v in ds.attrs.items() if k not in drop}),
        expected.drop_vars("output")
        .drop_attrs()
        .assign_attrs({k: v for k, v in expected.attrs.items() if k not in drop}),
    )


class _StopAfter:
    """A monitor that presses Ctrl-C once ``steps`` steps are recorded."""

    def __init__(self, steps: int) -> None:
        self.left = steps

    def start(self, done: int, total: int) -> None:
        pass

    def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
        self.left -= steps
        if self.left <= 0:
            raise KeyboardInterrupt

    def stop(self) -> None:
        pass


def test_an_interrupted_run_continues_its_group_when_it_resumes(tmp_path: Path) -> None:
    from lieflow.app.config import build, parse_config
    from lieflow.app.datasets import write_zarr_run
    from lieflow.app.zarr_sink import ZarrSink

    text = BASE.replace("steps = 20", "steps = 300").replace("save_every = 10", "save_every = 7")
    store, out = tmp_path / ZARR_STORE, tmp_path / "run.h5"
    zarr.open_group(str(store), mode="w")
    opened: list[ZarrSink] = []

    def more_sinks(writer: io.TrajectoryWriter) -> tuple[ZarrSink]:
        opened.append(ZarrSink.open(store, "run", writer))
        return (opened[-1],)

    setup = build(parse_config(text + 'checkpoint = "saves"\n'), output=out, replace=False)
    first = io.run(setup, resume=True, monitor=_StopAfter(100), more_sinks=more_sinks)  # type: ignore[arg-type]
    assert first.status == "interrupted" and 0 < first.completed_steps < 300
    group = zarr.open_group(str(store / "run"), mode="r")
    assert group.attrs["lieflow_stored_steps"] == first.completed_steps and opened[0].in_sync
    assert group.attrs["status"] == "interrupted"
    done = io.run(setup, resume=True, more_sinks=more_sinks)
    assert done.status == "complete" and done.new_steps == 300 - first.completed_steps
    assert opened[1].in_sync and not opened[1].error
    write_zarr_run(out, tmp_path / "copy.zarr", "run")
    new, was = zarr.open_group(str(store / "run")), zarr.open_group(str(tmp_path / "copy.zarr/run"))
    assert dict(new.attrs) == dict(was.attrs) and new.attrs["resumes"] == 1
    for key in was.array_keys():
        np.testing.assert_array_equal(new[key][...], was[key][...], strict=True)
    # a group that is not at the file's checkpoint is not continued: the sink writes nothing
    new.attrs["lieflow_stored_steps"] = 5
    longer = build(parse_config(text.replace("300", "310")), output=out, replace=False)
    io.run(longer, resume=True, more_sinks=more_sinks)
    assert not opened[2].in_sync and "holds 5 steps, the file 300" in opened[2].error
    assert zarr.open_group(str(store / "run")).attrs["lieflow_stored_steps"] == 5
