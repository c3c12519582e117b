"""lieflow on arrays of another library (lieflow.backends): one source of the schemes, maps
and solver, run on ``array_api_strict`` arrays (CPU, CI) and compared with NumPy, which it
must match to roundoff with the same iteration counts. GPU libraries only where installed."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf
from lieflow import backends

xps = pytest.importorskip("array_api_strict")


def _systems() -> list[tuple[str, lf.IsospectralSystem]]:
    out = [("rigid_body", lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0)))]
    lz = import_plugin("lieflow_zeitlin")
    out.append(("euler_zeitlin_16", lz.EulerZeitlin(16)))
    return out


def test_namespace_and_host_copies() -> None:
    W = np.arange(4.0).reshape(2, 2) + 1j
    assert backends.namespace(W) is np and backends.namespace(W, 2.0) is np
    Wa = xps.asarray(W)
    xp = backends.namespace(Wa)
    assert xp is xps and not backends.is_numpy(Wa)
    back = backends.to_numpy(Wa)
    assert isinstance(back, np.ndarray) and np.array_equal(back, W)
    placed = backends.from_host(np.eye(2), Wa)
    assert backends.namespace(placed) is xps and placed.dtype == xps.float64
    np.testing.assert_array_equal(backends.host_norms(Wa, 2), [np.linalg.norm(W)])
    with pytest.raises(lf.InputError, match="array API"):
        backends.namespace(Wa, object())
    c = backends.copy(Wa)
    assert c is not Wa and np.array_equal(backends.to_numpy(c), W)


@pytest.mark.parametrize("scheme_name", ["midpoint", "triple_jump", "gauss2", "gauss3"])
@pytest.mark.parametrize("index", [0, 1])
def test_scheme_steps_on_array_api_strict_match_numpy(scheme_name: str, index: int) -> None:
    name, system = _systems()[index]
    scheme = lf.schemes.get(scheme_name)
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    W = system.random_state(1)
    Wa = xps.asarray(W)
    warm = warm_a = None
    for _ in range(10):
        r = scheme.step(W, 0.05, system, solver, warm)
        ra = scheme.step(Wa, 0.05, system, solver, warm_a)
        assert ra.stats.iterations == r.stats.iterations
        W, warm, Wa, warm_a = r.W, r.warm, ra.W, ra.warm
        assert backends.namespace(Wa) is xps and backends.namespace(warm_a) is xps
    rel = np.max(np.abs(backends.to_numpy(Wa) - W)) / np.max(np.abs(W))
    assert rel <= 1e-13, (name, rel)
    # and the state is still in the algebra, on the array library's side
    P = system.algebra.project(Wa)
    assert backends.namespace(P) is xps
    assert np.max(np.abs(backends.to_numpy(P) - backends.to_numpy(Wa))) <= 1e-14


def test_a_batch_of_states_on_array_api_strict() -> None:
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W = np.stack([system.random_state(s) for s in range(3)])
    scheme = lf.schemes.get("midpoint")
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    r = scheme.step(W, 0.1, system, solver)
    ra = scheme.step(xps.asarray(W), 0.1, system, solver)
    assert ra.stats.iterations == r.stats.iterations
    np.testing.assert_allclose(backends.to_numpy(ra.W), r.W, rtol=0, atol=1e-15)


def _on_gpu(library: str) -> Callable[[np.ndarray], Any]:
    """``W -> W`` on the first CUDA device of ``library``; skips where there is none."""
    if library == "cupy":
        cp = pytest.importorskip("cupy")
        try:
            if cp.cuda.runtime.getDeviceCount() < 1:
                pytest.skip("no CUDA device")
        except Exception:
            pytest.skip("no CUDA runtime")
        return cast(Callable[[np.ndarray], Any], cp.asarray)
    if library == "torch":
        torch = pytest.importorskip("torch")
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device")
        return lambda W: torch.from_numpy(np.ascontiguousarray(W)).to("cuda")
    jax = pytest.importorskip("jax")
    if not any(d.platform == "gpu" for d in jax.devices()):
        pytest.skip("no GPU for JAX")
    jax.config.update("jax_enable_x64", True)
    return lambda W: jax.device_put(W, jax.devices("gpu")[0])


@pytest.mark.parametrize("library", ["cupy", "torch", "jax"])
@pytest.mark.parametrize("scheme_name", ["midpoint", "gauss2"])
def test_gpu_runs_match_numpy(library: str, scheme_name: str) -> None:
    """A step and a whole ``integrate`` run on a GPU library's arrays against the NumPy
    engine (skipped without a CUDA device)."""
    put = _on_gpu(library)
    lz = import_plugin("lieflow_zeitlin")
    system = lz.EulerZeitlin(32)
    W = system.random_state(2)
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    scheme = lf.schemes.get(scheme_name)
    r = scheme.step(W, 0.01, system, solver)
    rg = scheme.step(put(W), 0.01, system, solver)
    assert np.max(np.abs(backends.to_numpy(rg.W) - r.W)) <= 1e-13 * np.max(np.abs(r.W))
    kwargs = {"h": 0.01, "steps": 20, "save_every": 5, "solver": solver}
    ref = lf.integrate(system, scheme, W, engine="numpy", **kwargs)
    sol = lf.integrate(system, scheme, put(W), **kwargs)
    assert sol.status == lf.Status.SUCCESS
    assert np.max(np.abs(sol.W - ref.W)) <= 1e-12 * np.max(np.abs(ref.W))
    assert float(np.max(sol.casimir_drift)) <= 1e-13


@pytest.mark.parametrize("scheme_name", ["midpoint", "gauss2"])
@pytest.mark.parametrize("index", [0, 1])
def test_integrate_on_array_api_strict_matches_the_numpy_engine(
    scheme_name: str, index: int
) -> None:
    """The same Euler–Zeitlin N = 16 and rigid-body runs, warm starts included: the states
    reach the host at the consumer (a chunk at a time), diagnostics are the host's."""
    _, system = _systems()[index]
    scheme = lf.schemes.get(scheme_name)
    W0 = system.random_state(0)
    kwargs = {"h": 0.05, "steps": 40, "save_every": 10}
    ref = lf.integrate(system, scheme, W0, engine="numpy", **kwargs)
    sol = lf.integrate(system, scheme, xps.asarray(W0), **kwargs)
    assert isinstance(sol.W, np.ndarray) and sol.W.shape == ref.W.shape
    assert sol.status == ref.status == lf.Status.SUCCESS
    np.testing.assert_array_equal(sol.iterations, ref.iterations)
    assert np.max(np.abs(sol.W - ref.W)) <= 1e-13 * np.max(np.abs(ref.W))
    assert float(np.max(sol.casimir_drift)) <= 1e-13


