"""Euler–Zeitlin on the compiled engine (issue 18): complex128 loops, the plugin's compiled B
through the public ``compiled_B`` hook, the su(N) projection inside the loops.

The physics is checked against the exact Rossby–Haurwitz speed in
``test_zeitlin_orientation.py``; here the compiled engine is held to the numpy path (same
iterations, states to roundoff) and to the invariants (Casimirs, su(N) membership)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from typing import Any

import attrs
import numpy as np
import pytest

import lieflow as lf
from lieflow.engines import _compiled_maps, compiled, compiled_plan

lz = pytest.importorskip("lieflow_zeitlin")
pytest.importorskip("numba")


def _both(*args: Any, **kwargs: Any) -> tuple[lf.Solution, lf.Solution]:
    return (
        lf.integrate(*args, **kwargs, engine="numpy"),
        lf.integrate(*args, **kwargs, engine="compiled"),
    )


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2", "gauss4", "sydirk7"])
@pytest.mark.parametrize(
    "options",
    [{}, {"rotation": 0.8, "lamb": 3.0}, {"time": "matrix"}],
    ids=["euler", "rotating-qg", "matrix-time"],
)
def test_compiled_and_numpy_take_the_same_steps(scheme: str, options: dict[str, Any]) -> None:
    system = lz.EulerZeitlin(16, **options)
    W0 = lz.random_vorticity(16, 6, seed=1)
    h = 0.05 / system.fluid_time_unit  # 0.05 of fluid time, in the system's unit
    ref, fast = _both(system, lf.schemes.get(scheme), W0, h, steps=30)
    assert fast.W.dtype == np.complex128
    np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=1e-13 * np.abs(ref.W).max())
    assert np.max(np.abs(fast.iterations - ref.iterations)) <= 1


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2"])
def test_the_conjugation_update_runs_compiled_on_su_n(scheme: str) -> None:
    """The loops' conjugation updates in complex arithmetic (every transpose of the real
    code a conjugate transpose): the Cayley update of a composition of midpoint steps and
    the lifted update of Gauss-2, on su(16), take the numpy path's steps to roundoff and keep
    the Casimirs tr((iW)^k), k = 2, 3, 4 (an isospectral update's promise) at roundoff at a
    loose solve (rtol 1e-6): measured 2.7e-15 at most, against 3e-9 to 5e-8 with the
    commutator update."""
    system = lz.EulerZeitlin(16)
    W0 = lz.random_vorticity(16, 6, seed=2)
    h = 0.05 / system.fluid_time_unit
    solver = lf.solvers.FixedPoint(rtol=1e-6)
    updated = lf.schemes.get(scheme, update="conjugation")
    plan = compiled.plan(system, updated, solver, W0)
    assert isinstance(plan, compiled_plan.CompiledPlan) and plan.conjugation
    ref, fast = _both(system, updated, W0, h, steps=30, solver=solver)
    assert fast.W.dtype == np.complex128
    np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=1e-13 * np.abs(ref.W).max())
    assert not np.array_equal(fast.W, ref.W)  # the loops ran, not the numpy path
    C = system.casimirs(fast.W)
    assert np.max(np.abs(C - C[0]) / np.abs(C[0])) < 2e-14


def test_the_casimir_shift_is_folded_into_the_compiled_B() -> None:
    system = lz.EulerZeitlin(12)
    W0 = lz.random_vorticity(12, 5, seed=3)
    shifted = lf.systems.shifted.shifted(system, W0, "auto")
    assert isinstance(shifted, lf.systems.shifted.CasimirShifted) and shifted.c != 0
    plan = compiled.plan(shifted, lf.schemes.get("gauss3"), lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, compiled_plan.CompiledPlan)
    assert plan.B_params[1] == shifted.c  # B_params: [inline code, c, ...]
    ref, fast = _both(system, lf.schemes.get("gauss3"), W0, 0.2, steps=20, casimir_shift="auto")
    np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=1e-13 * np.abs(ref.W).max())


def test_an_ensemble_runs_trajectory_by_trajectory() -> None:
    system = lz.EulerZeitlin(10)
    W0 = np.stack([lz.random_vorticity(10, 4, seed=k) for k in range(3)])
    ref, fast = _both(system, lf.schemes.get("gauss2"), W0, 0.1, steps=15)
    np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=1e-13 * np.abs(ref.W).max())
    one = lf.integrate(system, lf.schemes.get("gauss2"), W0[1], 0.1, steps=15, engine="compiled")
    np.testing.assert_allclose(fast.W[:, 1], one.W, rtol=0, atol=1e-13)


def test_invariants_stay_at_roundoff_over_a_long_compiled_run() -> None:
    """500 steps at rms vorticity 1: Casimirs tr((iW)^k), k = 2, 3, 4, at roundoff (measured
    1.6e-14, 1.8e-13, 3.7e-14 relative on both engines; k = 3 is 13x smaller than k = 2),
    every state in su(N) (projected inside the loops), energy to the scheme's accuracy
    (9.3e-8 on both)."""
    system = lz.EulerZeitlin(16)
    W0 = lz.random_vorticity(16, 8, seed=0)
    sol = lf.integrate(system, lf.schemes.get("gauss2"), W0, 0.1, steps=500, engine="compiled")
    C = system.casimirs(sol.W)
    assert np.max(np.abs(C - C[0]) / np.abs(C[0])) < 5e-13
    assert float(system.phase_space_distance(sol.W).max()) < 1e-15
    traces = np.abs(np.trace(sol.W, axis1=-2, axis2=-1))
    assert traces.max() < 1e-14
    E = system.hamiltonian(sol.W)
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-6


def test_the_plan_uses_the_plugins_map_and_the_su_projection() -> None:
    system = lz.EulerZeitlin(8)
    W0 = system.random_state(seed=0)
    plan = compiled.plan(system, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, compiled_plan.CompiledPlan)
    assert plan.dtype == np.complex128 and plan.skew
    assert plan.B.function is lz._compiled.zeitlin_B
    assert plan.project.function is _compiled_maps.skew_hermitian_part


def test_the_compiled_B_calls_the_sweeps_by_their_symbol(tmp_path: Any) -> None:
    """Issue 37 item 11: ``zeitlin_B`` called the compiled Laplacian sweeps by name, so numba
    linked their code into it and optimized and generated it a second time (a first run's
    compile time). Now it holds only their symbol, which the linker resolves in each process,
    also in code loaded from numba's disk cache (a second process on the first one's cache
    reproduces the numpy B)."""
    code = textwrap.dedent(
        """
        import sys
        import numpy as np
        import lieflow as lf
        import lieflow_zeitlin as lz
        system = lz.EulerZeitlin(12)
        W = lz.random_vorticity(12, 5, seed=3)
        fn, params = system.compiled_B()
        out = np.zeros_like(W)
        fn(W, np.array(params), out)
        want = system.B(lf.SU(12).project(W))
        print(float(np.abs(out - want).max() / np.abs(want).max()))
        if sys.argv[1] == "compiled":  # (numba cannot show code loaded from its cache)
            ir = fn.inspect_llvm(lf.engines.compiled.map_signature(np.complex128).args)
            print("declare void @lieflow_zeitlin_sweeps_f8()" in ir, "_sweep_loops" in ir)
        """
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}  # empty: compiled, then loaded
    for how in ("compiled", "loaded"):
        out = subprocess.run([sys.executable, "-c", code, how], capture_output=True,
                             text=True, check=True, timeout=600, env=env)  # fmt: skip
        lines = out.stdout.splitlines()
        assert float(lines[-2 if how == "compiled" else -1]) < 1e-13
        if how == "compiled":
            assert lines[-1] == "True False"  # the sweeps' symbol, not their code


def test_single_precision_and_non_skew_complex_data_are_refused() -> None:
    system = lz.EulerZeitlin(8, dtype="complex64")
    W0 = system.random_state(seed=0)
    assert W0.dtype == np.complex64
    reason = compiled.plan(system, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(), W0)
    assert isinstance(reason, str) and "complex64" in reason
    with pytest.raises(lf.InputError, match="complex64"):
        lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2, engine="compiled")
    assert lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2).success


def test_a_compiled_B_that_raises_is_a_reason_not_a_crash() -> None:
    @attrs.frozen(eq=False)
    class Broken(lz.EulerZeitlin):
        def compiled_B(self, shift: float = 0.0) -> tuple[Any, np.ndarray] | None:
            raise RuntimeError("no sweeps today")

    system = Broken(8)
    W0 = system.random_state(seed=0)
    with pytest.raises(lf.InputError, match=r"compiled_B\(\) raised RuntimeError: no sweeps"):
        lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2, engine="compiled")
    assert lf.integrate(system, lf.schemes.get("midpoint"), W0, 0.1, steps=2).success


def test_auto_picks_compiled_for_complex_data_up_to_its_own_cut() -> None:
    work = compiled.AUTO_MIN_WORK
    assert compiled.wins(compiled.AUTO_MAX_N_COMPLEX, work, complex_data=True)
    assert not compiled.wins(compiled.AUTO_MAX_N_COMPLEX + 1, work, complex_data=True)
    assert compiled.wins(compiled.AUTO_MAX_N_COMPLEX + 1, work)  # real data: a higher cut
    assert not compiled.wins(8, work - 1, complex_data=True)


def test_toda_with_a_casimir_shift_stays_on_numpy() -> None:
    """``B - cW`` is not skew for the Toda lattice, so its stage values leave the symmetric
    matrices, and the loops would step with the unprojected stage: ``compiled_B(shift)``
    declines and ``engine="auto"`` runs numpy."""
    toda = lf.systems.PeriodicToda()
    W0 = toda.random_state(seed=0)
    shifted = lf.systems.shifted.shifted(toda, W0, 0.3)
    plan = compiled.plan(shifted, lf.schemes.get("gauss2"), lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, str) and "no compiled B" in plan
