"""lieflow sweep (issue 16): grids, the manifest, resume, failures, retries, executors, CLI."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import os
import re
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import damage_last_chunk
from processes import Children

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.config import ConfigError, build
from lieflow.app.io import _lock
from lieflow.app.sweeps import SweepMonitor, _worker, load_sweep, parse_sweep, run_id, sweep

BASE = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }

[initial]
random = true
seed = 0

[scheme]
name = "gauss2"

[run]
h = 0.1
steps = 40
save_every = 10
engine = "numpy"
"""


def write_grid(tmp_path: Path, sweep_table: str, base: str = BASE, name: str = "grid") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(base + "\n[sweep]\n" + sweep_table)
    return path


def threads() -> cf.ThreadPoolExecutor:
    return cf.ThreadPoolExecutor(2)


GRID = """
"scheme.name" = ["midpoint", "gauss2"]
"initial.seed" = [0, 1]

[[sweep.zip]]
"run.h" = [0.1, 0.05]
"run.steps" = [20, 40]
"""


# -- parsing -------------------------------------------------------------------------------


def test_grid_is_the_product_of_axes_and_zipped_groups(tmp_path: Path) -> None:
    g = load_sweep(write_grid(tmp_path, GRID))
    assert g.shape == (2, 2, 2)
    assert [a.name for a in g.axes] == ["scheme", "seed", "h"]
    assert g.axes[2].keys == ("run.h", "run.steps")
    assert len(g.runs) == 8
    assert g.directory == tmp_path / "grid"
    last = g.runs[-1]
    assert dict(last.params) == {"scheme.name": "gauss2", "initial.seed": 1, "run.h": 0.05,
                                 "run.steps": 40}  # fmt: skip
    cfg = last.config
    assert (cfg.scheme.name, cfg.initial.seed, cfg.run.h, cfg.run.steps) == ("gauss2", 1, 0.05, 40)
    assert cfg.run.output == last.output == tmp_path / "grid" / "runs" / f"{last.id}.h5"
    # the base configuration's other keys are kept
    assert cfg.system.params["inertia"] == [1.0, 2.0, 3.0] and cfg.run.engine == "numpy"


def test_nested_tables_are_dotted_keys_and_directory_option(tmp_path: Path) -> None:
    g = load_sweep(write_grid(tmp_path, 'directory = "out/study"\n[sweep.solver.params]\n'
                              "rtol = [1e-10, 1e-14]\n"))  # fmt: skip
    assert g.axes[0].keys == ("solver.params.rtol",) and g.axes[0].name == "rtol"
    assert g.directory == tmp_path / "out" / "study"
    assert [r.config.solver.params["rtol"] for r in g.runs] == [1e-10, 1e-14]


SPLIT = (
    BASE
    + """
[splitting]
method = "strang"
flows = [{ name = "scaled", params = { rate = 0.5 } }, { name = "scaled", params = { rate = 1.0 } }]
"""
)


def test_a_number_in_a_key_indexes_a_list_of_the_base_configuration(tmp_path: Path) -> None:
    g = load_sweep(write_grid(tmp_path, '"splitting.flows.1.params.rate" = [0.0, 2.0]\n', SPLIT))
    assert g.axes[0].name == "rate"
    flows = [r.config.splitting.flows for r in g.runs]  # type: ignore[union-attr]
    assert [[f.params["rate"] for f in fl] for fl in flows] == [[0.5, 0.0], [0.5, 2.0]]
    for key, needle in [
        ("splitting.flows.2.params.rate", "is a list of 2 in the base configuration, and '2'"),
        ("splitting.flows.x.params.rate", "and 'x' is not an index of it"),
        ("splitting.method.x", "splitting.method is 'strang' in the base configuration"),
    ]:
        with pytest.raises(ConfigError, match=re.escape(needle)):
            load_sweep(write_grid(tmp_path, f'"{key}" = [1.0]\n', SPLIT))


