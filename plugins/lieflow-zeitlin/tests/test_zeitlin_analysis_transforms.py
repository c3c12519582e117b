"""Fast transforms of lieflow-zeitlin (issue 17.1): spherical harmonics ↔ matrix ↔ grid by
three-term recurrences, O(N²) memory.

Checked against exact facts, not against the recurrences themselves: the quantized
coordinate functions ``Q(x_a) = iħ S_a`` (exact), ``Δ_N T_lm = -l(l+1) T_lm``, the
Condon–Shortley ladder ``[S_-, T_lm] = sqrt((l+m)(l-m+1)) T_{l,m-1}`` and
``T_ll ∝ (-1)^l S_+^l`` (the sign rules) at N up to 1024, Frobenius isometry, scipy's
spherical harmonics at random points; and against the eigensolver transforms
(``method="reference"``) at small and moderate N. Round trips at N = 1024 are ``slow``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

lz = pytest.importorskip("lieflow_zeitlin")

from lieflow_zeitlin import _recurrences as rec  # noqa: E402
from lieflow_zeitlin.laplacian import harmonics, spin_matrices  # noqa: E402

import lieflow as lf  # noqa: E402


def _single(N: int, l: int, m: int) -> np.ndarray:
    c = np.zeros(N * N, complex)
    c[lz.lm_index(l, m)] = 1.0
    return c


def _harmonic(N: int, l: int, m: int) -> np.ndarray:
    """``T_lm`` read off ``sh_to_matrix`` (``Q(Y_lm) = iκ T_lm``)."""
    return (lz.sh_to_matrix(_single(N, l, m)) / (1j * lz.kappa(N))).real


def _sparse_S(N: int) -> tuple[np.ndarray, np.ndarray]:
    """Diagonals of ``S_3`` and the lower ``S_+`` (``(S_+)_{i,i-1} = sqrt(i(N-i))``)."""
    i = np.arange(N)
    return i - (N - 1) / 2, np.sqrt(i[1:] * (N - i[1:]))


def _ladder_down(T: np.ndarray) -> np.ndarray:
    """``[S_-, T]`` with ``S_- = S_+^T`` (upper), in O(N²)."""
    N = T.shape[0]
    _, sp = _sparse_S(N)
    SmT = np.zeros_like(T)
    SmT[:-1] = sp[:, None] * T[1:]  # (S_- T)_{j-1,:} = sqrt(j(N-j)) T_{j,:}
    TSm = np.zeros_like(T)
    TSm[:, 1:] = T[:, :-1] * sp[None, :]  # (T S_-)_{:,j} = T_{:,j-1} sqrt(j(N-j))
    return SmT - TSm


# ------------------------------------------------------------------ the basis itself
@pytest.mark.parametrize("N", [2, 3, 4, 5, 9, 16, 33, 64, 128])
@pytest.mark.parametrize("compiled", [True, False])
def test_recurrence_basis_equals_the_eigensolver_basis(N: int, compiled: bool) -> None:
    if compiled and not rec.have_numba():
        pytest.skip("numba not installed")
    worst = 0.0
    for (m, V), (m2, V2) in zip(
        harmonics(N), rec.harmonics_by_recurrence(N, compiled=compiled), strict=True
    ):
        assert m == m2
        worst = max(worst, float(np.abs(V - V2).max()))
    assert worst < 5e-14 * max(1, N / 16)  # measured 8.2e-15 at N = 64


@pytest.mark.parametrize("N", [256, pytest.param(1024, marks=pytest.mark.slow)])
def test_recurrence_basis_is_orthogonal(N: int) -> None:
    for m in [0, 1, N // 8, N // 2, N - 3, N - 1]:
        Vt, k1, sf, sb = rec.harmonic_diagonal(N, m)
        n = N - m
        V = Vt[:n].T.copy()
        V[:, :k1] *= sf[:, None]
        V[:, k1:] *= sb[:, None]
        assert np.isfinite(V).all()
        assert np.abs(V.T @ V - np.eye(n)).max() < 2e-13  # measured 9.8e-14 at N = 1024


@pytest.mark.parametrize("N", [5, 64, 256, pytest.param(1024, marks=pytest.mark.slow)])
def test_degree_one_fields_are_the_spin_matrices_exactly(N: int) -> None:
    """``z = sqrt(4π/3) Y_10`` and ``x + iy = -sqrt(8π/3) Y_11``: ``Q(z) = iħS_3`` and
    ``Q(x + iy) = iħ S_+`` (lower), the orientation at every N."""
    hb = lz.hbar(N)
    s3, sp = _sparse_S(N)
    c = np.zeros((2, N * N), complex)
    c[0, lz.lm_index(1, 0)] = math.sqrt(4 * math.pi / 3)
    c[1, lz.lm_index(1, 1)] = -math.sqrt(8 * math.pi / 3)  # Y_11 alone: x + iy, not real
    W = lz.sh_to_matrix(c)
    assert np.abs(W[0] - np.diag(1j * hb * s3)).max() < 1e-13
    expected = np.zeros((N, N), complex)
    expected[np.arange(1, N), np.arange(N - 1)] = 1j * hb * sp
    assert np.abs(W[1] - expected).max() < 1e-13


@pytest.mark.parametrize(
    "N, pairs",
    [
        (64, [(5, 3), (40, 40), (63, 0), (63, 62), (30, 1)]),
        (256, [(7, 7), (200, 150), (255, 1), (255, 254), (128, 64)]),
        pytest.param(
            1024, [(3, 2), (700, 500), (1023, 1), (1023, 1000), (512, 300)], marks=pytest.mark.slow
        ),
    ],
)
def test_harmonics_obey_the_laplacian_and_the_condon_shortley_ladder(
    N: int, pairs: list[tuple[int, int]]
) -> None:
    lap = lz.HoppeYauLaplacian(N)
    for l, m in pairs:
        T = _harmonic(N, l, m)
        Tm = _harmonic(N, l, m - 1)
        assert abs(np.linalg.norm(T) - 1) < 1e-12
        assert np.abs(lap.apply(T) + l * (l + 1) * T).max() < 1e-9 * l * (l + 1)
        ladder = _ladder_down(T)
        assert np.abs(ladder - math.sqrt((l + m) * (l - m + 1)) * Tm).max() < 1e-10 * N
    # sectoral: T_ll is a positive multiple of (-1)^l S_+^l (lower diagonal l: one sign)
    for l in [1, 2, N // 3, N - 1]:
        d = np.diagonal(_harmonic(N, l, l), offset=-l)
        big = np.abs(d) > 1e-300
        assert np.all(np.sign(d[big]) == (-1) ** l)


# ------------------------------------------------------------------ transforms
@pytest.mark.parametrize("N", [2, 3, 7, 16, 45, 128])
def test_transforms_match_the_reference_transforms(N: int) -> None:
    rng = np.random.default_rng(N)
    c = np.stack([lz.random_sh(N, N - 1, seed=s) for s in range(3)]).reshape(3, 1, N * N)
    grid = lz.SphereGrid.for_size(N, "equiangular")
    W = lz.sh_to_matrix(c)
    assert W.shape == (3, 1, N, N)
    assert np.abs(W - lz.sh_to_matrix(c, method="reference")).max() < 1e-14 * N
    X = rng.standard_normal((2, N, N)) + 1j * rng.standard_normal((2, N, N))
    assert np.abs(lz.matrix_to_sh(X) - lz.matrix_to_sh(X, method="reference")).max() < 2e-14 * N
    f = lz.sh_to_grid(c, grid)
    assert f.shape == (3, 1, grid.nlat, grid.nlon)
    assert np.abs(f - lz.sh_to_grid(c, grid, method="reference")).max() < 1e-13 * N
    back = lz.grid_to_sh(f, grid, N)
    assert np.abs(back - lz.grid_to_sh(f, grid, N, method="reference")).max() < 1e-14 * N
    assert np.abs(back - c).max() < 1e-14 * N


def test_sh_to_grid_is_scipys_spherical_harmonics() -> None:
    from scipy.special import sph_harm_y

    N = 40
    c = lz.random_sh(N, N - 1, seed=3)
    grid = lz.SphereGrid(7, 11, "equiangular")  # coarse: evaluation is exact on any grid
    f = lz.sh_to_grid(c, grid)
    l, m = lz.degrees_and_orders(N)
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    Y = sph_harm_y(l[:, None, None], m[:, None, None], theta[None], phi[None])
    assert np.abs(f - np.einsum("k,kjl->jl", c, Y).real).max() < 1e-12


@pytest.mark.parametrize("many", [False, True])
def test_batched_transforms_fused_and_blas_agree(many: bool) -> None:
    """Up to 4 fields run fused with the compiled recurrence, more through the basis and
    BLAS: both give every field's own transform."""
    N = 24
    K = 6 if many else 2
    c = np.stack([lz.random_sh(N, N - 1, seed=s) for s in range(K)])
    grid = lz.SphereGrid.for_size(N)
    W = lz.sh_to_matrix(c)
    f = lz.sh_to_grid(c, grid)
    for k in range(K):
        assert np.abs(W[k] - lz.sh_to_matrix(c[k])).max() < 1e-14
        assert np.abs(f[k] - lz.sh_to_grid(c[k], grid)).max() < 1e-13
    assert np.abs(lz.matrix_to_sh(W) - c).max() < 1e-14
    assert np.abs(lz.grid_to_sh(f, grid, N) - c).max() < 5e-14


