"""The underflow guard's loops on NumPy arrays (:func:`lieflow.underflow.flush_tiny`),
compiled with numba. Imports numba: import it only where numba is installed."""

from __future__ import annotations

from typing import Any

import numpy as np

from .numba_cache import cached_njit


def _largest(row: Any) -> float:  # pragma: no cover - compiled
    """``max |row|``: a maximum is exact in any order, so the compiler may vectorize it
    (``fastmath``; a NaN may or may not show: the guard tolerates either)."""
    top = 0.0
    for i in range(row.size):
        top = max(top, abs(row[i]))
    return top


_largest_compiled = cached_njit(_largest, fastmath=True)


def _limits(real: Any, tau: float) -> Any:  # pragma: no cover - compiled
    """``tau`` times the largest ``|x|`` of each row (0 where that is not finite)."""
    out = np.zeros(real.shape[0])
    for r in range(real.shape[0]):
        top = _largest_compiled(real[r])
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


def _flush(real: Any, limits: Any, out: Any, same: bool) -> None:  # pragma: no cover
    """``out = real`` with the numbers below their row's limit set to zero; ``same``: ``out``
    is ``real`` (only those numbers are written)."""
    for r in range(real.shape[0]):
        limit = limits[r]
        row = real[r]
        dest = out[r]
        for i in range(row.size):
            a = row[i]
            if abs(a) < limit:
                dest[i] = 0.0
            elif not same:
                dest[i] = a


limits = cached_njit(_limits)
count_below = cached_njit(_count_below)
flush = cached_njit(_flush)
