"""The compiled engine (lieflow.engines.compiled): same steps as numpy to roundoff, same iterations,
same failures via the handover to numpy, clear errors for unsupported cases."""

from __future__ import annotations

import copy
import pickle
from typing import Any, ClassVar

import attrs
import numpy as np
import pytest

import lieflow as lf
from lieflow.engines import compiled, compiled_plan, map_checks

TODA_W0 = lf.systems.PAPER_W0

HADAMARD = {
    "rigid_body": lf.systems.RigidBody((1.0, 2.0, 3.0)),
    "generalized_rigid_body": lf.systems.GeneralizedRigidBody.random_inertia(6, seed=3),
    "periodic_toda": lf.systems.PeriodicToda(5),
}
SCHEMES = ["midpoint", "triple_jump", "sydirk7", "gauss2", "gauss3"]


@pytest.fixture
def numba() -> Any:
    return pytest.importorskip("numba")


def _state(system: lf.IsospectralSystem, seed: int = 0) -> np.ndarray:
    return 0.8 * system.random_state(seed=seed)


def _both(*args: Any, **kwargs: Any) -> tuple[lf.Solution, lf.Solution]:
    return (
        lf.integrate(*args, **kwargs, engine="numpy"),
        lf.integrate(*args, **kwargs, engine="compiled"),
    )


def _assert_same(ref: lf.Solution, fast: lf.Solution, atol: float = 1e-13) -> None:
    assert fast.status is ref.status and fast.n_steps == ref.n_steps
    scale = max(1.0, float(np.max(np.abs(ref.W))))
    np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=atol * scale)
    np.testing.assert_array_equal(fast.t, ref.t)
    np.testing.assert_array_equal(fast.saved_steps, ref.saved_steps)
    assert np.max(np.abs(fast.iterations - ref.iterations), initial=0) <= 1
    assert fast.solvers == ref.solvers
    for a, b in ((ref.energy_error, fast.energy_error), (ref.casimir_drift, fast.casimir_drift)):
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            assert a.shape == b.shape and a.dtype == b.dtype
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", sorted(HADAMARD))
def test_hadamard_factor_reproduces_B(name: str) -> None:
    system = HADAMARD[name]
    S = system.hadamard_factor
    assert S is not None and S.shape == (system.algebra.n,) * 2
    W = np.stack([system.random_state(seed=k) for k in range(3)])
    np.testing.assert_array_equal(S * W, system.B(W))
    S[...] = 0.0  # a copy: mutating it cannot corrupt the system
    np.testing.assert_array_equal(system.hadamard_factor * W, system.B(W))


def test_hadamard_factor_defaults_to_none() -> None:
    class Cubic(lf.IsospectralSystem):
        algebra = lf.SO(3)

        def B(self, W: np.ndarray) -> np.ndarray:
            return -(W**3)

        def hamiltonian(self, W: np.ndarray) -> np.ndarray:
            return 0.25 * np.sum(W**4, axis=(-2, -1))

    assert Cubic().hadamard_factor is None


@pytest.mark.usefixtures("numba")
@pytest.mark.parametrize("scheme_name", SCHEMES)
@pytest.mark.parametrize("name", sorted(HADAMARD))
def test_engines_agree(name: str, scheme_name: str) -> None:
    system = HADAMARD[name]
    ref, fast = _both(system, lf.schemes.get(scheme_name), _state(system), 0.1, steps=40)
    _assert_same(ref, fast)


@pytest.mark.usefixtures("numba")
def test_engines_agree_cold_saving_and_tolerances() -> None:
    system = HADAMARD["generalized_rigid_body"]
    solver = lf.solvers.FixedPoint(rtol=1e-10, atol=1e-12, max_iter=40)
    for scheme in ("midpoint", "gauss3"):
        ref, fast = _both(
            system, lf.schemes.get(scheme), _state(system), 0.05, steps=23, save_every=5,
            warm_start=False, solver=solver,
        )  # fmt: skip
        _assert_same(ref, fast, atol=1e-9)
        np.testing.assert_array_equal(fast.saved_steps, [0, 5, 10, 15, 20, 23])
    ref, fast = _both(system, lf.schemes.get("midpoint"), _state(system), 0.1, steps=7,
                      diagnostics=False)  # fmt: skip
    assert fast.energy_error is None and fast.casimir_drift is None
    _assert_same(ref, fast)