def test_the_compiled_engine_refuses_other_arrays_clearly() -> None:
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    with pytest.raises(lf.InputError, match="engine='compiled' runs NumPy arrays only"):
        lf.integrate(
            system,
            lf.schemes.get("midpoint"),
            xps.asarray(system.random_state(0)),
            h=0.1,
            steps=3,
            engine="compiled",
        )


@pytest.mark.parametrize("every", [2, 3, 5])
def test_check_every_reads_the_host_once_per_group(
    every: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``FixedPoint(check_every=k)`` on a device library: one host copy per ``k`` updates
    (counted at the solver's only copy), the first update the rule accepts is the same as
    with ``k = 1`` (the count is that one rounded up to the group), and the result agrees
    with NumPy's to roundoff."""
    from lieflow.solvers import fixed_point

    lz = import_plugin("lieflow_zeitlin")
    system = lz.EulerZeitlin(16)
    W = system.random_state(2)
    scheme = lf.schemes.get("midpoint")
    reference = scheme.step(W, 0.05, system, lf.solvers.FixedPoint(rtol=1e-13))
    n = reference.stats.iterations
    copies = []
    real_to_numpy = fixed_point.to_numpy

    def counting(x: object) -> np.ndarray:
        copies.append(1)
        return real_to_numpy(x)

    monkeypatch.setattr(fixed_point, "to_numpy", counting)
    solver = lf.solvers.FixedPoint(rtol=1e-13, check_every=every)
    r = scheme.step(xps.asarray(W), 0.05, system, solver)
    groups = -(-n // every)
    assert r.stats.iterations == groups * every
    assert len(copies) == 1 + groups  # ||x0|| once, then one copy per group
    rel = np.max(np.abs(backends.to_numpy(r.W) - reference.W)) / np.max(np.abs(reference.W))
    assert rel <= 1e-14


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_check_every_stops_at_max_iter_and_reports_divergence() -> None:
    """A group never runs past ``max_iter``, and a failure inside a group is reported (the
    step is refused, not returned)."""
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W = xps.asarray(system.random_state(0))
    problem = lf.schemes.MidpointProblem(system, W, 0.1)
    res = lf.solvers.FixedPoint(rtol=1e-300, atol=0.0, max_iter=7, check_every=3).solve(problem)
    assert res.iterations <= 7 and res.reason in ("roundoff", "max_iterations", "stalled")
    huge = lf.schemes.MidpointProblem(system, W, 1e6)
    bad = lf.solvers.FixedPoint(rtol=1e-13, check_every=4).solve(huge)
    assert not bad.converged and bad.reason in ("diverged", "non_finite", "stalled")
