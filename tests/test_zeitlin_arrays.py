"""The Hoppe–Yau Laplacian from one coefficient source, and the Euler–Zeitlin ``B`` on arrays
of any array-API library (numpy through the generic path, ``array_api_strict``), compared with
independent constructions: the double commutator with spin matrices built here, and the
numpy engine's sweeps."""

from __future__ import annotations

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
