"""The lieflow-zeitlin plugin: Euler's equations on the sphere as the Euler–Zeitlin system.

Hoppe–Yau Laplacian (double-commutator definition, spectrum, O(N²) solve), the quantization
(round trips, harmonics, the coordinate functions), the system under every registered scheme
and solver (structure to roundoff, observed orders, complex64, warm-start iteration counts),
the pictures and ``lieflow plot`` hook, and the example configuration. Small N only (<= 16).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lieflow as lf

lz = pytest.importorskip("lieflow_zeitlin")

from lieflow_zeitlin.laplacian import spin_matrices, tridiagonal  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "euler_n128.toml"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def _random_complex(N: int, seed: int, batch: tuple[int, ...] = ()) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (*batch, N, N)
    return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)


def _tight() -> lf.solvers.FixedPoint:
    return lf.solvers.FixedPoint(rtol=1e-15)


# --------------------------------------------------------------------------- registration
def test_installing_the_plugin_registers_the_system_and_its_plotter() -> None:
    registry = lf.default_registry()
    entry = registry.entry("system", "euler_zeitlin")
    assert "lieflow-zeitlin" in entry.source
    system = lf.systems.get("euler_zeitlin", N=5)
    assert isinstance(system, lz.EulerZeitlin)
    assert isinstance(system.algebra, lf.SU) and system.algebra.n == 5
    assert system.linear_B
    assert "euler_zeitlin" in registry.plotters
    assert "lieflow-zeitlin" in registry.plotters["euler_zeitlin"].source


def test_bad_parameters_are_clear_errors() -> None:
    with pytest.raises(lf.InputError, match="N must be an integer >= 2"):
        lz.EulerZeitlin(1)
    with pytest.raises(lf.InputError, match="complex128 or complex64"):
        lz.EulerZeitlin(4, dtype="float64")
    with pytest.raises(lf.InputError, match="random_degree"):
        lz.EulerZeitlin(4, random_degree=0)
    with pytest.raises(lf.InputError, match=r"\(\.\.\., 4, 4\)"):
        lz.HoppeYauLaplacian(4).solve(np.zeros((3, 3)))


# --------------------------------------------------------------------------- Laplacian
@pytest.mark.parametrize("N", [2, 3, 4, 7, 10])
def test_laplacian_is_minus_the_double_commutator(N: int) -> None:
    S = spin_matrices(N)
    # the spin matrices: [S1, S2] = i S3 and S1² + S2² + S3² = s(s+1) I, s = (N-1)/2
    np.testing.assert_allclose(S[0] @ S[1] - S[1] @ S[0], 1j * S[2], rtol=0, atol=1e-13)
    s = (N - 1) / 2
    np.testing.assert_allclose(sum(a @ a for a in S), s * (s + 1) * np.eye(N), atol=1e-12)
    P = _random_complex(N, seed=N, batch=(2,))
    reference = -sum(a @ (a @ P - P @ a) - (a @ P - P @ a) @ a for a in S)
    assert _rel(lz.HoppeYauLaplacian(N).apply(P), reference) <= 1e-12


@pytest.mark.parametrize("N", [2, 3, 5, 8])
def test_spectrum_is_minus_l_l_plus_1_with_multiplicity_2l_plus_1(N: int) -> None:
    L = lz.HoppeYauLaplacian(N)
    basis = np.eye(N * N).reshape(N * N, N, N)
    dense = L.apply(basis).reshape(N * N, N * N).real  # real symmetric in the E_ij basis
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    eigenvalues = np.linalg.eigvalsh(dense)
    l = np.arange(N)
    expected = np.sort(np.repeat(-(l * (l + 1.0)), 2 * l + 1))
    np.testing.assert_allclose(eigenvalues, expected, rtol=0, atol=1e-11 * N * N)
    np.testing.assert_array_equal(np.sort(L.eigenvalues()), expected)
    # diagonal ±m carries exactly the degrees l = |m| .. N-1
    for m in range(N):
        d, e = tridiagonal(N, m)
        T = np.diag(d) + np.diag(e, 1) + np.diag(e, -1)
        ev = np.linalg.eigvalsh(T)
        lm = np.arange(m, N)
        np.testing.assert_allclose(ev, np.sort(-(lm * (lm + 1.0))), rtol=0, atol=1e-11 * N * N)


@pytest.mark.parametrize(("N", "block"), [(2, None), (3, 1), (5, 2), (8, None), (13, 5), (16, 16)])
def test_solve_residual(N: int, block: int | None) -> None:
    L = lz.HoppeYauLaplacian(N) if block is None else lz.HoppeYauLaplacian(N, block=block)
    white = lf.SU(N).project(_random_complex(N, seed=1, batch=(3,)))
    smooth = lz.random_vorticity(N, degree=3, seed=2)
    for W in (white, smooth):
        P = L.solve(W)
        assert P.shape == W.shape and P.dtype == np.complex128
        assert _rel(L.apply(P), W) <= 1e-12
        assert np.max(np.abs(np.trace(P, axis1=-2, axis2=-1))) <= 1e-14
        assert lf.SU(N).contains(P, tol=1e-13)
    # off su(N): the pseudo-inverse (the trace is projected out), linear, batched
    X = _random_complex(N, seed=3, batch=(2, 2))
    P = L.solve(X)
    projected = X - (np.trace(X, axis1=-2, axis2=-1) / N)[..., None, None] * np.eye(N)
    assert _rel(L.apply(P), projected) <= 1e-12
    np.testing.assert_allclose(L.solve(X[1, 0]), P[1, 0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(L.solve(2 * X - 3j * X), (2 - 3j) * P, atol=1e-12)


def test_solve_in_single_precision_and_scaled() -> None:
    N = 12
    L = lz.HoppeYauLaplacian(N)
    W = lz.random_vorticity(N, degree=6, seed=4)
    P32 = L.solve(W.astype(np.complex64))
    assert P32.dtype == np.complex64
    assert _rel(P32, L.solve(W)) <= 1e-6
    scaled = lz.HoppeYauLaplacian(N, scale=1.0 / lz.hbar(N))
    np.testing.assert_allclose(scaled.solve(W), L.solve(W) / lz.hbar(N), rtol=1e-13, atol=0)
    np.testing.assert_allclose(scaled.apply(W), L.apply(W), rtol=0, atol=0)


@pytest.mark.parametrize("N", [2, 3, 8, 17, 33])
@pytest.mark.parametrize("shift", [0.0, 3.0])
def test_compiled_sweep_gives_the_numpy_bits(
    monkeypatch: pytest.MonkeyPatch, N: int, shift: float
) -> None:
    """With numba, the partitioned Thomas sweeps run as compiled loops; they must give the
    same bits as the numpy row operations (results must not depend on numba)."""
    from lieflow_zeitlin import laplacian

    if not laplacian.have_numba():
        pytest.skip("numba is not installed")
    L = lz.HoppeYauLaplacian(N, scale=1.7, shift=shift, block=max(1, N // 3))
    for dtype in (np.complex128, np.complex64):
        X = _random_complex(N, seed=N, batch=(3,)).astype(dtype)
        compiled = L.solve(X)
        monkeypatch.setattr(laplacian, "have_numba", lambda: False)
        plain = L.solve(X)
        monkeypatch.undo()
        assert compiled.dtype == plain.dtype == dtype
        assert np.array_equal(compiled, plain)
        traceless = X - (np.trace(X, axis1=-2, axis2=-1) / N)[:, None, None] * np.eye(N)
        tol = 1e-5 if dtype == np.complex64 else 1e-12
        assert _rel(L.apply(plain), 1.7 * traceless) <= tol


@pytest.mark.parametrize("N", [5, 100])
@pytest.mark.parametrize("rotation", [0.0, 2.0])
def test_stage_B_is_B_of_the_projected_stage_bit_for_bit(N: int, rotation: float) -> None:
    """EulerZeitlin.stage_B (the projection formed in the Laplacian's buffer) returns the
    bits of B(project_stage(W)), in both precisions, for stacks and for real input."""
    system = lz.EulerZeitlin(N, rotation=rotation, lamb=0.5)
    X = _random_complex(N, seed=N, batch=(2,))
    for Y in (X, X[0], X.astype(np.complex64), X.real, np.swapaxes(X, -1, -2)):
        expected = system.B(system.project_stage(Y))
        got = system.stage_B(Y)
        assert got.dtype == expected.dtype and got.shape == expected.shape
        assert np.array_equal(got, expected)


@pytest.mark.parametrize("N", [2, 3, 17, 64, 100])
@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
def test_projection_gives_the_bits_of_su_project(
    monkeypatch: pytest.MonkeyPatch, N: int, batch: tuple[int, ...]
) -> None:
    """The system's su(N) projection (compiled skew-Hermitian part where numba is
    installed) gives lieflow.SU.project's bits, with and without numba, in both precisions;
    non-complex and non-contiguous input too."""
    from lieflow_zeitlin import projection

    system = lz.EulerZeitlin(N)
    assert system.algebra is system.algebra  # built once
    X = _random_complex(N, seed=N + len(batch), batch=batch)
    inputs = [X, X.astype(np.complex64), X.real, np.swapaxes(X, -1, -2)]
    for Y in inputs:
        expected = lf.SU(N).project(Y)
        got = system.project_stage(Y)
        assert got.dtype == expected.dtype and got.shape == expected.shape
        assert np.array_equal(got, expected)
        assert np.array_equal(system.project(Y), expected)
        monkeypatch.setattr(projection, "have_numba", lambda: False)
        assert np.array_equal(system.project_stage(Y), expected)
        monkeypatch.undo()
    # it is the projection: skew-Hermitian, traceless, and Y's own part where Y is in su(N)
    P = system.project_stage(X)
    np.testing.assert_array_equal(P, -np.conj(np.swapaxes(P, -1, -2)))
    assert np.max(np.abs(np.trace(P, axis1=-2, axis2=-1))) <= 1e-14 * N
    np.testing.assert_allclose(system.project_stage(P), P, rtol=0, atol=1e-15)


@pytest.mark.parametrize("N", [4, 33, 100])
@pytest.mark.parametrize("batch", [(), (3,)])
def test_fused_casimirs_are_the_plain_traces(
    monkeypatch: pytest.MonkeyPatch, N: int, batch: tuple[int, ...]
) -> None:
    """The Casimirs tr((iW)^k), k = 2, 3, 4, from one product and one compiled pass
    (lieflow_zeitlin.traces, numba installed) are NumPy's ``Re Σ_ij (A^a)_ij (A^b)_ji``
    up to the order of the sums, for any complex matrix (not only su(N)), a transposed
    view too, and the eigenvalue sums on su(N); the hamiltonian's one dot product is
    ``-½ Re Σ conj(W) B(W)``."""
    from lieflow_zeitlin import system as system_module

    if not system_module._rec.have_numba():
        pytest.skip("numba is not installed")
    system = lz.EulerZeitlin(N)
    X = _random_complex(N, seed=N, batch=batch)
    for Y in (X, np.swapaxes(X, -1, -2), lf.SU(N).project(X)):
        A = 1j * Y
        A2 = A @ A
        plain = np.stack(
            [np.real(np.sum(F * np.swapaxes(G, -1, -2), axis=(-2, -1))) for F, G in
             ((A, A), (A, A2), (A2, A2))],
            axis=-1,
        )  # fmt: skip
        fused = system.casimirs(Y)
        assert fused.shape == (*batch, 3)
        tol = {"rtol": 1e-13, "atol": 1e-13 * np.abs(plain).max()}
        np.testing.assert_allclose(fused, plain, **tol)
        monkeypatch.setattr(system_module._rec, "have_numba", lambda: False)
        np.testing.assert_allclose(system.casimirs(Y), plain, **tol)  # NumPy's alone
        monkeypatch.undo()
    W = lf.SU(N).project(X)
    if batch:  # states (the product by zherk) and a matrix that is not one, in one batch
        Y = W.copy()
        Y[1] = X[1]
        np.testing.assert_array_equal(system.casimirs(Y)[1], system.casimirs(X[1]))
        np.testing.assert_array_equal(system.casimirs(Y)[::2], system.casimirs(W[::2]))
    lam = np.linalg.eigvalsh(1j * W)
    expected = np.stack([np.sum(lam**k, axis=-1) for k in (2, 3, 4)], axis=-1)
    np.testing.assert_allclose(system.casimirs(W), expected, rtol=1e-12)
    H = -0.5 * np.real(np.sum(np.conj(W) * system.B(W), axis=(-2, -1)))
    np.testing.assert_allclose(system.hamiltonian(W), H, rtol=1e-13)
    np.testing.assert_allclose(system.hamiltonian(W.astype(np.complex64)), H, rtol=1e-5)


def test_split_passes_have_the_serial_bits() -> None:
    """The plugin's compiled passes split into groups (numba's threads for large states:
    lieflow.numba_cache.SplitKernel) — the su(N) projection's skew part and the Casimir
    traces by bands of rows, the Laplacian sweeps by runs of columns — give the serial
    passes' bits for any number of groups."""
    from lieflow_zeitlin import laplacian, projection, traces

    if not laplacian.have_numba():
        pytest.skip("numba is not installed")
    N = 70
    X = _random_complex(N, seed=3, batch=(2,))
    R = X.view(np.float64)
    L = lz.HoppeYauLaplacian(N)
    factor = L._double
    nb, b = factor.lower.shape[:2]
    Y = np.zeros((2, nb * b * (N + 1)), dtype=np.complex128)
    Y[:, : N * N] = X.reshape(2, -1)
    Y = Y.view(np.float64).reshape(2, nb, b, 2 * (N + 1))
    results = []
    for groups in (1, 2, 3, 7, 1000):
        part = np.empty_like(R)
        projection._skew_part_compiled(groups, R, part)
        rows = np.empty((2, 2, N, 4))
        traces._row_traces(groups, R, (X @ X).view(np.float64), rows[0], False)
        S = lf.SU(N).project(X)  # the product's lower triangle alone, read as Hermitian
        P = np.tril(S @ S)
        traces._row_traces(groups, S.view(np.float64), P.view(np.float64), rows[1], True)
        swept = Y.copy()
        sweep = laplacian.sweep_kernel("d") if groups == 1 else laplacian._sweep_split
        sweep(groups, swept, factor.compact)
        results.append((part, rows, swept))
    for got in results[1:]:
        for a, e in zip(got, results[0], strict=True):
            assert np.array_equal(a, e)


