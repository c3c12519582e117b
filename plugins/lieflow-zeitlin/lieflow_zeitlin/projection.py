r"""The su(N) projection of Euler–Zeitlin states and stage values, one pass where numba is
installed.

Every fixed-point update of a scheme projects its stage values before ``B`` is evaluated
(:meth:`lieflow.IsospectralSystem.project_stage`), and every step projects its new state;
for su(N) that is

.. math:: P(X) = \tfrac12 (X - X^\dagger) - \tfrac{\operatorname{tr}}{N}\, I

(:meth:`lieflow.SU.project`). NumPy forms ``X - X^†`` from a transposed, conjugated view —
a strided read and a temporary — which at N = 128 costs more than the Laplacian solve of
``B`` itself (measured, one thread: 70–96 µs against 60 µs; N = 64: 16–22 µs against 24
µs). :func:`su_project` computes the same numbers with the skew-Hermitian part in one
compiled loop over the real and imaginary parts (``lieflow-zeitlin[fast]``), and the trace
removed by the same NumPy operations as :meth:`lieflow.SU.project`: the result has
:meth:`~lieflow.SU.project`'s bits (tested), with or without numba.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from lieflow.backends import is_numpy

from ._recurrences import _Kernel, have_numba, work_groups

#: ``range`` here; ``numba.prange`` in a split kernel's parallel build
#: (:class:`lieflow.numba_cache.SplitKernel`).
prange = range

Array = NDArray[Any]

_COMPLEX = (np.dtype(np.complex128), np.dtype(np.complex64))


#: Columns of ``X`` gathered at a time by :func:`_skew_part_loops` (as rows of ``X^†``), and
#: the padding of the gathered rows (numbers; rows a multiple of 4 KiB apart share cache
#: sets, so a gather writing down a column of the band would evict its own lines).
_BAND, _PAD = 32, 16


def _skew_part_loops(groups: int, X: Array, out: Array) -> None:
    """``out = (X - X^†)/2`` for ``K`` complex ``N×N`` matrices given as real views
    ``(K, N, 2N)`` (real and imaginary parts interleaved): entry by entry the operations
    NumPy performs for ``X - X.conj().swapaxes(-1, -2)`` followed by ``*= 0.5``.

    Band by band: ``_BAND`` columns of ``X`` are first gathered, conjugated, as rows
    (``-y`` for an imaginary part ``y``: ``a - (-y)`` is IEEE's ``a + y``), so the
    arithmetic runs along whole contiguous rows (N = 256: 0.20 -> 0.07 ms, one thread).
    The bands of all matrices are split into ``groups`` runs of consecutive bands (one per
    thread where ``groups > 1``: the same numbers)."""
    K, N = X.shape[0], X.shape[1]
    bands = (N + _BAND - 1) // _BAND
    for g in prange(groups):
        T = np.empty((_BAND, 2 * N + _PAD), dtype=X.dtype)
        for task in range(g * K * bands // groups, (g + 1) * K * bands // groups):
            k = task // bands
            ib = (task % bands) * _BAND
            rows = min(_BAND, N - ib)
            for j in range(N):
                for a in range(rows):
                    T[a, 2 * j] = X[k, j, 2 * (ib + a)]
                    T[a, 2 * j + 1] = -X[k, j, 2 * (ib + a) + 1]
            for a in range(rows):
                x = X[k, ib + a]
                o = out[k, ib + a]
                d = T[a]
                for c in range(2 * N):
                    o[c] = (x[c] - d[c]) * 0.5


_skew_part_compiled = _Kernel(_skew_part_loops, split=True)


def su_project(X: Any, fallback: Any) -> Array:
    r"""``P(X) = (X - X^†)/2 - (tr/N) I`` over the last two axes, a new array.

    NumPy ``complex128`` / ``complex64`` arrays take the compiled loop
    (:func:`_skew_part_loops`) when numba is installed; anything else — and everything
    without numba — is ``fallback(X)`` (:meth:`lieflow.SU.project`, whose bits the loop
    reproduces).
    """
    if (
        not is_numpy(X)
        or X.dtype not in _COMPLEX
        or X.ndim < 2
        or X.shape[-1] != X.shape[-2]
        or not have_numba()
    ):
        return fallback(X)
    N = X.shape[-1]
    flat = np.ascontiguousarray(X).reshape(-1, N, N)
    out = np.empty(flat.shape, dtype=X.dtype)
    real = flat.real.dtype
    skew_part_into(flat.view(real), out.view(real))
    remove_trace(out.reshape(-1, N * N)[:, :: N + 1], N)
    return out.reshape(X.shape)


def skew_part_into(X: Array, out: Array) -> None:
    """``out = (X - X^†)/2`` for real views ``(K, N, 2N)`` of complex matrices (numba
    installed): :func:`_skew_part_loops`, compiled (on numba's threads for large ``X``)."""
    _skew_part_compiled(work_groups(X.size), X, out)


def remove_trace(diagonal: Array, N: int) -> None:
    """Subtract the mean of each row of ``diagonal`` (the diagonals of ``N × N`` matrices,
    a view), as :meth:`lieflow.SU.project` removes the trace: its operations, its bits."""
    diagonal -= diagonal.sum(axis=-1, keepdims=True) / N
