"""The point-vortex plugin distribution (plugins/lieflow-vortices), tested as a user sees it.

Install it with ``pip install -e plugins/lieflow-vortices`` (CI does). The reference for the
dynamics is an independent direct integration of the vortex equations on the sphere
(``scipy.integrate.solve_ivp``), written here without the plugin's isospectral machinery.
"""

from __future__ import annotations

import ast
import os
from pathlib import Path

import lieflow_vortices as lv
import numpy as np
import pytest
from lieflow_vortices import BlockSO3, PointVortices, block_hat, block_vee, random_positions
from scipy.integrate import solve_ivp

import lieflow as lf

STRENGTHS = (1.0, 1.0, 1.0, -1.0)
PLUGIN_DIR = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def system() -> PointVortices:
    return PointVortices(strengths=STRENGTHS)


@pytest.fixture(scope="module")
def W0(system: PointVortices) -> np.ndarray:
    # well separated (min chord 0.5): fixed-point iteration contracts at h = 0.1
    return system.random_initial_condition(seed=0, min_distance=0.5)


def vortex_rhs(t: float, y: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """dx_i/dt = 1/(4π) sum_{j≠i} Γ_j (x_j × x_i) / (1 - x_i·x_j), directly in positions."""
    x = y.reshape(-1, 3)
    cross = np.cross(x[None, :, :], x[:, None, :])  # [i, j] = x_j × x_i
    gap = 1.0 - x @ x.T
    np.fill_diagonal(gap, np.inf)
    return (np.einsum("j,ijk->ik", gamma, cross / gap[:, :, None]) / (4 * np.pi)).ravel()


def reference_positions(x0: np.ndarray, gamma: np.ndarray, T: float) -> np.ndarray:
    ref = solve_ivp(
        vortex_rhs, (0.0, T), x0.ravel(), args=(gamma,), method="DOP853", rtol=1e-13, atol=1e-14
    )
    assert ref.success
    return ref.y[:, -1].reshape(-1, 3)


# ------------------------------------------------------------------------- plugin wiring
def test_registered_through_its_entry_point() -> None:
    registry = (
        lf.load_registry(autoload=True)
        if os.environ.get("LIEFLOW_DISABLE_PLUGIN_AUTOLOAD")
        else lf.default_registry()
    )
    entry = registry.systems["point_vortices"]
    assert "lieflow-vortices" in entry.source
    assert entry.factory is PointVortices
    made = registry.create("system", "point_vortices", strengths=(2.0, -1.0, 0.5))
    assert isinstance(made, lf.IsospectralSystem)
    assert made.K == 3 and str(made.algebra) == "so(3)^3"


def test_plugin_uses_only_the_public_api() -> None:
    # lieflow.backends: the documented helpers for arrays of other libraries (docs/gpu.md)
    public = {"lieflow", "lieflow.systems", "lieflow.numba_cache", "lieflow.backends"}
    for path in (PLUGIN_DIR / "lieflow_vortices").glob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                mods = [node.module or ""]
            else:
                continue
            for mod in mods:
                if mod.split(".")[0] == "lieflow":
                    assert mod in public, f"{path.name} imports {mod}"
        assert "lieflow._" not in path.read_text(encoding="utf-8")


# ------------------------------------------------------------------------- the algebra
def test_block_algebra() -> None:
    alg = BlockSO3(4)
    assert (alg.n, alg.K, alg.dimension, alg.skew) == (12, 4, 12, True)
    assert alg == BlockSO3(4) and hash(alg) == hash(BlockSO3(4))
    X = np.random.default_rng(1).standard_normal((2, 5, 12, 12))
    P = alg.project(X)
    np.testing.assert_allclose(alg.project(P), P, atol=0, rtol=0)
    assert alg.contains(P) and not alg.contains(X)
    blocks = P.reshape(2, 5, 4, 3, 4, 3)
    for i in range(4):
        for j in range(4):
            if i != j:
                assert not blocks[..., i, :, j, :].any()
    # the projection is orthogonal: <X - P(X), P(Y)> = 0
    Y = alg.random(seed=2)
    assert abs(float(alg.inner(X - P, Y).max())) < 1e-12
    m = block_vee(P)
    assert m.shape == (2, 5, 4, 3)
    np.testing.assert_array_equal(block_hat(m), P)
    with pytest.raises(lf.InputError):
        BlockSO3(0)


def test_vortex_projection_puts_each_vortex_on_its_sphere() -> None:
    """The phase space is the product of the spheres |m_i| = |Γ_i|: the projection of a
    perturbed state (off the spheres and off so(3)^K) lands on them."""
    system = PointVortices(strengths=(1.0, -2.0, 0.5))
    W = system.random_state(0)
    ambient = np.random.default_rng(9).standard_normal((system.algebra.n, system.algebra.n))
    V = system.project(1.1 * W + 1e-3 * ambient)
    m = block_vee(V)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), [1.0, 2.0, 0.5], rtol=1e-15)
    assert system.algebra.contains(V, tol=1e-15)
    assert float(system.phase_space_distance(1.1 * W)) == pytest.approx(0.1 / 1.1, rel=1e-12)