# --------------------------------------------------------------------------- quantization
@pytest.mark.parametrize("N", [2, 5, 9])
def test_quantization_round_trips(N: int) -> None:
    coeffs = lz.random_sh(N, degree=N - 1, seed=N, rms=1.3)
    W = lz.sh_to_matrix(coeffs)
    assert lf.SU(N).contains(W, tol=1e-14)  # real zero-mean field -> su(N)
    assert _rel(lz.matrix_to_sh(W), coeffs) <= 1e-13
    U = lf.U(N).project(_random_complex(N, seed=5, batch=(2,)))  # the mean (l = 0) too
    assert _rel(lz.sh_to_matrix(lz.matrix_to_sh(U)), U) <= 1e-13
    for kind in ("gauss", "equiangular"):
        grid = lz.SphereGrid.for_size(N, kind)
        f = lz.sh_to_grid(coeffs, grid)
        assert f.shape == (grid.nlat, grid.nlon)
        assert _rel(lz.grid_to_sh(f, grid, N), coeffs) <= 1e-12
        assert _rel(lz.grid_to_matrix(f, grid, N), W) <= 1e-12
        np.testing.assert_allclose(lz.matrix_to_grid(W, grid), f, atol=1e-12)
        # ∫ f² dΩ = Σ |ω_lm|² (Parseval; the quadrature is exact for degree < 2N)
        assert grid.integrate(f * f) == pytest.approx(np.sum(np.abs(coeffs) ** 2), rel=1e-12)
    with pytest.raises(lf.InputError, match="cannot resolve"):
        lz.grid_to_sh(np.zeros((2, 4)), lz.SphereGrid(2, 4), N=5)


