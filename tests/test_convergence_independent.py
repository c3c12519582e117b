"""Observed order of every registered scheme against an INDEPENDENT reference.

The reference solution is the matrix ODE ``dW/dt = [B(W), W]`` integrated by scipy's
``solve_ivp`` (DOP853, and Radau as a cross-check) at ``rtol = 1e-13``: a general-purpose,
non-structure-preserving integrator that shares no code with the schemes under test (only
the system's ``B``). The two references must agree to far below the errors used, so a
scheme that converges to the wrong solution, or at the wrong rate, fails.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import SCHEMES
from helpers import needs_vortices, plugin_param
from scipy.integrate import solve_ivp

import lieflow as lf

#: (scale of the random initial state, final time) per system
PROBLEMS = {"generalized_rigid_body": (4.0, 1.0), "point_vortices": (1.0, 4.0)}
#: largest step size tried (a single step of h = 4 is not a convergence study)
H_MAX = 1.0
#: errors below this are not used (the references agree to 4e-13, see the test below)
ERR_MIN = 1e-11
#: errors above this are not asymptotic yet
ERR_MAX = 1e-3


def _rhs(system: lf.IsospectralSystem, shape: tuple[int, ...], complex_: bool):  # type: ignore[no-untyped-def]
    def f(_t: float, y: np.ndarray) -> np.ndarray:
        W = (y[: y.size // 2] + 1j * y[y.size // 2 :]) if complex_ else y
        W = W.reshape(shape)
        B = system.B(W)
        dW = (B @ W - W @ B).ravel()
        return np.concatenate([dW.real, dW.imag]) if complex_ else dW

    return f


def reference(
    system: lf.IsospectralSystem, W0: np.ndarray, method: str, T: float = 1.0
) -> np.ndarray:
    """``W(T)`` by scipy's ``solve_ivp`` on the flattened matrix ODE."""
    complex_ = np.iscomplexobj(W0)
    y0 = np.concatenate([W0.real.ravel(), W0.imag.ravel()]) if complex_ else W0.ravel()
    sol = solve_ivp(
        _rhs(system, W0.shape, complex_),
        (0.0, T),
        y0,
        method=method,
        rtol=1e-13,
        atol=1e-15 * float(np.linalg.norm(W0)),
    )
    assert sol.success, sol.message
    y = sol.y[:, -1]
    W = y[: y.size // 2] + 1j * y[y.size // 2 :] if complex_ else y
    return np.asarray(W).reshape(W0.shape)


@functools.cache
def _problem(system_name: str) -> tuple[lf.IsospectralSystem, np.ndarray, float, np.ndarray]:
    system = lf.systems.get(system_name)
    scale, T = PROBLEMS[system_name]
    W0 = scale * system.random_state(seed=3)
    return system, W0, T, reference(system, W0, "DOP853", T)


def _final(
    system: lf.IsospectralSystem, scheme: lf.Scheme, W0: np.ndarray, T: float, n: int
) -> np.ndarray:
    solver = lf.solvers.Auto(lf.solvers.FixedPoint(rtol=1e-15), lf.solvers.Newton(rtol=1e-15))
    sol = lf.integrate(
        system, scheme, W0, T / n, steps=n, solver=solver, diagnostics=False, save_every=n
    )
    return sol.W_final


def observed_order(system_name: str, scheme: lf.Scheme) -> tuple[float, list[float]]:
    """``log2(e(h)/e(h/2))`` on the finest pair with both errors in ``[ERR_MIN, ERR_MAX]``."""
    system, W0, T, ref = _problem(system_name)
    scale = float(np.linalg.norm(ref))
    errs: list[float] = []
    for n in (1, 2, 4, 8, 16, 32, 64, 128, 256):
        if T / n > H_MAX:
            continue
        errs.append(float(np.linalg.norm(_final(system, scheme, W0, T, n) - ref)) / scale)
        if errs[-1] < ERR_MIN:
            break
    pairs = [
        (errs[i], errs[i + 1])
        for i in range(len(errs) - 1)
        if errs[i] <= ERR_MAX and errs[i + 1] >= ERR_MIN
    ]
    assert pairs, f"no step-size pair in the asymptotic range: {errs}"
    e1, e2 = pairs[-1]
    return float(np.log2(e1 / e2)), errs


@pytest.mark.parametrize("system_name", [plugin_param(name) for name in PROBLEMS])
def test_references_agree(system_name: str) -> None:
    """DOP853 and Radau (implicit, a different family) agree to 5 % of ``ERR_MIN``: an
    error of ``ERR_MIN`` is known to 5 %, its log2 to 0.07 (measured: 3e-16 for the
    generalized rigid body, 4e-13 for the vortices at T = 4)."""
    system, W0, T, ref = _problem(system_name)
    other = reference(system, W0, "Radau", T)
    assert np.linalg.norm(other - ref) / np.linalg.norm(ref) <= 5e-2 * ERR_MIN


@pytest.mark.parametrize("name", SCHEMES)
def test_order_against_independent_reference(name: str) -> None:
    scheme = lf.schemes.get(name)
    order, errs = observed_order("generalized_rigid_body", scheme)
    assert order == pytest.approx(scheme.order, abs=0.1), errs


@needs_vortices
@pytest.mark.parametrize(
    "name",
    [
        "gauss3",
        *(pytest.param(n, marks=pytest.mark.slow) for n in ("midpoint", "sydirk7", "gauss2")),
    ],
)
def test_order_nonlinear_B(name: str) -> None:
    """A nonlinear ``B`` (point vortices): same orders."""
    scheme = lf.schemes.get(name)
    order, errs = observed_order("point_vortices", scheme)
    assert order == pytest.approx(scheme.order, abs=0.1), errs


def test_a_wrong_scheme_fails() -> None:
    """The negative case: a scheme whose steps are ``h (1 + h)`` long (an O(h) error in
    the time it reaches) is measured at order 1, not 4, by the same procedure."""
    scheme = lf.schemes.get("gauss2")
    system, W0, T, ref = _problem("generalized_rigid_body")
    errs = []
    for n in (16, 32):
        W, h = W0, T / n
        for _ in range(n):
            W = scheme.step(W, h * (1.0 + h), system, lf.solvers.FixedPoint(rtol=1e-15)).W
        errs.append(float(np.linalg.norm(W - ref)))
    assert np.log2(errs[0] / errs[1]) == pytest.approx(1.0, abs=0.1)
