r"""The Casimirs ``tr((iW)^k)``, ``k = 2, 3, 4``, of Euler–Zeitlin states from one matrix
product and one compiled pass, where numba is installed.

With ``P = W W``, ``A = iW`` and ``tr(XY) = Σ_ij X_ij Y_ji``:

.. math:: \operatorname{tr} A^2 = -\operatorname{Re} \operatorname{tr}(W W),\qquad
          \operatorname{tr} A^3 = \operatorname{Im} \operatorname{tr}(W P),\qquad
          \operatorname{tr} A^4 = \operatorname{Re} \operatorname{tr}(P P)

(``A^2 = -P``; ``Re(-i z) = Im z``), for any complex ``W``. The three traces are read in
one pass over ``W`` and ``P``: band by band, ``_BAND`` columns of each are gathered as rows
(``W_ji`` for row ``i``), so every sum runs along contiguous rows; each row's three sums go
to their own slot and the rows are added afterwards by NumPy (pairwise). NumPy's form
(:meth:`EulerZeitlin.casimirs <lieflow_zeitlin.EulerZeitlin.casimirs>` without numba:
``1j * W``, a product, two transposed copies, three elementwise products and their sums)
makes ten passes over ``N × N`` arrays besides the product (N = 256, one thread: 4.8 against
0.2 ms); the sums are the same up to their order of addition (roundoff).

The product of a state: half of one. A state of su(N) is skew-Hermitian bit for bit (every
projection makes it so, :func:`~lieflow_zeitlin.projection.su_project`), so
``P = W W = -W W^†`` is Hermitian and BLAS ``zherk`` forms its lower triangle in half
the operations of ``zgemm`` (N = 256, one thread: 1.55 against 2.9 ms); the pass reads
the triangle (the upper entries as conjugates of the lower, which it writes into ``P``
as it goes) and checks that ``W_ij = -conj(W_ji)`` for every entry it reads. A matrix
that is not skew-Hermitian bit for bit (not a state) has its product formed again by
``zgemm`` and the pass run on that. ``zherk`` computes each entry of the triangle
in another order than ``zgemm`` (roundoff: the recorded drifts differ in their last bits).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._recurrences import _Kernel, work_groups

#: ``range`` here; ``numba.prange`` in a split kernel's parallel build
#: (:class:`lieflow.numba_cache.SplitKernel`).
prange = range

Array = NDArray[Any]

#: Columns gathered at a time, and the padding of the gathered rows (numbers: rows a
#: multiple of 4 KiB apart share cache sets).
_BAND, _PAD = 32, 16


def _row_traces_loops(groups: int, W: Array, P: Array, out: Array, lower: bool) -> None:
    """``out[k, i, :3] = (Σ_j Re(W_ij W_ji), Σ_j Im(W_ij P_ji), Σ_j Re(P_ij P_ji))`` for ``K``
    complex ``N × N`` matrices ``W``, ``P`` given as real views ``(K, N, 2N)`` (real and
    imaginary parts interleaved); ``out`` of shape ``(K, N, 4)``. Each sum adds its terms
    in the order of ``j``. The bands of all matrices are split into ``groups`` runs of
    consecutive bands (one per thread where ``groups > 1``: the same numbers).

    ``lower``: ``P`` holds a Hermitian matrix's lower triangle (``P_ij``, ``j <= i``; the
    rest is not read): each entry above it is read as ``conj(P_ji)`` and written into
    ``P`` before row ``i`` is summed (only lower entries are gathered, so no group reads
    what another writes); ``out[k, i, 3]`` counts the ``j`` with ``W_ij != -conj(W_ji)``
    (``W`` not skew-Hermitian bit for bit, whose ``P`` the caller then forms in full)."""
    K, N = W.shape[0], W.shape[1]
    bands = (N + _BAND - 1) // _BAND
    for g in prange(groups):
        TW = np.empty((_BAND, 2 * N + _PAD))
        TP = np.empty((_BAND, 2 * N + _PAD))
        for task in range(g * K * bands // groups, (g + 1) * K * bands // groups):
            k = task // bands
            ib = (task % bands) * _BAND
            rows = min(_BAND, N - ib)
            for j in range(N):
                for a in range(rows):
                    TW[a, 2 * j] = W[k, j, 2 * (ib + a)]
                    TW[a, 2 * j + 1] = W[k, j, 2 * (ib + a) + 1]
                    if lower and j < ib + a:  # P_ji above the triangle: conj(P_ij)
                        TP[a, 2 * j] = P[k, ib + a, 2 * j]
                        TP[a, 2 * j + 1] = -P[k, ib + a, 2 * j + 1]
                    else:
                        TP[a, 2 * j] = P[k, j, 2 * (ib + a)]
                        TP[a, 2 * j + 1] = P[k, j, 2 * (ib + a) + 1]
            for a in range(rows):
                w = W[k, ib + a]
                p = P[k, ib + a]
                tw = TW[a]
                tp = TP[a]
                bad = 0
                if lower:  # row i above the diagonal: P_ij = conj(P_ji), gathered
                    for j in range(ib + a + 1, N):
                        p[2 * j] = tp[2 * j]
                        p[2 * j + 1] = -tp[2 * j + 1]
                    for j in range(N):
                        bad += (w[2 * j] != -tw[2 * j]) | (w[2 * j + 1] != tw[2 * j + 1])
                s2 = 0.0
                s3 = 0.0
                s4 = 0.0
                for j in range(N):
                    wr, wi = w[2 * j], w[2 * j + 1]
                    pr, pi = p[2 * j], p[2 * j + 1]
                    s2 += wr * tw[2 * j] - wi * tw[2 * j + 1]
                    s3 += wr * tp[2 * j + 1] + wi * tp[2 * j]
                    s4 += pr * tp[2 * j] - pi * tp[2 * j + 1]
                out[k, ib + a, 0] = s2
                out[k, ib + a, 1] = s3
                out[k, ib + a, 2] = s4
                out[k, ib + a, 3] = bad


_row_traces = _Kernel(_row_traces_loops, split=True)

#: The powers :func:`casimirs_234` computes.
POWERS = (2, 3, 4)

#: From this N on (where it pays: N = 256, 8 -> 3.7 ms), the compiled pass; below it the
#: NumPy products, so that a small run compiles nothing for its diagnostics (a first run's
#: compile time, issue 37 item 11).
MIN_N = 64


def casimirs_234(W: Array) -> Array:
    """``tr((iW)^k)`` for ``k = 2, 3, 4`` (module docs), last axis indexes ``k``, for a
    ``complex128`` NumPy array ``W`` of shape ``(..., N, N)``; call it only where numba is
    installed (:func:`~lieflow_zeitlin._recurrences.have_numba`). Each matrix's product by
    ``zherk`` (half a ``zgemm``), again by ``zgemm`` where it is not skew-Hermitian bit for
    bit (module docs)."""
    from scipy.linalg.blas import zherk  # (scipy.linalg: 0.1 s to import, on first use)

    N = W.shape[-1]
    flat = np.ascontiguousarray(W).reshape(-1, N, N)
    K = flat.shape[0]
    # each P[k].T (Fortran order) gets -X^T conj(X) = (-X X^†)^T in its upper triangle:
    # P[k] read as C-ordered, P = -X X^† = X X (X skew-Hermitian) in its lower triangle
    # (beta = 0: the memory is not read; the upper triangle is written by the pass)
    P = np.empty(flat.shape, dtype=flat.dtype)
    for X, Y in zip(flat, P, strict=True):
        C = zherk(-1.0, X.T, beta=0.0, c=Y.T, trans=0, lower=0, overwrite_c=1)
        if not np.shares_memory(C, Y):  # (f2py wrote into a copy of c: take it)
            Y.T[...] = C
    rows = np.empty((K, N, 4))
    W2 = flat.view(np.float64)
    groups = work_groups(W2.size)
    _row_traces(groups, W2, P.view(np.float64), rows, True)
    sums = rows.sum(axis=1)
    redo = np.flatnonzero(sums[:, 3])  # not skew-Hermitian bit for bit: the full product
    if redo.size:
        Q = np.matmul(flat[redo], flat[redo])
        again = np.empty((redo.size, N, 4))
        _row_traces(groups, W2[redo], Q.view(np.float64), again, False)
        sums[redo] = again.sum(axis=1)
    sums[:, 0] *= -1.0
    return sums[:, :3].reshape(*W.shape[:-2], 3)
