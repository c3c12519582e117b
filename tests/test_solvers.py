"""Solvers on the stress cases of SPEC §5 (Toda with the paper's W0) and their contracts."""

from __future__ import annotations

import itertools
from typing import Any

import attrs
import numpy as np
import pytest
from helpers import tight

import lieflow as lf
from lieflow.schemes import MidpointProblem, ReducedProblem
from lieflow.tableaus import gauss

TODA = lf.systems.get("periodic_toda")
W0 = lf.systems.PAPER_W0


def test_midpoint_fixed_point_stalls_at_h_04() -> None:
    with pytest.raises(lf.ConvergenceError) as info:
        lf.integrate(TODA, lf.schemes.get("midpoint"), W0, 0.4, steps=5)
    err = info.value
    assert err.reason == "stalled" and err.step == 1 and err.t == 0.0
    assert err.solver == "fixed_point" and err.iterations == len(err.residuals) < 100
    assert all(np.isfinite(err.residuals))
    assert "Newton" in str(err) and "step 1" in str(err)


@pytest.mark.parametrize(
    "scheme",
    [
        lf.schemes.get("midpoint"),
        lf.schemes.get("sydirk7"),
        lf.schemes.get("gauss", stages=2, form="block"),
        lf.schemes.get("gauss", stages=3, form="block"),
    ],
    ids=lambda s: s.name,
)
def test_fixed_point_diverges_at_h_08(scheme: lf.Scheme) -> None:
    """Every fixed-point iteration of the block equation diverges (the reduced stage form of
    Gauss-2/3 still converges there: its iteration map is a different one)."""
    with pytest.raises(lf.ConvergenceError) as info:
        lf.integrate(TODA, scheme, W0, 0.8, steps=5)
    assert info.value.reason == "diverged"
    assert info.value.iterations < 20


@pytest.mark.parametrize("name", ["midpoint", "gauss2", "gauss3", "sydirk7"])
def test_newton_and_frozen_b_converge_at_h_08(name: str) -> None:
    scheme = lf.schemes.get(name)
    stages = scheme.tableau.stages if isinstance(scheme, lf.schemes.SyDIRK) else 1
    sol = lf.integrate(TODA, scheme, W0, 0.8, steps=30, solver=lf.solvers.Newton())
    assert sol.success
    assert sol.iterations.max() <= 10 * stages  # <= 10 Newton iterations per implicit solve
    assert sol.spectrum_drift().max() <= 1e-12
    frozen = lf.integrate(TODA, scheme, W0, 0.8, steps=30, solver=lf.solvers.FrozenB(max_iter=300))
    assert frozen.success
    np.testing.assert_allclose(frozen.W_final, sol.W_final, rtol=0, atol=1e-10)


def test_newton_converges_quadratically() -> None:
    problem = MidpointProblem(TODA, W0, 0.8)
    res = lf.solvers.Newton(rtol=1e-15).solve(problem)
    r = np.array(res.residuals)
    assert res.converged and res.iterations <= 7
    # the last few residuals: r_{k+1} <= C r_k^2 with a modest C
    tail = [(a, b) for a, b in itertools.pairwise(r) if a < 1e-2 and b > 1e-14]
    assert tail, r
    assert all(b <= 10.0 * a**2 for a, b in tail), r


def test_newton_gmres_matches_dense() -> None:
    system = lf.systems.GeneralizedRigidBody(np.linspace(1.0, 2.0, 8))
    W = system.random_state(seed=0)
    problem = ReducedProblem(system, W, 0.2, gauss(3))
    dense = lf.solvers.Newton(linear="dense").solve(problem)
    krylov = lf.solvers.Newton(linear="gmres").solve(problem)
    assert dense.converged and krylov.converged
    np.testing.assert_allclose(krylov.x, dense.x, rtol=0, atol=1e-13)


def test_auto_finishes_the_stiff_run_and_records_fallbacks() -> None:
    sol = lf.integrate(
        TODA, lf.schemes.get("midpoint"), W0, 0.8, steps=20, solver=lf.solvers.Auto()
    )
    assert sol.success and sol.n_steps == 20
    assert set(sol.solvers) == {"newton"}  # fixed point never converges at this step size
    easy = lf.integrate(
        TODA, lf.schemes.get("midpoint"), W0, 0.1, steps=20, solver=lf.solvers.Auto()
    )
    assert set(easy.solvers) == {"fixed_point"}


