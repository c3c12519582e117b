"""The passes of an Anderson update over one NumPy problem's numbers
(:func:`lieflow.solvers.anderson.update`), compiled with numba. Imports numba: import it
only where numba is installed.

Sums are reassociated by the compiler (``fastmath``: vectorized, several partial sums):
their last bits are the compiler's, which the acceleration tolerates (its coefficients
enter only the path to the fixed point, never the fixed point itself)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..numba_cache import cached_njit

#: Numbers handled at a time: the chunk of the new differences stays in the L1/L2 cache
#: while the history's columns stream past it.
CHUNK = 2048

_FAST = {"reassoc", "contract"}


def _record(
    x: Any, g: Any, f_prev: Any, g_prev: Any, f: Any, dF: Any, dG: Any, slot: int,
    columns: Any, have: bool, row: Any,
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """One pass over the numbers (real views, 1-D; ``dF``, ``dG``: ``(m, size)``): the
    residual ``f = g - x`` (written to ``f``, which may be ``f_prev``), and where ``have``
    the new columns ``dF[slot] = f - f_prev``, ``dG[slot] = g - g_prev`` with the Gram row
    ``row[j] = <dF[j], dF[slot]>`` for ``j`` in ``columns`` and ``slot``. Returns
    ``(<f, f>, <g, g>, <dF[slot], f>)`` (the last 0 without ``have``)."""
    n = x.size
    ff = 0.0
    gg = 0.0
    df_f = 0.0
    for j in range(row.size):
        row[j] = 0.0
    for start in range(0, n, CHUNK):
        stop = min(start + CHUNK, n)
        xs = x[start:stop]
        gs = g[start:stop]
        fp = f_prev[start:stop]
        fs = f[start:stop]
        if have:
            d = dF[slot][start:stop]
            e = dG[slot][start:stop]
            gp = g_prev[start:stop]
            dd = 0.0
            for i in range(stop - start):
                fi = gs[i] - xs[i]
                di = fi - fp[i]
                e[i] = gs[i] - gp[i]
                d[i] = di
                fs[i] = fi
                ff += fi * fi
                gg += gs[i] * gs[i]
                df_f += di * fi
                dd += di * di
            row[slot] += dd
            for c in range(columns.size):
                j = columns[c]
                h = dF[j][start:stop]
                s = 0.0
                for i in range(stop - start):
                    s += h[i] * d[i]
                row[j] += s
        else:
            for i in range(stop - start):
                fi = gs[i] - xs[i]
                fs[i] = fi
                ff += fi * fi
                gg += gs[i] * gs[i]
    return ff, gg, df_f


def _correct(g: Any, dG: Any, columns: Any, gamma: Any, out: Any) -> None:  # pragma: no cover
    """``out = g - Σ_c gamma[c] dG[columns[c]]`` (real views, 1-D; ``dG``: ``(m, size)``;
    at least one column), chunk by chunk: the combination summed in a small buffer, then
    subtracted from ``g``."""
    n = g.size
    acc = np.empty(CHUNK)
    for start in range(0, n, CHUNK):
        stop = min(start + CHUNK, n)
        size = stop - start
        h = dG[columns[0]][start:stop]
        w = gamma[0]
        for i in range(size):
            acc[i] = w * h[i]
        for c in range(1, columns.size):
            h = dG[columns[c]][start:stop]
            w = gamma[c]
            for i in range(size):
                acc[i] += w * h[i]
        gs = g[start:stop]
        o = out[start:stop]
        for i in range(size):
            o[i] = gs[i] - acc[i]


record = cached_njit(_record, fastmath=_FAST)
correct = cached_njit(_correct, fastmath=_FAST)
