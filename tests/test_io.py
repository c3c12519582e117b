"""HDF5 trajectory files: written as the run proceeds, equal to ``integrate``, resumable
bit-for-bit after Ctrl-C, a hard kill, or a save that was cut off half-way."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import rigid_body_config

import lieflow as lf
from lieflow.app import io
from lieflow.app.config import BuiltRun, ConfigError, build, load_config, parse_config


def config_text(scheme: str, steps: int) -> str:
    return rigid_body_config(scheme=scheme, h=0.1, steps=steps, save_every=10, output="traj.h5")


def write_config(tmp_path: Path, scheme: str = "gauss2", steps: int = 60) -> Path:
    path = tmp_path / "run.toml"
    path.write_text(config_text(scheme=scheme, steps=steps), encoding="utf-8")
    return path


def setup_for(config: Path, out: Path | None = None) -> BuiltRun:
    return build(load_config(config), output=out)


class StopAt:
    """A monitor that raises ``exc`` once step ``k`` has been recorded."""

    def __init__(self, k: int, exc: BaseException) -> None:
        self.k, self.exc = k, exc
        self.done = 0

    def start(self, done: int, total: int) -> None:
        self.done = done

    def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
        self.done += steps
        if self.done >= self.k:
            raise self.exc

    def stop(self) -> None:
        pass


def assert_same_file(a: Path, b: Path) -> None:
    ta, tb = io.read_trajectory(a), io.read_trajectory(b)
    for name in (
        "step",
        "t",
        "W",
        "energy",
        "energy_error",
        "casimirs",
        "casimir_drift",
        "iterations",
        "residual",
    ):
        assert np.array_equal(getattr(ta, name), getattr(tb, name)), name
    assert np.array_equal(ta.checkpoint.W, tb.checkpoint.W)
    assert ta.completed_steps == tb.completed_steps
    assert ta.status == tb.status == "complete"


@pytest.fixture
def reference(tmp_path: Path) -> Path:
    """An uninterrupted 60-step run."""
    config = write_config(tmp_path)
    summary = io.run(setup_for(config, tmp_path / "reference.h5"))
    assert summary.status == "complete"
    return summary.path


def test_file_matches_integrate(tmp_path: Path) -> None:
    config = write_config(tmp_path, scheme="sydirk7", steps=25)
    setup = setup_for(config)
    io.run(setup)
    traj = io.read_trajectory(setup.output)
    sol = lf.integrate(
        setup.system, setup.scheme, setup.W0, 0.1, steps=25, solver=setup.solver, save_every=10
    )
    assert np.array_equal(traj.step, sol.saved_steps)  # 0, 10, 20 and the last, 25
    assert np.array_equal(traj.W, sol.W)
    assert np.array_equal(traj.energy_error, sol.energy_error)
    assert np.array_equal(traj.casimir_drift, sol.casimir_drift)
    assert np.array_equal(traj.iterations, sol.iterations)
    meta = traj.meta
    assert meta["status"] == "complete" and meta["completed_steps"] == 25
    assert meta["config"] == config.read_text()
    for key in ("lieflow_version", "platform", "numpy", "scipy", "h5py", "python"):
        assert meta[key]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_datasets_are_chunked_and_resizable(reference: Path) -> None:
    with h5py.File(reference) as f:
        for name in ("W", "time", "step", "energy_error", "iterations"):
            assert f[name].chunks is not None
            assert f[name].maxshape[0] is None


def test_ctrl_c_then_resume_is_bitwise_identical(
    tmp_path: Path, reference: Path, one_step_chunks: None
) -> None:
    setup = setup_for(write_config(tmp_path), tmp_path / "interrupted.h5")
    summary = io.run(setup, monitor=StopAt(37, KeyboardInterrupt()))
    assert summary.status == "interrupted" and summary.completed_steps == 37
    traj = io.read_trajectory(setup.output)  # readable, checkpointed at the interruption
    assert traj.status == "interrupted" and traj.checkpoint.step == 37
    assert traj.energy_error.shape[0] == 38 and traj.iterations.shape[0] == 37
    assert list(traj.step) == [0, 10, 20, 30]

    resumed = io.run(setup, resume=True)
    assert resumed.new_steps == 23 and resumed.status == "complete"
    assert_same_file(setup.output, reference)


def test_hard_kill_then_resume_is_bitwise_identical(tmp_path: Path, reference: Path) -> None:
    """``os._exit`` in the middle of a run: no cleanup at all, like SIGKILL."""
    config = write_config(tmp_path)
    out = tmp_path / "killed.h5"
    script = textwrap.dedent(
        f"""
        import os
        from lieflow.app import io
        from lieflow.app.config import build, load_config

        class Kill:
            def start(self, done, total): self.done = done
            def advance(self, steps, iterations, err):
                self.done += steps
                if self.done == 37:
                    os._exit(9)
            def stop(self): pass

        import attrs
        setup = build(load_config({str(config)!r}), output={str(out)!r})
        run = attrs.evolve(setup.config.run, checkpoint=0.0)  # a checkpoint after every step
        setup = attrs.evolve(setup, config=attrs.evolve(setup.config, run=run))
        io.run(setup, monitor=Kill())
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert proc.returncode == 9, proc.stderr.decode()
    ck = io.read_checkpoint(out)
    assert ck.step == 37  # checkpointed after every step: nothing computed is lost
    assert io.read_trajectory(out).status == "running"

    io.run(setup_for(config, out), resume=True)
    assert_same_file(out, reference)


