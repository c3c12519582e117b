"""Observed order of every registered scheme within ±0.1 of theory (Gauss s = 1..4 too)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import tight

import lieflow as lf

T_FINAL = 1.0
SYSTEMS = ["rigid_body", "generalized_rigid_body", "periodic_toda"]


def _final(system: lf.IsospectralSystem, scheme: lf.Scheme, W0: np.ndarray, n: int) -> np.ndarray:
    solver = lf.solvers.Auto(tight(), lf.solvers.Newton(rtol=1e-15))
    sol = lf.integrate(
        system, scheme, W0, T_FINAL / n, steps=n, solver=solver, diagnostics=False, save_every=n
    )
    return sol.W_final


def observed_order(system: lf.IsospectralSystem, scheme: lf.Scheme) -> float:
    """``log2(e(h) / e(h/2))`` on the finest pair of step sizes whose errors lie in
    ``[1e-12, 1e-3]`` (asymptotic, yet well above roundoff), against Gauss-6 (order 12) at a
    much smaller step."""
    W0 = 2.0 * system.random_state(seed=3)
    ref = _final(system, lf.schemes.get("gauss", stages=6), W0, 128)
    ns = [1, 2, 4, 8, 16, 32, 64, 128]
    errs = []
    for n in ns:
        e = float(np.linalg.norm(_final(system, scheme, W0, n) - ref))
        errs.append(e)
        if e < 1e-11:
            break
    usable = [
        (errs[i], errs[i + 1])
        for i in range(len(errs) - 1)
        if errs[i] <= 1e-3 and errs[i + 1] >= 1e-12
    ]
    assert usable, f"no step-size pair in the asymptotic range: {errs}"
    e1, e2 = usable[-1]
    return float(np.log2(e1 / e2))


@pytest.mark.parametrize("system_name", SYSTEMS)
def test_registered_schemes_have_their_order(system_name: str, scheme: lf.Scheme) -> None:
    system = lf.systems.get(system_name)
    assert observed_order(system, scheme) == pytest.approx(scheme.order, abs=0.1)


@pytest.mark.parametrize("stages", [1, 4])
@pytest.mark.parametrize("system_name", SYSTEMS)
def test_gauss_any_stages(system_name: str, stages: int) -> None:
    scheme = lf.schemes.get("gauss", stages=stages)
    assert observed_order(lf.systems.get(system_name), scheme) == pytest.approx(2 * stages, abs=0.1)