def test_truncate_returns_the_computed_steps() -> None:
    sol = lf.integrate(TODA, lf.schemes.get("midpoint"), W0, 0.4, steps=5, on_failure="truncate")
    assert sol.status is lf.Status.FAILED and not sol.success
    assert sol.n_steps == 0 and sol.W.shape == (1, 4, 4)
    assert sol.failure is not None and sol.failure.reason == "stalled"


def test_max_iterations_is_an_error_not_a_silent_cap() -> None:
    with pytest.raises(lf.ConvergenceError, match="max_iterations"):
        lf.integrate(
            TODA,
            lf.schemes.get("gauss2"),
            W0,
            0.1,
            steps=1,
            solver=lf.solvers.FixedPoint(max_iter=3),
        )


def test_a_tolerance_below_roundoff_still_terminates() -> None:
    res = lf.solvers.FixedPoint(rtol=1e-30).solve(MidpointProblem(TODA, W0, 0.01))
    assert res.converged and res.reason in ("converged", "roundoff") and res.iterations < 30
    ref = tight().solve(MidpointProblem(TODA, W0, 0.01))
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-14)


def test_stopping_rule_verdicts() -> None:
    rule = lf.solvers.StoppingRule(rtol=1e-16, patience=3)
    flat = [1e-3, 1e-8, 1e-15, 3e-16, 4e-16, 5e-16, 3.5e-16]
    assert rule.verdict(flat[:4], met=False, growth=1.0) is None
    assert rule.verdict(flat, met=False, growth=1.0) == "roundoff"
    stuck = [1e-1, 1e-3, 2e-3, 3e-3, 2e-3]
    assert rule.verdict(stuck, met=False, growth=1.0) == "stalled"
    assert rule.verdict(stuck, met=False, growth=20.0) == "diverged"
    assert rule.verdict([0.5], met=False, growth=1e3) == "diverged"
    assert rule.verdict([float("nan")], met=False, growth=1.0) == "non_finite"
    assert rule.verdict([1e-3], met=True, growth=1.0) == "converged"
    slow = list(0.5 * 0.97 ** np.arange(12))
    assert rule.verdict(slow, met=False, growth=1.0) == "stalled"  # would need ~1000 its
    assert lf.solvers.StoppingRule(project=False).verdict(slow, False, 1.0) is None


def test_anderson_cuts_iterations(monkeypatch: pytest.MonkeyPatch) -> None:
    # Anderson on a 4 x 4 problem (below anderson.MIN_SIZE, where it does not pay and the
    # plain iteration runs): the algorithm itself on a slow contraction (~20 updates a step)
    monkeypatch.setattr(lf.solvers.anderson, "MIN_SIZE", 0)
    plain = lf.integrate(TODA, lf.schemes.get("midpoint"), W0, 0.1, steps=50)
    anderson = lf.integrate(
        TODA,
        lf.schemes.get("midpoint"),
        W0,
        0.1,
        steps=50,
        solver=lf.solvers.FixedPoint(anderson=3),
    )
    assert anderson.iterations.sum() < 0.75 * plain.iterations.sum()
    np.testing.assert_allclose(anderson.W_final, plain.W_final, rtol=0, atol=1e-12)


def test_warm_start_cuts_iterations_and_keeps_the_solution() -> None:
    system = lf.systems.get("generalized_rigid_body")
    W = system.random_state(seed=1)
    cold = lf.integrate(system, lf.schemes.get("gauss3"), W, 0.01, steps=100, warm_start=False)
    warm = lf.integrate(system, lf.schemes.get("gauss3"), W, 0.01, steps=100)
    assert warm.iterations.sum() < 0.8 * cold.iterations.sum()
    np.testing.assert_allclose(warm.W_final, cold.W_final, rtol=0, atol=1e-13)


def test_solver_options_are_validated() -> None:
    with pytest.raises(lf.InputError):
        lf.solvers.FixedPoint(rtol=0.0, atol=0.0)
    with pytest.raises(lf.InputError):
        lf.solvers.FixedPoint(rtol=-1.0)
    with pytest.raises(lf.InputError):
        lf.solvers.FixedPoint(anderson=-1)
    with pytest.raises(lf.InputError):
        lf.solvers.Newton(linear="lu")


S = lf.solvers