def test_sh_to_grid_matches_scipy_spherical_harmonics() -> None:
    from scipy.special import sph_harm_y

    N = 6
    grid = lz.SphereGrid.for_size(N, "equiangular")
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    for l, m in [(0, 0), (1, 0), (1, 1), (3, 2), (5, 5)]:
        c = np.zeros(N * N, dtype=complex)
        c[lz.lm_index(l, m)] = 1.0
        c[lz.lm_index(l, -m)] = (-1.0) ** m  # f = Y_lm + (-1)^m Y_l,-m = 2 Re Y_lm (m > 0)
        expected = (2.0 if m else 1.0) * sph_harm_y(l, m, theta, phi).real
        np.testing.assert_allclose(lz.sh_to_grid(c, grid), expected, atol=1e-13)


@pytest.mark.parametrize("N", [3, 6])
def test_harmonic_of_degree_l_is_an_eigenmatrix(N: int) -> None:
    L = lz.HoppeYauLaplacian(N)
    l_all, m_all = lz.degrees_and_orders(N)
    Q = lz.sh_to_matrix(np.eye(N * N))  # Q(Y_lm), one per row; orthogonal, norm κ
    for k, (l, m) in enumerate(zip(l_all, m_all, strict=True)):
        np.testing.assert_allclose(L.apply(Q[k]), -l * (l + 1) * Q[k], rtol=0, atol=1e-12)
        T = L.harmonic(int(l), int(m))
        np.testing.assert_allclose(1j * lz.kappa(N) * T, Q[k], rtol=0, atol=1e-14)
    gram = np.einsum("aij,bij->ab", Q.conj(), Q)
    np.testing.assert_allclose(gram, lz.kappa(N) ** 2 * np.eye(N * N), atol=1e-13)


