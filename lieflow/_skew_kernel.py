"""The fused loop of :func:`lieflow.algebras.skew_combination` on NumPy arrays, compiled with
numba. Imports numba: import it only where numba is installed."""

from __future__ import annotations

from typing import Any

import numpy as np

from .numba_cache import SplitKernel, cached_njit, work_groups

#: ``range`` here; ``numba.prange`` in a split kernel's parallel build
#: (:class:`lieflow.numba_cache.SplitKernel`).
prange = range

__all__ = ["BAND", "PAD", "combine", "work_groups"]

#: Rows of ``X^†`` gathered at a time (a band of ``BAND`` columns of ``X``, conjugated).
BAND = 32
#: Padding of the band's rows (numbers): rows a multiple of 4 KiB apart map to the same
#: cache sets, so a gather writing down a column of the band would evict its own lines.
PAD = 16


def _combine(
    groups: int,
    X: Any,
    s: float,
    A: Any,
    Y: Any,
    t: float,
    with_y: bool,
    parts: int,
    out: Any,
    old: Any,
    norms: bool,
    rows_sums: Any,
) -> None:  # pragma: no cover - compiled
    """``out = ((X - X^†) s + A) + Y t`` (``+ Y t`` only ``with_y``) over ``K`` matrices of
    ``n × n`` numbers given as real views ``(K, n, parts · n)`` (``parts = 2``: complex
    numbers, real and imaginary parts interleaved), entry by entry the operations NumPy
    performs for ``D = X - X^†; D *= s; D += A; Y *= t; D += Y``, each a separate rounding
    (numba contracts no multiply–add without ``fastmath``).

    Band by band: ``BAND`` rows of ``X^†`` are first gathered, conjugated, into a small
    buffer (``-y`` for an imaginary part ``y``: ``a - (-y)`` is IEEE's ``a + y``, the
    imaginary part of ``X_ij - conj(X_ji)``), so the arithmetic runs along whole
    contiguous rows.

    With ``norms``, each output row's ``Σ out²`` and ``Σ (out - old)²`` (``old`` of ``out``'s
    shape) go to ``rows_sums[k, row]``, summed while the row is in the cache
    (:func:`_row_squares`); the caller adds the rows.

    The bands of all matrices are split into ``groups`` runs of consecutive bands, one per
    thread where ``groups > 1`` (:class:`lieflow.numba_cache.SplitKernel`): each band's
    numbers are the same whoever computes them."""
    K, n = X.shape[0], X.shape[1]
    width = parts * n
    bands = (n + BAND - 1) // BAND
    for g in prange(groups):
        T = np.empty((BAND, width + PAD))
        for task in range(g * K * bands // groups, (g + 1) * K * bands // groups):
            k = task // bands
            ib = (task % bands) * BAND
            rows = min(BAND, n - ib)
            for j in range(n):
                for a in range(rows):
                    T[a, parts * j] = X[k, j, parts * (ib + a)]
                    if parts == 2:
                        T[a, 2 * j + 1] = -X[k, j, 2 * (ib + a) + 1]
            for a in range(rows):
                x = X[k, ib + a]
                z = A[k, ib + a]
                o = out[k, ib + a]
                d = T[a]
                if with_y:
                    y = Y[k, ib + a]
                    for c in range(width):
                        o[c] = ((x[c] - d[c]) * s + z[c]) + y[c] * t
                else:
                    for c in range(width):
                        o[c] = (x[c] - d[c]) * s + z[c]
                if norms:
                    size2, step2 = _row_squares(o, old[k, ib + a])
                    rows_sums[k, ib + a, 0] = size2
                    rows_sums[k, ib + a, 1] = step2


def _row_squares(o: Any, m: Any) -> tuple[float, float]:  # pragma: no cover - compiled
    """``(Σ o², Σ (o - m)²)`` over a row, summed in the compiler's order (``reassoc``:
    vectorized; the differences are IEEE's, as NumPy's ``o - m``)."""
    size2 = 0.0
    step2 = 0.0
    for c in range(o.size):
        d = o[c] - m[c]
        size2 += o[c] * o[c]
        step2 += d * d
    return size2, step2


_row_squares = cached_njit(_row_squares, fastmath={"reassoc"})
combine = SplitKernel(_combine)
