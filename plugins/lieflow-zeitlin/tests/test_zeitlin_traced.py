"""Euler–Zeitlin on the traced engine (issue 34): the plugin's array-API ``B`` (parallel cyclic
reduction), energy and Casimirs compiled by ``jax.jit`` with the scheme's step, run here on
JAX's CPU backend. The physics against the exact Rossby–Haurwitz speed; the engine against
the eager one and the conserved Casimirs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_zeitlin_orientation import TOLERANCE, measured_rh_speed, rh_speed

import lieflow as lf

lz = pytest.importorskip("lieflow_zeitlin")
jax = pytest.importorskip("jax")
jax.config.update("jax_enable_x64", True)


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2"])
def test_the_rossby_haurwitz_wave_moves_east_at_the_exact_speed(scheme: str) -> None:
    system = lz.EulerZeitlin(10)
    c = rh_speed(1.0, 3)
    speed, amplitude = measured_rh_speed(system, scheme, 3, steps=40, engine="jax")
    assert abs(speed - c) <= TOLERANCE[scheme] * c, (speed, c)
    assert amplitude <= 1e-5


def test_jax_arrays_take_the_eager_engines_steps_with_device_diagnostics() -> None:
    system = lz.EulerZeitlin(16, rotation=0.5)
    W0 = lz.random_vorticity(16, 6, seed=2)
    kwargs = dict(h=0.05, steps=24, save_every=8, solver=lf.solvers.FixedPoint(rtol=1e-14))
    ref = lf.integrate(system, lf.schemes.get("gauss2"), W0, engine="numpy", **kwargs)
    sol = lf.integrate(system, lf.schemes.get("gauss2"), jax.numpy.asarray(W0), **kwargs)
    scale = np.abs(ref.W).max()
    np.testing.assert_allclose(sol.W, ref.W, rtol=0, atol=1e-13 * scale)
    assert np.abs(sol.iterations - ref.iterations).max() <= 1
    # the energy and the Casimirs tr (iW)^k, k = 2, 3, 4, computed on the device
    assert sol.casimir_drift is not None and sol.casimir_drift.max() < 1e-13
    assert sol.energy_error is not None and ref.energy_error is not None
    np.testing.assert_allclose(sol.energy_error, ref.energy_error, rtol=0, atol=1e-12)


def test_lieflow_run_with_device_jax_runs_the_traced_engine(tmp_path: Path) -> None:
    from lieflow.app import config, io
    from lieflow.app.cli import main
    from lieflow.engines.traced import TracedSchemeFlow

    text = (
        '[system]\nname = "euler_zeitlin"\nparams = { N = 12 }\n'
        '[initial]\nrandom = true\nseed = 3\n[scheme]\nname = "midpoint"\n'
        '[run]\nh = 0.05\nsteps = 12\nsave_every = 4\noutput = "run.h5"\ndevice = "jax"\n'
    )
    (tmp_path / "run.toml").write_text(text)
    setup = config.build(config.load_config(tmp_path / "run.toml"))
    assert isinstance(setup.flow(), TracedSchemeFlow)
    assert main(["run", str(tmp_path / "run.toml"), "--no-progress"]) == 0
    traj = io.read_trajectory(tmp_path / "run.h5")
    np.testing.assert_array_equal(traj.step, [0, 4, 8, 12])
    ref = lf.integrate(setup.system, lf.schemes.get("midpoint"), setup.W0, h=0.05, steps=12,
                       save_every=4, engine="numpy")  # fmt: skip
    np.testing.assert_allclose(traj.W, ref.W, rtol=0, atol=1e-13 * np.abs(ref.W).max())


def test_anderson_acceleration_runs_traced_where_the_plain_iteration_fails() -> None:
    """N = 128 at h = 1/16 on a smooth rms-1 field: the plain fixed point stalls (its
    contraction estimate is 1.4 per update); Anderson(5) converges, traced as eagerly,
    with the same updates and states, and Casimirs at roundoff."""
    N = 128
    system = lz.EulerZeitlin(N)
    W0 = lz.random_vorticity(N, degree=8, seed=N)
    h = 1 / 16
    with pytest.raises(lf.ConvergenceError):
        lf.integrate(system, lf.schemes.get("midpoint"), W0, h=h, steps=1, engine="numpy",
                     solver=lf.solvers.FixedPoint(rtol=1e-13, max_iter=200))  # fmt: skip
    solver = lf.solvers.FixedPoint(rtol=1e-13, max_iter=200, anderson=5)
    kwargs = dict(h=h, steps=3, save_every=3, solver=solver)
    ref = lf.integrate(system, lf.schemes.get("midpoint"), W0, engine="numpy", **kwargs)
    sol = lf.integrate(system, lf.schemes.get("midpoint"), jax.numpy.asarray(W0), **kwargs)
    np.testing.assert_allclose(sol.W, ref.W, rtol=0, atol=1e-12 * np.abs(ref.W).max())
    assert np.abs(sol.iterations - ref.iterations).max() <= 1 and sol.iterations.max() < 40
    assert sol.casimir_drift is not None and sol.casimir_drift.max() < 1e-14