@pytest.mark.parametrize("N", [2, 5, 8])
def test_coordinate_functions_quantize_to_spin_matrices(N: int) -> None:
    r"""``Q(x_a) = iħ S_a`` (fixes κ and the Condon–Shortley signs), and
    ``(1/ħ)[Q(z), Q(g)] = -Q({z, g}) = Q(∂_φ g)`` exactly (fixes the bracket's orientation:
    ``{z, g} = -∂_φ g`` for the outward normal)."""
    S = spin_matrices(N)
    hb = lz.hbar(N)
    a = math.sqrt(2 * math.pi / 3)
    x = np.zeros((3, N * N), dtype=complex)
    x[0, lz.lm_index(1, -1)], x[0, lz.lm_index(1, 1)] = a, -a  # sin θ cos φ
    x[1, lz.lm_index(1, -1)], x[1, lz.lm_index(1, 1)] = 1j * a, 1j * a  # sin θ sin φ
    x[2, lz.lm_index(1, 0)] = math.sqrt(4 * math.pi / 3)  # cos θ
    for k in range(3):
        np.testing.assert_allclose(lz.sh_to_matrix(x[k]), 1j * hb * S[k], atol=1e-14)
    g = lz.random_sh(N, degree=N - 1, seed=6)
    _, m = lz.degrees_and_orders(N)
    Qz, Qg = lz.sh_to_matrix(x[2]), lz.sh_to_matrix(g)
    np.testing.assert_allclose(
        (Qz @ Qg - Qg @ Qz) / hb, lz.sh_to_matrix(1j * m * g), rtol=0, atol=1e-13
    )