def test_frobenius_isometry_and_skew_hermitian() -> None:
    N = 200
    c = lz.random_sh(N, N - 1, seed=5)
    W = lz.sh_to_matrix(c)
    assert np.abs(W + W.conj().T).max() < 1e-15
    assert abs(np.linalg.norm(W) ** 2 - N / (4 * math.pi) * np.sum(np.abs(c) ** 2)) < 1e-12


@pytest.mark.parametrize(
    "N",
    [256, pytest.param(512, marks=pytest.mark.slow), pytest.param(1024, marks=pytest.mark.slow)],
)
def test_round_trips(N: int) -> None:
    c = lz.random_sh(N, N - 1, seed=0)
    W = lz.sh_to_matrix(c)
    assert np.abs(lz.matrix_to_sh(W) - c).max() < 1e-13 * np.abs(c).max() * N / 64
    grid = lz.SphereGrid.for_size(N)
    f = lz.sh_to_grid(c, grid)
    back = lz.grid_to_sh(f, grid, N)
    # relative to the field: the Gauss nodes carry ~1e-13 N of error (measured 4.6e-11 of
    # max|ω| at N = 1024; the scipy transforms give the same)
    assert np.linalg.norm(back - c) < 1e-12 * np.linalg.norm(c) * N / 64
    W2 = lz.grid_to_matrix(lz.matrix_to_grid(W, grid), grid, N)
    # measured 5.6e-11 of max|W| at N = 1024, 8.8e-12 at 512: the Gauss nodes again
    assert np.abs(W2 - W).max() < 1e-16 * N**2 * np.abs(W).max()