def test_run_ids_are_deterministic_readable_and_order_independent() -> None:
    a = run_id({"scheme.name": "gauss2", "run.h": 0.1})
    swapped = run_id({"run.h": 0.1, "scheme.name": "gauss2"})
    assert a.split("_")[-1] == swapped.split("_")[-1]  # same hash, whatever the key order
    assert a.startswith("gauss2_h0.1_") and a != run_id({"scheme.name": "gauss2", "run.h": 0.2})
    assert run_id({"system.params.inertia": [1.0, 2.0, 3.0]}).startswith("inertia1-2-3_")


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ('"scheme.nme" = ["a", "b"]', "[scheme] nme: unknown key"),
        ('"bogus.h" = [1]', "[sweep] bogus.h: unknown key"),
        ("foo = 3", "[sweep] foo: unknown key"),
        ('"run.h" = 0.1', "expected a non-empty list"),
        ('"run.h" = []', "expected a non-empty list"),
        ('"run.output" = ["a.h5"]', "cannot be swept"),
        ('"run.h" = [0.1]\n[[sweep.zip]]\n"run.h" = [0.2]', "swept twice"),
        ('[[sweep.zip]]\n"run.h" = [0.1, 0.2]\n"run.steps" = [1]', "lists of different lengths"),
        ('"run.h" = [-0.1]', "[run] h: must be positive"),
        ('"scheme" = [1]', "whole section"),
        ('"run.h" = [0.1, 0.2, 0.1]', "[sweep] run.h: the point [0.1] is listed twice"),
    ],
)
def test_bad_grids_are_refused_naming_the_key(tmp_path: Path, table: str, needle: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_sweep(write_grid(tmp_path, table))
    assert needle in str(err.value)


def test_grid_without_sweep_or_with_an_output_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"\[sweep\]: missing section"):
        parse_sweep(BASE)
    with pytest.raises(ConfigError, match=r"\[run\] output: is not used by a sweep"):
        parse_sweep(BASE.replace("[run]", '[run]\noutput = "x.h5"') + '[sweep]\n"run.h" = [1.0]')


# -- running -------------------------------------------------------------------------------


def _files_equal(a: Path, b: Path) -> None:
    ta, tb = io.read_trajectory(a), io.read_trajectory(b)
    for name in ("W", "energy", "energy_error", "casimirs", "casimir_drift", "iterations",
                 "residual", "step", "t"):  # fmt: skip
        assert np.array_equal(getattr(ta, name), getattr(tb, name)), name


def test_sweep_runs_every_run_writes_manifest_and_skips_complete_runs(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, GRID)
    res = sweep(grid, threads())
    assert res.ok and res.counts["complete"] == 8 and res.skipped == 0
    manifest = json.loads(res.manifest.read_text())
    assert manifest["format"] == "lieflow-sweep" and len(manifest["runs"]) == 8
    for rec in manifest["runs"]:
        assert rec["status"] == "complete" and rec["error"] == ""
        assert rec["completed_steps"] == rec["requested_steps"] == rec["params"]["run.steps"]
        path = res.directory / rec["output"]
        tr = io.read_trajectory(path)
        assert tr.status == "complete" and tr.meta["scheme"] == rec["params"]["scheme.name"]
        # each file holds exactly what `lieflow run` of the run's own configuration writes
        assert "initial.seed = " in tr.meta["config"]
    # the same run computed on its own
    rec = manifest["runs"][5]
    spec = next(s for s in load_sweep(grid).runs if s.id == rec["id"])
    io.run(build(spec.config, output=tmp_path / "alone.h5"))
    _files_equal(tmp_path / "alone.h5", res.directory / rec["output"])
    mtimes = {p: p.stat().st_mtime_ns for p in (res.directory / "runs").glob("*.h5")}
    again = sweep(grid, threads())
    assert again.ok and again.skipped == 8
    assert {p: p.stat().st_mtime_ns for p in mtimes} == mtimes  # complete files untouched
    errors = [r["max_energy_error"] for r in res.runs]
    assert all(isinstance(e, float) and 0 <= e < 1e-3 for e in errors)
    assert [r["max_energy_error"] for r in again.runs] == errors  # carried over
    res.manifest.unlink()
    assert [r["max_energy_error"] for r in sweep(grid, threads()).runs] == errors  # from files


class _StopAfter:
    """A Monitor that interrupts a run after ``steps`` steps (like Ctrl-C)."""

    def __init__(self, steps: int) -> None:
        self.steps, self.done = steps, 0

    def start(self, done: int, total: int) -> None:
        self.done = done

    def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
        self.done += steps
        if self.done >= self.steps:
            raise KeyboardInterrupt

    def stop(self) -> None:
        pass