def test_random_vorticity_is_seeded_smooth_and_in_su_n() -> None:
    N, degree, rms = 12, 4, 2.5
    W = lz.random_vorticity(N, degree, seed=7, rms=rms)
    np.testing.assert_array_equal(W, lz.random_vorticity(N, degree, seed=7, rms=rms))
    assert not np.allclose(W, lz.random_vorticity(N, degree, seed=8, rms=rms))
    np.testing.assert_array_equal(W, -W.conj().T)  # skew-Hermitian exactly
    assert abs(np.trace(W)) <= 1e-15
    c = lz.matrix_to_sh(W)
    l, _ = lz.degrees_and_orders(N)
    assert np.max(np.abs(c[(l == 0) | (l > degree)])) <= 1e-14  # band-limited, zero mean
    assert math.sqrt(np.sum(np.abs(c) ** 2) / (4 * math.pi)) == pytest.approx(rms, rel=1e-13)
    W32 = lz.random_vorticity(N, degree, seed=7, rms=rms, dtype=np.complex64)
    assert W32.dtype == np.complex64 and _rel(W32, W) <= 1e-6


def test_random_state_and_algebra_random_are_smooth() -> None:
    """The base class's ``random_state`` (unit Frobenius norm) draws from the plugin's
    ``VorticityAlgebra``: smooth, band-limited to ``random_degree``, in ``dtype``."""
    system = lz.EulerZeitlin(10, random_degree=3)
    W = system.random_state(seed=1)
    assert np.linalg.norm(W) == pytest.approx(1.0, rel=1e-14)
    np.testing.assert_allclose(
        W, system.algebra.random(1) / np.linalg.norm(system.algebra.random(1))
    )
    l, _ = lz.degrees_and_orders(10)
    assert np.max(np.abs(lz.matrix_to_sh(W)[l > 3])) <= 1e-14
    single = lz.EulerZeitlin(10, dtype="complex64")
    assert single.random_state(seed=1).dtype == np.complex64
    assert single.algebra.random(1, scale=2.0).dtype == np.complex64
    assert lz.EulerZeitlin().N == 8  # a default size: the registry's contract


