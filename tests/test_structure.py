"""Geometric properties of every registered (system, scheme) pair, plugins included:
isospectrality, coadjoint orbits (iterates stay in the algebra), Casimirs, time symmetry."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SCHEMES
from helpers import HermitianBody, TracelessHermitianBody, tight
from hypothesis import given, settings
from hypothesis import strategies as st

import lieflow as lf


def _run(
    system: lf.IsospectralSystem, scheme: lf.Scheme, W0: np.ndarray, steps: int
) -> lf.Solution:
    return lf.integrate(system, scheme, W0, h=0.05, steps=steps, solver=tight())


def test_geometry_over_200_steps(system: lf.IsospectralSystem, scheme: lf.Scheme) -> None:
    sol = _run(system, scheme, system.random_state(seed=7), steps=200)
    assert sol.success and sol.n_steps == 200
    assert sol.spectrum_drift().max() <= 1e-12
    assert sol.phase_space_distance().max() <= 1e-13
    # The returned states are projected onto the phase space, so the line above holds
    # by construction; the step the scheme takes from the last state, before any
    # projection, must land on the phase space too (symmetric for Toda, on the spheres
    # for vortices, traceless for su(N)): this can fail.
    nxt = scheme.step(sol.W_final, 0.05, system, tight()).W
    assert float(system.phase_space_distance(nxt)) <= 1e-13
    assert sol.casimir_drift is not None and sol.casimir_drift.max() <= 1e-12
    assert sol.energy_error is not None and sol.energy_error.max() < 1e-2


@pytest.mark.parametrize("system_cls", [HermitianBody, TracelessHermitianBody])
@pytest.mark.parametrize("name", ["midpoint", "gauss2", "gauss3", "sydirk7", "modin_viviani"])
def test_complex_algebras(system_cls: type, name: str) -> None:
    system = system_cls()
    sol = _run(system, lf.schemes.get(name), system.random_state(seed=3), steps=100)
    assert sol.W.dtype == np.complex128
    assert sol.spectrum_drift().max() <= 1e-12
    # skew-Hermitian by construction (W1 = W0 + sum (BW - (BW)^†)); the trace of an su(n)
    # step is not, and the unprojected step must keep it at roundoff
    nxt = lf.schemes.get(name).step(sol.W_final, 0.05, system, tight()).W
    assert float(system.phase_space_distance(nxt)) <= 1e-13
    assert sol.casimir_drift is not None and sol.casimir_drift.max() <= 1e-12


#: The registered schemes that are symmetric (self-adjoint) methods: fixed data, so that a
#: scheme that stops being symmetric fails :func:`test_time_symmetry` instead of skipping
#: it (issue 29.9); :func:`test_the_symmetric_schemes_are_listed` keeps the list whole.
SYMMETRIC = (
    "block", "gauss", "gauss2", "gauss3", "gauss4", "midpoint", "modin_viviani", "suzuki5",
    "sydirk7", "triple_jump",
)  # fmt: skip
NOT_SYMMETRIC: tuple[str, ...] = ()


def test_the_symmetric_schemes_are_listed() -> None:
    assert sorted(SYMMETRIC + NOT_SYMMETRIC) == SCHEMES
    for name in NOT_SYMMETRIC:
        assert not lf.schemes.get(name).tableau.is_symmetric(), f"{name} is symmetric now"


@pytest.mark.parametrize("name", SYMMETRIC)
def test_time_symmetry(system: lf.IsospectralSystem, name: str) -> None:
    """Symmetric methods: step(-h) after step(h) is the identity (to solver tolerance)."""
    scheme = lf.schemes.get(name)
    assert scheme.tableau.is_symmetric()
    W0 = system.random_state(seed=11)
    W1 = scheme.step(W0, 0.1, system, tight()).W
    back = scheme.step(W1, -0.1, system, tight()).W
    np.testing.assert_allclose(back, W0, rtol=0, atol=1e-13)


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    h=st.floats(0.01, 0.2),
    name=st.sampled_from(["midpoint", "gauss2", "gauss3"]),
)
def test_isospectral_for_random_rigid_bodies(seed: int, h: float, name: str) -> None:
    rng = np.random.default_rng(seed)
    system = lf.systems.GeneralizedRigidBody(rng.uniform(0.5, 3.0, size=4))
    W0 = system.random_state(rng)
    sol = lf.integrate(system, lf.schemes.get(name), W0, h=h, steps=20, solver=tight())
    assert sol.spectrum_drift().max() <= 1e-12
    # (so(n): skew by construction; the spectrum and Casimirs are the real test here)
    assert sol.casimir_drift is not None and sol.casimir_drift.max() <= 1e-12


def test_ensemble_matches_individual_runs() -> None:
    system = lf.systems.get("rigid_body")
    stack = np.stack([system.random_state(seed=k) for k in range(5)])
    scheme = lf.schemes.get("gauss2")
    together = lf.integrate(system, scheme, stack, h=0.1, steps=30, solver=tight())
    assert together.W.shape == (31, 5, 3, 3)
    for k in range(5):
        alone = lf.integrate(system, scheme, stack[k], h=0.1, steps=30, solver=tight())
        np.testing.assert_allclose(together.W_final[k], alone.W_final, rtol=0, atol=1e-14)


@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
def test_default_casimirs_are_traces_of_powers(batch: tuple[int, ...]) -> None:
    """``Re tr W^k`` from the eigenvalues (an independent evaluation), for one state and
    stacks, real (so(n), gl(n)) and complex (u(n)) data."""
    rng = np.random.default_rng(5)
    for system in (lf.systems.GeneralizedRigidBody.random_inertia(6, seed=2),
                   lf.systems.GeneralizedRigidBody.random_inertia(5, seed=2),
                   lf.systems.GeneralizedRigidBody.random_inertia(3, seed=2),
                   lf.systems.PeriodicToda(5), HermitianBody(4)):  # fmt: skip
        alg = system.algebra
        X = rng.standard_normal((*batch, alg.n, alg.n))
        if alg.dtype.kind == "c":
            X = X + 1j * rng.standard_normal(X.shape)
        W = alg.project(X)
        C = system.casimirs(W)
        lam = np.linalg.eigvals(W)
        powers = [k for k in system.casimir_powers if k <= alg.n]
        want = np.stack([np.real(np.sum(lam**k, axis=-1)) for k in powers], axis=-1)
        assert C.shape == (*batch, len(powers)) and C.dtype == np.float64
        np.testing.assert_allclose(C, want, rtol=1e-10, atol=1e-10)
