"""The traced engine (issue 34): the whole step compiled by ``jax.jit`` from the same array-API
source as the eager engine, run here on JAX's CPU backend.

Its two pieces of control logic are held to the scalar code they restate — the stopping rule
(:func:`lieflow.engines.traced_loops.verdict` against
:func:`lieflow.solvers.fixed_point.stopping_verdict`, code for code) and the warm start
(:mod:`lieflow.engines.traced_warm` against :class:`lieflow.WarmStart`) — and whole runs to the
physics: the Casimirs the flow conserves, and a composition against the scheme it equals."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lieflow as lf
from lieflow import stepping
from lieflow.engines import scheme_flow, traced, traced_loops, traced_warm
from lieflow.solvers.fixed_point import REASONS, StoppingRule, stopping_verdict

jax = pytest.importorskip("jax")
jax.config.update("jax_enable_x64", True)
jnp = jax.numpy


def _body(seed: int = 0) -> tuple[lf.IsospectralSystem, np.ndarray]:
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    return system, system.random_state(seed)


# ----------------------------------------------------------------- the stopping rule on arrays
@st.composite
def _histories(draw: Any) -> tuple[StoppingRule, list[float], bool, float]:
    rule = StoppingRule(
        rtol=draw(st.sampled_from([1e-14, 1e-10, 1e-6])),
        max_iter=draw(st.integers(2, 30)),
        patience=draw(st.integers(1, 8)),
        window=draw(st.integers(2, 12)),
        project=draw(st.booleans()),
        divergence_factor=draw(st.sampled_from([5.0, 100.0])),
    )
    k = draw(st.integers(1, rule.max_iter))
    kind = st.one_of(
        st.floats(1e-18, 1e2, allow_nan=False),  # contracting, stagnating, growing
        st.sampled_from([rule.roundoff_floor / 2, rule.roundoff_floor, rule.rtol]),
    )
    res = draw(st.lists(kind, min_size=k, max_size=k))
    if draw(st.integers(0, 9)) == 0:  # a non-finite last update
        res[-1] = draw(st.sampled_from([float("nan"), float("inf")]))
    growth = draw(st.sampled_from([0.5, 1.0, 9.0, 11.0, 120.0, float("inf")]))
    return rule, res, draw(st.booleans()), growth


@settings(max_examples=150, deadline=None)
@given(_histories())
def test_the_traced_stopping_rule_is_the_scalar_rule(case: Any) -> None:
    rule, res, met, growth = case
    expected = stopping_verdict(res, len(res), met, growth, rule.rtol, rule.roundoff_floor,
                                rule.divergence_factor, rule.max_iter, rule.patience,
                                rule.window, rule.project)  # fmt: skip
    buffer = np.full(rule.max_iter, np.inf)
    buffer[: len(res)] = res
    floor = rule.roundoff_floor
    got = traced_loops.verdict(rule, floor, jnp.asarray(buffer), len(res), met, growth)
    assert REASONS[int(got)] == REASONS[expected]


# ------------------------------------------------------------------ the warm start on arrays
@pytest.mark.parametrize("depth", [1, 2, 3, 5])
def test_the_warm_start_as_arrays_predicts_and_trusts_as_the_warm_start(depth: int) -> None:
    """A smooth sequence of offsets with noise (so that the trusted depth moves up and
    down): every prediction and trust of the arrays equals :class:`WarmStart`'s."""
    rng = np.random.default_rng(depth)
    state = lf.WarmStart.keeping(depth)
    arrays = traced_warm.from_warm_start(state, (2, 3), np.float64, np)
    for k in range(14):
        t = 0.3 * k
        solved = np.array([[np.sin(t), np.cos(2 * t), t * t], [1.0, -t, np.exp(-t)]])
        solved += (1e-3 if k % 5 == 4 else 1e-9) * rng.standard_normal(solved.shape)
        guess = state.predict().guess
        mine = traced_warm.predict(arrays, np)
        np.testing.assert_allclose(mine, np.zeros((2, 3)) if guess is None else guess,
                                   rtol=1e-13, atol=1e-13)  # fmt: skip
        state = state.advance(solved)
        arrays = traced_warm.advance(arrays, solved, np)
        assert int(arrays.trusted) == state.trusted
        assert int(arrays.count) == len(state.history())
    rows = [arrays.history[j] for j in range(int(arrays.count))]
    back = lf.WarmStart.keeping(depth).replaced(rows, int(arrays.trusted))
    for a, b in zip(back.history(), state.history(), strict=True):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------- runs