# --------------------------------------------------------------------------- the system
def test_energy_and_casimirs() -> None:
    N = 9
    system = lz.EulerZeitlin(N, time="matrix")
    W = np.stack([lz.random_vorticity(N, 5, seed=s) for s in range(3)])
    P = system.B(W)
    H = system.hamiltonian(W)
    assert H.shape == (3,) and np.all(H > 0)
    np.testing.assert_allclose(H, -0.5 * np.real(np.einsum("kij,kij->k", W.conj(), P)))
    # B = (grad H)^†: the directional derivative of H is <-B, dW>... = Re tr(B^† dW) with
    # grad H = -P = P^† for skew-Hermitian P
    dW = lf.SU(N).project(_random_complex(N, seed=9))
    eps = 1e-6
    dH = (system.hamiltonian(W[0] + eps * dW) - system.hamiltonian(W[0] - eps * dW)) / (2 * eps)
    assert dH == pytest.approx(float(np.real(np.sum(np.conj(P[0].conj().T) * dW))), rel=1e-7)
    # the fluid's energy and enstrophy, exactly: H = (N/4π) ½∫|∇ψ|² = (N/4π) ½ Σ |ω_lm|²/(l(l+1))
    c = lz.matrix_to_sh(W)
    l, _ = lz.degrees_and_orders(N)
    k2 = N / (4 * math.pi)
    fluid_H = 0.5 * k2 * np.sum(np.abs(c[:, 1:]) ** 2 / (l[1:] * (l[1:] + 1.0)), axis=-1)
    np.testing.assert_allclose(H, fluid_H, rtol=1e-12)
    np.testing.assert_allclose(system.enstrophy(W), k2 * np.sum(np.abs(c) ** 2, axis=-1))
    C = system.casimirs(W)
    lam = np.linalg.eigvalsh(1j * W)  # iW is Hermitian
    expected = np.stack([np.sum(lam**k, axis=-1) for k in system.casimir_powers], axis=-1)
    np.testing.assert_allclose(C, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(system.enstrophy(W), C[..., 0], rtol=1e-13)
    # fluid time (the default): B and H scale by 1/ħ
    scaled = lz.EulerZeitlin(N)
    assert scaled.time == "fluid" and lz.EulerZeitlin(N, hbar_scaled=True).time == "fluid"
    np.testing.assert_allclose(scaled.B(W), P / lz.hbar(N), rtol=1e-13)
    np.testing.assert_allclose(scaled.hamiltonian(W), H / lz.hbar(N), rtol=1e-13)


SCHEMES = sorted(lf.default_registry().schemes)


@pytest.mark.parametrize("name", SCHEMES)
def test_structure_to_roundoff_for_every_scheme(name: str) -> None:
    """A strong smooth flow (rms vorticity 1, h ρ(W) ≈ 0.5), 30 steps: isospectral,
    skew-Hermitian and traceless, Casimirs conserved, to roundoff."""
    system = lz.EulerZeitlin(8)
    W0 = lz.random_vorticity(8, degree=4, seed=10)
    sol = lf.integrate(system, lf.schemes.get(name), W0, h=0.25, steps=30, solver=_tight())
    assert sol.success and sol.n_steps == 30
    assert sol.spectrum_drift().max() <= 1e-12
    assert sol.algebra_distance().max() <= 1e-14
    W = sol.W
    assert np.max(np.abs(W + np.swapaxes(W, -1, -2).conj())) <= 1e-14
    assert np.max(np.abs(np.trace(W, axis1=-2, axis2=-1))) <= 1e-13
    assert sol.casimir_drift is not None and sol.casimir_drift.max() <= 1e-12
    assert sol.energy_error is not None and sol.energy_error.max() <= 1e-3


def _final(scheme: lf.Scheme, system: lf.IsospectralSystem, W0: np.ndarray, n: int) -> np.ndarray:
    solver = lf.solvers.Auto(_tight(), lf.solvers.Newton(rtol=1e-15))
    return lf.integrate(
        system, scheme, W0, 1.0 / n, steps=n, solver=solver, diagnostics=False, save_every=n
    ).W_final


@pytest.mark.parametrize(
    ("name", "order"), [("midpoint", 2), ("gauss2", 4), ("triple_jump", 4), ("gauss3", 6)]
)
def test_observed_order(name: str, order: int) -> None:
    """``log2(e(h)/e(h/2))`` on the finest step pair with errors in ``[1e-12, 1e-2]``,
    against Gauss-6 (order 12) at h = 1/64; fluid time (ħ-scaled) 1, N = 5."""
    system = lz.EulerZeitlin(5, time="fluid")
    W0 = lz.random_vorticity(5, degree=4, seed=11, rms=1.5)
    ref = _final(lf.schemes.get("gauss", stages=6), system, W0, 64)
    scheme = lf.schemes.get(name)
    errs: list[float] = []
    for n in [2, 4, 8, 16, 32, 64]:
        errs.append(float(np.linalg.norm(_final(scheme, system, W0, n) - ref)))
        if errs[-1] < 1e-11:
            break
    pairs = [
        (errs[i], errs[i + 1])
        for i in range(len(errs) - 1)
        if errs[i] <= 1e-2 and errs[i + 1] >= 1e-12
    ]
    assert pairs, errs
    assert math.log2(pairs[-1][0] / pairs[-1][1]) == pytest.approx(order, abs=0.1), errs


SOLVERS = ["fixed_point", "newton", "frozen_b", "auto"]


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("name", ["midpoint", "gauss2", "sydirk7"])
def test_every_solver_runs(name: str, solver: str) -> None:
    system = lz.EulerZeitlin(6)
    W0 = lz.random_vorticity(6, degree=3, seed=12)
    scheme = lf.schemes.get(name)
    ref = lf.integrate(system, scheme, W0, h=0.3, steps=4, solver=_tight()).W_final
    params: dict[str, Any] = {} if solver == "auto" else {"rtol": 1e-14}
    sol = lf.integrate(system, scheme, W0, h=0.3, steps=4, solver=lf.solvers.get(solver, **params))
    assert sol.success
    assert _rel(sol.W_final, ref) <= 1e-12
    assert sol.spectrum_drift().max() <= 1e-12


@pytest.mark.parametrize("name", ["midpoint", "gauss2"])
def test_complex64(name: str) -> None:
    """complex64 states are accepted (precision-aware membership test), B is solved in single
    precision, and a run agrees with the complex128 run to single precision."""
    system = lz.EulerZeitlin(8, dtype="complex64")
    W0 = system.algebra.random(13)
    assert W0.dtype == np.complex64 and system.validate(W0).dtype == np.complex64
    assert system.B(W0).dtype == np.complex64
    sol = lf.integrate(system, lf.schemes.get(name), W0, h=0.25, steps=20)
    assert sol.success
    assert sol.spectrum_drift().max() <= 1e-5
    assert sol.algebra_distance().max() <= 1e-6
    W0_double = lf.SU(8).project(W0.astype(np.complex128))  # traceless to double roundoff
    ref = lf.integrate(lz.EulerZeitlin(8), lf.schemes.get(name), W0_double, 0.25, steps=20)
    assert _rel(sol.W_final, ref.W_final) <= 1e-5


@pytest.mark.parametrize("solver", ["fixed_point", "newton", "frozen_b"])
@pytest.mark.parametrize("name", ["midpoint", "sydirk7", "gauss2", "block", "modin_viviani"])
def test_complex64_stays_single_precision_through_a_step(name: str, solver: str) -> None:
    system = lz.EulerZeitlin(8, dtype="complex64")
    W0 = system.algebra.random(13)
    step = lf.schemes.get(name).step(W0, 0.25, system, lf.solvers.get(solver, rtol=1e-5))
    assert step.W.dtype == np.complex64


def test_midpoint_warm_started_iterations() -> None:
    """Iterations (updates) per step of the warm-started midpoint fixed point on a smooth
    rms-1 state, N = 16 (ρ(W) ≈ 1.8), after the first 5 steps, in matrix time (h = 0.05 is
    fluid time 0.05 ħ = 0.006). These are the measured counts: ≤ 3 needs a small step
    (h = 0.05) and rtol 1e-10; the default rtol 1e-14 takes 4 at h = 0.05 and 5 at h = 0.1
    (the extrapolated warm start is off by ~1e-5 relative)."""
    system = lz.EulerZeitlin(16, time="matrix")
    W0 = lz.random_vorticity(16, degree=8, seed=0)
    midpoint = lf.schemes.get("midpoint")

    def iterations(h: float, rtol: float) -> np.ndarray:
        sol = lf.integrate(
            system, midpoint, W0, h, steps=15, solver=lf.solvers.FixedPoint(rtol=rtol)
        )
        return sol.iterations[5:]

    assert iterations(0.05, 1e-10).max() <= 3
    assert iterations(0.05, 1e-14).max() <= 4
    assert iterations(0.1, 1e-14).max() <= 5
    cold = lf.integrate(
        system, midpoint, W0, 0.1, steps=15, solver=lf.solvers.FixedPoint(), warm_start=False
    )
    assert cold.iterations[5:].min() >= iterations(0.1, 1e-14).max() + 2


# --------------------------------------------------------------------------- pictures
def test_orthographic_projection_orientation() -> None:
    """Seen from (lat 0, lon 0): north up, east right; seen from the north pole: z = 1."""
    from lieflow_zeitlin.plotting import orthographic_image, plot_grid

    grid = plot_grid(4, resolution=90)
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    z = np.cos(theta)
    y = np.sin(theta) * np.sin(phi)
    img = orthographic_image(grid, z, center=(0.0, 0.0), pixels=101)
    assert img[5, 50] > 0.85 and img[95, 50] < -0.85 and abs(img[50, 50]) < 0.05
    assert np.ma.is_masked(img[0, 0])
    img = orthographic_image(grid, y, center=(0.0, 0.0), pixels=101)
    assert img[50, 95] > 0.85 and img[50, 5] < -0.85  # east (lon 90°) on the right
    img = orthographic_image(grid, z, center=(90.0, 0.0), pixels=101)
    assert img[50, 50] > 0.99


def test_vorticity_pngs(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from lieflow_zeitlin.plotting import save_figures, save_vorticity_png
    from matplotlib.image import imread

    W = lz.random_vorticity(6, degree=3, seed=14)
    paths = [
        save_vorticity_png(W, tmp_path / f"{kind}.png", projection=kind, resolution=30)
        for kind in ("equirectangular", "orthographic", "both")
    ]
    for p in paths:
        assert p.read_bytes()[:8] == PNG_SIGNATURE and imread(p).ndim == 3
    sol = lf.integrate(lz.EulerZeitlin(6), lf.schemes.get("midpoint"), W, 0.5, steps=4)
    written = save_figures(sol, tmp_path / "figs", prefix="run", count=3, resolution=30)
    assert [p.name for p in written] == [
        "run_vorticity.png",
        "run_vorticity_map.png",
        "run_vorticity_final.png",
        "run_drift.png",
    ]
    assert all(p.read_bytes()[:8] == PNG_SIGNATURE for p in written)


# --------------------------------------------------------------------------- CLI
def _small_example(tmp_path: Path) -> Path:
    """The example configuration with N = 8, 4 steps, a save every 2."""
    text = EXAMPLE.read_text(encoding="utf-8")
    for old, new in [
        ("N = 128", "N = 8"),
        ("random_degree = 8", "random_degree = 4"),
        ("steps = 1000", "steps = 4"),
        ("save_every = 10", "save_every = 2"),
    ]:
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "small.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_example_configuration_parses() -> None:
    pytest.importorskip("h5py")
    from lieflow.app.config import build, load_config

    setup = build(load_config(EXAMPLE), output=Path("unused.h5"))
    cfg = setup.config
    assert cfg.system.name == "euler_zeitlin" and setup.system.N == 128
    assert cfg.scheme.name == "gauss2" and cfg.run.steps == 1000 and cfg.run.save_every == 10
    W0 = setup.W0
    assert W0.shape == (128, 128) and lf.SU(128).contains(W0, tol=1e-14)
    l, _ = lz.degrees_and_orders(128)
    assert np.max(np.abs(lz.matrix_to_sh(W0)[l > 8])) <= 1e-12  # smooth: degrees <= 8


def test_lieflow_run_and_plot_on_a_small_copy_of_the_example(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("h5py")
    pytest.importorskip("matplotlib")
    from matplotlib.image import imread

    from lieflow.app import io
    from lieflow.app.cli import main

    config = _small_example(tmp_path)
    assert main(["run", str(config), "--no-progress"]) == 0
    traj = io.read_trajectory(tmp_path / "euler_n128.h5")
    assert traj.status == "complete" and traj.completed_steps == 4
    assert list(traj.step) == [0, 2, 4] and traj.W.shape == (3, 8, 8)
    assert np.max(traj.energy_error) <= 1e-6
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "euler_n128.h5"), "--out", str(tmp_path / "png")]) == 0
    written = [Path(line) for line in capsys.readouterr().out.split()]
    assert [p.name for p in written] == [
        "euler_n128_energy.png",
        "euler_n128_casimirs.png",
        "euler_n128_iterations.png",
        "euler_n128_vorticity.png",
        "euler_n128_vorticity_map.png",
        "euler_n128_vorticity_final.png",
        "euler_n128_drift.png",
        "euler_n128_spectra.png",
        "euler_n128_distribution.png",
        "euler_n128_statistics.png",
    ]
    for p in written:
        assert p.read_bytes()[:8] == PNG_SIGNATURE and imread(p).ndim == 3


