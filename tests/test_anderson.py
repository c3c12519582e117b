"""Anderson acceleration (lieflow.solvers.anderson): the exact fixed point of linear
contractions, the same converged steps as the plain iteration with the conserved quantities
of the exact flow, fewer updates where the contraction is slow, convergence where plain
iteration fails, no stall at roundoff; one source on NumPy, array_api_strict and JAX (traced
under jax.jit inside lax.while_loop)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from helpers import import_plugin, needs_zeitlin

import lieflow as lf
from lieflow import backends
from lieflow.solvers import anderson
from lieflow.solvers.fixed_point import FixedPoint

RTOL = 1e-13


def _contraction(n: int, top: float, seed: int, complex_data: bool = False) -> Any:
    """``(M, b, exact)``: ``x -> M x + b`` with ``M`` normal, eigenvalues spread over
    ``[0, top]`` (complex: turned by a common phase, a segment that polynomial acceleration
    can exploit; on a disk around 0 nothing can), and its fixed point."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    lam = np.linspace(0.0, top, n)
    b = rng.standard_normal(n)
    if complex_data:
        lam = lam * np.exp(0.3j)
        b = b + 1j * rng.standard_normal(n)
    M = (Q * lam) @ Q.T
    return M, b, np.linalg.solve(np.eye(n) - M, b)


def _iterate(F: Callable[[Any], Any], x0: Any, depth: int, core_ndim: int | None = None,
             max_iter: int = 2000) -> tuple[Any, int]:  # fmt: skip
    """Iterate ``x <- F(x)`` (``depth = 0``: plain; else through start/update) until every
    problem's relative update is below RTOL; the last map value and the updates taken."""
    xp = backends.namespace(x0)
    core = x0.ndim if core_ndim is None else core_ndim
    axes = tuple(range(x0.ndim - core, x0.ndim))
    state = anderson.start(x0, depth, core_ndim) if depth else None
    x = x0
    for k in range(1, max_iter + 1):
        g = F(x)
        step = xp.sqrt(xp.sum(xp.abs(g - x) ** 2, axis=axes))
        size = xp.sqrt(xp.sum(xp.abs(g) ** 2, axis=axes))
        if bool(xp.all(step <= RTOL * size)):
            return g, k
        if state is None:
            x = g
        else:
            state, x = anderson.update(state, x, g)
    raise AssertionError("no convergence")


@pytest.fixture
def everywhere(monkeypatch: pytest.MonkeyPatch) -> None:
    """Anderson on any problem size (the toy problems are small)."""
    monkeypatch.setattr(anderson, "MIN_SIZE", 0)


@pytest.mark.usefixtures("everywhere")
@pytest.mark.parametrize("complex_data", [False, True])
def test_linear_contraction_reaches_the_exact_fixed_point(complex_data: bool) -> None:
    M, b, exact = _contraction(120, 0.95, seed=1, complex_data=complex_data)
    x0 = np.zeros_like(exact)
    plain, plain_updates = _iterate(lambda x: M @ x + b, x0, 0)
    fast, fast_updates = _iterate(lambda x: M @ x + b, x0, 5)
    scale = np.linalg.norm(exact)
    # ||x - exact|| <= ||f|| / (1 - 0.95): 20 rtol at most
    assert np.linalg.norm(plain - exact) <= 20 * RTOL * scale
    assert np.linalg.norm(fast - exact) <= 20 * RTOL * scale
    assert fast_updates < plain_updates / 2, (fast_updates, plain_updates)


@pytest.mark.usefixtures("everywhere")
def test_a_batch_is_accelerated_per_problem() -> None:
    (M1, b1, e1), (M2, b2, e2) = _contraction(60, 0.95, 2), _contraction(60, 0.3, 3)
    Ms, bs = np.stack([M1, M2]), np.stack([b1, b2])

    def F(x: np.ndarray) -> np.ndarray:
        return np.einsum("kij,kj->ki", Ms, x) + bs

    both, updates = _iterate(F, np.zeros((2, 60)), 5, core_ndim=1)
    _, alone_updates = _iterate(lambda x: M1 @ x + b1, np.zeros(60), 5)
    for got, exact in ((both[0], e1), (both[1], e2)):
        assert np.linalg.norm(got - exact) <= 20 * RTOL * np.linalg.norm(exact)
    # the slow problem's own coefficients: as fast as alone (the fast one does not mix in)
    assert updates <= alone_updates + 2, (updates, alone_updates)