# ------------------------------------------------------------------------- dynamics
def test_vector_field_matches_the_vortex_equations(system: PointVortices) -> None:
    x = random_positions(system.K, seed=3)
    W = system.initial_condition(x)
    dW = lf.LieAlgebra.bracket(system.B(W), W)
    dx = block_vee(dW) / system.strengths[:, None]
    np.testing.assert_allclose(dx.ravel(), vortex_rhs(0.0, x.ravel(), system.strengths), atol=1e-15)


def test_gauss3_trajectory_matches_solve_ivp(system: PointVortices, W0: np.ndarray) -> None:
    T = 10.0
    x0 = system.positions(W0)
    expected = reference_positions(x0, system.strengths, T)
    assert np.abs(expected - x0).max() > 0.5  # the vortices really move
    errors = {}
    for h in (0.4, 0.2, 0.1):
        sol = lf.integrate(system, lf.schemes.get("gauss3"), W0, h=h, t_final=T)
        errors[h] = np.abs(system.positions(sol.W_final) - expected).max()
    assert errors[0.1] < 1e-10  # measured 6e-13
    assert errors[0.4] / errors[0.2] > 40  # order 6: ratio 64 (measured 64)


def test_B_derivative_is_the_frechet_derivative(system: PointVortices) -> None:
    rng = np.random.default_rng(4)
    W = np.stack([system.random_initial_condition(seed=s, min_distance=0.3) for s in (5, 6)])
    for dW in (system.algebra.project(rng.standard_normal(W.shape)), rng.standard_normal(W.shape)):
        eps = 1e-5
        fd = (system.B(W + eps * dW) - system.B(W - eps * dW)) / (2 * eps)
        exact = system.B_derivative(W, dW)
        for k in range(W.shape[0]):
            rel = np.linalg.norm(fd[k] - exact[k]) / np.linalg.norm(exact[k])
            assert rel <= 1e-7, rel


def test_B_is_the_dagger_of_grad_eta(system: PointVortices, W0: np.ndarray) -> None:
    """d/dε eta(W + εE) = <B(W)^†, E> for any direction E, and eta = -2H."""
    E = np.random.default_rng(7).standard_normal(W0.shape)
    eps = 1e-5
    fd = (system.hamiltonian(W0 + eps * E) - system.hamiltonian(W0 - eps * E)) / (2 * eps)
    assert abs(fd - np.sum(system.B(W0).T * E)) <= 1e-9 * abs(fd)
    x, g = system.positions(W0), system.strengths
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    H = -sum(g[i] * g[j] * np.log(1 - x[i] @ x[j]) for i, j in pairs) / (4 * np.pi)
    assert system.energy(W0) == pytest.approx(H, rel=1e-14)
    assert system.hamiltonian(W0) == pytest.approx(-2 * H, rel=1e-14)


def test_conservation_over_200_steps(system: PointVortices, W0: np.ndarray) -> None:
    sol = lf.integrate(system, lf.schemes.get("gauss3"), W0, h=0.1, steps=200)
    assert sol.casimir_drift.shape == (201, system.K)
    assert sol.energy_error.max() < 1e-10  # measured 1.3e-12 (order 6 at h = 0.1)
    assert sol.casimir_drift.max() <= 1e-13  # measured 1.1e-15: |m_i|^2 = Γ_i^2
    # the returned states are projected onto the spheres |m_i| = |Γ_i|; the next step,
    # before projection, must be on them too (isospectrality, not construction)
    nxt = lf.schemes.get("gauss3").step(sol.W_final, 0.1, system, lf.solvers.FixedPoint()).W
    assert float(system.phase_space_distance(nxt)) <= 1e-14  # measured 1.5e-16
    J = system.moment_of_vorticity(sol.W)
    assert np.abs(J - J[0]).max() <= 1e-13  # measured 1.7e-15
    np.testing.assert_allclose(np.linalg.norm(system.positions(sol.W), axis=-1), 1.0, atol=1e-14)


def test_batch_matches_single_runs(system: PointVortices) -> None:
    W = np.stack([system.random_initial_condition(seed=s, min_distance=0.5) for s in (0, 8, 9)])
    batch = lf.integrate(system, lf.schemes.get("gauss3"), W, h=0.1, steps=5)
    assert batch.casimir_drift.shape == (6, 3, system.K)
    for k in range(3):
        one = lf.integrate(system, lf.schemes.get("gauss3"), W[k], h=0.1, steps=5)
        np.testing.assert_allclose(batch.W_final[k], one.W_final, rtol=0, atol=1e-13)


