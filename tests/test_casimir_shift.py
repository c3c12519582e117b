"""The Casimir shift (``lieflow.systems.shifted``): the same flow, a Lie–Poisson scheme of the
same order, fewer iterations and smaller errors where ``B(W)`` is close to a multiple of
``W``. References are outside the shifted scheme: the commutator identity, finite
differences of the Hamiltonian, scipy's DOP853, and the unshifted run's invariants."""

from __future__ import annotations

import types

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from test_poisson import (
    GRADIENT_TOL,
    POISSON_TOL,
    _lie_poisson_systems,
    _start,
    gradient_defect,
    poisson_defect,
)

import lieflow as lf
from lieflow.app.reproduce import Case
from lieflow.systems.shifted import CasimirShifted, casimir_shift, shifted

TIGHT = lf.solvers.FixedPoint(rtol=1e-15)


def _paper_grb() -> tuple[lf.IsospectralSystem, np.ndarray]:
    """The paper's so(10) generalized rigid body with lieflow's recorded seed 0."""
    return Case("generalized_rigid_body", "", 10, 0.01, 1, 1e-14).build(0)


@pytest.mark.parametrize("system", _lie_poisson_systems())
def test_same_vector_field_and_B_is_the_gradient_of_eta_minus_the_casimir(
    system: lf.IsospectralSystem,
) -> None:
    W = _start(system)
    c = casimir_shift(system, W)
    sh = CasimirShifted(system, 0.7 if c == 0 else c)
    P = system.project_stage(W)
    exact = system.B(P) @ P - P @ system.B(P)
    got = sh.B(P) @ P - P @ sh.B(P)
    assert np.max(np.abs(got - exact)) <= 1e-14 * max(1.0, float(np.max(np.abs(exact))))
    # B - cW is the gradient of the shifted system's Hamiltonian, eta - (c/2) Re tr W^2
    # (for Toda, whose eta is a gradient only up to a Casimir, of its gradient_hamiltonian
    # shifted the same way)
    eta = getattr(system, "gradient_hamiltonian", None)
    if eta is None:
        assert gradient_defect(sh, W) <= GRADIENT_TOL
        eta = system.hamiltonian
    else:
        probe = types.SimpleNamespace(
            algebra=sh.algebra,
            B=sh.B,
            hamiltonian=lambda V: eta(V) - 0.5 * sh.c * np.real(np.trace(V @ V)),
        )
        assert gradient_defect(probe, W) <= GRADIENT_TOL  # type: ignore[arg-type]
    # ... and not of the unshifted Hamiltonian: the test can fail
    wrong = types.SimpleNamespace(algebra=sh.algebra, B=sh.B, hamiltonian=eta)
    assert gradient_defect(wrong, W) > 1e-3  # type: ignore[arg-type]


@pytest.mark.parametrize("system", _lie_poisson_systems())
def test_the_shifted_step_is_a_poisson_map(system: lf.IsospectralSystem) -> None:
    W = _start(system)
    sh = CasimirShifted(system, casimir_shift(system, W) or 0.7)
    assert poisson_defect(sh, lf.schemes.get("gauss3"), W, 0.2) <= POISSON_TOL


def test_least_squares_shift_and_resolution() -> None:
    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W = body.random_state(0)
    B = body.B(W)
    c = casimir_shift(body, W)
    assert c == pytest.approx(np.sum(W * B) / np.sum(W * W), rel=1e-15)
    # the minimiser of ||B - cW||_F: nearby values are worse
    best = np.linalg.norm(B - c * W)
    assert best < min(np.linalg.norm(B - (c + d) * W) for d in (-1e-3, 1e-3))
    assert shifted(body, W, 0.0) is body and shifted(body, W, 0) is body
    assert shifted(body, W, "auto").c == c  # type: ignore[attr-defined]
    assert shifted(body, W, -0.5).c == -0.5  # type: ignore[attr-defined]
    for bad in ("yes", None, True, [1.0]):
        with pytest.raises(lf.InputError, match="casimir_shift must be a number or"):
            shifted(body, W, bad)  # type: ignore[arg-type]
    with pytest.raises(lf.InputError, match="must be finite"):
        CasimirShifted(body, float("nan"))
    assert casimir_shift(body, np.zeros((3, 3))) == 0.0


def test_order_against_dop853_and_invariants_at_roundoff() -> None:
    """gauss2 with the shift converges with order 4 to scipy's solution of the unshifted
    ODE (observed order within 0.1), keeps the spectrum and Casimirs to roundoff."""
    grb = lf.systems.get("generalized_rigid_body")
    W0 = grb.random_state(3)
    n, T = W0.shape[-1], 2.0

    def f(t: float, y: np.ndarray) -> np.ndarray:
        W = y.reshape(n, n)
        B = grb.B(W)
        return (B @ W - W @ B).ravel()

    ref = solve_ivp(f, (0, T), W0.ravel(), method="DOP853", rtol=1e-13, atol=1e-15)
    W_ref = ref.y[:, -1].reshape(n, n)
    errors = []
    for h in (0.4, 0.2, 0.1):
        sol = lf.integrate(grb, lf.schemes.get("gauss2"), W0, h=h, t_final=T, solver=TIGHT,
                           casimir_shift="auto", engine="numpy")  # fmt: skip
        errors.append(float(np.linalg.norm(sol.W_final - W_ref)))
        assert sol.spectrum_drift().max() <= 1e-13
        assert sol.casimir_drift is not None and sol.casimir_drift.max() <= 1e-13
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(orders - 4.0) <= 0.1), orders


