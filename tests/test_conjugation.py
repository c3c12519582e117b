"""Updates in conjugation form (SPEC §4.7, :mod:`lieflow.schemes.conjugation`).

(a) at convergence they equal the commutator update to roundoff; (b) on steps stopped after
one or two updates they keep the spectrum to roundoff while the commutator update does not;
(c) their states stay in the algebra; (d) they keep the scheme's order with a loose solve.
Expected values come from spectra (``eigvalsh``), algebraic identities, and the observed
order's theory value.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import HermitianBody, TracelessHermitianBody

import lieflow as lf
from lieflow import tableaus
from lieflow.errors import ConvergenceError, InputError
from lieflow.schemes import BlockGauss, ModinViviani, SyDIRK, conjugation
from lieflow.solvers import FixedPoint

TODA_W0 = np.array([[-1.0, -1, 0, 1], [-1, 1, 1, 0], [0, 1, -1, -1], [1, 0, -1, 1]])


class LowerTriangularFlow(lf.IsospectralSystem):
    """A test-only system on gl(n) whose ``B(W)`` (the lower triangle of ``W``) is not skew:
    ``dW/dt = [B(W), W]`` is isospectral by similarity, not by orthogonal conjugation."""

    linear_B = True

    def __init__(self, n: int = 4) -> None:
        self.n = n

    @property
    def algebra(self) -> lf.LieAlgebra:
        return lf.GL(self.n)

    def B(self, W: np.ndarray) -> np.ndarray:
        return np.tril(W)

    def hamiltonian(self, W: np.ndarray) -> np.ndarray:
        return 0.5 * np.sum(np.tril(W) * W, axis=(-2, -1))


def _schemes(update: str) -> dict[str, lf.Scheme]:
    return {
        "midpoint": SyDIRK(update=update),
        "triple_jump": SyDIRK(tableaus.triple_jump(), update=update),
        "gauss2": BlockGauss(tableaus.gauss(2), update=update),
        "gauss3_block": BlockGauss(tableaus.gauss(3), form="block", update=update),
        "modin_viviani2": ModinViviani(tableaus.gauss(2), update=update),
    }


def _case(name: str) -> tuple[lf.IsospectralSystem, np.ndarray]:
    if name == "so10":
        system = lf.systems.get("generalized_rigid_body", J=np.linspace(1.0, 2.0, 10))
        return system, system.algebra.random(seed=1)
    if name == "toda":
        return lf.systems.get("periodic_toda"), TODA_W0
    if name == "su5":
        system = TracelessHermitianBody(5)
        return system, system.algebra.random(seed=2)
    if name == "u4":
        system = HermitianBody(4)
        return system, system.algebra.random(seed=3)
    system = LowerTriangularFlow(4)
    return system, np.random.default_rng(4).standard_normal((4, 4))


CASES = ["so10", "toda", "su5", "u4", "gl_lower"]
SCHEMES = list(_schemes("commutator"))


def _spectrum(W: np.ndarray) -> np.ndarray:
    """Eigenvalues, sorted: of a symmetric, a skew-Hermitian (as ``i W``) or any matrix."""
    if np.allclose(W, W.conj().T, rtol=0, atol=1e-10):
        return np.linalg.eigvalsh(W)
    if np.allclose(W, -W.conj().T, rtol=0, atol=1e-10):
        return np.linalg.eigvalsh(1j * W)
    ev = np.linalg.eigvals(W)
    return ev[np.lexsort((ev.imag, ev.real))]


def _spectrum_drift(W0: np.ndarray, W1: np.ndarray) -> float:
    e0, e1 = _spectrum(W0), _spectrum(W1)
    return float(np.max(np.abs(e1 - e0)) / np.max(np.abs(e0)))


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("scheme_name", SCHEMES)
def test_equals_commutator_update_at_convergence(case: str, scheme_name: str) -> None:
    system, W0 = _case(case)
    W0 = system.project(W0)
    solver = FixedPoint(rtol=1e-15, max_iter=200)
    old = _schemes("commutator")[scheme_name].step(W0, 0.1, system, solver).W
    new = _schemes("conjugation")[scheme_name].step(W0, 0.1, system, solver).W
    assert np.linalg.norm(new - old) <= 2e-15 * np.linalg.norm(W0)
    assert np.linalg.norm(new - W0) > 1e-3 * np.linalg.norm(W0)  # a real step


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("scheme_name", SCHEMES)
def test_isospectral_for_a_loose_solve(case: str, scheme_name: str) -> None:
    system, W0 = _case(case)
    W0 = system.project(W0)
    solver = FixedPoint(rtol=0.05, max_iter=50)  # one to three updates per solve
    old = _schemes("commutator")[scheme_name].step(W0, 0.1, system, solver)
    new = _schemes("conjugation")[scheme_name].step(W0, 0.1, system, solver)
    assert new.stats.iterations == old.stats.iterations
    assert old.stats.iterations <= 3 * len(_schemes("commutator")[scheme_name].tableau.b)
    assert _spectrum_drift(W0, new.W) <= 4e-15
    assert _spectrum_drift(W0, old.W) >= 1e-11  # what the commutator update loses
    # (c) in the algebra (Toda: on its symmetric phase space) to roundoff
    assert float(np.max(system.algebra.distance(new.W))) <= 1e-15
    if case == "toda":
        assert np.linalg.norm(new.W - new.W.T) <= 1e-14


@pytest.mark.parametrize("update", ["commutator", "conjugation"])
def test_casimirs_over_a_run_with_a_loose_solve(update: str) -> None:
    """200 steps of the so(10) body at ``rtol = 1e-6``: the conjugation update keeps
    ``tr W^2`` and ``tr W^4`` to roundoff, the commutator update drifts by the solve's
    error times the number of steps."""
    system, W0 = _case("so10")
    sol = lf.integrate(
        system, SyDIRK(update=update), W0, 0.1, steps=200, solver=FixedPoint(rtol=1e-6),
        engine="numpy", save_every=200,
    )  # fmt: skip
    W1 = sol.W_final
    drift = max(
        abs(np.trace(np.linalg.matrix_power(W1, k)) / np.trace(np.linalg.matrix_power(W0, k)) - 1)
        for k in (2, 4)
    )
    if update == "conjugation":
        assert drift <= 1e-14
    else:
        assert drift >= 1e-11


def _observed_order(scheme: lf.Scheme, solver: lf.Solver) -> float:
    """``log2(e(h)/e(h/2))`` at ``h = 1/8, 1/16`` on the so(10) body over ``T = 1``
    against Gauss-6 (order 12) at ``h = 1/64`` solved to roundoff."""
    system, W0 = _case("so10")

    def final(s: lf.Scheme, n: int, sol: lf.Solver) -> np.ndarray:
        out = lf.integrate(system, s, W0, 1.0 / n, steps=n, solver=sol, save_every=n)
        return out.W_final

    ref = final(lf.schemes.get("gauss", stages=6), 64, FixedPoint(rtol=1e-15))
    e1, e2 = (np.linalg.norm(final(scheme, n, solver) - ref) for n in (8, 16))
    return float(np.log2(e1 / e2))


@pytest.mark.parametrize(
    ("scheme", "order"),
    [(SyDIRK(update="conjugation"), 2), (BlockGauss(tableaus.gauss(2), update="conjugation"), 4)],
)
def test_order_kept_with_an_accuracy_tolerance(scheme: lf.Scheme, order: int) -> None:
    """The stopping rule on accuracy: ``rtol`` well below the local error (``1e-10`` here,
    errors ``1e-4 .. 1e-7``) keeps the order."""
    assert _observed_order(scheme, FixedPoint(rtol=1e-10)) == pytest.approx(order, abs=0.1)


def test_cayley_identity_for_non_skew_B() -> None:
    """``C W0 C^{-1} = (I + aB) M (I - aB)`` when ``W0 = (I - aB) M (I + aB)`` (the
    midpoint equation solved), for a general real ``B``."""
    rng = np.random.default_rng(5)
    M, B = rng.standard_normal((2, 6, 6))
    a, eye = 0.07, np.eye(6)
    W0 = (eye - a * B) @ M @ (eye + a * B)
    expected = (eye + a * B) @ M @ (eye - a * B)
    got = conjugation.cayley_update(W0, B, a, skew=False)
    assert np.linalg.norm(got - expected) <= 1e-14 * np.linalg.norm(expected)


def test_orthonormalize_reaches_roundoff_and_refuses_far_matrices() -> None:
    rng = np.random.default_rng(6)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 8, 8)))
    U = Q + 1e-4 * rng.standard_normal(Q.shape)
    V = np.eye(8) + conjugation.orthonormalize(U - np.eye(8))
    assert np.max(np.linalg.norm(np.swapaxes(V, -1, -2) @ V - np.eye(8), axis=(-2, -1))) <= 1e-14
    assert np.linalg.norm(V - Q) <= 1e-3  # the nearest unitary, not just any
    with pytest.raises(ConvergenceError, match="far from unitary"):
        conjugation.orthonormalize(3.0 * Q - np.eye(8))


def test_update_option_is_validated() -> None:
    with pytest.raises(InputError, match="update must be one of"):
        SyDIRK(update="cayley")
    with pytest.raises(InputError, match="update must be one of"):
        BlockGauss(update="polar")


@pytest.mark.parametrize("case", ["so10", "toda"])
@pytest.mark.parametrize("scheme_name", ["midpoint", "gauss2"])
def test_compiled_engine_runs_the_same_update(case: str, scheme_name: str) -> None:
    """The compiled loops' conjugation updates (:mod:`lieflow.engines._compiled_formulations`)
    agree with the numpy path to roundoff, and keep the Casimirs at a loose solve."""
    pytest.importorskip("numba")
    from lieflow.engines import compiled

    system, W0 = _case(case)
    scheme = _schemes("conjugation")[scheme_name]
    solver = FixedPoint(rtol=1e-6)
    plan = compiled.plan(system, scheme, solver, W0)
    assert not isinstance(plan, str) and plan.conjugation
    finals = [
        lf.integrate(
            system, scheme, W0, 0.1, steps=40, solver=solver, engine=engine, save_every=40
        ).W_final
        for engine in ("numpy", "compiled")
    ]
    assert np.linalg.norm(finals[1] - finals[0]) <= 1e-13 * np.linalg.norm(W0)
    assert not np.array_equal(finals[1], finals[0])  # the loops ran, not the numpy path
    assert _spectrum_drift(W0, finals[1]) <= 1e-14


@pytest.mark.parametrize("name", ["midpoint", "sydirk7", "triple_jump", "suzuki5", "gauss",
                                  "gauss3", "modin_viviani"])  # fmt: skip
def test_registered_schemes_take_the_update(name: str) -> None:
    """Every registered scheme takes ``update`` (so run configurations can set it)."""
    assert lf.schemes.get(name, update="conjugation").update == "conjugation"
    assert lf.schemes.get(name).update == "commutator"


def test_one_source_for_any_array_library() -> None:
    """The updates run on arrays of another array-API library (``array_api_strict``, which
    refuses anything outside the standard) and give NumPy's numbers."""
    xp = pytest.importorskip("array_api_strict")
    rng = np.random.default_rng(7)
    n = 5
    W0, B = (X - X.T for X in rng.standard_normal((2, n, n)))
    Bs = rng.standard_normal((2, n, n))
    Bs = Bs - np.swapaxes(Bs, -1, -2)
    tab = tableaus.gauss(2)
    Gdag = conjugation.frozen_stage_conjugator(Bs, tab.A, 0.1)
    pairs = [
        (conjugation.cayley_update(W0, B, 0.05, True),
         conjugation.cayley_update(xp.asarray(W0), xp.asarray(B), 0.05, True)),
        (conjugation.lifted_update(W0, Gdag, Bs, 0.1 * tab.b, True),
         conjugation.lifted_update(xp.asarray(W0), conjugation.frozen_stage_conjugator(
             xp.asarray(Bs), tab.A, 0.1), xp.asarray(Bs), 0.1 * tab.b, True)),
        (conjugation.cayley_update(W0 + B.T @ B, B @ B, 0.05, False),
         conjugation.cayley_update(xp.asarray(W0 + B.T @ B), xp.asarray(B @ B), 0.05, False)),
    ]  # fmt: skip
    for expected, got in pairs:
        assert not isinstance(got, np.ndarray)
        assert np.max(np.abs(np.asarray(got) - expected)) <= 1e-15 * np.max(np.abs(expected))
