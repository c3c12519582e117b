"""Steps that land on su(N) up to their trace: the final projection of a step reduced to
removing the trace (``SchemeFlow.step_from_phase_space``, ``lieflow.SU.project_skew_hermitian``)
returns what the projection returns, bit for bit."""

from __future__ import annotations

import lieflow_zeitlin as lz
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lieflow as lf
from lieflow.schemes import MidpointProblem
from lieflow.stepping import advance


@settings(max_examples=60, deadline=None)
@given(
    N=st.one_of(st.integers(2, 12), st.just(70)),  # 70: minus_dagger in 64 x 64 blocks
    seed=st.integers(0, 2**32 - 1),
    h=st.floats(-4.0, 4.0, allow_subnormal=False).filter(lambda h: h != 0),
    scale=st.integers(-100, 100),
    single=st.booleans(),
)
def test_commutator_update_keeps_an_exactly_skew_hermitian_state_so(
    N: int, seed: int, h: float, scale: int, single: bool
) -> None:
    """``W1 = W0 + h (C - C^†)`` of a state of su(N) (exactly skew-Hermitian, +0 real
    diagonal: what the projection returns) is exactly skew-Hermitian for *any* stage value
    ``M`` and sign of ``h``, so its su(N) projection — lieflow's and the plugin's compiled
    one — is its trace removal (``SU.project_skew_hermitian``), bit for bit."""
    rng = np.random.default_rng(seed)
    dtype = np.complex64 if single else np.complex128
    X = rng.standard_normal((N, N)) + 1j * rng.standard_normal((N, N))
    X = (X * 10.0 ** (scale // (8 if single else 1))).astype(dtype)
    su = lf.SU(N)
    W0 = su.project(X)
    # exactly skew-Hermitian with a +0 real diagonal (the trace removal is not idempotent
    # bit for bit: the projection of a state moves its diagonal by roundoff)
    assert np.array_equal(W0, -W0.conj().T)
    assert not np.signbit(np.diagonal(W0).real).any()
    M = (rng.standard_normal((N, N)) + 1j * rng.standard_normal((N, N))).astype(dtype)
    M *= np.abs(W0).max()
    system = lz.EulerZeitlin(N)
    W1 = MidpointProblem(system, W0, h).update(M)
    assert W1.dtype == W0.dtype
    if np.isfinite(W1).all():
        trace_removed = su.project_skew_hermitian(W1)
        assert trace_removed is not W1
        assert su.project(W1).tobytes() == trace_removed.tobytes()
        assert system.project(W1).tobytes() == trace_removed.tobytes()


@pytest.mark.parametrize("name", ["midpoint", "triple_jump", "gauss2"])
@pytest.mark.parametrize("update", ["commutator", "conjugation"])
def test_a_run_on_su_n_has_the_states_of_projected_steps(name: str, update: str) -> None:
    """After its first step the numpy engine steps a flow by ``step_from_phase_space``,
    which on su(N) only removes the trace where the scheme keeps exact skew symmetry
    (SyDIRK with the commutator update); every state equals, bit for bit, the state of
    ``SchemeFlow.step`` (which always projects)."""
    scheme = lf.schemes.get(name, update=update)
    system = lz.EulerZeitlin(16)
    W0, h, steps = lz.random_vorticity(16, degree=4, seed=5), 0.05, 12
    solver = lf.solvers.FixedPoint(rtol=1e-12)
    flow = lf.SchemeFlow(system, scheme, solver, warm_start=1)
    assert flow._exact == ("c" if scheme.keeps_skew else "")
    sol = lf.integrate(system, flow, W0, h, steps=steps, diagnostics=False)
    W, state = W0, flow.init(W0)
    for k in range(steps):
        W, state, _ = flow.step(W, k * h, h, state)
        assert W.tobytes() == sol.W[k + 1].tobytes(), k
    one_by_one = np.concatenate([c.W for c in advance(flow, W0, h, steps, batch=1)])
    assert one_by_one.tobytes() == sol.W[1:].tobytes()


def test_only_a_promised_su_n_projection_is_reduced_to_the_trace_removal() -> None:
    """The shortcut needs the projection's bits: su(N) itself and lieflow-zeitlin's
    algebra (``projects_as_su = True`` in its class body) take it; a subclass of SU that
    projects otherwise does not inherit the promise, and its projection runs after every
    step (here one that also zeroes the diagonal: its states keep a zero diagonal)."""

    class OffDiagonal(lf.SU):
        def project(self, X: np.ndarray) -> np.ndarray:
            Y = np.array(super().project(X))
            Y[..., np.arange(self.n), np.arange(self.n)] = 0
            return Y

    class Flat(lf.IsospectralSystem):
        def __init__(self, algebra: lf.LieAlgebra) -> None:
            self._algebra = algebra

        @property
        def algebra(self) -> lf.LieAlgebra:
            return self._algebra

        def B(self, W: np.ndarray) -> np.ndarray:  # a rigid body's: -W * C, C symmetric
            return -W * (1.0 + np.add.outer(np.arange(4), np.arange(4)))

        def hamiltonian(self, W: np.ndarray) -> float:
            return float(
                0.5 * np.sum(np.abs(W) ** 2 * (1.0 + np.add.outer(np.arange(4), np.arange(4))))
            )

    scheme = lf.schemes.get("midpoint")
    assert scheme.keeps_skew
    assert lf.SchemeFlow(lz.EulerZeitlin(8), scheme)._exact == "c"
    assert lf.SchemeFlow(Flat(lf.SU(4)), scheme)._exact == "c"
    other = Flat(OffDiagonal(4))
    assert lf.SchemeFlow(other, scheme)._exact == ""
    W0 = other.algebra.project(lf.SU(4).random(seed=1))
    sol = lf.integrate(other, scheme, W0, 0.1, steps=5, engine="numpy", diagnostics=False)
    assert not np.diagonal(sol.W[1:], axis1=-2, axis2=-1).any()
