"""The phase space of every registered system: its projection, and the distance from it.

``IsospectralSystem.project`` maps onto the set the exact flow keeps states in (symmetric
matrices for the Toda lattice, the spheres ``|m_i| = |Γ_i|`` for point vortices, su(N) for
Euler–Zeitlin, so(n) for rigid bodies) and ``project_stage`` onto its linear span. These
tests check that both are projections, that the distance detects every way of leaving the
phase space (``LieAlgebra.distance`` is identically 0 on gl(n) and cannot), and that the
projection changes a converged step by roundoff only (measured: <= 1.7e-16 relative, 0 for
Toda; the stage projection changes a Toda step by <= 7e-17).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SCHEMES
from hypothesis import given, settings
from hypothesis import strategies as st

import lieflow as lf
from lieflow.schemes import MidpointProblem
from lieflow.stepping import advance

EPS = float(np.finfo(float).eps)


def _ambient(system: lf.IsospectralSystem, seed: int, dtype: np.dtype | None = None) -> np.ndarray:
    """A random matrix of the system's size and kind (not in the phase space)."""
    rng = np.random.default_rng(seed)
    n = system.algebra.n
    X = rng.standard_normal((n, n))
    if system.algebra.dtype.kind == "c":
        X = X + 1j * rng.standard_normal((n, n))
    return X.astype(dtype or system.algebra.dtype)


def test_random_states_are_on_the_phase_space(system: lf.IsospectralSystem) -> None:
    for seed in range(3):
        assert float(system.phase_space_distance(system.random_state(seed))) <= 4 * EPS


def test_project_is_a_projection(system: lf.IsospectralSystem) -> None:
    X = _ambient(system, 0)
    P = system.project(X)
    assert P.shape == X.shape and P.dtype == X.dtype
    assert float(system.phase_space_distance(P)) <= 4 * EPS
    np.testing.assert_allclose(system.project(P), P, rtol=0, atol=4 * EPS * np.linalg.norm(P))
    # the nearest point: no other point Q of the phase space (Q = project(anything)) is
    # closer, near P (local optimality) or far from it
    d = np.linalg.norm(X - P)
    for seed in range(20):
        Q = system.project(P + 10.0 ** (-seed % 4) * _ambient(system, 100 + seed))
        assert np.linalg.norm(X - Q) >= d * (1 - 1e-12)


def test_project_stage_is_linear_and_orthogonal(system: lf.IsospectralSystem) -> None:
    X, Y = _ambient(system, 1), _ambient(system, 2)
    PX, PY = system.project_stage(X), system.project_stage(Y)
    tol = 8 * EPS * (np.linalg.norm(X) + np.linalg.norm(Y))
    np.testing.assert_allclose(system.project_stage(2 * X - 3 * Y), 2 * PX - 3 * PY, atol=tol)
    np.testing.assert_allclose(system.project_stage(PX), PX, rtol=0, atol=tol)
    assert abs(lf.LieAlgebra.inner(X - PX, PY)) <= tol * np.linalg.norm(Y)
    # the phase space lies in the span: projecting a state onto the span changes nothing
    W = system.random_state(4)
    np.testing.assert_allclose(system.project_stage(W), W, rtol=0, atol=4 * EPS)


def test_stage_B_is_B_of_the_stage_projection_bit_for_bit(system: lf.IsospectralSystem) -> None:
    """``stage_B`` (what the fixed-point maps evaluate; the rigid bodies fuse the stage
    projection into ``B``) is exactly ``B(project_stage(W))``, single precision and stacks
    included."""
    for dtype in (None, np.float32 if system.algebra.dtype.kind == "f" else np.complex64):
        X = _ambient(system, 5, dtype)
        for W in (X, np.stack([X, 2 * X])):
            got, want = system.stage_B(W), system.B(system.project_stage(W))
            assert got.dtype == want.dtype and np.array_equal(got, want)


def test_a_subclass_that_overrides_B_keeps_it_at_stage_values() -> None:
    class Faster(lf.systems.RigidBody):
        def B(self, W: np.ndarray) -> np.ndarray:
            return 2 * super().B(W)

    body, plain = Faster(), lf.systems.RigidBody()
    X = _ambient(body, 6)
    assert np.array_equal(body.stage_B(X), 2 * plain.stage_B(X))


def test_distance_is_batched(system: lf.IsospectralSystem) -> None:
    X = np.stack([[_ambient(system, s + 3 * k) for s in range(3)] for k in range(2)])
    d = system.phase_space_distance(X)
    assert d.shape == (2, 3)
    assert d[1, 2] == pytest.approx(float(system.phase_space_distance(X[1, 2])), rel=1e-14)
    P = system.project(X)
    np.testing.assert_allclose(P[1, 2], system.project(X[1, 2]), rtol=0, atol=1e-15)