def test_interrupted_runs_resume_bit_for_bit_and_steps_can_grow(
    tmp_path: Path, one_step_chunks: None
) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1, 2]')
    g = load_sweep(grid)
    # two runs interrupted part-way (as by Ctrl-C or a killed job), one never started
    for spec, stop in zip(g.runs[:2], (13, 27), strict=True):
        summary = io.run(build(spec.config), monitor=_StopAfter(stop))
        assert summary.status == "interrupted" and 0 < summary.completed_steps < 40
    res = sweep(g, threads())
    assert res.ok and res.skipped == 0
    ref = sweep(g.runs[0].config.source, threads(), directory=tmp_path / "ref")
    assert ref.ok
    for spec in g.runs:
        _files_equal(spec.output, tmp_path / "ref" / "runs" / spec.output.name)
    assert io.read_trajectory(g.runs[0].output).meta["resumes"] == 1
    # more steps in the grid: the complete runs are continued, not redone
    longer = write_grid(tmp_path, '"initial.seed" = [0, 1, 2]',
                        BASE.replace("steps = 40", "steps = 60"))  # fmt: skip
    res = sweep(longer, threads())
    assert res.ok and res.skipped == 0
    assert [r["completed_steps"] for r in res.runs] == [60, 60, 60]


def test_a_failed_run_is_recorded_and_the_others_finish(tmp_path: Path) -> None:
    table = '"scheme.name" = ["gauss2", "no_such_scheme"]\n"solver.params.max_iter" = [100, 1]'
    grid = write_grid(tmp_path, table, BASE + '\n[solver]\nname = "fixed_point"\n')
    res = sweep(grid, threads())
    assert not res.ok
    by = {(r["params"]["scheme.name"], r["params"]["solver.params.max_iter"]): r for r in res.runs}
    assert by["gauss2", 100]["status"] == "complete"
    assert by["gauss2", 1]["status"] == "failed"
    assert "did not converge at step 1" in by["gauss2", 1]["error"]
    assert by["no_such_scheme", 100]["status"] == "failed"
    assert "no_such_scheme" in by["no_such_scheme", 100]["error"]
    assert len(res.failed) == 3
    manifest = json.loads(res.manifest.read_text())
    assert manifest["counts"] == {"pending": 0, "running": 0, "complete": 1, "failed": 3,
                                  "interrupted": 0}  # fmt: skip


class _LosingExecutor(cf.Executor):
    """Runs tasks inline, but loses the first ``lose`` attempts of every run (as if its
    worker died) after letting it compute ``partial`` steps."""

    def __init__(self, lose: int, partial: int = 0) -> None:
        self.lose, self.partial = lose, partial
        self.seen: dict[str, int] = {}

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> cf.Future[Any]:
        task = args[0]
        fut: cf.Future[Any] = cf.Future()
        n = self.seen[task["id"]] = self.seen.get(task["id"], 0) + 1
        if n <= self.lose:
            if self.partial:
                from lieflow.app.config import parse_config

                cfg = parse_config(task["text"], base_dir=task["base_dir"])
                io.run(build(cfg, output=task["output"], replace=False), resume=True,
                       monitor=_StopAfter(self.partial * n))  # fmt: skip
            fut.set_exception(RuntimeError(f"worker lost (attempt {n})"))
        else:
            fut.set_result(fn(*args, **kwargs))
        return fut


def test_a_lost_task_is_redone_from_its_checkpoint(tmp_path: Path, one_step_chunks: None) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1]')
    res = sweep(grid, _LosingExecutor(lose=2, partial=10))
    assert res.ok
    assert [r["attempts"] for r in res.runs] == [3, 3]
    for r in res.runs:
        assert io.read_trajectory(res.directory / r["output"]).meta["resumes"] == 2
    ref = sweep(grid, threads(), directory=tmp_path / "ref")
    for r in res.runs:
        _files_equal(res.directory / r["output"], ref.directory / r["output"])


def test_a_task_lost_too_often_is_failed_with_the_reason(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0]')
    res = sweep(grid, _LosingExecutor(lose=5), max_attempts=2)
    (rec,) = res.runs
    assert rec["status"] == "failed" and "worker lost (attempt 2)" in rec["error"]
    assert rec["attempts"] == 2


def test_a_busy_file_is_retried_until_its_writer_lets_go(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1]')
    g = load_sweep(grid)
    g.runs[0].output.parent.mkdir(parents=True)
    lock = _lock._OutputLock.acquire(g.runs[0].output)  # another writer holds run 0's file
    threading.Timer(1.5, lock.release).start()
    t0 = time.monotonic()
    res = sweep(g, threads())
    assert res.ok and time.monotonic() - t0 >= 1.4
    assert [r["attempts"] for r in res.runs] == [1, 1]


