"""The step size a diverging fixed point suggests (issue 34, item 2): estimated from the state as
``1 / (ρ(A) s)`` (:mod:`lieflow.schemes.contraction`), it must be right within a factor of
two on both sides — twice it fails, half of it converges — for the Euler–Zeitlin field whose
contraction grows with N."""

from __future__ import annotations

import re

import numpy as np
import pytest

import lieflow as lf
from lieflow.schemes import contraction

lz = pytest.importorskip("lieflow_zeitlin")


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2"])
def test_the_suggested_step_size_converges_and_twice_the_limit_does_not(scheme: str) -> None:
    N = 64
    system = lz.EulerZeitlin(N)
    W0 = lz.random_vorticity(N, degree=8, seed=N)
    limit = contraction.step_size_limit(system, lf.schemes.get(scheme), W0)
    assert limit is not None
    h_max, rho, s = limit
    # the spread of B's eigenvalues, independently: B = P = Q(ψ) is skew-Hermitian
    ev = np.linalg.eigvalsh(1j * system.B(W0))
    assert s == pytest.approx(ev[-1] - ev[0], rel=1e-12)
    assert rho == pytest.approx(0.5 if scheme == "midpoint" else 1 / np.sqrt(12), rel=1e-12)
    solver = lf.solvers.FixedPoint(rtol=1e-13, max_iter=300)
    with pytest.raises(lf.ConvergenceError) as failed:
        lf.integrate(system, lf.schemes.get(scheme), W0, h=2 * h_max, steps=2, solver=solver,
                     engine="numpy")  # fmt: skip
    message = str(failed.value)
    assert f"converges for h below about {h_max:.3g}" in message
    suggested = float(re.search(r"try h = ([0-9.e-]+) or less", message).group(1))  # type: ignore[union-attr]
    assert h_max / 4 <= suggested <= h_max / 2
    sol = lf.integrate(system, lf.schemes.get(scheme), W0, h=h_max / 2, steps=2, solver=solver,
                       engine="numpy")  # fmt: skip
    assert sol.iterations.max() < 60
