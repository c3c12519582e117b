"""The passes of an Anderson update over one NumPy problem's numbers
(:func:`lieflow.solvers.anderson.update`), compiled with numba. Imports numba: import it
only where numba is installed.

The numbers come as real 2-D views ``(rows, width)`` (a matrix of ``n`` complex numbers
per row: ``width = 2n``), the history as ``(m, rows, width)``. With ``triangle`` (the
unknowns are skew-Hermitian, skew-symmetric if real: :func:`lieflow.solvers.anderson.update`)
only the upper triangle ``j >= i`` of each matrix is read or written, and the inner
products weigh its off-diagonal numbers twice (for skew-Hermitian matrices: the Frobenius
inner product); the correction's lower triangle is then the mirror image of its upper
one. Sums are reassociated by the compiler (``fastmath``: vectorized, several partial
sums): their last bits are the compiler's, which the acceleration tolerates (its
coefficients enter the path to the fixed point, never the fixed point itself)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..numba_cache import cached_njit

#: Numbers handled at a time: a chunk of the new differences stays in the L1/L2 cache
#: while the history's columns stream past it.
CHUNK = 2048
#: Rows gathered at a time by the mirror pass (and the padding of the gathered rows: rows
#: a multiple of 4 KiB apart share cache sets).
BAND, PAD = 32, 16

_FAST = {"reassoc", "contract"}


def _record(
    x: Any,
    g: Any,
    f_prev: Any,
    g_prev: Any,
    f: Any,
    dF: Any,
    dG: Any,
    slot: int,
    columns: Any,
    have: bool,
    row: Any,
    parts: int,
    triangle: bool,
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """One pass over the numbers: the residual ``f = g - x`` (written to ``f``, which may
    be ``f_prev``), and where ``have`` the new columns ``dF[slot] = f - f_prev``,
    ``dG[slot] = g - g_prev`` with the Gram row ``row[j] = <dF[j], dF[slot]>`` for ``j``
    in ``columns`` and ``slot``. Returns ``(<f, f>, <g, g>, <dF[slot], f>)`` (the last 0
    without ``have``). Row by row, in chunks of :data:`CHUNK` numbers; with ``triangle``
    from the diagonal entry, which weighs one (the others two)."""
    rows, width = x.shape
    sums = np.zeros(3)
    for j in range(row.size):
        row[j] = 0.0
    w = 2.0 if triangle else 1.0
    for r in range(rows):
        first = parts * r if triangle else 0
        for start in range(first, width, CHUNK):
            stop = min(start + CHUNK, width)
            xs = x[r, start:stop]
            gs = g[r, start:stop]
            fp = f_prev[r, start:stop]
            fs = f[r, start:stop]
            a = 0.0
            b = 0.0
            if have:
                d = dF[slot, r, start:stop]
                e = dG[slot, r, start:stop]
                gp = g_prev[r, start:stop]
                c = 0.0
                dd = 0.0
                for i in range(stop - start):
                    fi = gs[i] - xs[i]
                    di = fi - fp[i]
                    e[i] = gs[i] - gp[i]
                    d[i] = di
                    fs[i] = fi
                    a += fi * fi
                    b += gs[i] * gs[i]
                    c += di * fi
                    dd += di * di
                if triangle and start == first:  # the diagonal entry once, not twice
                    for i in range(parts):
                        c -= 0.5 * d[i] * fs[i]
                        dd -= 0.5 * d[i] * d[i]
                sums[2] += w * c
                row[slot] += w * dd
                for k in range(columns.size):
                    h = dF[columns[k], r, start:stop]
                    t = 0.0
                    for i in range(stop - start):
                        t += h[i] * d[i]
                    if triangle and start == first:
                        for i in range(parts):
                            t -= 0.5 * h[i] * d[i]
                    row[columns[k]] += w * t
            else:
                for i in range(stop - start):
                    fi = gs[i] - xs[i]
                    fs[i] = fi
                    a += fi * fi
                    b += gs[i] * gs[i]
            if triangle and start == first:
                for i in range(parts):
                    a -= 0.5 * fs[i] * fs[i]
                    b -= 0.5 * gs[i] * gs[i]
            sums[0] += w * a
            sums[1] += w * b
    return sums[0], sums[1], sums[2]


def _correct(
    g: Any, dG: Any, columns: Any, gamma: Any, out: Any, parts: int, triangle: bool
) -> None:  # pragma: no cover - compiled
    """``out = g - Σ_c gamma[c] dG[columns[c]]`` (at least one column); with ``triangle``
    on the upper triangle, then its mirror image ``out_ji = -conj(out_ij)`` below."""
    rows, width = g.shape
    acc = np.empty(CHUNK)
    for r in range(rows):
        for start in range(parts * r if triangle else 0, width, CHUNK):
            stop = min(start + CHUNK, width)
            size = stop - start
            h = dG[columns[0], r, start:stop]
            w = gamma[0]
            for i in range(size):
                acc[i] = w * h[i]
            for c in range(1, columns.size):
                h = dG[columns[c], r, start:stop]
                w = gamma[c]
                for i in range(size):
                    acc[i] += w * h[i]
            gs = g[r, start:stop]
            o = out[r, start:stop]
            for i in range(size):
                o[i] = gs[i] - acc[i]
    if not triangle:
        return
    # the lower triangle, band by band: BAND columns of the upper triangle gathered as
    # rows (negated real parts: -conj(z) = -re + i im), then written along rows
    n = rows
    T = np.empty((BAND, width + PAD))
    for jb in range(0, n, BAND):
        count = min(BAND, n - jb)
        for i in range(min(jb + count, n)):
            for a in range(count):
                T[a, parts * i] = -out[i, parts * (jb + a)]
                if parts == 2:
                    T[a, parts * i + 1] = out[i, parts * (jb + a) + 1]
        for a in range(count):
            j = jb + a
            o = out[j]
            t = T[a]
            for i in range(parts * j):
                o[i] = t[i]


record = cached_njit(_record, fastmath=_FAST)
correct = cached_njit(_correct, fastmath=_FAST)
