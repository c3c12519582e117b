"""The Hoppe–Yau Laplacian from one coefficient source, and the Euler–Zeitlin ``B`` on arrays
of any array-API library (numpy through the generic path, ``array_api_strict``), compared with
independent constructions: the double commutator with spin matrices built here, and the
numpy engine's sweeps."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

lz = pytest.importorskip("lieflow_zeitlin")

from lieflow_zeitlin import laplacian  # noqa: E402


def _spin(N: int) -> list[np.ndarray]:
    """Spin-(N-1)/2 matrices built from the angular-momentum ladder, independently of the
    plugin: S_3 = diag(mu), (S_+)_{mu+1, mu} = sqrt(s(s+1) - mu(mu+1)), ascending mu."""
    s = (N - 1) / 2
    mu = np.arange(N) - s
    Sp = np.diag(np.sqrt(s * (s + 1) - mu[:-1] * (mu[:-1] + 1)), -1).astype(complex)
    return [(Sp + Sp.T) / 2, (Sp - Sp.T) / 2j, np.diag(mu).astype(complex)]


def _dense_laplacian(N: int) -> np.ndarray:
    """-Σ_a [S_a, [S_a, E_jk]] for every elementary matrix: (N², N²), column jk."""
    S = _spin(N)
    cols = []
    for idx in range(N * N):
        E = np.zeros((N, N), dtype=complex)
        E.flat[idx] = 1
        cols.append((-sum(a @ (a @ E - E @ a) - (a @ E - E @ a) @ a for a in S)).ravel())
    return np.array(cols).T


@pytest.mark.parametrize("N", [2, 3, 4, 7, 8])
def test_tridiagonal_and_packed_coefficients_match_the_double_commutator(N: int) -> None:
    dense = _dense_laplacian(N)
    # the operator maps each diagonal m = j - k to itself, spectrum -l(l+1) (mult. 2l+1)
    l = np.arange(N)
    np.testing.assert_allclose(
        np.linalg.eigvalsh((dense + dense.conj().T) / 2),
        np.sort(np.repeat(-(l * (l + 1.0)), 2 * l + 1)),
        rtol=0,
        atol=1e-10 * N * N,
    )
    d_packed, e_packed, valid = laplacian._packed_coefficients(N)
    flat = np.arange(N * (N + 1)).reshape(N, N + 1)
    for m in range(-(N - 1), N):
        n = N - abs(m)
        i = np.arange(n)
        rows, cols = (i + m, i) if m >= 0 else (i, i - m)
        block = dense[np.ix_(rows * N + cols, rows * N + cols)]
        d, e = laplacian.tridiagonal(N, m)
        np.testing.assert_allclose(
            block, np.diag(d) + np.diag(e, 1) + np.diag(e, -1), rtol=0, atol=1e-12
        )
        # the packed layout stores entry (r, c) of W at flat index rN + c of an N x (N+1)
        # matrix; the same system sits there on consecutive rows of one column
        pos = flat.ravel()[rows * N + cols]
        r, c = np.divmod(pos, N + 1)
        assert np.all(c == c[0]) and np.all(np.diff(r) == 1) and valid[r, c].all()
        np.testing.assert_allclose(d_packed[r, c], d, rtol=0, atol=1e-12)
        np.testing.assert_allclose(e_packed[r[1:], c[1:]], e, rtol=0, atol=1e-12)
        assert e_packed[r[0], c[0]] == 0  # decoupled from whatever sits above it
    assert valid.sum() == N * N and np.all(d_packed[~valid] == 0) and np.all(e_packed[~valid] == 0)


# --------------------------------------------------------------------------- B on any arrays
xps = pytest.importorskip("array_api_strict")


def _rel(a: object, b: np.ndarray) -> float:
    a = np.asarray(a)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def _fields(N: int) -> list[np.ndarray]:
    rng = np.random.default_rng(N)
    white = rng.standard_normal((2, N, N)) + 1j * rng.standard_normal((2, N, N))
    return [lz.random_vorticity(N, degree=min(N - 1, 8), seed=N), white]


@pytest.mark.parametrize("N", [2, 3, 4, 7, 8, 16, 33, 64])
@pytest.mark.parametrize(("scale", "shift"), [(1.0, 0.0), (0.3, 0.0), (2.0, 5.0)])
def test_cyclic_reduction_solve_matches_the_sweeps(N: int, scale: float, shift: float) -> None:
    L = lz.HoppeYauLaplacian(N, scale=scale, shift=shift)
    for W in _fields(N):
        P = L.solve(W)  # numpy: the sequential sweeps (another algorithm)
        Pa = L.solve(xps.asarray(W))
        assert isinstance(Pa, type(xps.asarray(W))) and Pa.dtype == xps.complex128
        assert tuple(Pa.shape) == W.shape
        assert _rel(Pa, P) <= 1e-14
        # and it solves the system (apply is the packed operator, checked above)
        traceless = W - (np.trace(W, axis1=-2, axis2=-1) / N)[..., None, None] * np.eye(N)
        np.testing.assert_allclose(
            L.apply(np.asarray(Pa)), scale * traceless, rtol=0, atol=1e-14 * N * N * np.abs(W).max()
        )
        assert np.abs(np.trace(np.asarray(Pa), axis1=-2, axis2=-1)).max() <= 1e-13 * np.abs(P).max()


def test_cyclic_reduction_single_precision_real_input_and_batches() -> None:
    N = 12
    L = lz.HoppeYauLaplacian(N)
    W = lz.random_vorticity(N, degree=6, seed=4)
    P = L.solve(W)
    P32 = L.solve(xps.asarray(W.astype(np.complex64)))
    assert P32.dtype == xps.complex64 and _rel(P32, P) <= 1e-5
    real = np.random.default_rng(0).standard_normal((3, 2, N, N))
    Pr = L.solve(xps.asarray(real))
    assert Pr.dtype == xps.complex128 and _rel(Pr, L.solve(real)) <= 1e-13


@pytest.mark.parametrize("rotation", [0.0, 1.5])
def test_euler_zeitlin_B_on_array_api_strict_arrays(rotation: float) -> None:
    system = lz.EulerZeitlin(16, rotation=rotation, lamb=0.5 if rotation else 0.0)
    W = system.random_state(3)
    B = system.B(W)
    Ba = system.B(xps.asarray(W))
    assert Ba.dtype == xps.complex128 and _rel(Ba, B) <= 1e-13


def _exact_m0(N: int, f: np.ndarray, pin: Fraction) -> np.ndarray:
    """The traceless solution of the ``m = 0`` system for a traceless real ``f``, in exact
    rational arithmetic (its coefficients are integers: ``e_i = i (N - i)``)."""
    d = [Fraction(-((N - 1) * (2 * i + 1) - 2 * i * i)) for i in range(N)]
    e = [Fraction(i * (N - i)) for i in range(1, N)]
    d[0] += pin
    rhs = [Fraction(float(v)) for v in f]
    c, g = [Fraction(0)] * N, [Fraction(0)] * N
    D = d[0]
    c[0], g[0] = e[0] / D, rhs[0] / D
    for i in range(1, N):
        D = d[i] - e[i - 1] * c[i - 1]
        c[i] = e[i] / D if i < N - 1 else Fraction(0)
        g[i] = (rhs[i] - e[i - 1] * g[i - 1]) / D
    x = [Fraction(0)] * N
    x[-1] = g[-1]
    for i in range(N - 2, -1, -1):
        x[i] = g[i] - c[i] * x[i + 1]
    mean = sum(x) / N
    return np.array([float(v - mean) for v in x])


@pytest.mark.skipif(
    np.finfo(np.longdouble).eps > 1e-18, reason="numpy.longdouble is plain double here"
)
@pytest.mark.parametrize("N", [64, 128])
def test_the_singular_block_is_solved_to_roundoff_by_both_algorithms(N: int) -> None:
    """The pinned m = 0 system (condition ~N³ before the trace is removed) against exact
    arithmetic: the sweeps' and the cyclic reduction's factors are computed in extended
    precision (in float64 they were off by 1.3e-14 / 6.5e-14 and 7e-14 / 1.2e-12)."""
    L = lz.HoppeYauLaplacian(N)
    rng = np.random.default_rng(N)
    W = rng.standard_normal((N, N)) + 1j * rng.standard_normal((N, N))
    f = np.diag(W).real - np.diag(W).real.mean()
    exact = _exact_m0(N, f, Fraction(-1, 2))
    for P in (L.solve(W), np.asarray(L.solve(xps.asarray(W)))):
        scale = np.max(np.abs(P))
        assert np.max(np.abs(np.diag(P).real - exact)) <= 5e-15 * scale
