"""``integrate(..., out=path)``: a run streamed into the trajectory format of ``lieflow run``,
resumable, with one chunk of steps in memory; the writer's header decoupled from BuiltRun."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import lieflow as lf
from lieflow.app import io
from lieflow.app.config import ConfigError
from lieflow.app.reproduce import Case
from lieflow.runs import RunSpec


def _body() -> tuple[lf.IsospectralSystem, np.ndarray]:
    return Case("generalized_rigid_body", "n = 5", 5, 0.05, 1, 1e-14).build(1)


def test_streamed_run_matches_the_in_memory_run(tmp_path: Path) -> None:
    system, W0 = _body()
    scheme = lf.schemes.get("gauss2")
    mem = lf.integrate(system, scheme, W0, 0.05, steps=23, save_every=5, engine="numpy")
    out = tmp_path / "run.h5"
    sol = lf.integrate(system, scheme, W0, 0.05, steps=23, save_every=5, engine="numpy", out=out)
    # the Solution: first and last state, every step's diagnostics
    assert sol.saved_steps.tolist() == [0, 23]
    np.testing.assert_array_equal(sol.W[-1], mem.W[-1])
    np.testing.assert_array_equal(sol.iterations, mem.iterations)
    assert sol.energy_error is not None and mem.energy_error is not None
    assert sol.casimir_drift is not None and mem.casimir_drift is not None
    np.testing.assert_allclose(sol.energy_error, mem.energy_error, rtol=0, atol=1e-15)
    np.testing.assert_allclose(sol.casimir_drift, mem.casimir_drift, rtol=0, atol=1e-15)
    assert sol.success and len(sol.solvers) == 23
    # the file: the saved states of the in-memory run, the format `lieflow run` writes
    traj = io.read_trajectory(out)
    assert traj.status == "complete" and traj.meta["system"] == "generalized_rigid_body"
    assert traj.meta["scheme"] == sol.scheme and traj.meta["format"] == io.FORMAT
    np.testing.assert_array_equal(traj.step, mem.saved_steps)
    np.testing.assert_array_equal(traj.W, mem.W)


def test_streamed_run_resumes_bit_for_bit(tmp_path: Path) -> None:
    system, W0 = _body()
    scheme = lf.schemes.get("midpoint")
    whole = lf.integrate(system, scheme, W0, 0.05, steps=30, save_every=3, out=tmp_path / "a.h5")
    out = tmp_path / "b.h5"
    lf.integrate(system, scheme, W0, 0.05, steps=12, save_every=3, out=out)
    sol = lf.integrate(system, scheme, W0, 0.05, steps=30, save_every=3, out=out, resume=True)
    np.testing.assert_array_equal(sol.W[-1], whole.W[-1])
    np.testing.assert_array_equal(sol.iterations, whole.iterations)
    a, b = io.read_trajectory(tmp_path / "a.h5"), io.read_trajectory(out)
    np.testing.assert_array_equal(a.W, b.W)
    np.testing.assert_array_equal(a.energy, b.energy)
    assert b.meta["resumes"] == 1
    # another h is refused with what changed; an existing file without resume or replace too
    with pytest.raises(ConfigError, match=r"h: 0\.05 -> 0\.1"):
        lf.integrate(system, scheme, W0, 0.1, steps=30, save_every=3, out=out, resume=True)
    with pytest.raises(ConfigError, match="already exists"):
        lf.integrate(system, scheme, W0, 0.05, steps=3, out=out)
    again = lf.integrate(system, scheme, W0, 0.05, steps=3, out=out, replace=True)
    assert again.n_steps == 3 and io.read_trajectory(out).completed_steps == 3


def test_streaming_options_need_out_and_memory_error_names_them() -> None:
    system, W0 = _body()
    with pytest.raises(lf.InputError, match="out=PATH"):
        lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2, resume=True)
    from lieflow.runs import check_memory as _check_memory

    with pytest.raises(lf.InputError, match=r'out="run.h5"'):
        _check_memory(2**62, 10, 1)


def test_streamed_failure_keeps_the_steps_before_it(tmp_path: Path) -> None:
    system, W0 = _body()
    solver = lf.solvers.FixedPoint(max_iter=2)
    out = tmp_path / "f.h5"
    sol = lf.integrate(system, lf.schemes.get("gauss2"), 50 * W0, 0.5, steps=5, solver=solver,
                       out=out, on_failure="truncate")  # fmt: skip
    assert not sol.success and sol.failure is not None
    assert io.read_trajectory(out).status == "failed"
    with pytest.raises(lf.ConvergenceError):
        lf.integrate(system, lf.schemes.get("gauss2"), 50 * W0, 0.5, steps=5, solver=solver,
                     out=out, replace=True)  # fmt: skip


def test_writer_takes_a_header(tmp_path: Path) -> None:
    """TrajectoryWriter needs a TrajectoryHeader, not a BuiltRun."""
    system, W0 = _body()
    header = io.TrajectoryHeader(system=system, system_name="generalized_rigid_body",
                                 scheme="midpoint", solver="fixed_point", h=0.1, save_every=2,
                                 requested_steps=4, identity="{}", W0=W0,
                                 output=tmp_path / "h.h5")  # fmt: skip
    spec = RunSpec.build(system, lf.schemes.get("midpoint"), W0, 0.1, steps=4, save_every=2)
    outcome = spec.execute((io.TrajectoryWriter.open(header),))
    assert outcome.failure is None and outcome.status == "complete"
    assert io.read_trajectory(tmp_path / "h.h5").step.tolist() == [0, 2, 4]


def test_streamed_memory_is_bounded(tmp_path: Path) -> None:
    """Peak traced memory of a streamed run: a few states plus its per-step diagnostics,
    whatever its length (a subprocess, so tracemalloc sees only this run)."""
    script = textwrap.dedent(
        """
        import sys, tracemalloc
        import lieflow as lf
        from lieflow.app.reproduce import Case
        system, W0 = Case("generalized_rigid_body", "n", 96, 0.01, 1, 1e-14).build(0)
        steps, out = int(sys.argv[1]), sys.argv[2]
        lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.01, steps=4, out=out + "w")
        tracemalloc.start()
        sol = lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.01, steps=steps,
                           out=out, engine="numpy")
        diagnostics = sol.casimir_drift.nbytes + sol.energy_error.nbytes
        print(tracemalloc.get_traced_memory()[1] / W0.nbytes, diagnostics / W0.nbytes)
        """
    )
    for steps in (10, 100):
        res = subprocess.run([sys.executable, "-c", script, str(steps), str(tmp_path / f"{steps}")],
                             capture_output=True, text=True, check=True)  # fmt: skip
        peak, diagnostics = map(float, res.stdout.split()[-2:])
        # issue 18: <= 20 states (100 saved states kept in memory would be 100)
        assert peak < 20 + 4 * diagnostics, (steps, peak, diagnostics)
