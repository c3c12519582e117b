"""The warm start's extrapolations and prediction errors over large NumPy histories
(:mod:`lieflow.warm_start`), compiled with numba. Imports numba: import it only where numba
is installed.

The arrays come as flat real views (complex numbers as interleaved real and imaginary
parts, ``parts = 2``). An extrapolation ``Σ_j w_j x_j`` is formed entry by entry as NumPy
forms ``acc = w_0 * x_0; acc += w_1 * x_1; ...`` with Python-int weights: for complex
arrays each ``w * x`` is the complex product ``(w + 0i)(a + bi) = (w a - 0 b) + (w b + 0 a) i``
(numba contracts no multiply–add without ``fastmath``): the same bits. The prediction
errors' sums of squares add in the compiler's order (vectorized): they only rank the
predictions against each other.

The history comes as a tuple of arrays (numba's ``UniTuple``, whose length is part of the
type), padded to a fixed length (:func:`_padded`: 8, else the next power of two) with the
count passed beside it, so that one compilation serves every history a run builds up (1, 2,
... points as it starts) instead of one per length."""

from __future__ import annotations

from typing import Any

import numpy as np

from .numba_cache import SplitKernel, cached_njit, work_groups

__all__ = ["CHUNK", "errors", "extrapolate", "work_groups"]

#: ``range`` here; ``numba.prange`` in a split kernel's parallel build
#: (:class:`lieflow.numba_cache.SplitKernel`).
prange = range

#: Real numbers handled at a time (the chunk of an extrapolation stays in the L1 cache
#: while the history's arrays stream past it).
CHUNK = 2048


def _extrapolate(
    groups: int, w: Any, xs: Any, m: int, parts: int, out: Any
) -> None:  # pragma: no cover
    """``out = Σ_{j < m} w[j] xs[j]`` with NumPy's roundings (module docs); ``m >= 2``. The
    chunks are split into ``groups`` runs (one per thread where ``groups > 1``)."""
    n = out.size
    chunks = (n + CHUNK - 1) // CHUNK
    for g in prange(groups):
        for i in range(g * chunks // groups, (g + 1) * chunks // groups):
            start = i * CHUNK
            stop = min(start + CHUNK, n)
            _weighted_sum(w, xs, m, parts, start, stop, out[start:stop])


def _weighted_sum(
    w: Any, xs: Any, m: int, parts: int, start: int, stop: int, acc: Any
) -> None:  # pragma: no cover - compiled
    """``acc = Σ_{j < m} w[j] xs[j][start:stop]``, NumPy's roundings (``m >= 1``). (Each
    array is read through its slice, indexed from 0: indices the compiler knows are not
    negative, so the loops are vectorized.)"""
    n = stop - start
    x = xs[0][start:stop]
    c = w[0]
    if parts == 2:
        for i in range(0, n, 2):
            a = x[i]
            b = x[i + 1]
            acc[i] = c * a - 0.0 * b
            acc[i + 1] = c * b + 0.0 * a
        for j in range(1, m):
            x = xs[j][start:stop]
            c = w[j]
            for i in range(0, n, 2):
                a = x[i]
                b = x[i + 1]
                acc[i] = acc[i] + (c * a - 0.0 * b)
                acc[i + 1] = acc[i + 1] + (c * b + 0.0 * a)
    else:
        for i in range(n):
            acc[i] = c * x[i]
        for j in range(1, m):
            x = xs[j][start:stop]
            c = w[j]
            for i in range(n):
                acc[i] = acc[i] + c * x[i]


def _errors(
    groups: int, solved: Any, xs: Any, M: int, C: Any, out: Any
) -> None:  # pragma: no cover
    """``out[0] = ||solved||²`` and ``out[m] = ||solved - p_m||²`` for ``m = 1 .. M``
    (the first ``M`` arrays of ``xs``), ``p_m = Σ_{j < m} C[m - 1, j] xs[j]``
    (``p_1 = xs[0]``) with the values :func:`_extrapolate` gives (formed as real sums: a
    complex product's ``0 b`` term changes at most the sign of a zero, which its square
    does not see). Each chunk's sums are kept and the chunks added in order, so the chunks
    may be split into ``groups`` runs (one per thread) with the same result."""
    n = solved.size
    chunks = (n + CHUNK - 1) // CHUNK
    sums = np.zeros((chunks, M + 1))
    for g in prange(groups):
        p = np.empty(CHUNK)
        for i in range(g * chunks // groups, (g + 1) * chunks // groups):
            start = i * CHUNK
            stop = min(start + CHUNK, n)
            s = solved[start:stop]
            sums[i, 0] = _squares(s, s, False)
            sums[i, 1] = _squares(s, xs[0][start:stop], True)
            for m in range(2, M + 1):
                _weighted_sum(C[m - 1], xs, m, 1, start, stop, p)
                sums[i, m] = _squares(s, p[: stop - start], True)
    for m in range(M + 1):
        total = 0.0
        for i in range(chunks):
            total += sums[i, m]
        out[m] = total


def _squares(s: Any, p: Any, difference: bool) -> float:  # pragma: no cover - compiled
    """``Σ_i (s_i - p_i)²`` (``Σ_i s_i²`` without ``difference``), summed in the compiler's
    order (``reassoc``: vectorized)."""
    acc = 0.0
    if difference:
        for i in range(s.size):
            d = s[i] - p[i]
            acc += d * d
    else:
        for i in range(s.size):
            acc += s[i] * s[i]
    return acc


_weighted_sum = cached_njit(_weighted_sum)
_squares = cached_njit(_squares, fastmath={"reassoc"})
_extrapolate_pass = SplitKernel(_extrapolate)
_errors_pass = SplitKernel(_errors)


def _padded(xs: tuple[Any, ...]) -> tuple[Any, ...]:
    """``xs`` padded with its first array (not read) to 8 arrays, or to the next power of
    two above 8: a fixed length, so one compilation of a pass serves every shorter history."""
    size = 8
    while size < len(xs):
        size *= 2
    return (*xs, *(xs[0],) * (size - len(xs)))


def extrapolate(groups: int, w: Any, xs: tuple[Any, ...], parts: int, out: Any) -> None:
    """``out = Σ_j w[j] xs[j]`` over the ``len(xs)`` arrays (:func:`_extrapolate`) in
    ``groups`` runs of chunks."""
    _extrapolate_pass(groups, w, _padded(xs), len(xs), parts, out)


def errors(groups: int, solved: Any, xs: tuple[Any, ...], C: Any, out: Any) -> None:
    """The squared norms of ``solved`` and of its differences from the ``len(xs)``
    predictions (:func:`_errors`) in ``groups`` runs of chunks."""
    _errors_pass(groups, solved, _padded(xs), len(xs), C, out)