def test_resume_truncates_a_save_cut_off_half_way(
    tmp_path: Path, reference: Path, one_step_chunks: None
) -> None:
    setup = setup_for(write_config(tmp_path), tmp_path / "torn.h5")
    io.run(setup, monitor=StopAt(20, KeyboardInterrupt()))
    with h5py.File(setup.output, "r+") as f:  # rows of a save that never got its checkpoint
        for name in ("step", "energy", "energy_error", "iterations", "residual"):
            ds = f[name]
            ds.resize(ds.shape[0] + 7, axis=0)
            ds[-7:] = 12345
        for name in ("saved_step", "time", "W"):
            ds = f[name]
            ds.resize(ds.shape[0] + 1, axis=0)
        f["saved_step"][-1] = 27
    assert io.read_trajectory(setup.output).energy_error.shape[0] == 21  # reader ignores them
    io.run(setup, resume=True)
    assert_same_file(setup.output, reference)


def test_resume_can_extend_the_run(tmp_path: Path, reference: Path) -> None:
    short = write_config(tmp_path, steps=40)
    out = tmp_path / "extended.h5"
    io.run(setup_for(short, out))
    longer = write_config(tmp_path, steps=60)
    summary = io.run(setup_for(longer, out), resume=True)
    assert summary.new_steps == 20
    assert_same_file(out, reference)
    again = io.run(setup_for(longer, out), resume=True)  # nothing left to do
    assert again.new_steps == 0 and again.status == "complete"


def test_resume_refuses_another_configuration(tmp_path: Path, reference: Path) -> None:
    other = write_config(tmp_path, scheme="gauss3")
    with pytest.raises(ConfigError, match="different configuration"):
        io.run(setup_for(other, reference), resume=True)


def test_resume_without_a_file_starts_afresh(tmp_path: Path, reference: Path) -> None:
    out = tmp_path / "fresh.h5"
    io.run(setup_for(write_config(tmp_path), out), resume=True)
    assert_same_file(out, reference)


def test_failed_step_keeps_the_steps_before_it(tmp_path: Path) -> None:
    text = config_text(scheme="midpoint", steps=20).replace(
        "params = { rtol = 1e-15 }", "params = { rtol = 1e-15, max_iter = 2 }"
    )
    setup = build(parse_config(text, base_dir=tmp_path))
    with pytest.raises(lf.LieflowError, match="status 'failed'"):
        io.run(setup)
    traj = io.read_trajectory(setup.output)
    assert traj.status == "failed"
    assert traj.completed_steps == traj.iterations.shape[0]


def test_reading_a_file_that_is_not_a_trajectory(tmp_path: Path) -> None:
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(lf.LieflowError, match="not a lieflow trajectory"):
        io.read_trajectory(tmp_path / "other.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(lf.LieflowError, match="not an HDF5 file"):
        io.read_trajectory(tmp_path / "junk.h5")
    with pytest.raises(lf.LieflowError, match="does not exist"):
        io.read_trajectory(tmp_path / "missing.h5")


def test_config_identity_ignores_steps_and_output(tmp_path: Path) -> None:
    a = parse_config(config_text(scheme="gauss2", steps=10), base_dir=tmp_path)
    b = parse_config(
        config_text(scheme="gauss2", steps=99).replace("traj.h5", "x.h5"), base_dir=tmp_path
    )
    c = parse_config(config_text(scheme="gauss3", steps=10), base_dir=tmp_path)
    assert a.identity() == b.identity() != c.identity()
    assert a.run.output == tmp_path / "traj.h5"
    assert a.initial.seed == 3 and a.solver.params["rtol"] == 1e-15


def test_environment_has_versions() -> None:
    env = io.environment()
    assert env["numpy"] == np.__version__
    assert env["lieflow_version"] == lf.__version__
    assert os.path.sep not in env["python"]


def test_plot_into_a_file_is_refused_with_a_message(tmp_path: Path) -> None:
    from lieflow.app.plotting import plot_trajectory

    out = tmp_path / "run.h5"
    io.run(setup_for(write_config(tmp_path, steps=5), out))
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("keep me")
    with pytest.raises(lf.LieflowError, match="is a file, not a directory"):
        plot_trajectory(out, blocker)
    assert blocker.read_text() == "keep me"


def test_checkpoint_warm_start_keeps_the_runs_depth(tmp_path: Path) -> None:
    """``Checkpoint.warm`` rebuilds the warm start a run had at its checkpoint: all the
    solutions it kept (five by default), equal to those of the same steps in memory."""
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W0 = system.algebra.random(seed=3)
    scheme = lf.schemes.get("gauss2")
    path = tmp_path / "run.h5"
    lf.integrate(system, scheme, W0, h=0.1, steps=8, save_every=8, out=path, engine="numpy")
    warm = io.read_checkpoint(path).warm
    steps = list(itertools.islice(lf.iterate(system, scheme, W0, 0.1, lf.solvers.FixedPoint()), 8))
    expected = steps[-1].warm
    assert expected is not None and warm.depth == expected.depth == 5
    assert warm.trusted == expected.trusted
    assert len(warm.history()) == 5
    for got, want in zip(warm.history(), expected.history(), strict=True):
        np.testing.assert_array_equal(got, want)