def _off_phase_space(system: lf.IsospectralSystem, W: np.ndarray) -> np.ndarray:
    """A direction out of the phase space: asymmetric for Toda, a trace for su(N), a
    radial one for vortices, symmetric for so(n)."""
    n = W.shape[-1]
    if isinstance(system, lf.systems.PeriodicToda):
        E = np.zeros((n, n))
        E[0, 1] = 1.0
        return E
    vortices = sys.modules.get("lieflow_vortices")  # loaded if the plugin's system is here
    if vortices is not None and isinstance(system, vortices.PointVortices):
        return W  # changes every radius |m_i|
    if system.algebra.dtype.kind == "c":
        return 1j * np.eye(n)  # skew-Hermitian, not traceless
    return np.eye(n)


@pytest.mark.parametrize("size", [1e-10, 1e-6])
def test_distance_detects_leaving_the_phase_space(
    system: lf.IsospectralSystem, size: float
) -> None:
    W = system.random_state(5)
    E = _off_phase_space(system, W)
    V = W + size * E / np.linalg.norm(E)
    d = float(system.phase_space_distance(V))
    assert d == pytest.approx(size / np.linalg.norm(V), rel=0.5)


def test_toda_asymmetry_is_invisible_to_the_algebra_but_not_to_the_phase_space() -> None:
    toda = lf.systems.get("periodic_toda")
    W = toda.random_state(0)
    W[0, 1] += 1e-8
    assert float(toda.algebra.distance(W)) == 0.0  # gl(n): every matrix is in the algebra
    assert float(toda.phase_space_distance(W)) > 1e-9


def test_toda_refuses_a_non_symmetric_initial_condition(tmp_path: Path) -> None:
    """Issue 29.4: the scheme would integrate the symmetric part, silently (an
    antisymmetric W0 gave an all-zero trajectory marked complete)."""
    toda = lf.systems.get("periodic_toda")
    skew = np.triu(np.ones((4, 4)), 1)
    skew -= skew.T
    W = toda.random_state(0)
    W[0, 1] += 1e-8
    for bad in (skew, W, np.arange(16.0).reshape(4, 4)):
        with pytest.raises(lf.InputError, match=r"symmetric W0.*gl_gradient=True"):
            lf.integrate(toda, lf.schemes.get("midpoint"), bad, 0.1, steps=2)
    # roundoff asymmetry (a rotated diagonal matrix) and the gradient extension are fine
    Q, _ = np.linalg.qr(np.random.default_rng(3).standard_normal((4, 4)))
    rotated = Q @ np.diag([1.0, 2.0, 3.0, 4.0]) @ Q.T
    assert float(toda.phase_space_distance(rotated)) > 0.0
    np.testing.assert_array_equal(toda.validate(rotated), rotated)
    ext = lf.systems.get("periodic_toda", gl_gradient=True)
    np.testing.assert_array_equal(ext.validate(skew), skew)
    # and from a configuration file: the same error, before any file is written
    config = tmp_path / "run.toml"
    np.save(tmp_path / "w0.npy", skew)
    config.write_text(
        '[system]\nname = "periodic_toda"\n[initial]\nfile = "w0.npy"\n'
        '[scheme]\nname = "midpoint"\n[run]\nh = 0.1\nsteps = 3\n'
    )
    from lieflow.app.cli import main

    assert main(["run", str(config), "--out", str(tmp_path / "t.h5"), "--no-progress"]) != 0
    assert not (tmp_path / "t.h5").exists()


@pytest.mark.parametrize("name", SCHEMES)
def test_projection_changes_a_converged_step_by_roundoff(
    system: lf.IsospectralSystem, name: str
) -> None:
    """``scheme.step`` (no projection of the new state) lands on the phase space to
    roundoff, so projecting it changes nothing measurable (measured: <= 1.7e-16)."""
    W0 = system.random_state(7)
    W1 = lf.schemes.get(name).step(W0, 0.1, system, lf.solvers.FixedPoint()).W
    assert float(system.phase_space_distance(W1)) <= 8 * EPS
    assert np.linalg.norm(system.project(W1) - W1) <= 8 * EPS * np.linalg.norm(W1)


def test_solution_measures_the_phase_space() -> None:
    toda = lf.systems.get("periodic_toda")
    sol = lf.integrate(toda, lf.schemes.get("gauss2"), lf.systems.PAPER_W0, 0.1, steps=20)
    assert sol.phase_space_distance().shape == (21,)
    assert sol.phase_space_distance().max() <= 4 * EPS
    np.testing.assert_array_equal(sol.algebra_distance(), sol.phase_space_distance())