@pytest.mark.usefixtures("numba")
@pytest.mark.parametrize("scheme_name", ["midpoint", "gauss3"])
def test_ensemble_matches_single_runs(scheme_name: str) -> None:
    system = HADAMARD["rigid_body"]
    scheme = lf.schemes.get(scheme_name)
    W = np.stack([_state(system, seed=k) for k in range(4)]).reshape(2, 2, 3, 3)
    ref, fast = _both(system, scheme, W, 0.1, steps=30, save_every=10)
    _assert_same(ref, fast)
    assert fast.W.shape == (4, 2, 2, 3, 3)
    assert fast.energy_error is not None and fast.energy_error.shape == (31, 2, 2)
    assert fast.casimir_drift is not None and fast.casimir_drift.shape == (31, 2, 2, 1)
    for i in range(2):
        for j in range(2):
            one = lf.integrate(system, scheme, W[i, j], 0.1, steps=30, engine="compiled")
            np.testing.assert_allclose(fast.W_final[i, j], one.W_final, rtol=0, atol=1e-13)


@pytest.mark.usefixtures("numba")
def test_long_run_spans_chunks_and_preserves_structure() -> None:
    system = HADAMARD["rigid_body"]
    W0 = _state(system)
    ref, fast = _both(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2500, save_every=500)
    _assert_same(ref, fast, atol=1e-12)
    assert fast.casimir_drift is not None and fast.casimir_drift.max() < 1e-13
    assert float(np.max(np.abs(fast.W + np.swapaxes(fast.W, -1, -2)))) == 0.0


@pytest.mark.usefixtures("numba")
@pytest.mark.parametrize("scheme_name", ["midpoint", "sydirk7"])
def test_hard_step_raises_the_same_error(scheme_name: str) -> None:
    toda = lf.systems.PeriodicToda()
    errors = []
    for engine in ("numpy", "compiled"):
        with pytest.raises(lf.ConvergenceError) as info:
            lf.integrate(toda, lf.schemes.get(scheme_name), TODA_W0, 0.8, steps=5, engine=engine)
        errors.append(info.value)
    a, b = errors
    assert (a.reason, a.step, a.t, a.solver, a.iterations) == (
        b.reason, b.step, b.t, b.solver, b.iterations,
    )  # fmt: skip
    assert a.residuals == b.residuals


@pytest.mark.usefixtures("numba")
@pytest.mark.parametrize("h", [0.35, 0.8])
def test_auto_finishes_hard_steps_through_the_handover(h: float) -> None:
    """At h = 0.35 some steps are finished by Newton (handed over), others compiled."""
    toda = lf.systems.PeriodicToda()
    ref, fast = _both(toda, lf.schemes.get("midpoint"), TODA_W0, h, steps=20,
                      solver=lf.solvers.Auto())  # fmt: skip
    _assert_same(ref, fast, atol=1e-12)
    assert "newton" in fast.solvers


@pytest.mark.usefixtures("numba")
def test_truncate_after_handover() -> None:
    toda = lf.systems.PeriodicToda()
    ref, fast = _both(toda, lf.schemes.get("midpoint"), TODA_W0, 0.4, steps=5,
                      on_failure="truncate")  # fmt: skip
    assert fast.status is lf.Status.FAILED and fast.failure is not None
    assert ref.failure is not None and fast.failure.reason == ref.failure.reason
    _assert_same(ref, fast)


@pytest.mark.usefixtures("numba")
def test_progress_bar_advances_per_chunk() -> None:
    pytest.importorskip("rich")
    system = HADAMARD["rigid_body"]
    sol = lf.integrate(system, lf.schemes.get("midpoint"), _state(system), 0.1, steps=1500,
                       progress=True, engine="compiled")  # fmt: skip
    assert sol.success and sol.n_steps == 1500


@pytest.mark.usefixtures("numba")
@pytest.mark.parametrize(
    ("case", "match"),
    [
        ({"solver": lf.solvers.Newton()}, "solver 'newton'"),
        ({"solver": lf.solvers.FrozenB()}, "solver 'frozen_b'"),
        ({"solver": lf.solvers.Auto(first=lf.solvers.FrozenB())}, "solver 'auto'"),
        ({"scheme": lf.schemes.get("gauss2", form="block")}, "not compiled"),
        ({"scheme": lf.schemes.get("modin_viviani")}, "not compiled"),
        ({"W0": np.float32}, "float64"),
    ],
)
def test_compiled_refuses_unsupported_cases(case: dict[str, Any], match: str) -> None:
    system = HADAMARD["rigid_body"]
    W0 = _state(system)
    scheme = case.get("scheme", lf.schemes.get("midpoint"))
    solver = case.get("solver")
    if case.get("W0") is np.float32:
        W0 = W0.astype(np.float32)
    with pytest.raises(lf.InputError, match=match):
        lf.integrate(system, scheme, W0, 0.1, steps=2, solver=solver, engine="compiled")
    auto = lf.integrate(system, scheme, W0, 0.1, steps=2, solver=solver)  # falls back to numpy
    assert auto.success


