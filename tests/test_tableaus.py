from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

import lieflow as lf
from lieflow import tableaus as T

S3, S15 = np.sqrt(3.0), np.sqrt(15.0)
CLOSED = {
    1: ([[0.5]], [1.0]),
    2: ([[0.25, 0.25 - S3 / 6], [0.25 + S3 / 6, 0.25]], [0.5, 0.5]),
    3: (
        [
            [5 / 36, 2 / 9 - S15 / 15, 5 / 36 - S15 / 30],
            [5 / 36 + S15 / 24, 2 / 9, 5 / 36 - S15 / 24],
            [5 / 36 + S15 / 30, 2 / 9 + S15 / 15, 5 / 36],
        ],
        [5 / 18, 4 / 9, 5 / 18],
    ),
}


@pytest.mark.parametrize("s", [1, 2, 3])
def test_gauss_matches_closed_forms(s: int) -> None:
    A, b = CLOSED[s]
    tab = T.gauss(s)
    np.testing.assert_allclose(tab.A, A, rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(tab.b, b, rtol=0, atol=2.3e-16)
    assert tab.order == 2 * s


@pytest.mark.parametrize("s", [1, 2, 3, 4, 5, 6])
def test_gauss_order_conditions(s: int) -> None:
    """B(2s): sum b c^(k-1) = 1/k, k <= 2s; C(s): sum_j a_ij c_j^(k-1) = c_i^k / k, k <= s."""
    tab = T.gauss(s)
    for k in range(1, 2 * s + 1):
        assert tab.b @ tab.c ** (k - 1) == pytest.approx(1 / k, abs=1e-15)
    for k in range(1, s + 1):
        np.testing.assert_allclose(tab.A @ tab.c ** (k - 1), tab.c**k / k, atol=1e-15)
    assert tab.is_symplectic()


def test_compositions() -> None:
    x = 1 / (2 - 2 ** (1 / 3))
    np.testing.assert_allclose(T.triple_jump().b, [x, 1 - 2 * x, x], rtol=1e-15)
    p = 1 / (4 - 4 ** (1 / 3))
    np.testing.assert_allclose(T.suzuki5().b, [p, p, 1 - 4 * p, p, p], rtol=1e-15)
    y = T.yoshida6()
    assert y.b[3] == pytest.approx(1.31518632068391121888424972824, rel=1e-15)
    for tab in (T.triple_jump(), T.suzuki5(), y, T.midpoint()):
        assert tab.is_symplectic() and tab.is_diagonally_implicit
        assert tab.b.sum() == pytest.approx(1.0, abs=1e-15)


def test_tableau_is_immutable() -> None:
    tab = T.gauss(2)
    with pytest.raises(ValueError):
        tab.A[0, 0] = 1.0


def test_non_symplectic_tableau_is_refused() -> None:
    radau = T.radau_iia2()
    assert not radau.is_symplectic()
    assert float(Fraction(5, 12)) == radau.A[0, 0]
    with pytest.raises(lf.TableauError, match="not symplectic"):
        lf.schemes.BlockGauss(radau)
    with pytest.raises(lf.TableauError, match="not symplectic"):
        lf.schemes.ModinViviani(radau)
    with pytest.raises(lf.TableauError, match="not a composition"):
        lf.schemes.SyDIRK(T.gauss(2))


def test_malformed_tableaus() -> None:
    with pytest.raises(lf.TableauError, match="consistent"):
        lf.ButcherTableau(A=[[0.5]], b=[0.9], order=1, name="bad")
    with pytest.raises(lf.TableauError, match="s×s"):
        lf.ButcherTableau(A=[[0.5, 0.0]], b=[1.0], order=1, name="bad")
    with pytest.raises(lf.TableauError):
        T.gauss(0)


def test_named_tableaus_are_built_once_and_cannot_be_changed() -> None:
    """The named tableaus are values: one object per name (built once, its order checked
    once), whose arrays nobody can write into."""
    for make in (T.midpoint, T.triple_jump, lambda: T.gauss(3)):
        t = make()
        assert make() is t
        for arr in (t.A, t.b, t.c):
            with pytest.raises(ValueError, match="read-only"):
                arr[0] = 0.0
