"""Single precision stays single on every registered system (float32 / complex64).

Every method of a system (B, its derivative, eta, Casimirs, the projections) and a whole
run must keep the precision of the state: numpy promotes ``float32 * float64-array`` to
float64, which is how ``-W * self.weights`` used to return float64 in the rigid bodies and
the Toda lattice.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf


def _single(system: lf.IsospectralSystem) -> tuple[np.ndarray, np.dtype]:
    W = system.random_state(seed=0)
    dt = np.dtype(np.complex64 if np.iscomplexobj(W) else np.float32)
    return W.astype(dt), dt


def test_system_methods_keep_single_precision(system: lf.IsospectralSystem) -> None:
    W, dt = _single(system)
    real = np.dtype(np.float32)
    assert system.B(W).dtype == dt
    assert system.B_derivative(W, W).dtype == dt
    assert system.project(W).dtype == dt
    assert system.project_stage(W).dtype == dt
    assert system.algebra.project(W).dtype == dt
    assert np.asarray(system.hamiltonian(W)).dtype == real
    assert np.asarray(system.casimirs(W)).dtype == real
    assert np.asarray(system.phase_space_distance(W)).dtype == real


def test_double_precision_stays_double(system: lf.IsospectralSystem) -> None:
    W = system.random_state(seed=0)
    dt = np.dtype(np.complex128 if np.iscomplexobj(W) else np.float64)
    assert W.dtype == dt
    assert system.B(W).dtype == dt and system.project(W).dtype == dt


@pytest.mark.parametrize("name", ["midpoint", "gauss3", "sydirk7", "modin_viviani"])
def test_single_precision_run(system: lf.IsospectralSystem, name: str) -> None:
    W, dt = _single(system)
    sol = lf.integrate(system, lf.schemes.get(name), W, h=0.05, steps=20, engine="numpy")
    assert sol.success and sol.W.dtype == dt
    eps = float(np.finfo(np.float32).eps)
    assert sol.phase_space_distance().max() <= 8 * eps
    assert sol.spectrum_drift().max() <= 1e3 * eps  # isospectral to single-precision roundoff


def test_single_precision_compiled_or_fallback() -> None:
    """engine="auto" on a float32 rigid body: whatever engine runs, float32 comes back."""
    system = lf.systems.get("generalized_rigid_body")
    W = system.random_state(0).astype(np.float32)
    sol = lf.integrate(system, lf.schemes.get("gauss2"), W, h=0.05, steps=2000)
    assert sol.W.dtype == np.float32


def test_newton_stops_at_single_precision_roundoff() -> None:
    """Newton on a complex64 midpoint solve stops once it reaches float32 roundoff (the
    floor scales with the precision) instead of wandering on the noise to its cap; the
    complex128 solve is unchanged (quadratic convergence to rtol 1e-14)."""
    lz = import_plugin("lieflow_zeitlin")
    from lieflow.schemes.sydirk import MidpointProblem

    system = lf.systems.get("euler_zeitlin", N=12, time="fluid")
    W0 = lz.random_vorticity(12, degree=4, seed=0)
    double = lf.solvers.Newton().solve(MidpointProblem(system, W0, 0.1))
    single = lf.solvers.Newton().solve(MidpointProblem(system, W0.astype(np.complex64), 0.1))
    assert double.reason == "converged" and double.residuals[-1] <= 1e-14
    assert single.reason == "roundoff"
    assert single.iterations <= double.iterations + 2
    assert single.residuals[-1] <= 1e-6
    err = np.linalg.norm(single.x - double.x) / np.linalg.norm(double.x)
    assert err <= 1e-6  # float32 accuracy
