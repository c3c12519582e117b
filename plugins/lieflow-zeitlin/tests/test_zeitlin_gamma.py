r"""Total angular momentum, ``γ = ‖L‖/√C₂`` and random initial vorticity with a prescribed
``γ`` (:mod:`lieflow_zeitlin.momentum`).

Checked against facts computed without the module's formulas: ``L_a = ∫ x_a ω dΩ`` and
``C₂ = ∫ ω² dΩ`` by the quadrature of a latitude–longitude grid, the closed form
``γ = √(4π/3)`` of any solid-body rotation (a flipped or rescaled convention — ``½∫ω²``,
``‖W‖_F²`` without ``4π/N``, the wrong spin matrix — changes it), ``γ = 0`` without degree 1,
conservation of ``L`` by the flow, and the change to the frame that turns with the
solid-body part.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import lieflow as lf

lz = pytest.importorskip("lieflow_zeitlin")

from lieflow_zeitlin.laplacian import spin_matrices  # noqa: E402


def _grid_fields(N: int) -> tuple[lz.SphereGrid, np.ndarray]:
    """A grid exact for degree ``< N`` (and products of two such fields) and ``x, y, z`` on it."""
    grid = lz.SphereGrid.for_size(N, oversample=2)
    th, ph = grid.theta[:, None], grid.phi[None, :]
    xyz = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th) + 0 * ph])
    return grid, xyz


@pytest.mark.parametrize("a", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (0.3, -2, 0.5)])
def test_solid_body_rotation_has_the_closed_form_gamma(a: tuple[float, float, float]) -> None:
    N = 12
    grid, xyz = _grid_fields(N)
    b = np.asarray(a)
    W = lz.grid_to_matrix(np.einsum("a,ajk->jk", b, xyz), grid, N)
    np.testing.assert_allclose(lz.angular_momentum(W), (4 * math.pi / 3) * b, atol=1e-13)
    assert lz.gamma(W) == pytest.approx(math.sqrt(4 * math.pi / 3), rel=1e-13)
    assert lz.GAMMA_MAX == pytest.approx(2.0466534158929770, rel=1e-15)
    np.testing.assert_allclose(lz.solid_body_rotation(W), b / 2, atol=1e-13)  # ω = 2Ω·x


def test_momentum_and_enstrophy_equal_the_grid_integrals() -> None:
    """For a random field of every degree: ``∫ x_a ω dΩ`` and ``∫ ω² dΩ`` by quadrature."""
    N = 16
    grid, xyz = _grid_fields(N)
    W = lz.random_vorticity(N, degree=N - 1, seed=3) + 0.7j * lz.hbar(N) * spin_matrices(N)[0]
    f = lz.matrix_to_grid(W, grid)
    L = grid.integrate(xyz * f)
    np.testing.assert_allclose(lz.angular_momentum(W), L, rtol=1e-12, atol=1e-13)
    assert lz.enstrophy_integral(W) == pytest.approx(grid.integrate(f * f), rel=1e-12)
    assert lz.gamma(W) == pytest.approx(np.linalg.norm(L) / math.sqrt(grid.integrate(f * f)))


def test_a_field_without_degree_one_has_gamma_zero() -> None:
    N = 20
    coeffs = lz.random_sh(N, 9, seed=5)
    l, _ = lz.degrees_and_orders(N)
    coeffs[l == 1] = 0
    W = lz.sh_to_matrix(coeffs)
    assert lz.gamma(W) < 1e-15
    coeffs[l == 1] = lz.random_sh(N, 1, seed=6)[l == 1]  # any degree-1 part: gamma > 0
    assert lz.gamma(lz.sh_to_matrix(coeffs)) > 1e-3


def test_gamma_of_a_stack_and_of_zero() -> None:
    W = np.stack([lz.random_vorticity_gamma(10, g, seed=1, degrees=(2, 5)) for g in (0.2, 1.4)])
    np.testing.assert_allclose(lz.gamma(W), [0.2, 1.4], rtol=1e-13)
    with pytest.raises(lf.InputError, match="fluid at rest"):
        lz.gamma(np.zeros((4, 4), complex))


@pytest.mark.parametrize("target", [0.0, 0.05, 0.6, 1.3, 2.0, lz.GAMMA_MAX])
def test_random_vorticity_has_the_prescribed_gamma_and_enstrophy(target: float) -> None:
    N = 24
    W = lz.random_vorticity_gamma(N, target, seed=11, degrees=(3, 8), rms=0.7)
    assert lz.gamma(W) == pytest.approx(target, rel=1e-12, abs=1e-14)
    assert lz.enstrophy_integral(W) == pytest.approx(4 * math.pi * 0.7**2, rel=1e-13)
    assert np.abs(W + W.conj().T).max() == 0.0
    assert abs(np.trace(W)) < 1e-14
    l, _ = lz.degrees_and_orders(N)
    c = lz.matrix_to_sh(W)
    outside = (l != 1) & ((l < 3) | (l > 8))
    assert np.abs(c[outside]).max() < 1e-13  # degree 1 and the band 3..8 only
    rest = (l >= 3) & (l <= 8)
    if target < lz.GAMMA_MAX:
        assert np.all(np.abs(c[rest]) > 0)


def test_random_vorticity_is_reproducible_and_paired_across_gamma() -> None:
    N = 16
    a = lz.random_vorticity_gamma(N, 0.5, seed=4)
    assert np.array_equal(a, lz.random_vorticity_gamma(N, 0.5, seed=4))
    assert not np.allclose(a, lz.random_vorticity_gamma(N, 0.5, seed=5))
    b = lz.random_vorticity_gamma(N, 1.5, seed=4)
    # one seed: the same axis and the same shape of the rest, in other proportions
    La, Lb = lz.angular_momentum(a), lz.angular_momentum(b)
    np.testing.assert_allclose(La / np.linalg.norm(La), Lb / np.linalg.norm(Lb), atol=1e-13)
    l, _ = lz.degrees_and_orders(N)
    ca, cb = lz.matrix_to_sh(a)[l >= 2], lz.matrix_to_sh(b)[l >= 2]
    share = math.sqrt((1 - (1.5 / lz.GAMMA_MAX) ** 2) / (1 - (0.5 / lz.GAMMA_MAX) ** 2))
    np.testing.assert_allclose(cb, share * ca, atol=1e-14)
    # the axis can be chosen without changing the rest
    z = lz.random_vorticity_gamma(N, 0.5, seed=4, axis=(0, 0, 3))
    np.testing.assert_allclose(lz.angular_momentum(z)[:2], 0, atol=1e-14)
    np.testing.assert_allclose(lz.matrix_to_sh(z)[l >= 2], ca, atol=1e-14)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gamma": 2.1}, "gamma must be in"),
        ({"gamma": -0.1}, "gamma must be in"),
        ({"gamma": math.nan}, "gamma must be in"),
        ({"gamma": 0.5, "degrees": (1, 5)}, "degrees must be"),
        ({"gamma": 0.5, "degrees": (4, 3)}, "degrees must be"),
        ({"gamma": 0.5, "degrees": (2, 16)}, "degrees must be"),
        ({"gamma": 0.5, "rms": 0.0}, "rms must be"),
        ({"gamma": 0.5, "axis": (0, 0, 0)}, "axis must be"),
    ],
)
def test_random_vorticity_refuses_bad_input(kwargs: dict, match: str) -> None:
    with pytest.raises(lf.InputError, match=match):
        lz.random_vorticity_gamma(16, seed=0, **kwargs)


def test_the_flow_conserves_angular_momentum() -> None:
    """Isospectral midpoint steps keep ``L`` (Zeitlin's SU(2) momentum map) to roundoff."""
    N = 16
    W0 = lz.random_vorticity_gamma(N, 0.8, seed=2, degrees=(2, 6))
    system = lf.systems.get("euler_zeitlin", N=N)
    sol = lf.integrate(system, lf.schemes.get("midpoint"), W0, h=0.02, steps=200,
                       solver=lf.solvers.FixedPoint(rtol=1e-14), save_every=50)  # fmt: skip
    L = lz.angular_momentum(sol.W)
    np.testing.assert_allclose(L, np.broadcast_to(L[0], L.shape), rtol=0, atol=1e-13)
    assert not np.allclose(sol.W[-1], W0, atol=1e-3)  # the flow did move


def test_the_rotating_frame_of_the_solid_body_part() -> None:
    """With ``L`` along ``z``, the same flow seen from the frame that turns at
    ``Ω = solid_body_rotation(W)_z`` is ``EulerZeitlin(rotation=Ω)``:
    ``V(t) = e^{iΩt S_3} W(t) e^{-iΩt S_3}`` (a wrong sign of ``Ω`` misses by O(1))."""
    N, T = 12, 2.0
    W0 = lz.random_vorticity_gamma(N, 1.2, seed=7, degrees=(2, 5), axis=(0, 0, 1))
    omega = float(lz.solid_body_rotation(W0)[2])
    assert omega > 0.3
    turning = lf.systems.get("euler_zeitlin", N=N, rotation=omega)
    # in that frame the stream matrix has no solid-body part
    assert np.abs(lz.angular_momentum(turning.B(W0))).max() < 1e-12
    kwargs = dict(h=0.01, steps=200, solver=lf.solvers.FixedPoint(rtol=1e-14))
    gauss = lf.schemes.get("gauss2")
    W = lf.integrate(lf.systems.get("euler_zeitlin", N=N), gauss, W0, **kwargs).W_final
    V = lf.integrate(turning, gauss, W0, **kwargs).W_final
    phase = np.exp(1j * omega * T * np.diag(spin_matrices(N)[2]).real)
    turned = phase[:, None] * W * phase.conj()[None, :]
    assert np.abs(V - turned).max() < 1e-7 * np.abs(W).max()
    assert np.abs(W - V).max() > 0.1 * np.abs(W).max()  # the frames do differ