def test_busy_for_too_long_is_a_failure(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0]')
    g = load_sweep(grid)
    g.runs[0].output.parent.mkdir(parents=True)
    lock = _lock._OutputLock.acquire(g.runs[0].output)
    try:
        res = sweep(g, threads(), busy_timeout=0.5)
    finally:
        lock.release()
    assert res.runs[0]["status"] == "failed" and "being written by another" in res.runs[0]["error"]


def test_one_sweep_per_directory(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0]')
    g = load_sweep(grid)
    g.directory.mkdir()
    lock = _lock._OutputLock.acquire(g.manifest)
    try:
        with pytest.raises(io.OutputBusyError, match="in use by another `lieflow sweep`"):
            sweep(g, threads())
    finally:
        lock.release()


def test_default_local_pool_one_blas_thread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The default executor: spawned worker processes with one BLAS thread each (the
    suite's own one-thread setting removed first, so that the pool must set it)."""
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1, 2]')
    for name in _worker._THREAD_VARS:
        monkeypatch.delenv(name, raising=False)
    before = {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    res = lf.sweep(grid, workers=2)
    assert res.ok
    pids = {r["pid"] for r in res.runs}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2
    assert {v: os.environ.get(v) for v in before} == before  # restored in this process
    with cf.ProcessPoolExecutor(1) as pool:  # any Executor works
        assert lf.sweep(grid, pool).skipped == 3
    if sys.platform.startswith("linux"):
        # OpenBLAS starts its threads when numpy is imported, before any initializer runs,
        # so the variables must be in each worker's environment from its start: a worker
        # then has its main thread only
        assert {r["threads"] for r in res.runs} == {1}


class _RecordingExecutor(cf.Executor):
    """Runs tasks inline and records the order in which runs were submitted."""

    def __init__(self) -> None:
        self.order: list[str] = []

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> cf.Future[Any]:
        self.order.append(args[0]["id"])
        fut: cf.Future[Any] = cf.Future()
        fut.set_result(fn(*args, **kwargs))
        return fut


def test_longest_runs_are_submitted_first(tmp_path: Path) -> None:
    """Runs go to the executor by decreasing number of steps (grid order among equals), so
    a sweep does not end on one long run while the other workers idle; the manifest keeps
    the grid's order."""
    grid = load_sweep(write_grid(tmp_path, '"run.steps" = [10, 40, 20]\n"initial.seed" = [0, 1]\n'))
    pool = _RecordingExecutor()
    res = sweep(grid.source, executor=pool)
    by_id = {r.id: r.config.run.steps for r in grid.runs}
    assert [by_id[i] for i in pool.order] == [40, 40, 20, 20, 10, 10]
    assert pool.order[:2] == [r.id for r in grid.runs if r.config.run.steps == 40]
    manifest = json.loads(res.manifest.read_text())
    assert [r["id"] for r in manifest["runs"]] == [r.id for r in grid.runs]


def test_executor_arguments_are_checked(tmp_path: Path) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0]')
    with pytest.raises(lf.InputError, match="executor must be"):
        sweep(grid, "mpi")
    with pytest.raises(lf.InputError, match="executor must be"):
        sweep(grid, object())
    with pytest.raises(lf.InputError, match="workers must be a positive integer"):
        sweep(grid, workers=0)
    with pytest.raises(lf.InputError, match="executor='dask'"):
        sweep(grid, scheduler="tcp://127.0.0.1:1")
    with pytest.raises(lf.InputError, match="has its own workers"):
        sweep(grid, "dask", scheduler="tcp://127.0.0.1:1", workers=2)


# -- command line ----------------------------------------------------------------------------