@pytest.mark.parametrize(
    ("make", "argument"),
    [
        (lambda: S.FixedPoint(rtol="1e-3"), "rtol"),  # issue 29.4: numpy's TypeError before
        (lambda: S.FixedPoint(atol=None), "atol"),
        (lambda: S.FixedPoint(max_iter=2.5), "max_iter"),
        (lambda: S.FixedPoint(max_iter="100"), "max_iter"),
        (lambda: S.FixedPoint(patience=True), "patience"),
        (lambda: S.FixedPoint(anderson="3"), "anderson"),
        (lambda: S.FixedPoint(roundoff_floor=0.0), "roundoff_floor"),
        (lambda: S.FixedPoint(divergence_factor=float("inf")), "divergence_factor"),
        (lambda: S.FrozenB(rtol=float("nan")), "rtol"),
        (lambda: S.FrozenB(max_iter=0), "max_iter"),
        (lambda: S.Newton(rtol="tight"), "rtol"),
        (lambda: S.Newton(max_iter="30"), "max_iter"),
        (lambda: S.Newton(dense_max=0), "dense_max"),
        (lambda: S.Newton(max_halvings=-1), "max_halvings"),
        (lambda: S.Auto(first=S.FixedPoint), "first"),  # the class, not an instance
        (lambda: S.Auto(fallback="newton"), "fallback"),
        (lambda: S.get("fixed_point", rtol="1e-3"), "rtol"),
    ],
)
def test_solver_arguments_of_the_wrong_type_or_range_name_the_argument(
    make: Any, argument: str
) -> None:
    with pytest.raises(lf.InputError, match=rf"^{argument} must be"):
        make()


def test_solver_arguments_of_numpy_types_are_accepted() -> None:
    solver = S.FixedPoint(rtol=np.float64(1e-10), max_iter=np.int64(50), anderson=np.int32(2))
    assert solver.rule.max_iter == 50
    assert S.Auto(first=S.FrozenB(), fallback=S.Newton(rtol=1e-12)).fallback.rtol == 1e-12


def test_newton_needs_the_derivative_of_a_nonlinear_B() -> None:
    class Cubic(lf.IsospectralSystem):
        algebra = lf.SO(3)

        def B(self, W: np.ndarray) -> np.ndarray:
            return -W * np.sum(W * W, axis=(-2, -1), keepdims=True)

        def hamiltonian(self, W: np.ndarray) -> np.ndarray:
            return np.sum(W * W, axis=(-2, -1)) ** 2

    system = Cubic()
    with pytest.raises(lf.LieflowError, match="B_derivative"):
        lf.schemes.get("midpoint").step(system.random_state(0), 0.1, system, lf.solvers.Newton())
    # the other solvers need no derivative
    lf.schemes.get("midpoint").step(system.random_state(0), 0.1, system, lf.solvers.FrozenB())


def test_the_cap_accepts_an_update_at_roundoff() -> None:
    """A contracting iteration that reaches max_iter with its update below the roundoff
    floor is done ("roundoff"), not failed (issue 14: point vortices, contraction 0.76,
    update 2.4e-14 at the cap); above the floor the cap is still an error."""
    rule = lf.solvers.StoppingRule(max_iter=20)
    contracting = list(1e-2 * 0.2 ** np.arange(20))  # ends at 5e-16 < floor
    assert contracting[-1] < rule.roundoff_floor
    assert rule.verdict(contracting[:19], met=False, growth=1.0) is None
    assert rule.verdict(contracting, met=False, growth=1.0) == "roundoff"
    short = [1e-2 * 0.5**k for k in range(20)]  # ends at 2e-8 (no early "stalled" here)
    assert attrs.evolve(rule, project=False).verdict(short, False, 1.0) == "max_iterations"


def test_compiled_rule_agrees_at_the_cap() -> None:
    """The compiled engine's rule gives the same verdicts at the cap: the shared
    ``stopping_verdict`` compiled with numba (``_compiled_rules.verdict``, the same function)."""
    from lieflow.engines import _compiled_rules
    from lieflow.engines.compiled import kernels
    from lieflow.solvers.fixed_point import REASONS

    try:
        kernels()
    except ImportError:
        pytest.skip("numba is not installed")
    rule = lf.solvers.StoppingRule(max_iter=20, project=False)
    seen = set()
    for res in (1e-2 * 0.2 ** np.arange(20), 1e-2 * 0.5 ** np.arange(20)):
        expected = rule.verdict(list(res), met=False, growth=1.0)
        code = _compiled_rules.verdict(
            np.array(res), 20, False, 1.0, rule.rtol, rule.roundoff_floor,
            rule.divergence_factor, 20, rule.patience, rule.window, False,
        )  # fmt: skip
        assert REASONS[code] == expected
        seen.add(expected)
    assert len(seen) == 2  # the two sequences end differently


