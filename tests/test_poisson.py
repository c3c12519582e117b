"""Lie–Poisson structure, checked by finite differences (tests that fail when it is broken).

* **Gradient test**: ``B(W) = (∇η(W))^†`` — ``d/dε η(W + εX) = Re tr(B(W) X)`` for every
  direction ``X`` of an orthonormal basis of the algebra, at a state of the phase space.
  For the periodic Toda lattice ``η`` is :meth:`PeriodicToda.gradient_hamiltonian` (the
  paper's ``η`` minus the gl(n) Casimir ``2 tr W²``, which changes ``∇η`` by ``4W^T``).
* **Poisson-tensor test**: the one-step map ``Φ`` of an isospectral scheme is a Poisson map
  of the Lie–Poisson structure, ``DΦ(W) Π(W) DΦ(W)^T = Π(Φ(W))``, with
  ``Π(W)X = [X^†, W]`` (so that ``dW/dt = Π(W)∇η = [B, W]``) in coordinates of an
  orthonormal basis of the algebra; ``DΦ`` by 4th-order central differences.

Both are run on every registered system, and on deliberately broken systems (a rigid body
whose ``B`` is not a gradient; the paper's Toda ``B`` off the symmetric matrices) that
must fail them. Measured: gradient defects <= 2e-12, Poisson defects <= 8e-13 relative
(every registered system with gauss3 at h = 0.2, every registered scheme on the generalized
rigid body); broken systems 7e-2 .. 3e-1.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import SCHEMES

import lieflow as lf
from lieflow.algebras import dagger

SOLVER = lf.solvers.FixedPoint(rtol=1e-15)
#: acceptance thresholds (measured: gradient <= 2e-12, Poisson <= 8e-13; broken: >= 7e-2)
GRADIENT_TOL = 1e-9
POISSON_TOL = 1e-10


@functools.cache
def _basis_of(algebra: lf.LieAlgebra) -> np.ndarray:
    """An orthonormal basis of ``algebra`` (Frobenius pairing), shape ``(dim, n, n)``:
    the projections of the unit matrices, orthonormalised (SVD)."""
    n = algebra.n
    units = np.eye(n * n).reshape(n * n, n, n)
    if algebra.dtype.kind == "c":
        units = np.concatenate([units, 1j * units])
    P = algebra.project(units.astype(algebra.dtype))
    flat = np.concatenate([P.real.reshape(len(P), -1), P.imag.reshape(len(P), -1)], axis=1)
    _, s, vt = np.linalg.svd(flat, full_matrices=False)
    rank = int(np.sum(s > 1e-10))
    assert rank == algebra.dimension, (rank, algebra.dimension)
    v = vt[:rank]
    basis = v[:, : n * n] + 1j * v[:, n * n :] if algebra.dtype.kind == "c" else v[:, : n * n]
    return np.asarray(basis.reshape(rank, n, n))


def basis(system: lf.IsospectralSystem) -> np.ndarray:
    return _basis_of(system.algebra)


def coords(E: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``<e_a, W>`` for each basis element."""
    return np.asarray(lf.LieAlgebra.inner(E, W[None]))


