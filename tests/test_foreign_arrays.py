"""Every documented option on arrays of other libraries (issue 37, item 5), and the steps
traced by ``jax.jit`` (the compiled device engine's contract, issue 34).

Eager runs on ``array_api_strict`` (the strict reference of the array API standard) and on
JAX arrays are compared with the NumPy engine — states to 1e-12 relative, the same solver
updates — and with the conserved quantities (Casimir drift at roundoff). Traced runs call
``scheme.step`` inside ``jax.jit`` with a probe solver that iterates the problem's own map
(``problem.map``, ``problem.frozen_map``, or Newton's iteration from
:func:`lieflow.solvers.newton.dense_direction`, :func:`~lieflow.solvers.newton.gmres_direction`
and :func:`~lieflow.solvers.newton.line_search`) a fixed number of times with
``jax.lax`` loops: any host read (``float()``, ``bool()``, ``np.`` on a tracer) fails the
trace.

Not here: Anderson acceleration (its array-API kernel is another change), the Euler–Zeitlin
system under ``jax.jit`` (its Laplacian keeps device copies of its multipliers per device; a
copy made inside a trace is a tracer, and the next trace fails on it) and its energy and
Casimirs on device arrays (computed with NumPy, on the host).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf
from lieflow import backends
from lieflow.schemes import conjugation
from lieflow.solvers import newton
from lieflow.solvers.base import SolveResult
from lieflow.solvers.krylov import gmres

xps = pytest.importorskip("array_api_strict")

H = 0.05
STEPS = 4


def _system(name: str) -> lf.IsospectralSystem:
    if name == "point_vortices":
        import_plugin("lieflow_vortices")
    if name == "euler_zeitlin":
        import_plugin("lieflow_zeitlin")
        return lf.systems.get("euler_zeitlin", N=6)
    if name == "toda_gl_gradient":
        return lf.systems.get("periodic_toda", n=4, gl_gradient=True)
    return lf.systems.get(name)


SYSTEMS = [
    "rigid_body",
    "generalized_rigid_body",
    "periodic_toda",
    "toda_gl_gradient",
    "point_vortices",
    "euler_zeitlin",
]


def _auto() -> lf.solvers.Auto:
    """Auto whose fixed point gives up at once: Newton finishes every solve."""
    return lf.solvers.Auto(lf.solvers.FixedPoint(rtol=1e-14, max_iter=2), lf.solvers.Newton())


#: (scheme, update, solver) — every scheme form, both updates and every solver but Anderson
OPTIONS: list[tuple[str, str, Callable[[], lf.Solver]]] = [
    ("midpoint", "commutator", lf.solvers.Newton),
    ("triple_jump", "conjugation", lambda: lf.solvers.FrozenB(rtol=1e-14)),
    ("gauss2", "conjugation", lambda: lf.solvers.Newton(linear="gmres")),
    ("gauss2", "commutator", lambda: lf.solvers.FrozenB(rtol=1e-14)),
    ("block", "commutator", lambda: lf.solvers.FrozenB(rtol=1e-14)),
    ("block", "conjugation", lf.solvers.Newton),
    ("modin_viviani", "commutator", _auto),
    ("modin_viviani", "conjugation", lambda: lf.solvers.FrozenB(rtol=1e-14)),
]


def _relative(a: Any, b: np.ndarray) -> float:
    return float(np.max(np.abs(backends.to_numpy(a) - b)) / np.max(np.abs(b)))


def _run_matches_numpy(system: lf.IsospectralSystem, option: tuple[Any, ...], put: Any) -> None:
    scheme_name, update, make_solver = option
    scheme = lf.schemes.get(scheme_name, update=update)
    W0 = system.random_state(0)
    kwargs: dict[str, Any] = {"h": H, "steps": STEPS}
    ref = lf.integrate(system, scheme, W0, solver=make_solver(), engine="numpy", **kwargs)
    sol = lf.integrate(system, scheme, put(W0), solver=make_solver(), **kwargs)
    assert sol.status == ref.status == lf.Status.SUCCESS
    assert _relative(sol.W, ref.W) <= 1e-12
    np.testing.assert_array_equal(sol.iterations, ref.iterations)
    assert set(sol.solvers) == set(ref.solvers)
    # conserved quantities: the spectrum (Casimirs) to roundoff, the states on the phase space
    assert float(np.max(sol.casimir_drift)) <= 1e-12
    assert float(np.max(system.phase_space_distance(sol.W))) <= 1e-13


#: The default run's share of the systems × options product (each option on at least one
#: system, each system with two solvers or more); the rest is marked slow.
STRICT_DEFAULT = {
    ("rigid_body", 0),
    ("rigid_body", 6),
    ("generalized_rigid_body", 1),
    ("generalized_rigid_body", 5),
    ("periodic_toda", 2),
    ("periodic_toda", 5),
    ("periodic_toda", 7),
    ("toda_gl_gradient", 2),
    ("toda_gl_gradient", 4),
    ("point_vortices", 0),
    ("point_vortices", 3),
    ("point_vortices", 7),
    ("euler_zeitlin", 1),
    ("euler_zeitlin", 2),
}


def _cases(default: set[tuple[str, int]]) -> list[Any]:
    return [
        pytest.param(
            name,
            option,
            id=f"{name}-{option[0]}-{option[1]}",
            marks=() if (name, i) in default else pytest.mark.slow,
        )
        for name in SYSTEMS
        for i, option in enumerate(OPTIONS)
    ]


@pytest.mark.parametrize(("name", "option"), _cases(STRICT_DEFAULT))
def test_every_option_on_array_api_strict_matches_numpy(name: str, option: Any) -> None:
    _run_matches_numpy(_system(name), option, xps.asarray)


def test_a_batch_of_states_runs_newton_and_the_block_form_on_array_api_strict() -> None:
    """A stack of three states: Newton's dense columns and GMRES's one real system span
    the batch, as on NumPy."""
    system = lf.systems.get("generalized_rigid_body")
    W0 = np.stack([system.random_state(s) for s in range(3)])
    for solver in (lf.solvers.Newton(), lf.solvers.Newton(linear="gmres")):
        scheme = lf.schemes.get("block", update="conjugation")
        ref = lf.integrate(system, scheme, W0, h=H, steps=2, solver=solver, engine="numpy")
        sol = lf.integrate(system, scheme, xps.asarray(W0), h=H, steps=2, solver=solver)
        assert _relative(sol.W, ref.W) <= 1e-12
        np.testing.assert_array_equal(sol.iterations, ref.iterations)


def test_iterate_yields_arrays_of_the_input_library() -> None:
    system = lf.systems.get("periodic_toda", n=5)
    W0 = system.random_state(0)
    scheme = lf.schemes.get("gauss2")
    ref = lf.iterate(system, scheme, W0, H, lf.solvers.Newton())
    got = lf.iterate(system, scheme, xps.asarray(W0), H, lf.solvers.Newton())
    for _, a, b in zip(range(3), got, ref, strict=False):
        assert backends.namespace(a.W) is xps and a.index == b.index
        assert _relative(a.W, b.W) <= 1e-13


@pytest.mark.parametrize("name", SYSTEMS[:-1])  # Euler–Zeitlin's diagnostics are NumPy's
def test_diagnostics_and_projections_on_array_api_strict(name: str) -> None:
    """Energy, Casimirs, the phase-space projection and ``B`` of each system in the array's
    own library, equal to NumPy's (a state pushed off the phase space, so that the
    projection has work to do)."""
    system = _system(name)
    W = system.random_state(3)
    W = W + 1e-3 * np.random.default_rng(0).standard_normal(W.shape).astype(W.dtype)
    Wa = xps.asarray(W)
    for f in (system.hamiltonian, system.casimirs, system.project, system.B):
        got = f(Wa)
        assert backends.namespace(got) is xps
        np.testing.assert_allclose(backends.to_numpy(got), f(W), rtol=1e-13, atol=1e-15)


def test_the_conjugators_orthonormalisation_without_host_reads() -> None:
    """On another library Newton–Schulz runs a static number of updates: the NumPy result
    where NumPy converges; NaN (the step then reports a non-finite state) where NumPy
    refuses a conjugator far from unitary."""
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    near = Q + 1e-6 * rng.standard_normal((6, 6)) - np.eye(6)
    got = conjugation.orthonormalize(xps.asarray(near))
    np.testing.assert_allclose(
        backends.to_numpy(got), conjugation.orthonormalize(near), rtol=0, atol=1e-15
    )
    far = 3.0 * Q - np.eye(6)
    with pytest.raises(lf.ConvergenceError, match="far from unitary"):
        conjugation.orthonormalize(far)
    assert np.isnan(backends.to_numpy(conjugation.orthonormalize(xps.asarray(far)))).all()


def test_gmres_solves_against_a_direct_solve() -> None:
    rng = np.random.default_rng(0)
    n = 60
    A = np.eye(n) + 0.5 * rng.standard_normal((n, n)) / math.sqrt(n)
    b = rng.standard_normal(n)
    exact = np.linalg.solve(A, b)
    for restart in (50, 7):  # one cycle; several restarts
        x = gmres(lambda v: A @ v, b, rtol=1e-13, restart=restart, cycles=60)
        assert np.linalg.norm(x - exact) <= 1e-11 * np.linalg.norm(exact)
        xa = gmres(
            lambda v: xps.asarray(A) @ v, xps.asarray(b), rtol=1e-13, restart=restart, cycles=60
        )
        assert np.linalg.norm(backends.to_numpy(xa) - exact) <= 1e-11 * np.linalg.norm(exact)
    # an exact Krylov space of dimension 2 (a breakdown), and a zero right-hand side
    D = np.diag(np.r_[2.0 * np.ones(n // 2), 3.0 * np.ones(n - n // 2)])
    np.testing.assert_allclose(gmres(lambda v: D @ v, b, rtol=1e-15), b / np.diag(D), rtol=1e-14)
    assert not gmres(lambda v: A @ v, np.zeros(n), rtol=1e-12).any()


# -------------------------------------------------------------------------------------
# JAX: eagerly, and traced by jax.jit


@pytest.fixture(scope="module")
def jax_np() -> Any:
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)  # lieflow's states are float64/complex128
    return jax


#: (system, scheme, update, solver) on JAX arrays eagerly (a few seconds each: JAX's eager
#: dispatch is slow), each solver and form once; the first in the default run
JAX_EAGER = [
    ("periodic_toda", "block", "conjugation", lf.solvers.Newton),
    ("euler_zeitlin", "triple_jump", "conjugation", lambda: lf.solvers.FrozenB(rtol=1e-14)),
    ("point_vortices", "block", "conjugation", lf.solvers.Newton),
    ("periodic_toda", "modin_viviani", "conjugation", lambda: lf.solvers.FrozenB(rtol=1e-14)),
    ("generalized_rigid_body", "triple_jump", "commutator", _auto),
    ("euler_zeitlin", "gauss2", "conjugation", lambda: lf.solvers.Newton(linear="gmres")),
]


@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=() if i < 1 else pytest.mark.slow) for i, c in enumerate(JAX_EAGER)],
    ids=lambda c: f"{c[0]}-{c[1]}",
)
def test_options_on_jax_arrays_eagerly(jax_np: Any, case: Any) -> None:
    name, *option = case
    _run_matches_numpy(_system(name), tuple(option), jax_np.numpy.asarray)


class Probe:
    """A solver for tests: ``updates`` iterations of the problem's own map under
    ``jax.lax.fori_loop`` — ``"map"`` (fixed point), ``"frozen"`` (``frozen_map``),
    ``"newton"`` (dense direction and backtracking, the frozen step where no trial
    descends) or ``"gmres"`` (matrix-free direction, full steps) — then one more map
    value; reported converged. Everything traced: nothing is read on the host."""

    name = "probe"

    def __init__(self, jax: Any, kind: str, updates: int) -> None:
        self.jax, self.kind, self.updates = jax, kind, updates

    def solve(self, problem: Any) -> SolveResult:
        lax, xp = self.jax.lax, self.jax.numpy
        if self.kind in ("map", "frozen"):
            F = problem.map if self.kind == "map" else problem.frozen_map
            x = lax.fori_loop(0, self.updates, lambda _, x: F(x), problem.x0)
            return SolveResult(x, True, self.updates, (0.0,), "converged", self.name)

        def iteration(_: int, x: Any) -> Any:
            rhs = problem.map(x) - x
            if self.kind == "gmres":
                d = newton.gmres_direction(
                    problem, x, rhs, forcing=1e-15, while_loop=lax.while_loop
                )
                return x + d
            d = newton.dense_direction(problem, x, rhs)
            xn, _, descent = newton.line_search(
                problem, x, d, newton.total_norm(rhs), trials=8, while_loop=lax.while_loop
            )
            return xp.where(descent, xn, problem.frozen_map(x))

        x = problem.map(lax.fori_loop(0, self.updates, iteration, problem.x0))
        return SolveResult(x, True, self.updates, (0.0,), "converged", self.name)


def _traced_step_matches_numpy(
    jax: Any, name: str, scheme_name: str, update: str, kind: str, updates: int
) -> None:
    """The second step of a run, warm-started from the first's offsets, traced, against
    NumPy's."""
    system = _system(name)
    scheme = lf.schemes.get(scheme_name, update=update)
    W0 = system.random_state(0)
    solver = lf.solvers.FixedPoint(rtol=1e-15)
    first = scheme.step(W0, H, system, solver)
    ref = scheme.step(first.W, H, system, solver, first.warm).W
    probe = Probe(jax, kind, updates)
    step = jax.jit(lambda W, warm: system.project(scheme.step(W, H, system, probe, warm).W))
    got = step(jax.numpy.asarray(first.W), jax.numpy.asarray(first.warm))
    assert _relative(got, system.project(ref)) <= 1e-12
    # diagnostics traced too, on the device
    energy = jax.jit(system.hamiltonian)(got)
    casimirs = jax.jit(system.casimirs)(got)
    np.testing.assert_allclose(backends.to_numpy(energy), system.hamiltonian(ref), rtol=1e-12)
    np.testing.assert_allclose(
        backends.to_numpy(casimirs), system.casimirs(W0), rtol=1e-12, atol=1e-14
    )


