"""The underflow guard's loops on NumPy arrays (:func:`lieflow.underflow.flush_tiny`),
compiled with numba. Imports numba: import it only where numba is installed."""

from __future__ import annotations

from typing import Any

import numpy as np

from .numba_cache import SplitKernel, cached_njit, work_groups

__all__ = ["CHUNK", "count_below", "flush", "limits", "work_groups"]

#: ``range`` here; ``numba.prange`` in a split kernel's parallel build
#: (:class:`lieflow.numba_cache.SplitKernel`).
prange = range


def _largest(row: Any) -> float:  # pragma: no cover - compiled
    """``max |row|``: a maximum is exact in any order, so the compiler may vectorize it
    (``fastmath``; a NaN may or may not show: the guard tolerates either)."""
    top = 0.0
    for i in range(row.size):
        top = max(top, abs(row[i]))
    return top


_largest_compiled = cached_njit(_largest, fastmath=True)


#: Numbers per task of the split passes (:class:`lieflow.numba_cache.SplitKernel`).
CHUNK = 1 << 15


def _limits(groups: int, real: Any, tau: float) -> Any:  # pragma: no cover - compiled
    """``tau`` times the largest ``|x|`` of each row (0 where that is not finite): the
    maxima of chunks of :data:`CHUNK` numbers, split into ``groups`` runs of chunks (one
    per thread where ``groups > 1``), then their maximum (a maximum is exact in any
    order: the same numbers)."""
    rows, size = real.shape
    chunks = (size + CHUNK - 1) // CHUNK
    tops = np.zeros((rows, chunks))
    tasks = rows * chunks
    for g in prange(groups):
        for task in range(g * tasks // groups, (g + 1) * tasks // groups):
            r = task // chunks
            c = task - r * chunks
            tops[r, c] = _largest_compiled(real[r, c * CHUNK : min(size, (c + 1) * CHUNK)])
    out = np.zeros(rows)
    for r in range(rows):
        top = 0.0
        for c in range(chunks):
            top = max(top, tops[r, c])
        if top < np.inf:
            out[r] = tau * top
    return out


def _count_below(real: Any, limits: Any) -> int:  # pragma: no cover - compiled
    """How many nonzero numbers of each row lie below its limit, summed."""
    count = 0
    for r in range(real.shape[0]):
        limit = limits[r]
        row = real[r]
        for i in range(row.size):
            a = abs(row[i])
            count += 1 if (a < limit and a > 0.0) else 0
    return count


def _flush(groups: int, real: Any, limits: Any, out: Any, same: bool) -> None:  # pragma: no cover
    """``out = real`` with the numbers below their row's limit set to zero; ``same``: ``out``
    is ``real`` (only those numbers are written). By chunks of :data:`CHUNK` numbers,
    split into ``groups`` runs (one per thread where ``groups > 1``)."""
    rows, size = real.shape
    chunks = (size + CHUNK - 1) // CHUNK
    tasks = rows * chunks
    for g in prange(groups):
        for task in range(g * tasks // groups, (g + 1) * tasks // groups):
            r = task // chunks
            start = (task - r * chunks) * CHUNK
            limit = limits[r]
            row = real[r, start : min(size, start + CHUNK)]
            dest = out[r, start : min(size, start + CHUNK)]
            for i in range(row.size):
                a = row[i]
                if abs(a) < limit:
                    dest[i] = 0.0
                elif not same:
                    dest[i] = a


limits = SplitKernel(_limits)
count_below = cached_njit(_count_below)
flush = SplitKernel(_flush)