def test_method_is_checked() -> None:
    with pytest.raises(lf.InputError, match="method"):
        lz.sh_to_matrix(np.zeros(4), method="fast")  # type: ignore[arg-type]
    with pytest.raises(lf.InputError, match="N <= 1400"):
        lz.matrix_to_sh(np.zeros((1500, 1500)), method="recurrence")


def test_spin_matrices_helper_agrees() -> None:
    S1, S2, S3 = spin_matrices(6)
    s3, sp = _sparse_S(6)
    assert np.allclose(np.diag(S3), s3) and np.allclose(np.diagonal(S1 + 1j * S2, -1), sp)


def test_transforms_without_numba(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without numba the same recurrences run as numpy row operations (basis, then BLAS)."""
    monkeypatch.setattr(rec, "have_numba", lambda: False)
    N = 40
    c = np.stack([lz.random_sh(N, N - 1, seed=s) for s in range(2)])
    grid = lz.SphereGrid.for_size(N)
    W = lz.sh_to_matrix(c)
    assert np.abs(W - lz.sh_to_matrix(c, method="reference")).max() < 1e-13
    assert np.abs(lz.matrix_to_sh(W) - c).max() < 1e-13
    f = lz.sh_to_grid(c, grid)
    assert np.abs(f - lz.sh_to_grid(c, grid, method="reference")).max() < 1e-12
    assert np.abs(lz.grid_to_sh(f, grid, N) - c).max() < 1e-13


@pytest.mark.parametrize("cache_max_n", [512, 8])
def test_degree_multiplier_cached_and_generated(
    cache_max_n: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The exact dissipative sub-steps multiply degree l by g[l]: with the cached eigenbasis
    (N <= 512) and with the basis generated per call (larger N, O(N²) memory)."""
    from lieflow_zeitlin import dissipation

    monkeypatch.setattr(dissipation, "CACHE_MAX_N", cache_max_n)
    N = 16
    c = lz.random_sh(N, N - 1, seed=6)
    g = np.exp(-0.3 * np.arange(N))
    out = lz.degree_multiplier(lz.sh_to_matrix(c), g)
    l, _ = lz.degrees_and_orders(N)
    assert np.abs(lz.matrix_to_sh(out) - g[l] * c).max() < 1e-15