@pytest.mark.parametrize("scheme", ["midpoint", "gauss3"])
def test_newton_agrees_with_fixed_point(system: PointVortices, W0: np.ndarray, scheme: str) -> None:
    sc = lf.schemes.get(scheme)
    fp = sc.step(W0, 0.1, system, lf.solvers.FixedPoint(), None)
    nt = sc.step(W0, 0.1, system, lf.solvers.Newton(), None)
    assert nt.stats.iterations <= 5  # quadratic convergence (measured 3)
    assert np.abs(fp.W - nt.W).max() <= 1e-12


def test_newton_solves_a_stiff_step(system: PointVortices) -> None:
    """A close co-rotating pair (chord 0.26): fixed point stalls at h = 0.1, Newton does not."""
    W = system.initial_condition(random_positions(system.K, seed=1))
    sc = lf.schemes.get("gauss3")
    with pytest.raises(lf.ConvergenceError):
        sc.step(W, 0.1, system, lf.solvers.FixedPoint(), None)
    res = sc.step(W, 0.1, system, lf.solvers.Newton(), None)
    np.testing.assert_allclose(system.casimirs(res.W), system.strengths**2, rtol=1e-14)
    assert abs(system.energy(res.W) / system.energy(W) - 1) < 1e-4


# ------------------------------------------------------------------------- states and inputs
def test_states_round_trip(system: PointVortices) -> None:
    x = random_positions(4, seed=11)
    np.testing.assert_array_equal(x, random_positions(4, seed=11))
    np.testing.assert_allclose(np.linalg.norm(x, axis=-1), 1.0, atol=1e-15)
    W = system.initial_condition(3.0 * x)  # positions are normalised
    np.testing.assert_allclose(system.positions(W), x, atol=1e-15)
    np.testing.assert_allclose(system.casimirs(W), system.strengths**2, rtol=1e-15)
    np.testing.assert_array_equal(system.validate(W), W)
    far = random_positions(6, seed=12, min_distance=0.8)
    gaps = np.sqrt(np.maximum(2 * (1 - far @ far.T), 0.0))[~np.eye(6, dtype=bool)]
    assert gaps.min() >= 0.8


@pytest.mark.parametrize(
    ("strengths", "match"),
    [
        ((1.0,), "at least K = 2"),
        ((), "at least K = 2"),
        ((1.0, 0.0, 2.0), "vortex 1 is zero"),
        ((1.0, np.inf), "vortex 1 is inf"),
        ((1.0, np.nan), "vortex 1 is nan"),
        ([[1.0, 2.0]], "1-D"),
        ("ab", "non-zero finite"),
    ],
)
def test_bad_strengths(strengths: object, match: str) -> None:
    with pytest.raises(lf.InputError, match=match):
        PointVortices(strengths=strengths)  # type: ignore[arg-type]


def test_bad_initial_conditions(system: PointVortices, W0: np.ndarray) -> None:
    m = block_vee(W0)
    m[2] *= 1.001
    with pytest.raises(lf.InputError, match="vortex 2 has"):
        system.validate(block_hat(m))
    with pytest.raises(lf.InputError, match="vortex 2 has"):
        lf.integrate(system, lf.schemes.get("gauss3"), block_hat(m), h=0.1, steps=1)
    off = W0.copy()
    off[0, 5], off[5, 0] = 0.1, -0.1
    with pytest.raises(lf.AlgebraError, match="block-diagonal"):
        system.validate(off)
    with pytest.raises(lf.InputError, match=r"\(\.\.\., 12, 12\)"):
        system.validate(W0[:9, :9])
    x = system.positions(W0)
    x[3] = x[1]
    with pytest.raises(lf.InputError, match="vortices 1 and 3 coincide"):
        system.validate(system.initial_condition(x))
    x[3] = 0.0
    with pytest.raises(lf.InputError, match="vortex 3 is the zero vector"):
        system.initial_condition(x)
    with pytest.raises(lf.InputError, match="4 vortices"):
        system.initial_condition(np.ones((3, 3)))
    with pytest.raises(lf.InputError, match="min_distance"):
        random_positions(4, seed=0, min_distance=2.5)
    with pytest.raises(lf.InputError, match="lower min_distance"):
        random_positions(30, seed=0, min_distance=1.5, max_tries=3)


def test_exports() -> None:
    assert set(lv.__all__) <= set(dir(lv))
    assert lv.COLLISION_GAP > 0