def test_toda_gradient_extension_has_all_of_gl_n_as_phase_space() -> None:
    ext = lf.systems.get("periodic_toda", gl_gradient=True)
    X = np.random.default_rng(0).standard_normal((4, 4))
    assert float(ext.phase_space_distance(X)) == 0.0
    assert ext.hadamard_factor is None
    # same B, same trajectory on symmetric matrices
    toda = lf.systems.get("periodic_toda")
    W = toda.random_state(1)
    np.testing.assert_array_equal(ext.B(W), toda.B(W))
    a = lf.integrate(toda, lf.schemes.get("gauss3"), W, 0.1, steps=50, engine="numpy")
    b = lf.integrate(ext, lf.schemes.get("gauss3"), W, 0.1, steps=50, engine="numpy")
    np.testing.assert_allclose(a.W_final, b.W_final, rtol=0, atol=1e-13)


@settings(max_examples=150, deadline=None)
@given(
    n=st.one_of(st.integers(2, 12), st.just(70)),  # 70: minus_dagger in 64 x 64 blocks
    seed=st.integers(0, 2**32 - 1),
    h=st.floats(-4.0, 4.0, allow_subnormal=False).filter(lambda h: h != 0),
    scale=st.integers(-100, 100),
    single=st.booleans(),
)
def test_commutator_update_keeps_an_exactly_skew_state_exactly_skew(
    n: int, seed: int, h: float, scale: int, single: bool
) -> None:
    """``W1 = W0 + h (C - C^T)`` (the midpoint rule's update, ``C = B(P M) P M``) of an
    exactly skew ``W0`` with a +0 diagonal (what the projection returns) is exactly skew
    with a +0 diagonal for *any* stage value ``M`` and sign of ``h``: the projection
    returns it bit for bit, so a stepping loop may skip it (``SchemeFlow.step_from_phase_space``;
    the proof is in ``StageProblem.commutator_update``)."""
    rng = np.random.default_rng(seed)
    dtype = np.float32 if single else np.float64
    X = (rng.standard_normal((n, n)) * 10.0 ** (scale // (8 if single else 1))).astype(dtype)
    W0 = lf.SO(n).project(X)  # exactly skew, +0 diagonal
    assert W0.tobytes() == lf.SO(n).project(W0).tobytes()
    M = rng.standard_normal((n, n)).astype(dtype) * W0.dtype.type(np.abs(W0).max())
    body = lf.systems.GeneralizedRigidBody.random_inertia(n, seed=seed % 1000)
    W1 = MidpointProblem(body, W0, h).update(M)
    assert W1.dtype == W0.dtype
    if np.isfinite(W1).all():
        assert body.project(W1).tobytes() == W1.tobytes()


@pytest.mark.parametrize("name", ["midpoint", "triple_jump", "gauss2"])
@pytest.mark.parametrize("update", ["commutator", "conjugation"])
def test_a_run_skips_only_projections_that_return_the_state_unchanged(
    name: str, update: str
) -> None:
    """After its first step the numpy engine steps a flow by ``step_from_phase_space``,
    which leaves out the final projection where the scheme keeps exact skew-symmetry
    (``Scheme.keeps_skew``: SyDIRK with the commutator update); every state equals, bit
    for bit, the state of ``SchemeFlow.step`` (which always projects) — on so(n), where
    the skip applies, and elsewhere (the Cayley form, Gauss), where it does not."""
    scheme = lf.schemes.get(name, update=update)
    assert scheme.keeps_skew == (name != "gauss2" and update == "commutator")
    body = lf.systems.GeneralizedRigidBody.random_inertia(6, seed=3)
    W0, h, steps = body.random_state(4), 0.05, 30
    solver = lf.solvers.FixedPoint(rtol=1e-12)
    sol = lf.integrate(body, scheme, W0, h, steps=steps, solver=solver, engine="numpy",
                       diagnostics=False, warm_start=1)  # fmt: skip
    flow = lf.SchemeFlow(body, scheme, solver, warm_start=1)
    W, state = W0, flow.init(W0)
    for k in range(steps):
        W, state, _ = flow.step(W, k * h, h, state)
        assert W.tobytes() == sol.W[k + 1].tobytes(), k
    # the stepping loop's step-by-step loop (a monitor or Ctrl-C handler watching) does the same
    one_by_one = np.concatenate([c.W for c in advance(flow, W0, h, steps, batch=1)])
    assert one_by_one.tobytes() == sol.W[1:].tobytes()
