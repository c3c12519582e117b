"""The same tableau through the block algorithm (block and reduced forms) and the classic
Modin–Viviani form gives the same step; SyDIRK agrees with the block algorithm on its DIRK
tableau; every solver finds the same solution."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import HermitianBody, tight

import lieflow as lf
from lieflow import tableaus as T
from lieflow.schemes import BlockGauss, ModinViviani, SyDIRK

TABLEAUS = [T.gauss(1), T.gauss(2), T.gauss(3), T.triple_jump()]


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("tab", TABLEAUS, ids=lambda t: t.name)
def test_three_formulations_agree(system: lf.IsospectralSystem, tab: lf.ButcherTableau) -> None:
    W0 = system.random_state(seed=5)
    h = 0.1
    ref = BlockGauss(tab, form="reduced").step(W0, h, system, tight()).W
    assert _rel(BlockGauss(tab, form="block").step(W0, h, system, tight()).W, ref) <= 1e-13
    assert _rel(ModinViviani(tab).step(W0, h, system, tight()).W, ref) <= 1e-13
    if tab.is_diagonally_implicit:
        assert _rel(SyDIRK(tab).step(W0, h, system, tight()).W, ref) <= 1e-13


SOLVERS = [
    lf.solvers.FixedPoint(rtol=1e-15),
    lf.solvers.FixedPoint(rtol=1e-15, anderson=3),
    lf.solvers.Newton(rtol=1e-15),
    lf.solvers.Newton(rtol=1e-15, linear="gmres"),
    lf.solvers.FrozenB(rtol=1e-15),
    lf.solvers.Auto(),
]


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: repr(s)[:40])
@pytest.mark.parametrize(
    "name", ["midpoint", "gauss2", "gauss3", "sydirk7", "block", "modin_viviani"]
)
def test_all_solvers_agree(system: lf.IsospectralSystem, name: str, solver: lf.Solver) -> None:
    scheme = lf.schemes.get(name)
    W0 = system.random_state(seed=2)
    ref = scheme.step(W0, 0.1, system, tight()).W
    assert _rel(scheme.step(W0, 0.1, system, solver).W, ref) <= 1e-12


@pytest.mark.parametrize("name", ["midpoint", "gauss3", "modin_viviani"])
def test_complex_system_through_every_solver(name: str) -> None:
    system = HermitianBody(3)
    W0 = system.random_state(seed=1)
    scheme = lf.schemes.get(name)
    ref = scheme.step(W0, 0.2, system, tight()).W
    for solver in SOLVERS:
        assert _rel(scheme.step(W0, 0.2, system, solver).W, ref) <= 1e-12