#: (system, scheme, update, probe, updates): every scheme form, both updates, every system
#: and every solver's iteration once (a few seconds of compilation each)
TRACED = [
    ("rigid_body", "gauss2", "commutator", "map", 60),
    ("generalized_rigid_body", "block", "conjugation", "map", 60),
    ("periodic_toda", "modin_viviani", "conjugation", "frozen", 40),
    ("point_vortices", "triple_jump", "commutator", "map", 60),
    ("toda_gl_gradient", "midpoint", "conjugation", "map", 60),
    ("rigid_body", "midpoint", "commutator", "newton", 6),
    ("rigid_body", "midpoint", "conjugation", "gmres", 6),
]


@pytest.mark.parametrize("case", TRACED, ids=lambda c: "-".join(map(str, c[:4])))
def test_steps_trace_under_jit(jax_np: Any, case: tuple[Any, ...]) -> None:
    """Every scheme form and update, every system, the maps of every solver (the fixed
    point, FrozenB, Newton's dense and GMRES directions with the line search) traced
    inside ``jax.lax`` loops, then the energy and Casimirs of the result."""
    _traced_step_matches_numpy(jax_np, *case)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["map", "frozen", "newton", "gmres"])
@pytest.mark.parametrize("update", ["commutator", "conjugation"])
@pytest.mark.parametrize(
    "scheme_name", ["midpoint", "triple_jump", "gauss2", "block", "modin_viviani"]
)
@pytest.mark.parametrize("name", SYSTEMS[:-1])
def test_every_traced_combination(
    jax_np: Any, name: str, scheme_name: str, update: str, kind: str
) -> None:
    updates = {"map": 60, "frozen": 40}.get(kind, 6)
    _traced_step_matches_numpy(jax_np, name, scheme_name, update, kind, updates)


def test_gmres_traced_equals_eager(jax_np: Any) -> None:
    rng = np.random.default_rng(2)
    n = 40
    A = np.eye(n) + 0.4 * rng.standard_normal((n, n)) / math.sqrt(n)
    b = rng.standard_normal(n)
    Aj = jax_np.numpy.asarray(A)
    traced = jax_np.jit(
        lambda v: gmres(
            lambda u: Aj @ u, v, rtol=1e-13, restart=8, cycles=40, while_loop=jax_np.lax.while_loop
        )
    )(jax_np.numpy.asarray(b))
    eager = gmres(lambda u: A @ u, b, rtol=1e-13, restart=8, cycles=40)
    np.testing.assert_allclose(backends.to_numpy(traced), eager, rtol=0, atol=1e-13)
    np.testing.assert_allclose(A @ eager, b, rtol=0, atol=1e-11)