@pytest.mark.parametrize("scheme", ["midpoint", "gauss2"])
def test_a_traced_run_takes_the_eager_engines_steps(scheme: str) -> None:
    system, W0 = _body()
    kwargs: dict[str, Any] = dict(h=0.1, steps=60, save_every=20,
                                  solver=lf.solvers.FixedPoint(rtol=1e-14))  # fmt: skip
    ref = lf.integrate(system, lf.schemes.get(scheme), W0, engine="numpy", **kwargs)
    sol = lf.integrate(system, lf.schemes.get(scheme), jnp.asarray(W0), engine="auto", **kwargs)
    assert isinstance(sol.W, np.ndarray) and sol.W.shape == ref.W.shape
    np.testing.assert_allclose(sol.W, ref.W, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(sol.saved_steps, [0, 20, 40, 60])
    assert np.abs(sol.iterations - ref.iterations).max() <= 1
    assert sol.solvers == ("fixed_point",) * 60
    # the Casimir ||W||^2 is conserved: at roundoff on every step
    assert sol.casimir_drift is not None and sol.casimir_drift.max() < 1e-14
    assert sol.energy_error is not None
    np.testing.assert_allclose(sol.energy_error, ref.energy_error, rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    "solver",
    [
        lf.solvers.Newton(),
        lf.solvers.Newton(linear="gmres"),
        lf.solvers.FrozenB(),
        lf.solvers.Auto(lf.solvers.FixedPoint(max_iter=6)),
    ],
    ids=["newton-dense", "newton-gmres", "frozen-b", "auto"],
)
def test_every_solver_runs_traced_with_the_eager_engines_updates(solver: Any) -> None:
    """Newton (its direction dense or by GMRES, the line search and the frozen-B fallback
    as traced loops), FrozenB and Auto (a fixed point capped at 6 updates, so that some
    steps fall back to Newton) on the generalized rigid body."""
    system = lf.systems.get("generalized_rigid_body")
    W0 = system.random_state(1)
    kwargs: dict[str, Any] = dict(h=0.5, steps=6, save_every=3, solver=solver)
    ref = lf.integrate(system, lf.schemes.get("gauss2"), W0, engine="numpy", **kwargs)
    sol = lf.integrate(system, lf.schemes.get("gauss2"), jnp.asarray(W0), engine="jax", **kwargs)
    np.testing.assert_allclose(sol.W, ref.W, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(sol.iterations, ref.iterations)
    assert sol.solvers == ref.solvers
    assert sol.casimir_drift is not None and sol.casimir_drift.max() < 1e-14


class _HostDiagnostics(type(_body()[0])):  # type: ignore[misc]
    """The rigid body with Casimirs written for NumPy only: they do not trace, so the chunk
    brings every state to the host, where the stepping loop computes the diagnostics."""

    def casimirs(self, W: Any) -> Any:
        W = np.asarray(W)
        return np.einsum("...ij,...ji->...", W, W)[..., None]


def test_diagnostics_that_do_not_trace_are_computed_on_the_host() -> None:
    base, W0 = _body(1)
    system = _HostDiagnostics(base.inertia)
    kwargs: dict[str, Any] = dict(h=0.05, steps=30, save_every=10)
    ref = lf.integrate(system, lf.schemes.get("midpoint"), W0, engine="numpy", **kwargs)
    sol = lf.integrate(system, lf.schemes.get("midpoint"), jnp.asarray(W0), **kwargs)
    np.testing.assert_allclose(sol.W, ref.W, rtol=0, atol=1e-13)
    assert sol.casimir_drift is not None and ref.casimir_drift is not None
    np.testing.assert_allclose(sol.casimir_drift, ref.casimir_drift, rtol=0, atol=1e-14)


def test_a_composition_of_traced_midpoint_steps_is_the_triple_jump() -> None:
    """A :class:`~lieflow.Splitting` of traced midpoint sub-steps of Yoshida's sizes is the
    triple-jump SyDIRK scheme (the same sub-steps; stepped alone, the flow stays
    compiled)."""
    system, W0 = _body(2)
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    inner = scheme_flow(system, lf.schemes.get("midpoint"), solver, jnp.asarray(W0), 20,
                        engine="jax")  # fmt: skip
    assert isinstance(inner, traced.TracedSchemeFlow)
    gammas, _ = lf.tableaus.composition_weights("triple_jump")
    split = lf.Splitting([inner], [(0, g) for g in gammas], order=4)
    sol = lf.integrate(system, split, jnp.asarray(W0), h=0.1, steps=20, save_every=20)
    ref = lf.integrate(system, lf.schemes.get("triple_jump"), W0, h=0.1, steps=20,
                       save_every=20, solver=solver, engine="numpy")  # fmt: skip
    np.testing.assert_allclose(sol.W, ref.W, rtol=0, atol=1e-13)


def test_a_step_that_fails_fails_as_on_the_eager_engine() -> None:
    system, W0 = _body(3)
    kwargs: dict[str, Any] = dict(h=3.0, steps=5, solver=lf.solvers.FixedPoint(max_iter=20))
    with pytest.raises(lf.ConvergenceError) as eager:
        lf.integrate(system, lf.schemes.get("midpoint"), W0, engine="numpy", **kwargs)
    with pytest.raises(lf.ConvergenceError) as on_jax:
        lf.integrate(system, lf.schemes.get("midpoint"), jnp.asarray(W0), **kwargs)
    assert (on_jax.value.step, on_jax.value.reason) == (eager.value.step, eager.value.reason)


class _ArrayDiagnostics(type(_body()[0])):  # type: ignore[misc]
    """The rigid body with its energy and Casimir in array-API operations: they trace, so
    the device computes them."""

    def hamiltonian(self, W: Any) -> Any:
        xp = lf.backends.namespace(W)
        return 0.5 * xp.sum(W * W * xp.asarray(self.weights), axis=(-2, -1))

    def casimirs(self, W: Any) -> Any:
        xp = lf.backends.namespace(W)
        return xp.sum(W * xp.matrix_transpose(W), axis=(-2, -1))[..., None]


def test_chunks_end_at_the_states_needed_and_hold_them_only() -> None:
    base, W0 = _body(4)
    system = _ArrayDiagnostics(base.inertia)
    np.testing.assert_allclose(system.hamiltonian(W0), base.hamiltonian(W0), rtol=1e-15)
    np.testing.assert_allclose(system.casimirs(W0), base.casimirs(W0), rtol=1e-15)
    flow = scheme_flow(system, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(),
                       jnp.asarray(W0), 12, engine="jax")  # fmt: skip
    recording = stepping.Recording(save_every=5, last=12, diagnostics=True)
    chunks = list(stepping.advance(flow, jnp.asarray(W0), 0.1, 12, recording=recording))
    assert [(c.start, c.size) for c in chunks] == [(0, 5), (5, 5), (10, 2)]
    for c in chunks:
        assert c.W.shape == (1, 3, 3) and c.held is not None and c.held.tolist() == [c.size - 1]
        assert c.energy is not None and c.energy.shape == (c.size,)
        assert c.casimirs is not None and c.casimirs.shape == (c.size, 1)
        with pytest.raises(ValueError, match="holds the states of steps"):
            c.states(np.ones(c.size, dtype=bool))


def test_a_run_resumed_from_its_file_is_the_uninterrupted_run(tmp_path: Path) -> None:
    """``engine="jax"`` on NumPy arrays (JAX's CPU backend), through a trajectory file: the
    checkpoint's warm start carries over exactly."""
    pytest.importorskip("h5py")
    system, W0 = _body(5)
    kwargs: dict[str, Any] = dict(h=0.1, save_every=5, engine="jax")
    scheme = lf.schemes.get("gauss2")
    lf.integrate(system, scheme, W0, steps=10, out=tmp_path / "a.h5", **kwargs)
    resumed = lf.integrate(system, scheme, W0, steps=20, out=tmp_path / "a.h5", resume=True,
                           **kwargs)  # fmt: skip
    whole = lf.integrate(system, scheme, W0, steps=20, out=tmp_path / "b.h5", **kwargs)
    np.testing.assert_array_equal(resumed.W_final, whole.W_final)
    np.testing.assert_array_equal(resumed.iterations, whole.iterations)


class _OwnSolver(lf.solvers.FixedPoint):
    """A solver of one's own (its own ``solve``): no traced form."""

    def solve(self, problem: Any) -> Any:
        return super().solve(problem)


def test_auto_and_named_engines() -> None:
    system, W0 = _body()
    solver = lf.solvers.FixedPoint()
    midpoint = lf.schemes.get("midpoint")
    assert isinstance(scheme_flow(system, midpoint, solver, jnp.asarray(W0), 10),
                      traced.TracedSchemeFlow)  # fmt: skip
    assert not isinstance(scheme_flow(system, midpoint, solver, W0, 10), traced.TracedSchemeFlow)
    strict = pytest.importorskip("array_api_strict")
    assert type(scheme_flow(system, midpoint, solver, strict.asarray(W0), 10)) is lf.SchemeFlow
    with pytest.raises(lf.InputError, match="engine='compiled' runs NumPy arrays only"):
        scheme_flow(system, midpoint, solver, jnp.asarray(W0), 10, engine="compiled")
    with pytest.raises(lf.InputError, match="no traced form"):
        scheme_flow(system, midpoint, _OwnSolver(), W0, 10, engine="jax")
    with pytest.raises(lf.InputError, match="engine must be one of"):
        scheme_flow(system, midpoint, solver, W0, 10, engine="gpu")  # type: ignore[arg-type]