def poisson_matrix(E: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``P_ab = <e_a, [e_b^†, W]>``: the Lie–Poisson tensor in the basis ``E``."""
    cols = np.stack([coords(E, dagger(e) @ W - W @ dagger(e)) for e in E], axis=1)
    return cols


def gradient_defect(system: lf.IsospectralSystem, W: np.ndarray) -> float:
    """``max_X |dη(W)[X] - Re tr(B(W) X)| / ||B(W)||`` over the basis ``X`` (4th-order
    central differences of step ``1e-4 ||W||``)."""
    eta = getattr(system, "gradient_hamiltonian", system.hamiltonian)
    eps = 1e-4 * float(np.linalg.norm(W))
    B = system.B(W)
    worst = 0.0
    for X in basis(system):
        f = [float(eta(W + k * eps * X)) for k in (-2, -1, 1, 2)]
        fd = (f[0] - 8 * f[1] + 8 * f[2] - f[3]) / (12 * eps)
        exact = float(np.real(np.trace(B @ X)))
        worst = max(worst, abs(fd - exact))
    return worst / float(np.linalg.norm(B))


def poisson_defect(
    system: lf.IsospectralSystem, scheme: lf.Scheme, W: np.ndarray, h: float
) -> float:
    """``||DΦ P(W) DΦ^T - P(Φ(W))|| / ||P(Φ(W))||`` for one step ``Φ`` of ``scheme``."""
    E = basis(system)

    def phi(V: np.ndarray) -> np.ndarray:
        return coords(E, scheme.step(V, h, system, SOLVER).W)

    eps = 2e-4 * float(np.linalg.norm(W))
    J = np.stack(
        [
            (
                -phi(W + 2 * eps * e)
                + 8 * phi(W + eps * e)
                - 8 * phi(W - eps * e)
                + phi(W - 2 * eps * e)
            )
            / (12 * eps)
            for e in E
        ],
        axis=1,
    )
    W1 = scheme.step(W, h, system, SOLVER).W
    target = poisson_matrix(E, W1)
    return float(np.linalg.norm(J @ poisson_matrix(E, W) @ J.T - target) / np.linalg.norm(target))


# ------------------------------------------------------------------ deliberately broken


class NonGradientBody(lf.systems.RigidBody):
    """A rigid body whose angular velocity is ``omega = M m`` with a NON-symmetric ``M``:
    ``B = -hat(M m)`` is no gradient; ``η`` is the energy of the symmetric part."""

    M = np.diag([1.0, 0.5, 1.0 / 3.0]) + 0.3 * np.array([[0, 1, 0], [-1, 0, 1], [0, -1, 0]])

    def B(self, W: np.ndarray) -> np.ndarray:
        return -lf.systems.hat(np.einsum("ij,...j->...i", self.M, lf.systems.vee(W)))

    @property
    def hadamard_factor(self) -> None:
        return None

    def hamiltonian(self, W: np.ndarray) -> np.ndarray:
        m = lf.systems.vee(W)
        return np.einsum("...i,ij,...j->...", m, 0.5 * (self.M + self.M.T), m)


def _systems() -> list:  # type: ignore[type-arg]
    """Every registered system, as pytest params with the registry name as id."""
    from conftest import SYSTEMS, make_system

    return [pytest.param(make_system(name), id=name) for name in SYSTEMS]


def _lie_poisson_systems() -> list:  # type: ignore[type-arg]
    """Where the Poisson-tensor test applies: every registered system, the Toda lattice
    through its gl(n) gradient extension (the paper's ``B`` is not a gradient on gl(n))."""
    out = []
    for p in _systems():
        (s,) = p.values
        if isinstance(s, lf.systems.PeriodicToda):
            s = lf.systems.get("periodic_toda", gl_gradient=True)
        out.append(pytest.param(s, id=p.id))
    return out


def _start(system: lf.IsospectralSystem) -> np.ndarray:
    W = system.random_state(seed=4)
    if isinstance(system, lf.systems.PeriodicToda) and system.gl_gradient:
        # a generic gl(n) state: the extension is Lie-Poisson on all of gl(n)
        W = W + 0.3 * np.random.default_rng(4).standard_normal(W.shape) / W.shape[-1]
    return W


# ------------------------------------------------------------------ gradient test


@pytest.mark.parametrize("system", _systems())
def test_B_is_the_gradient_of_eta(system: lf.IsospectralSystem) -> None:
    assert gradient_defect(system, system.random_state(seed=2)) <= GRADIENT_TOL


def test_toda_extension_is_a_gradient_on_all_of_gl_n() -> None:
    ext = lf.systems.get("periodic_toda", gl_gradient=True)
    assert gradient_defect(ext, _start(ext)) <= GRADIENT_TOL


def test_gradient_test_fails_for_a_wrong_B() -> None:
    """The negative cases: a non-gradient B; the paper's Toda B off the symmetric
    matrices; the paper's Toda eta with its Casimir part (gradient off by 4 W^T)."""
    body = NonGradientBody()
    assert gradient_defect(body, body.random_state(0)) > 1e-2
    toda = lf.systems.get("periodic_toda")
    W = toda.random_state(0) + 0.1 * np.random.default_rng(0).standard_normal((4, 4))
    assert gradient_defect(toda, W) > 1e-2

    class CasimirEta(lf.systems.PeriodicToda):
        def gradient_hamiltonian(self, W: np.ndarray) -> np.ndarray:
            eta_tilde = lf.systems.PeriodicToda.gradient_hamiltonian(self, W)
            return eta_tilde + 2.0 * np.einsum("...ij,...ji->...", W, W)  # the paper's eta

    assert gradient_defect(CasimirEta(), toda.random_state(0)) > 1.0


# ------------------------------------------------------------------ Poisson-tensor test


@pytest.mark.parametrize("system", _lie_poisson_systems())
def test_one_step_map_is_poisson(system: lf.IsospectralSystem) -> None:
    d = poisson_defect(system, lf.schemes.get("gauss3"), _start(system), 0.2)
    assert d <= POISSON_TOL


@pytest.mark.parametrize("name", SCHEMES)
def test_every_scheme_is_poisson(name: str) -> None:
    system = lf.systems.get("generalized_rigid_body")
    assert poisson_defect(system, lf.schemes.get(name), system.random_state(3), 0.2) <= POISSON_TOL


def test_poisson_test_fails_for_a_non_gradient_B() -> None:
    body = NonGradientBody()
    assert poisson_defect(body, lf.schemes.get("gauss2"), body.random_state(1), 0.2) > 1e-4


def test_paper_toda_map_is_not_poisson_on_gl_n_but_agrees_with_the_extension() -> None:
    """The paper's B off the symmetric matrices breaks the structure on gl(n); on the
    symmetric phase space its map is the (Poisson) map of the gradient extension."""
    toda = lf.systems.get("periodic_toda")
    ext = lf.systems.get("periodic_toda", gl_gradient=True)
    W = toda.random_state(4)
    scheme = lf.schemes.get("gauss3")
    assert poisson_defect(toda, scheme, W, 0.2) > 1e-4
    assert poisson_defect(ext, scheme, W, 0.2) <= POISSON_TOL
    np.testing.assert_allclose(
        scheme.step(W, 0.2, toda, SOLVER).W, scheme.step(W, 0.2, ext, SOLVER).W, atol=1e-14
    )