@pytest.mark.parametrize("n", [3, 10])  # norms by math.hypot; by vdot
@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan, 1e200])
def test_lean_check_reports_non_finite_without_warnings(bad: float, n: int) -> None:
    """The single-problem check measures ``||new||`` first and forms ``new - old`` only
    when it is finite: a blown-up update is ``non_finite`` and raises no floating-point
    warning (and no ``np.errstate`` per update is needed)."""
    import warnings

    from lieflow.solvers.fixed_point import IterationMonitor, StoppingRule

    x0 = np.ones((n, n))
    for old in (x0, np.full((n, n), bad)):
        monitor = IterationMonitor(StoppingRule(), 2, x0)
        new = x0.copy()
        new[0, 1] = bad
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert monitor.check(new, old) == "non_finite"
        assert len(monitor.residuals) == 1 and np.isnan(monitor.residuals[0])
    monitor = IterationMonitor(StoppingRule(), 2, x0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert monitor.check(x0, np.full((n, n), np.inf)) == "non_finite"


@pytest.mark.parametrize("n", [3, 10, 100])
@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan, 1e300])
def test_all_finite_is_exact_and_quiet(bad: float, n: int) -> None:
    """``backends.all_finite`` (by a norm for float64 states: hypot, vdot) is ``False``
    exactly when an entry is inf or nan — a huge finite entry, whose square overflows the
    norm, is finite — and raises no floating-point warning."""
    import warnings

    from lieflow.backends import all_finite

    x = np.ones((n, n))
    x[-1, 0] = bad
    with np.errstate(over="ignore"):
        single = x.astype(np.float32)  # 1e300 becomes inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert all_finite(x) == bool(np.isfinite(bad))
        assert all_finite(np.full((n, n), 1e300))
        assert not all_finite(single) and all_finite(np.ones((n, n), np.float32))


@pytest.mark.parametrize("n", [3, 10, 70])
def test_lean_single_check_agrees_with_the_batched_one(n: int) -> None:
    """One problem is judged by the lean check (norms by ``math.hypot`` up to 64 entries, a
    dot product up to 4096, ``einsum`` beyond); as a batch of one, by ``batch_norm``. The
    two take the same updates, with relative updates equal to roundoff."""
    body = lf.systems.GeneralizedRigidBody.random_inertia(n, seed=1)
    W = body.random_state(2)
    solver = lf.solvers.FixedPoint(rtol=1e-13)
    one = solver.solve(MidpointProblem(body, W, 0.05))
    batch = solver.solve(MidpointProblem(body, W[None], 0.05))
    assert one.reason == batch.reason == "converged"
    assert one.iterations == batch.iterations >= 4
    np.testing.assert_allclose(one.residuals, batch.residuals, rtol=1e-12, atol=0)
    assert np.array_equal(one.x, batch.x[0])


def test_lean_check_step_is_the_norm_of_the_difference_bit_for_bit() -> None:
    """The tiny-array check measures ``||new - old||`` as ``math.dist`` of the entries,
    reusing ``old``'s entries when ``old`` is the iterate it judged last (FixedPoint's
    plain iteration) and reading them afresh otherwise (Anderson, Newton): either way the
    relative update is exactly ``hypot(new - old) / hypot(new)``."""
    import math

    from lieflow.solvers.fixed_point import IterationMonitor, StoppingRule

    rng = np.random.default_rng(5)
    x0 = rng.standard_normal((3, 3))
    iterates = [x0 + 10.0 ** -(k + 1) * rng.standard_normal((3, 3)) for k in range(5)]
    other = x0 + 1e-3  # an ``old`` that is not the last iterate
    monitor = IterationMonitor(StoppingRule(rtol=1e-30, patience=50), 2, x0)
    pairs = [(iterates[0], x0), (iterates[1], iterates[0]), (iterates[2], other),
             (iterates[3], iterates[2]), (iterates[4], iterates[4].copy())]  # fmt: skip
    verdicts = [monitor.check(new, old) for new, old in pairs]
    assert verdicts == [None] * 4 + ["converged"]  # the last update is 0
    expected = [math.hypot(*(new - old).ravel()) / math.hypot(*new.ravel()) for new, old in pairs]
    assert monitor.residuals == expected