@pytest.mark.usefixtures("numba")
def test_compiled_runs_anderson_where_it_never_engages() -> None:
    # below anderson.MIN_SIZE numbers FixedPoint(anderson=m) is the plain iteration, bit for
    # bit, on either engine; the compiled engine runs it as such
    system = HADAMARD["generalized_rigid_body"]
    W0 = _state(system)
    solver = lf.solvers.FixedPoint(anderson=3)
    numpy_run, compiled_run = _both(system, lf.schemes.get("gauss2"), W0, 0.1, steps=50,
                                    solver=solver)  # fmt: skip
    plain = lf.integrate(system, lf.schemes.get("gauss2"), W0, 0.1, steps=50, engine="numpy")
    np.testing.assert_array_equal(numpy_run.W, plain.W)
    np.testing.assert_array_equal(numpy_run.iterations, plain.iterations)
    np.testing.assert_allclose(compiled_run.W, numpy_run.W, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(compiled_run.iterations, numpy_run.iterations)


@pytest.mark.usefixtures("numba")
def test_compiled_refuses_anderson_where_it_engages() -> None:
    n = 200  # 40,000 numbers per problem: at least anderson.MIN_SIZE
    system = lf.systems.GeneralizedRigidBody.random_inertia(n, seed=0)
    W0 = np.zeros((n, n))
    reason = compiled.plan(system, lf.schemes.get("midpoint"),
                           lf.solvers.FixedPoint(anderson=2), W0)  # fmt: skip
    assert isinstance(reason, str) and "Anderson" in reason and "engine='numpy'" in reason


@pytest.mark.usefixtures("numba")
def test_compiled_refuses_systems_without_a_faithful_hadamard_factor() -> None:
    class Liar(lf.systems.RigidBody):
        def B(self, W: np.ndarray) -> np.ndarray:  # B changed, hadamard_factor not updated
            return 2.0 * super().B(W)

    liar = Liar()
    with pytest.raises(lf.InputError, match="does not reproduce"):
        lf.integrate(liar, lf.schemes.get("midpoint"), _state(liar), 0.01, steps=2,
                     engine="compiled")  # fmt: skip
    ref = lf.integrate(liar, lf.schemes.get("midpoint"), _state(liar), 0.01, steps=2,
                       engine="numpy")  # fmt: skip
    auto = lf.integrate(liar, lf.schemes.get("midpoint"), _state(liar), 0.01, steps=2)
    np.testing.assert_array_equal(auto.W, ref.W)


class _Counted(lf.systems.RigidBody):
    """A rigid body that counts its calls of ``B`` (in a list: the system is frozen)."""

    calls: ClassVar[list[int]] = []

    def B(self, W: np.ndarray) -> np.ndarray:
        self.calls.append(1)
        return super().B(W)


@pytest.mark.usefixtures("numba")
def test_compiled_maps_are_checked_once_per_system_and_dtype() -> None:
    system = _Counted()
    system.calls.clear()
    scheme = lf.schemes.get("midpoint")
    first = lf.integrate(system, scheme, _state(system), 0.1, steps=3, engine="compiled",
                         diagnostics=False)  # fmt: skip
    assert len(system.calls) == 2  # the check: on W0 and off it; the loops call their own B
    again = lf.integrate(system, scheme, _state(system, seed=1), 0.1, steps=3,
                         engine="compiled", diagnostics=False)  # fmt: skip
    assert len(system.calls) == 2  # kept on the system: not checked again
    ref = lf.integrate(system, scheme, _state(system, seed=1), 0.1, steps=3, engine="numpy",
                       diagnostics=False)  # fmt: skip
    _assert_same(ref, again)
    assert first.success
    system.calls.clear()
    other = _Counted()  # another system: checked on its own
    lf.integrate(other, scheme, _state(other), 0.1, steps=1, engine="compiled",
                 diagnostics=False)  # fmt: skip
    assert len(system.calls) == 2


class _Mutable(lf.IsospectralSystem):
    """A user's system that is not a value: its ``S`` can be changed in place."""

    algebra = lf.SO(3)
    linear_B = True

    def __init__(self) -> None:
        self.S = -lf.systems.RigidBody((1.0, 2.0, 3.0)).weights.copy()

    @property
    def hadamard_factor(self) -> np.ndarray:
        return self.S

    def B(self, W: np.ndarray) -> np.ndarray:
        return W * self.S

    def hamiltonian(self, W: np.ndarray) -> np.ndarray:
        return -0.5 * np.sum(W * W * self.S, axis=(-2, -1))


@pytest.mark.usefixtures("numba")
def test_changed_compiled_maps_are_checked_again_and_used() -> None:
    system = _Mutable()
    scheme = lf.schemes.get("midpoint")
    W0 = _state(system)
    _assert_same(*_both(system, scheme, W0, 0.1, steps=4))
    system.S[0, 1] = system.S[1, 0] = -5.0  # compiled_B's params change with B
    ref, fast = _both(system, scheme, W0, 0.1, steps=4)
    _assert_same(ref, fast)
    # the engine keeps the checked maps per live system, not on it: a pickle or a copy is
    # another system and starts without them
    assert map_checks._KEPT.of(system)
    system.S[0, 1] = system.S[1, 0] = -0.25
    clone = pickle.loads(pickle.dumps(system))
    assert map_checks._KEPT.of(clone) == {}
    _assert_same(*_both(clone, scheme, W0, 0.1, steps=4))
    assert map_checks._KEPT.of(clone)
    assert map_checks._KEPT.of(copy.deepcopy(HADAMARD["rigid_body"])) == {}
    assert "_derived" not in vars(system) and "_derived" not in vars(clone)


@pytest.mark.usefixtures("numba")
def test_a_plan_is_kept_for_the_same_scheme_and_solver() -> None:
    system = lf.systems.GeneralizedRigidBody.random_inertia(5, seed=4)
    mid, fp = lf.schemes.get("midpoint"), lf.solvers.FixedPoint()
    first = compiled.plan(system, mid, fp, _state(system))
    assert compiled.plan(system, mid, fp, _state(system, seed=1)) is first
    gauss = compiled.plan(system, lf.schemes.get("gauss3"), fp, _state(system))
    loose = compiled.plan(system, mid, lf.solvers.FixedPoint(rtol=1e-8), _state(system))
    assert isinstance(first, compiled_plan.CompiledPlan) and first.kind == "sydirk"
    assert isinstance(gauss, compiled_plan.CompiledPlan) and gauss.kind == "reduced"
    assert isinstance(loose, compiled_plan.CompiledPlan) and loose.rule.rtol == 1e-8
    assert first.rule.rtol == 1e-14
    # kept by value (the last plan per dtype): a scheme and solver built anew, as
    # lf.schemes.get does on every call, find it; another update or tolerance does not
    first = compiled.plan(system, mid, fp, _state(system))
    fresh = lf.schemes.get("midpoint"), lf.solvers.FixedPoint()
    assert compiled.plan(system, *fresh, _state(system)) is first
    cayley = compiled.plan(system, lf.schemes.SyDIRK(update="conjugation"), fp, _state(system))
    assert isinstance(cayley, compiled_plan.CompiledPlan) and cayley is not first
    assert cayley.conjugation and not first.conjugation
    capped = compiled.plan(system, mid, lf.solvers.FixedPoint(max_iter=7), _state(system))
    assert isinstance(capped, compiled_plan.CompiledPlan) and capped.rule.max_iter == 7
    # one kept plan run with and without warm starts, in turn: each as numpy runs it
    for warm in (False, True, False):
        _assert_same(*_both(system, mid, _state(system), 0.05, steps=30, solver=fp,
                            warm_start=warm))  # fmt: skip


def test_builtin_systems_are_read_only_values() -> None:
    moments = np.array([1.0, 2.0, 3.0])
    body = lf.systems.RigidBody(moments)
    grb = lf.systems.GeneralizedRigidBody(moments)
    toda = lf.systems.PeriodicToda(4)
    for arr in (body.inertia, body.weights, grb.J, grb.weights, toda.sign):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 7.0
    moments[0] = 9.0  # the caller's array is copied, not frozen, and not shared
    assert body.inertia[0] == 1.0 and grb.J[0] == 1.0


@pytest.mark.usefixtures("numba")
def test_compiled_refuses_systems_without_a_compiled_B() -> None:
    class Cubic(lf.IsospectralSystem):
        algebra = lf.SO(3)

        def B(self, W: np.ndarray) -> np.ndarray:
            return -(W**3)

        def hamiltonian(self, W: np.ndarray) -> np.ndarray:
            return 0.25 * np.sum(W**4, axis=(-2, -1))

    system = Cubic()
    assert system.compiled_B() is None
    with pytest.raises(lf.InputError, match="has no compiled B"):
        lf.integrate(system, lf.schemes.get("midpoint"), 0.5 * system.random_state(seed=0),
                     0.01, steps=2, engine="compiled")  # fmt: skip


def test_engine_is_validated_and_numba_is_optional(monkeypatch: pytest.MonkeyPatch) -> None:
    system = HADAMARD["rigid_body"]
    W0, mid = _state(system), lf.schemes.get("midpoint")
    with pytest.raises(lf.InputError, match="engine"):
        lf.integrate(system, mid, W0, 0.1, steps=2, engine="fortran")  # type: ignore[arg-type]

    def missing() -> Any:
        raise ImportError("No module named 'numba'")

    monkeypatch.setattr(compiled, "kernels", missing)
    with pytest.raises(lf.InputError, match=r"lieflow\[fast\]"):
        lf.integrate(system, mid, W0, 0.1, steps=2, engine="compiled")
    ensemble = np.broadcast_to(W0, (compiled.AUTO_MIN_WORK // 2, 3, 3))
    assert lf.integrate(system, mid, ensemble, 0.1, steps=2).success  # auto: numpy
    monkeypatch.setattr(compiled, "available", lambda: False)
    assert lf.integrate(system, mid, ensemble, 0.1, steps=2).success


@pytest.mark.usefixtures("numba")
def test_auto_picks_compiled_only_for_small_n() -> None:
    small = lf.systems.GeneralizedRigidBody.random_inertia(4, seed=0)
    large = lf.systems.GeneralizedRigidBody.random_inertia(compiled.AUTO_MAX_N + 1, seed=0)
    fp, mid = lf.solvers.FixedPoint(), lf.schemes.get("midpoint")
    work = compiled.AUTO_MIN_WORK
    for system, steps, K, wins in (
        (small, work, 1, True),
        (small, work // 4, 4, True),
        (small, work - 1, 1, False),
        (large, work, 1, False),
    ):
        plan = compiled.plan(system, mid, fp, system.random_state(seed=0))
        assert isinstance(plan, compiled_plan.CompiledPlan)
        assert compiled.wins(plan.n, steps, K) is wins


@pytest.mark.usefixtures("numba")
def test_stopping_rule_is_one_function_on_both_engines() -> None:
    """The compiled loops judge with the numpy path's rule: the same function object,
    compiled, giving the same reason on every case (not just accept/fail)."""
    from lieflow.engines import _compiled_rules
    from lieflow.solvers import fixed_point

    assert getattr(_compiled_rules.verdict, "py_func", None) is fixed_point.stopping_verdict
    rule = lf.solvers.StoppingRule(rtol=1e-16, patience=3)
    cases = [
        [1e-3, 1e-8, 1e-15, 3e-16],
        [1e-3, 1e-8, 1e-15, 3e-16, 4e-16, 5e-16, 3.5e-16],
        [1e-1, 1e-3, 2e-3, 3e-3, 2e-3],
        [0.5],
        [float("nan")],
        list(0.5 * 0.97 ** np.arange(12)),
        list(0.5 * 0.5 ** np.arange(12)),
        list(0.5 * 0.6 ** np.arange(100)),  # the cap, at roundoff: accepted
        list(0.5 * 0.9 ** np.arange(100)),  # the cap, not at roundoff
    ]
    seen = set()
    for res in cases:
        for growth in (1.0, 20.0, 1e3, float("inf")):
            for met in (False, True):
                for r in (rule, attrs.evolve(rule, project=False, max_iter=len(res))):
                    want = r.verdict(list(res), met, growth)
                    got = _compiled_rules.verdict(
                        np.array(res), len(res), met, growth, r.rtol, r.roundoff_floor,
                        r.divergence_factor, r.max_iter, r.patience, r.window, r.project,
                    )  # fmt: skip
                    assert fixed_point.REASONS[got] == want, (res, growth, met, r)
                    seen.add(want)
    assert seen == set(fixed_point.REASONS)