@pytest.mark.usefixtures("everywhere")
def test_array_api_strict_runs_the_same_source() -> None:
    xps = pytest.importorskip("array_api_strict")
    M, b, _ = _contraction(80, 0.9, seed=4, complex_data=True)
    Ma, ba = xps.asarray(M), xps.asarray(b)
    on_numpy, k = _iterate(lambda x: M @ x + b, np.zeros_like(b), 4)
    on_strict, ka = _iterate(lambda x: Ma @ x + ba, xps.zeros_like(ba), 4)
    assert backends.namespace(on_strict) is xps and ka == k
    np.testing.assert_allclose(backends.to_numpy(on_strict), on_numpy, rtol=0, atol=1e-13)


@pytest.mark.usefixtures("everywhere")
@pytest.mark.parametrize("complex_data", [False, True])
def test_skew_unknowns_upper_triangles_and_the_array_path_agree(
    monkeypatch: pytest.MonkeyPatch, complex_data: bool
) -> None:
    """X -> A X A^† + C on skew(-Hermitian) matrices: the compiled path on upper triangles
    (skew=True), on whole arrays, and the array-API path (no kernel) each reach the exact
    fixed point in about the same updates; mixed iterates with skew=True are exactly
    skew off the diagonal; update never writes into the x it is given."""
    n = 40
    rng = np.random.default_rng(7)
    # A normal with eigenvalues in [0.5, 0.98]: F contracts by 0.25 ... 0.96 (slow: Anderson
    # pays)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = (Q * np.linspace(0.5, 0.98, n)) @ Q.T
    C = rng.standard_normal((n, n)) + (1j * rng.standard_normal((n, n)) if complex_data else 0)
    C = C - np.conj(C.T)
    # the exact fixed point: (I - A (x) conj(A)) vec X = vec C, row-major vec
    K = np.eye(n * n) - np.kron(A, np.conj(A))
    exact = np.linalg.solve(K, C.ravel()).reshape(n, n)

    def F(X: np.ndarray) -> np.ndarray:
        return A @ X @ np.conj(A.T) + C

    def solve(skew: bool) -> tuple[np.ndarray, int, bool]:
        state = anderson.start(np.zeros_like(C), 5, 2)
        x, exact_skew = np.zeros_like(C), True
        for k in range(1, 400):
            g = F(x)
            if np.linalg.norm(g - x) <= RTOL * np.linalg.norm(g):
                return g, k, exact_skew
            before = x.copy()
            state, x_next = anderson.update(state, x, g, skew)
            np.testing.assert_array_equal(x, before)  # x itself is never written
            if x_next is not g:
                off = x_next + np.conj(x_next.T)
                exact_skew &= bool(np.all(off[~np.eye(n, dtype=bool)] == 0))
            x = x_next
        raise AssertionError("no convergence")

    plain_updates = _iterate(F, np.zeros_like(C), 0, max_iter=5000)[1]
    results = {"triangle": solve(True), "whole": solve(False)}
    monkeypatch.setattr(anderson, "_kernel", lambda: None)
    results["array api"] = solve(True)  # (skew is ignored there)
    updates = [k for _, k, _ in results.values()]
    for name, (x, k, _) in results.items():
        assert np.linalg.norm(x - exact) <= 50 * RTOL * np.linalg.norm(exact), name
        assert k < plain_updates / 2, (name, k, plain_updates)
    assert max(updates) <= min(updates) + 3, updates
    assert results["triangle"][2]


def test_put_writes_in_place_or_returns_the_new_array() -> None:
    stack = np.zeros((3, 2))
    out, entry = backends.put(stack, np.asarray(1), np.ones(2), np.full(2, 0.25))
    assert out is stack and np.array_equal(stack[1], [0.75, 0.75]) and entry.base is stack
    xps = pytest.importorskip("array_api_strict")
    s = xps.zeros((3, 2))
    out, entry = backends.put(s, 2, xps.ones(2))
    assert np.array_equal(backends.to_numpy(out)[2], [1.0, 1.0])


def _jax() -> Any:
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    return jax