def test_cli_sweep_summary_exit_codes_and_dry_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1]\n"solver.params.max_iter" = [100, 1]',
                      BASE + '\n[solver]\nname = "fixed_point"\n')  # fmt: skip
    assert main(["sweep", str(grid), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "4 runs (2 x 2)" in out and not (tmp_path / "grid").exists()
    assert main(["sweep", str(grid), "--workers", "1", "--no-progress", "--out",
                 str(tmp_path / "d")]) == 1  # fmt: skip
    captured = capsys.readouterr()
    assert "4 runs: 2 complete (0 already), 2 failed" in captured.out
    assert captured.err.count("failed: runs/") == 2 and "did not converge" in captured.err
    assert "[4/4]" in captured.err  # one line per finished run when not on a terminal
    ok = write_grid(tmp_path, '"initial.seed" = [0, 1]', name="ok")
    assert main(["sweep", str(ok), "--dry-run"]) == 0
    assert capsys.readouterr().out.count("to run ") == 2
    assert main(["sweep", str(ok), "--no-progress"]) == 0
    assert main(["sweep", str(ok), "--no-progress"]) == 0
    assert "2 complete (2 already)" in capsys.readouterr().out
    assert main(["sweep", str(ok), "--dry-run"]) == 0
    assert capsys.readouterr().out.count("complete ") == 2
    assert main(["sweep", str(ok), "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "--executor dask" in capsys.readouterr().err
    assert main(["sweep", str(ok), "--workers", "0"]) == 2
    bad = write_grid(tmp_path, '"scheme.nme" = ["x"]', name="bad")
    assert main(["sweep", str(bad)]) == 2
    assert "[scheme] nme: unknown key" in capsys.readouterr().err


def test_ensemble_grid_and_progress_monitor(tmp_path: Path) -> None:
    """A sweep of ensemble runs, watched by a SweepMonitor."""
    seen: dict[str, Any] = {"updates": 0, "finished": []}

    class Watch(SweepMonitor):
        def start(self, runs: int, skipped: int) -> None:
            seen["start"] = (runs, skipped)

        def update(self, counts: Any, steps: int, total_steps: int) -> None:
            seen["updates"] += 1
            seen["last"] = (dict(counts), steps, total_steps)

        def finished(self, record: Any) -> None:
            seen["finished"].append(record["status"])

    base = BASE.replace("seed = 0", "seeds = [0, 1, 2]")
    grid = write_grid(tmp_path, '"scheme.name" = ["midpoint", "gauss2"]', base)
    res = sweep(grid, threads(), monitor=Watch())
    assert res.ok and seen["start"] == (2, 0) and seen["finished"] == ["complete"] * 2
    counts, steps, total = seen["last"]
    assert total == 80 and steps == 80 and counts["complete"] == 2
    tr = io.read_trajectory(res.directory / res.runs[0]["output"])
    assert tr.W.shape == (5, 3, 3, 3) and tr.energy_error.shape == (41, 3)


def test_ctrl_c_stops_the_sweep_resumably_and_rerunning_finishes_it(
    tmp_path: Path, children: Children
) -> None:
    """``lieflow sweep`` in its own process group, SIGINT to the group as a terminal's Ctrl-C
    sends it: exit 130 soon, runs marked interrupted; the same command then completes them,
    bit for bit equal to uninterrupted runs."""
    import signal
    import subprocess
    import sys

    base = BASE.replace("steps = 40", "steps = 600").replace("save_every = 10", "save_every = 20")
    grid = write_grid(
        tmp_path, '"initial.seed" = [0, 1, 2, 3]', base.replace("h = 0.1", "h = 0.01")
    )
    cmd = [sys.executable, "-m", "lieflow", "sweep", str(grid), "--workers", "2", "--no-progress"]
    proc = children.popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    progress = tmp_path / "grid" / ".progress"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list(progress.glob("*.json"))) < 2:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)  # its own process group, as a terminal's Ctrl-C
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()
    assert b"sweep interrupted; run the same command again" in err
    manifest = json.loads((tmp_path / "grid" / "manifest.json").read_text())
    statuses = [r["status"] for r in manifest["runs"]]
    assert "interrupted" in statuses and "running" not in statuses, statuses
    for rec in manifest["runs"]:
        path = tmp_path / "grid" / rec["output"]
        if path.exists():
            assert io.read_trajectory(path).status in ("interrupted", "complete")
    res = sweep(grid, threads())
    assert res.ok
    spec = load_sweep(grid).runs[0]
    io.run(build(spec.config, output=tmp_path / "ref.h5"))
    _files_equal(spec.output, tmp_path / "ref.h5")


@pytest.mark.slow
def test_a_script_without_a_main_guard_gets_a_clear_error(tmp_path: Path) -> None:
    """The local pool spawns its workers, which import the calling script: unguarded, they
    die at once; the sweep says why instead of failing every run."""
    import subprocess
    import sys

    grid = write_grid(tmp_path, '"initial.seed" = [0, 1]')
    script = tmp_path / "study.py"
    script.write_text(f"import lieflow\nlieflow.sweep({str(grid)!r}, workers=1)\n")
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert proc.returncode != 0
    assert 'protect the call with `if __name__ == "__main__":`' in proc.stderr
    guarded = tmp_path / "guarded.py"
    guarded.write_text(
        "import lieflow\n"
        "if __name__ == '__main__':\n"
        f"    assert lieflow.sweep({str(grid)!r}, workers=1).ok\n"
    )
    proc = subprocess.run([sys.executable, str(guarded)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr


def test_a_file_created_by_another_attempt_meanwhile_is_retried_not_failed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Attempt B finds no file, attempt A then creates and finishes it, B's exclusive create
    is refused: B reports "busy" (retried later, then skipped), not a failure."""
    from lieflow.app.sweeps import run_task

    spec = load_sweep(write_grid(tmp_path, '"initial.seed" = [0]')).runs[0]
    io.run(build(spec.config))  # attempt A
    real_exists = Path.exists
    monkeypatch.setattr(Path, "exists", lambda p: p != spec.output and real_exists(p))
    task = {"text": spec.config.text, "source": "g", "base_dir": str(tmp_path),
            "output": str(spec.output)}  # fmt: skip
    out = run_task(task)
    assert out["status"] == "busy" and "already exists" in out["error"]


def test_a_file_a_killed_worker_left_damaged_is_run_again_from_the_start(
    tmp_path: Path,
) -> None:
    """A Dask worker SIGKILLed while it wrote can leave the run's file unreadable past its
    checkpoint; the task that takes the run over starts it again (the run is deterministic:
    the same bits as a run never interrupted)."""
    from lieflow.app.sweeps import run_task

    spec = load_sweep(write_grid(tmp_path, '"initial.seed" = [0]')).runs[0]
    io.run(build(spec.config))
    ref = io.read_trajectory(spec.output)
    damage_last_chunk(spec.output, "iterations")
    task = {"text": spec.config.text, "source": "g", "base_dir": str(tmp_path),
            "output": str(spec.output)}  # fmt: skip
    out = run_task(task)
    assert out["status"] == "complete" and "is damaged" in out["restarted"], out
    again = io.read_trajectory(spec.output)
    assert np.array_equal(again.W, ref.W) and np.array_equal(again.iterations, ref.iterations)


def test_an_executor_that_refuses_work_stops_the_sweep_with_the_manifest_written(
    tmp_path: Path,
) -> None:
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1]')
    pool = threads()
    pool.shutdown()
    with pytest.raises(lf.LieflowError, match="the executor refused to run more runs"):
        sweep(grid, pool)
    manifest = json.loads((tmp_path / "grid" / "manifest.json").read_text())
    assert [r["status"] for r in manifest["runs"]] == ["pending", "pending"]
    assert sweep(grid, threads()).ok  # and it continues later


@pytest.mark.slow
def test_a_killed_worker_of_the_local_pool_is_replaced_and_its_run_resumed(
    tmp_path: Path,
) -> None:
    import signal

    base = BASE.replace("steps = 40", "steps = 400").replace("h = 0.1", "h = 0.01")
    grid = write_grid(tmp_path, '"initial.seed" = [0, 1, 2]', base)
    g = load_sweep(grid)
    result: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: result.update(res=sweep(g, workers=2)))
    thread.start()
    victim = None
    deadline = time.monotonic() + 120
    while victim is None and thread.is_alive() and time.monotonic() < deadline:
        for p in (g.directory / ".progress").glob("*.json"):
            with contextlib.suppress(OSError, ValueError):
                info = json.loads(p.read_text())
                if info["done"] < info["total"]:
                    victim = (info["pid"], p.stem)
                    os.kill(info["pid"], signal.SIGKILL)
                    break
        time.sleep(0.02)
    thread.join(timeout=180)
    assert victim is not None and not thread.is_alive()
    res = result["res"]
    assert res.ok, [r["error"] for r in res.runs]
    rec = next(r for r in res.runs if r["id"] == victim[1])
    assert rec["attempts"] == 2 and rec["pid"] != victim[0]
    spec = next(s for s in g.runs if s.id == victim[1])
    io.run(build(spec.config, output=tmp_path / "ref.h5"))
    _files_equal(spec.output, tmp_path / "ref.h5")