def test_fewer_iterations_and_smaller_errors_on_the_papers_generalized_rigid_body() -> None:
    """Measured: gauss4 at h = 1 over t = 20, 26.2 -> 9.2 updates per step, energy error
    1.7e-8 -> 5e-15; at h = 2 the unshifted iteration diverges, the shifted one reaches
    1.2e-12 (``docs/choosing.md``)."""
    grb, W0 = _paper_grb()
    scheme = lf.schemes.get("gauss4")
    kw = {"t_final": 20.0, "engine": "numpy"}
    plain = lf.integrate(grb, scheme, W0, h=1.0, **kw)  # type: ignore[arg-type]
    shift = lf.integrate(grb, scheme, W0, h=1.0, casimir_shift="auto", **kw)  # type: ignore[arg-type]
    assert shift.iterations.mean() < 0.5 * plain.iterations.mean()
    assert plain.energy_error is not None and shift.energy_error is not None
    assert plain.energy_error.max() > 1e-9 and shift.energy_error.max() < 1e-13
    with pytest.raises(lf.ConvergenceError):
        lf.integrate(grb, scheme, W0, h=2.0, **kw)  # type: ignore[arg-type]
    big = lf.integrate(grb, scheme, W0, h=2.0, casimir_shift="auto", **kw)  # type: ignore[arg-type]
    assert big.energy_error is not None and big.energy_error.max() < 1e-11
    # the same trajectory: the shifted and unshifted runs agree to the schemes' accuracy
    assert np.linalg.norm(shift.W_final - plain.W_final) < 1e-4 * np.linalg.norm(W0)


def test_compiled_engine_runs_the_shift_and_agrees_with_numpy() -> None:
    pytest.importorskip("numba")
    grb, W0 = _paper_grb()
    scheme = lf.schemes.get("gauss3")
    a = lf.integrate(grb, scheme, W0, h=1.0, steps=20, casimir_shift="auto", engine="numpy")
    b = lf.integrate(grb, scheme, W0, h=1.0, steps=20, casimir_shift="auto", engine="compiled")
    np.testing.assert_array_equal(a.iterations, b.iterations)
    assert np.max(np.abs(a.W - b.W)) <= 1e-13


def test_zero_shift_is_the_unshifted_scheme_bit_for_bit() -> None:
    grb, W0 = _paper_grb()
    scheme = lf.schemes.get("gauss2")
    a = lf.integrate(grb, scheme, W0, h=0.5, steps=10, engine="numpy")
    b = lf.integrate(grb, scheme, W0, h=0.5, steps=10, engine="numpy", casimir_shift=0.0)
    np.testing.assert_array_equal(a.W, b.W)


def test_a_flow_takes_no_shift() -> None:
    grb, W0 = _paper_grb()
    flow = lf.SchemeFlow(grb, lf.schemes.get("midpoint"))
    with pytest.raises(lf.InputError, match="casimir_shift configure a Scheme"):
        lf.integrate(grb, flow, W0, h=0.1, steps=2, casimir_shift="auto")
    # ... but a SchemeFlow may step a shifted system itself
    sh = CasimirShifted(grb, casimir_shift(grb, W0))
    sol = lf.integrate(grb, lf.SchemeFlow(sh, lf.schemes.get("midpoint")), W0, h=0.1, steps=2)
    ref = lf.integrate(grb, lf.schemes.get("midpoint"), W0, h=0.1, steps=2, engine="numpy",
                       casimir_shift="auto")  # fmt: skip
    np.testing.assert_array_equal(sol.W, ref.W)


def test_streamed_run_resumes_bit_for_bit_and_refuses_another_shift(tmp_path) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("h5py")
    grb, W0 = _paper_grb()
    scheme = lf.schemes.get("gauss3")
    kw = {"h": 1.0, "casimir_shift": "auto", "engine": "numpy", "save_every": 5}
    whole = lf.integrate(grb, scheme, W0, steps=20, out=tmp_path / "a.h5", **kw)  # type: ignore[arg-type]
    lf.integrate(grb, scheme, W0, steps=10, out=tmp_path / "b.h5", **kw)  # type: ignore[arg-type]
    resumed = lf.integrate(grb, scheme, W0, steps=20, out=tmp_path / "b.h5", resume=True, **kw)  # type: ignore[arg-type]
    np.testing.assert_array_equal(whole.W_final, resumed.W_final)
    with pytest.raises(lf.LieflowError, match="casimir_shift"):
        lf.integrate(grb, scheme, W0, steps=30, out=tmp_path / "b.h5", resume=True,
                     **{**kw, "casimir_shift": 0.0})  # type: ignore[arg-type]  # fmt: skip


def test_config_key(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from lieflow.app.config import ConfigError, build, parse_config

    text = """
[system]
name = "generalized_rigid_body"

[initial]
random = true
seed = 1

[scheme]
name = "gauss2"

[run]
h = 0.5
steps = 4
casimir_shift = "{value}"
"""
    cfg = parse_config(text.replace('"{value}"', '"auto"'), base_dir=tmp_path)
    assert cfg.run.casimir_shift == "auto" and '"casimir_shift": "auto"' in cfg.identity()
    setup = build(cfg)
    flow = setup.flow()
    assert isinstance(flow.system, CasimirShifted)  # type: ignore[attr-defined]
    assert flow.system.c == casimir_shift(setup.system, setup.W0)  # type: ignore[attr-defined]
    assert (
        parse_config(text.replace('"{value}"', "-0.25"), base_dir=tmp_path).run.casimir_shift
        == -0.25
    )
    plain = parse_config(text.replace('casimir_shift = "{value}"\n', ""), base_dir=tmp_path)
    assert plain.run.casimir_shift == 0.0 and "casimir_shift" not in plain.identity()
    with pytest.raises(ConfigError, match=r'\[run\] casimir_shift: expected "auto" or a number'):
        parse_config(text.replace("{value}", "yes"), base_dir=tmp_path)