def _traced(F: Callable[[Any], Any], x0: Any, depth: int, core_ndim: int) -> tuple[Any, int]:
    """:func:`_iterate` as one compiled program: start/update inside ``lax.while_loop``."""
    jax = _jax()
    jnp = jax.numpy

    def run(x0: Any) -> Any:
        def norms(x: Any, g: Any) -> Any:
            return jnp.sqrt(jnp.sum(jnp.abs(g - x) ** 2)), jnp.sqrt(jnp.sum(jnp.abs(g) ** 2))

        def cond(carry: Any) -> Any:
            _, x, g, k = carry
            step, size = norms(x, g)
            return (step > RTOL * size) & (k < 500)

        def body(carry: Any) -> Any:
            state, x, g, k = carry
            state, x = anderson.update(state, x, g)
            return state, x, F(x), k + 1

        carry = (anderson.start(x0, depth, core_ndim), x0, F(x0), 1)
        _, _, g, k = jax.lax.while_loop(cond, body, carry)
        return g, k

    g, k = jax.jit(run)(x0)
    return np.asarray(g), int(k)


@pytest.mark.usefixtures("everywhere")
def test_jax_traced_matches_eager_on_a_contraction() -> None:
    jax = _jax()
    M, b, exact = _contraction(100, 0.95, seed=5, complex_data=True)
    eager, k = _iterate(lambda x: M @ x + b, np.zeros_like(b), 5)
    Mj, bj = jax.numpy.asarray(M), jax.numpy.asarray(b)
    traced, kt = _traced(lambda x: Mj @ x + bj, jax.numpy.zeros_like(bj), 5, 1)
    assert kt == k
    assert np.linalg.norm(traced - eager) <= RTOL * np.linalg.norm(exact)


def test_jax_traced_matches_eager_on_a_lieflow_map(monkeypatch: pytest.MonkeyPatch) -> None:
    jax = _jax()
    lz = import_plugin("lieflow_zeitlin")
    from lieflow.schemes.sydirk import MidpointProblem

    monkeypatch.setattr(anderson, "MIN_SIZE", 0)
    monkeypatch.setattr(anderson, "ENGAGE", 0.0)  # mix from the second update on
    system = lz.EulerZeitlin(8)
    W0 = 4.0 * system.random_state(0)
    h = 0.5
    eager = FixedPoint(rtol=RTOL, anderson=4).solve(MidpointProblem(system, W0, h))
    plain = FixedPoint(rtol=RTOL).solve(MidpointProblem(system, W0, h))
    assert eager.converged and eager.iterations < plain.iterations

    def solve(W0j: Any) -> Any:
        problem = MidpointProblem(system, W0j, h)
        return problem.x0, problem.map

    W0j = jax.numpy.asarray(W0)
    x0, F = solve(W0j)
    traced, k = _traced(F, x0, 4, 2)
    assert abs(k - eager.iterations) <= 1
    assert np.max(np.abs(traced - eager.x)) <= 1e-12 * np.max(np.abs(eager.x))


# Euler–Zeitlin: the smooth rms-1 field of benchmarks.device, warm-started steps


def _field(N: int) -> np.ndarray:
    lz = import_plugin("lieflow_zeitlin")
    W: np.ndarray = lz.random_vorticity(N, degree=8, seed=N)
    return W


def _run(N: int, h: float, steps: int, depth: int, rtol: float = RTOL) -> lf.Solution:
    system = lf.systems.get("euler_zeitlin", N=N, time="fluid", diagnostics_every=0)
    return lf.integrate(system, lf.schemes.get("midpoint"), _field(N), h=h, steps=steps,
                        solver=FixedPoint(rtol=rtol, anderson=depth),
                        engine="numpy")  # fmt: skip


def _levels(W: np.ndarray) -> np.ndarray:
    """The vorticity levels: eigenvalues of the Hermitian ``iW`` (LAPACK, not lieflow)."""
    return np.linalg.eigvalsh(1j * W)


@needs_zeitlin
@pytest.mark.parametrize(("N", "h"), [(128, 1 / 32), (256, 1 / 32)])
def test_euler_zeitlin_fewer_updates_same_solution(N: int, h: float) -> None:
    plain = _run(N, h, 3, 0)
    fast = _run(N, h, 3, 5)
    assert plain.iterations.mean() >= 15  # a slow contraction
    assert fast.iterations.sum() <= 0.75 * plain.iterations.sum()
    scale = np.max(np.abs(plain.W_final))
    assert np.max(np.abs(fast.W_final - plain.W_final)) <= 1e-12 * scale
    # isospectral: the exact flow keeps every vorticity level (the Casimirs)
    levels0 = _levels(plain.W[0])
    for sol in (plain, fast):
        drift = np.max(np.abs(_levels(sol.W_final) - levels0)) / np.max(np.abs(levels0))
        assert drift <= 1e-13, drift
    # the same step, hence the same energy (the midpoint rule keeps it to O(h²) only)
    energy = plain.system.hamiltonian
    assert abs(energy(fast.W_final) - energy(plain.W_final)) <= 1e-12 * energy(plain.W_final)