# --------------------------------------------------------------------------- plot hook
def _registry_with(*plugins: tuple[str, Any]) -> lf.Registry:
    return lf.load_registry(autoload=False, plugins=plugins)


class _Plugin:
    def __init__(self, *plotters: tuple[str, Any]) -> None:
        self.plotters = plotters

    @lf.hookimpl
    def lieflow_register(self, registry: lf.RegistryBuilder) -> None:
        for system, function in self.plotters:
            registry.add_plotter(system, function)


def test_add_plotter_validates() -> None:
    def plot(trajectory: Any, out_dir: Path, stem: str) -> list[Path]:
        """Doc line."""
        return []

    registry = _registry_with(("p", _Plugin(("rigid_body", plot))))
    assert registry.plotters["rigid_body"].function is plot
    assert registry.plotters["rigid_body"].description == "Doc line."
    with pytest.raises(lf.PluginError, match="already registered"):
        _registry_with(("a", _Plugin(("rigid_body", plot))), ("b", _Plugin(("rigid_body", plot))))
    with pytest.raises(lf.PluginError, match="invalid system name"):
        _registry_with(("p", _Plugin(("Rigid Body", plot))))
    with pytest.raises(lf.PluginError, match="not callable"):
        _registry_with(("p", _Plugin(("rigid_body", 3))))
    # a broken plugin's plotters are discarded with it
    with pytest.warns(lf.plugins.PluginWarning):
        registry = lf.load_registry(
            autoload=False,
            plugins=[("p", _Plugin(("rigid_body", plot), ("Bad", plot)))],
            errors="warn",
        )
    assert "rigid_body" not in registry.plotters


def test_a_failing_plotter_is_a_plugin_error(tmp_path: Path) -> None:
    pytest.importorskip("h5py")
    pytest.importorskip("matplotlib")
    from lieflow.app import io
    from lieflow.app.config import build, load_config
    from lieflow.app.plotting import plot_trajectory

    config = _small_example(tmp_path)
    io.run(build(load_config(config)))

    def broken(trajectory: Any, out_dir: Path, stem: str) -> list[Path]:
        raise RuntimeError("boom")

    registry = _registry_with(("p", _Plugin(("euler_zeitlin", broken))))
    with pytest.raises(lf.PluginError, match="boom"):
        plot_trajectory(tmp_path / "euler_n128.h5", tmp_path / "png", registry=registry)
    assert (tmp_path / "png" / "euler_n128_energy.png").exists()
    builtins_only = lf.load_registry(autoload=False)
    assert (
        len(plot_trajectory(tmp_path / "euler_n128.h5", tmp_path / "a", registry=builtins_only))
        == 3
    )