def test_euler_zeitlin_converges_where_plain_fails() -> None:
    lz = import_plugin("lieflow_zeitlin")
    from lieflow.schemes.sydirk import MidpointProblem

    N, h = 256, 1 / 16
    system = lz.EulerZeitlin(N)
    W0 = _field(N)
    assert not FixedPoint(rtol=RTOL).solve(MidpointProblem(system, W0, h)).converged
    res = FixedPoint(rtol=RTOL, anderson=5).solve(MidpointProblem(system, W0, h))
    assert res.converged and res.iterations <= 30
    # the midpoint equation W0 = (I - h/2 B) M (I + h/2 B), B = B(M), to roundoff
    M = res.x
    B = system.B(M)
    eye = np.eye(N)
    W0_again = (eye - h / 2 * B) @ M @ (eye + h / 2 * B)
    assert np.max(np.abs(W0_again - W0)) <= 1e-12 * np.max(np.abs(W0))


@needs_zeitlin
def test_euler_zeitlin_fast_contraction_is_left_plain() -> None:
    # N = 128 at h = 1/256: 5 updates a step, nothing to gain: the same bits as plain
    plain, fast = _run(128, 1 / 256, 3, 0), _run(128, 1 / 256, 3, 5)
    np.testing.assert_array_equal(fast.W, plain.W)
    np.testing.assert_array_equal(fast.iterations, plain.iterations)


@needs_zeitlin
@pytest.mark.parametrize("engage", [anderson.ENGAGE, 0.0])
def test_no_stall_at_roundoff(monkeypatch: pytest.MonkeyPatch, engage: float) -> None:
    # rtol below the roundoff floor: the stopping rule ends on stagnation ("roundoff");
    # accelerated, even from the first update of a fast contraction (engage = 0), the
    # iteration must not wander off there (a naive Anderson took 332 updates against 6)
    monkeypatch.setattr(anderson, "ENGAGE", engage)
    h = 1 / 32 if engage else 1 / 256
    plain = _run(128, h, 2, 0, rtol=1e-17)
    fast = _run(128, h, 2, 5, rtol=1e-17)
    assert fast.iterations.max() <= plain.iterations.max() + 2
    scale = np.max(np.abs(plain.W_final))
    assert np.max(np.abs(fast.W_final - plain.W_final)) <= 1e-13 * scale


@pytest.mark.parametrize(("name", "h"), [("generalized_rigid_body", 0.1), ("periodic_toda", 0.5)])
def test_small_problems_run_the_plain_iteration(name: str, h: float) -> None:
    system = lf.systems.get(name)
    W0 = system.random_state(seed=1)
    scheme = lf.schemes.get("gauss2")
    solvers = FixedPoint(), FixedPoint(anderson=5)
    runs = [
        lf.integrate(system, scheme, W0, h, steps=20, solver=s, engine="numpy") for s in solvers
    ]
    np.testing.assert_array_equal(runs[1].W, runs[0].W)
    np.testing.assert_array_equal(runs[1].iterations, runs[0].iterations)


def test_start_rejects_a_depth_below_one() -> None:
    with pytest.raises(ValueError, match="depth"):
        anderson.start(np.zeros(3), 0)


@pytest.mark.parametrize("batch", [False, True])
def test_every_scheme_with_anderson_mixing(
    monkeypatch: pytest.MonkeyPatch, scheme: lf.Scheme, batch: bool
) -> None:
    # mixing from the second update on, on a small system: every scheme's unknown (a
    # matrix, stacked stages, a batch of either) gives the step of a tight plain solve
    lz = import_plugin("lieflow_zeitlin")
    monkeypatch.setattr(anderson, "MIN_SIZE", 0)
    monkeypatch.setattr(anderson, "ENGAGE", 0.0)
    system = lz.EulerZeitlin(6)
    W0 = 3.0 * system.random_state(1)
    if batch:
        W0 = np.stack([W0, 0.5 * system.random_state(2)])
    tight = FixedPoint(rtol=1e-15, max_iter=500)
    ref = scheme.step(W0, 0.2, system, tight).W
    got = scheme.step(W0, 0.2, system, FixedPoint(rtol=1e-15, anderson=3)).W
    assert np.max(np.abs(got - ref)) <= 1e-13 * np.max(np.abs(ref))
