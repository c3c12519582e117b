r"""Three-term recurrences for the matrix harmonics ``T_lm`` and the Legendre functions.

These build one *diagonal* (matrix harmonics) or one *order* (Legendre functions) of a basis
at a time, in O(N²) time and memory each, so that a whole transform costs O(N³) flops —
the size of the transform itself — without an eigensolver and without holding the
``N³/3`` numbers of the whole basis (the fast transforms of :mod:`.quantization`).

Matrix harmonics
----------------
On the lower diagonal ``m`` (entries ``(i+m, i)``, ``i = 0..n-1``, ``n = N-m``) the
anticommutator ``X ↦ S_3 X + X S_3`` multiplies entry ``i`` by ``c_i = 2i + m - (N-1)``; it is
a rank-1 tensor operator, so it maps ``T_lm`` into ``T_{l±1,m}`` only:

.. math:: c_i\, T_{lm}[i] = a_{l+1}\, T_{l+1,m}[i] + a_l\, T_{l-1,m}[i],\qquad
          a_l = \sqrt{\frac{(l^2 - m^2)(N^2 - l^2)}{4l^2 - 1}}

(the quantized ``z Y_lm`` recurrence; the positive signs are those of the Condon–Shortley
ladder of :func:`~lieflow_zeitlin.laplacian.harmonics`, checked against it in the tests).
For fixed ``i`` this is a recurrence in ``l`` whose solution is row ``i`` of the orthogonal
matrix ``V_m`` (the unit eigenvector of the Jacobi matrix ``(a_l)`` for the eigenvalue
``c_i``). It is run from both ends: *forward* from ``T_mm`` (closed form, entries
``∝ (-1)^m Π_{j=i+1}^{i+m} sqrt(j(N-j))``) up to ``l* = round(sqrt(mN))``, where
``2 a_l ≈ N - m`` is largest and every row is oscillatory, and *backward* from
``T_{N-1,m}`` (closed form up to sign, ``∝ 1/sqrt(i! (N-1-i)! (i+m)! (N-1-i-m)!)``, the
stretched 3j symbol) down to ``l*``. Each direction grows out of its forbidden region, where
it is stable; the two are matched at ``l*, l*+1`` (ratio by least squares, which also carries
the sign) and the row is normalised to one. Starting values below ``1e-300`` are raised to it
(the rows are rescaled anyway), which keeps every value finite for ``N <= MAX_N``.

Legendre functions
------------------
The orthonormal ``P̄_lm(cos θ) = Y_lm(θ, 0)`` (Condon–Shortley phase, as
:func:`scipy.special.sph_legendre_p`) by the standard forward recurrence in ``l`` (stable):
``P̄_mm = (-1)^m sqrt((2m+1)/4π · Π_{k<=m} (2k-1)/2k) sin^m θ`` and
``P̄_lm = α_lm (x P̄_{l-1,m} - β_lm P̄_{l-2,m})``.

Both kernels are compiled with numba when it is installed (``lieflow-zeitlin[fast]``) and
run as row-wise numpy otherwise (same arithmetic, more Python overhead).
"""

from __future__ import annotations

import functools
import importlib
import math
from collections.abc import Callable
from typing import Any

import attrs
import numpy as np
from numpy.typing import NDArray

Array = NDArray[Any]

#: Largest N for which the harmonic recurrence keeps every value finite (the dynamic range
#: of a row is about ``2^N``; starting values are floored at ``1e-300``).
MAX_N = 1400

_FLOOR = 1e-300


@functools.cache
def have_numba() -> bool:
    """Whether numba can be imported (``lieflow-zeitlin[fast]``). The first call imports it:
    the first use of a compiled kernel, not the import of the plugin (numba takes 0.15 s to
    import, which every command that loads the plugins paid before)."""
    try:
        importlib.import_module("numba")
    except ImportError:
        return False
    return True


@attrs.frozen
class _Kernel:
    """``func`` compiled with numba at its first call, with an on-disk cache in the user's
    cache directory (:func:`lieflow.numba_cache.cached_njit`); ``fastmath`` lets the compiler
    reassociate sums (vectorised dot products; the order of additions is then the
    compiler's); ``reciprocal`` also lets it use reciprocals (LLVM's ``arcp``: 1.4x faster
    sweeps in :func:`_degree_squares`, which already multiplies by ``1/a``). Call it only
    where :func:`have_numba`."""

    func: Callable[..., Any]
    fastmath: bool = False
    reciprocal: bool = False
    #: The function's first argument is the number of groups it splits its work into
    #: (:class:`lieflow.numba_cache.SplitKernel`): more than one runs its parallel build.
    split: bool = False

    def __call__(self, *args: Any) -> Any:
        return self.dispatcher(self.split and args[0] > 1)(*args)

    def dispatcher(self, parallel: bool = False) -> Any:
        """numba's compiled function (compiled on the first call, then the same object): what
        another compiled function calls; ``parallel``: the build of a split kernel that
        runs its groups on numba's threads."""
        return _compile(self.func, self.fastmath, self.reciprocal, parallel)


@functools.cache
def _compile(
    func: Callable[..., Any], fastmath: bool, reciprocal: bool = False, parallel: bool = False
) -> Any:
    from lieflow.numba_cache import SplitKernel

    flags = ({"reassoc", "contract"} | ({"arcp"} if reciprocal else set())) if fastmath else False
    return SplitKernel(func, {"nogil": True, "fastmath": flags}).dispatcher(parallel)


def work_groups(size: int) -> int:
    """How many groups a split kernel divides a pass over ``size`` real numbers into
    (:func:`lieflow.numba_cache.work_groups`); call it only where numba is installed."""
    from lieflow.numba_cache import work_groups as groups

    return groups(size)


# ------------------------------------------------------------------ matrix harmonics
def harmonic_coefficients(N: int, m: int) -> Array:
    """``a[k] = a_{m+k}`` for ``k = 0..n`` (``n = N - m``; ``a[0] = a[n] = 0``)."""
    n = N - m
    a = np.zeros(n + 1)
    l = np.arange(m + 1, N, dtype=float)
    a[1:n] = np.sqrt((l * l - m * m) * (N * N - l * l) / (4 * l * l - 1))
    return a


def _unit_log(logv: Array) -> Array:
    """``logv`` shifted so that ``Σ exp(2 logv) = 1``."""
    logv = logv - logv.max()
    return logv - 0.5 * math.log(float(np.sum(np.exp(2 * logv))))


def harmonic_start(N: int, m: int) -> tuple[Array, Array]:
    """Starting rows: ``T_mm`` on diagonal ``m`` (sign ``(-1)^m``) and ``|T_{N-1,m}|``,
    unit norm, floored at ``1e-300`` in magnitude."""
    from scipy.special import gammaln  # 0.1 s to import: on first use, not with the plugin

    n = N - m
    j = np.arange(1, N, dtype=float)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (np.log(j) + np.log(N - j)))])
    i = np.arange(n)
    logf = _unit_log(cum[i + m] - cum[i])
    logb = _unit_log(-0.5 * (gammaln(i + 1) + gammaln(N - i) + gammaln(i + m + 1) + gammaln(n - i)))
    f0 = (-1.0) ** m * np.exp(np.maximum(logf, math.log(_FLOOR)))
    b0 = np.exp(np.maximum(logb, math.log(_FLOOR)))
    return f0, b0


def split_degree(N: int, m: int) -> int:
    """``k1``: rows ``k < k1`` (degree ``m + k``) come from the forward recurrence, the rest
    from the backward one (``k1 = n`` when the diagonal is short enough to run forward only)."""
    n = N - m
    kstar = min(max(round(math.sqrt(m * N)) - m, 0), n - 1)
    return n if kstar + 3 > n else kstar + 2


def _harmonic_kernel(
    N: int, m: int, a: Array, f0: Array, b0: Array, k1: int, Vt: Array, sf: Array, sb: Array
) -> None:
    """Fill ``Vt`` (``(n+1, n)``, row ``n`` zero) with the unscaled recurrence rows and
    ``sf``/``sb`` with the column scales of rows ``< k1`` / ``>= k1`` (explicit loops for
    numba)."""
    n = N - m
    c = np.empty(n)
    nf = np.zeros(n)
    nb = np.zeros(n)
    for i in range(n):
        c[i] = 2.0 * i + m - (N - 1)
        Vt[0, i] = f0[i]
        Vt[n, i] = 0.0
        nf[i] = f0[i] * f0[i]
    if k1 > 1:
        inv = 1.0 / a[1]
        for i in range(n):
            v = c[i] * f0[i] * inv
            Vt[1, i] = v
            nf[i] += v * v
    for k in range(1, k1 - 1):
        inv = 1.0 / a[k + 1]
        ak = a[k]
        for i in range(n):
            v = (c[i] * Vt[k, i] - ak * Vt[k - 1, i]) * inv
            Vt[k + 1, i] = v
            nf[i] += v * v
    if k1 == n:
        for i in range(n):
            s = 1.0 / math.sqrt(nf[i])
            sf[i] = s
            sb[i] = s
        return
    for i in range(n):
        Vt[n - 1, i] = b0[i]
        nb[i] = b0[i] * b0[i]
    for k in range(n - 2, k1 - 1, -1):
        inv = 1.0 / a[k + 1]
        ak = a[k + 2]
        for i in range(n):
            v = (c[i] * Vt[k + 1, i] - ak * Vt[k + 2, i]) * inv
            Vt[k, i] = v
            nb[i] += v * v
    # the backward values at k1 - 1 and k1 - 2 (the forward rows hold those places)
    inv1 = 1.0 / a[k1]
    inv2 = 1.0 / a[k1 - 1]
    for i in range(n):
        b1 = (c[i] * Vt[k1, i] - a[k1 + 1] * Vt[k1 + 1, i]) * inv1
        b2 = (c[i] * b1 - a[k1] * Vt[k1, i]) * inv2
        r = (Vt[k1 - 1, i] * b1 + Vt[k1 - 2, i] * b2) / (b1 * b1 + b2 * b2)
        s = 1.0 / math.sqrt(nf[i] + r * r * nb[i])
        sf[i] = s
        sb[i] = s * r


def _harmonic_rows(
    N: int, m: int, a: Array, f0: Array, b0: Array, k1: int, Vt: Array, sf: Array, sb: Array
) -> None:
    """:func:`_harmonic_kernel` with numpy row operations (no numba)."""
    n = N - m
    c = 2.0 * np.arange(n) + m - (N - 1)
    Vt[0] = f0
    Vt[n] = 0.0
    if k1 > 1:
        Vt[1] = c * f0 / a[1]
    for k in range(1, k1 - 1):
        Vt[k + 1] = (c * Vt[k] - a[k] * Vt[k - 1]) / a[k + 1]
    nf = np.einsum("ki,ki->i", Vt[:k1], Vt[:k1])
    if k1 == n:
        sf[:] = sb[:] = 1.0 / np.sqrt(nf)
        return
    Vt[n - 1] = b0
    for k in range(n - 2, k1 - 1, -1):
        Vt[k] = (c * Vt[k + 1] - a[k + 2] * Vt[k + 2]) / a[k + 1]
    nb = np.einsum("ki,ki->i", Vt[k1:n], Vt[k1:n])
    b1 = (c * Vt[k1] - a[k1 + 1] * Vt[k1 + 1]) / a[k1]
    b2 = (c * b1 - a[k1] * Vt[k1]) / a[k1 - 1]
    r = (Vt[k1 - 1] * b1 + Vt[k1 - 2] * b2) / (b1 * b1 + b2 * b2)
    sf[:] = 1.0 / np.sqrt(nf + r * r * nb)
    sb[:] = sf * r


_harmonic_compiled = _Kernel(_harmonic_kernel)


def _harmonic_sweeps(
    N: int,
    m: int,
    a: Array,
    f0: Array,
    b0: Array,
    k1: int,
    C: Array,
    accf: Array,
    accb: Array,
    Xf: Array,
    Xb: Array,
    coef: Array,
    stats: Array,
) -> None:
    """The recurrences of :func:`_harmonic_kernel` with three rolling rows, fused with the
    products (numba): for every unscaled row ``v_k``, ``acc[q] += C[q, k] v_k`` (``accf``
    for ``k < k1``, ``accb`` after) and ``coef[q, k] = Σ_i X[q, i] v_k[i]`` (``Xf``/``Xb``).
    ``stats`` rows: ``nf``, ``nb`` (sums of squares), the backward values at ``k1 - 1`` and
    ``k1 - 2`` and the forward ones there (for the matching)."""
    n = N - m
    Q = C.shape[0]
    P = Xf.shape[0]
    c = np.empty(n)
    u = np.zeros(n)
    v = np.empty(n)
    w = np.empty(n)
    for i in range(n):
        c[i] = 2.0 * i + m - (N - 1)
        v[i] = f0[i]
        stats[0, i] = 0.0
        stats[1, i] = 0.0
    for k in range(k1):
        if k > 0:
            inv = 1.0 / a[k]
            ak = a[k - 1]
            for i in range(n):
                w[i] = (c[i] * v[i] - ak * u[i]) * inv
            u, v, w = v, w, u
        for i in range(n):
            stats[0, i] += v[i] * v[i]
        for q in range(Q):
            cq = C[q, k]
            for i in range(n):
                accf[q, i] += cq * v[i]
        for q in range(P):
            t = 0.0
            for i in range(n):
                t += Xf[q, i] * v[i]
            coef[q, k] = t
    if k1 == n:
        return
    for i in range(n):
        stats[4, i] = v[i]
        stats[5, i] = u[i]
        u[i] = 0.0
        v[i] = b0[i]
    for k in range(n - 1, k1 - 3, -1):
        if k < n - 1:
            inv = 1.0 / a[k + 1]
            ak = a[k + 2]
            for i in range(n):
                w[i] = (c[i] * v[i] - ak * u[i]) * inv
            u, v, w = v, w, u
        if k < k1:
            row = 2 if k == k1 - 1 else 3
            for i in range(n):
                stats[row, i] = v[i]
            continue
        for i in range(n):
            stats[1, i] += v[i] * v[i]
        for q in range(Q):
            cq = C[q, k]
            for i in range(n):
                accb[q, i] += cq * v[i]
        for q in range(P):
            t = 0.0
            for i in range(n):
                t += Xb[q, i] * v[i]
            coef[q, k] = t


_sweeps_compiled = _Kernel(_harmonic_sweeps, fastmath=True)


def _scales(stats: Array, k1: int, n: int) -> tuple[Array, Array]:
    """Column scales ``(sf, sb)`` from the statistics of :func:`_harmonic_sweeps`."""
    if k1 == n:
        s = 1.0 / np.sqrt(stats[0])
        return s, s
    b1, b2, f1, f2 = stats[2], stats[3], stats[4], stats[5]
    r = (f1 * b1 + f2 * b2) / (b1 * b1 + b2 * b2)
    s = 1.0 / np.sqrt(stats[0] + r * r * stats[1])
    return s, s * r


def harmonic_synthesis(N: int, m: int, C: Array) -> Array:
    """``C @ V_m.T`` for real ``C`` of shape ``(Q, n)`` (columns by degree ``m + k``), fused
    with the recurrence (numba required): ``O(n)`` memory besides the result."""
    n = N - m
    a = harmonic_coefficients(N, m)
    f0, b0 = harmonic_start(N, m)
    k1 = split_degree(N, m)
    Q = C.shape[0]
    accf = np.zeros((Q, n))
    accb = np.zeros((Q, n))
    stats = np.zeros((6, n))
    empty = np.zeros((0, n))
    _sweeps_compiled(
        N,
        m,
        a,
        f0,
        b0,
        k1,
        np.ascontiguousarray(C),
        accf,
        accb,
        empty,
        empty,
        np.zeros((0, n)),
        stats,
    )
    sf, sb = _scales(stats, k1, n)
    return accf * sf + accb * sb


def harmonic_scales(N: int, m: int) -> tuple[Array, Array, Array, int, Array, Array]:
    """``(a, f0, b0, k1, sf, sb)`` of diagonal ``m``: the recurrence's coefficients, its
    starting rows, the split degree and the column scales (one sweep, numba required)."""
    n = N - m
    a = harmonic_coefficients(N, m)
    f0, b0 = harmonic_start(N, m)
    k1 = split_degree(N, m)
    stats = np.zeros((6, n))
    empty = np.zeros((0, n))
    _sweeps_compiled(N, m, a, f0, b0, k1, empty, empty, empty, empty, empty, empty, stats)
    sf, sb = _scales(stats, k1, n)
    return a, f0, b0, k1, sf, sb


def harmonic_analysis(N: int, m: int, X: Array) -> Array:
    """``X @ V_m`` for real ``X`` of shape ``(P, n)`` (entries along the diagonal): one sweep
    for the scales, one for the products (numba required)."""
    n = N - m
    a, f0, b0, k1, sf, sb = harmonic_scales(N, m)
    empty = np.zeros((0, n))
    stats = np.zeros((6, n))
    coef = np.zeros((X.shape[0], n))
    _sweeps_compiled(N, m, a, f0, b0, k1, empty, empty, empty, X * sf, X * sb, coef, stats)
    return coef


def harmonic_diagonal(
    N: int, m: int, *, compiled: bool | None = None
) -> tuple[Array, int, Array, Array]:
    """``(Vt, k1, sf, sb)`` for diagonal ``m``: ``V_m[i, k] = Vt[k, i] * (sf[i] if k < k1
    else sb[i])`` is the matrix of :func:`~lieflow_zeitlin.laplacian.harmonics` (``Vt`` has
    ``n + 1`` rows; the last is zero padding)."""
    n = N - m
    a = harmonic_coefficients(N, m)
    f0, b0 = harmonic_start(N, m)
    k1 = split_degree(N, m)
    Vt = np.empty((n + 1, n))
    sf = np.empty(n)
    sb = np.empty(n)
    use = have_numba() if compiled is None else compiled
    kernel = _harmonic_compiled if use and have_numba() else _harmonic_rows
    kernel(N, m, a, f0, b0, k1, Vt, sf, sb)
    return Vt, k1, sf, sb


def harmonics_by_recurrence(N: int, *, compiled: bool | None = None) -> Any:
    """The ``(m, V_m)`` of :func:`~lieflow_zeitlin.laplacian.harmonics`, by recurrence
    (``m = N-1, ..., 0``)."""
    for m in range(N - 1, -1, -1):
        Vt, k1, sf, sb = harmonic_diagonal(N, m, compiled=compiled)
        V = Vt[: N - m].T.copy()
        V[:, :k1] *= sf[:, None]
        V[:, k1:] *= sb[:, None]
        yield m, V


# ------------------------------------------------------------------ sums by degree
def _degree_squares(
    N: int,
    k1s: Array,
    start: Array,
    a: Array,
    f0: Array,
    b0: Array,
    sf: Array,
    sb: Array,
    W: Array,
    out: Array,
) -> None:
    """``out[q, m + k] += w_m ((x·v_k)² + (y·v_k)²)`` over the diagonals ``m`` of each
    ``W[q]``: ``x + iy`` is the lower diagonal ``m`` of the skew-Hermitian part of ``W[q]``
    times the column scales (``sf`` for ``k < k1``, ``sb`` after), ``v_k`` the unscaled rows
    of :func:`_harmonic_kernel` (same arithmetic: forward from ``f0``, backward from
    ``b0``), ``w_0 = 1``, ``w_m = 2`` (the upper diagonal's coefficients have the same
    moduli). Diagonal ``m``'s tables start at ``start[m]``. The recurrence and the two
    products share one pass over the entries; every work row is local, so the compiler can
    vectorise that pass (numba)."""
    K = W.shape[0]
    c = np.empty(N)
    u = np.empty(N)
    v = np.empty(N)
    re = np.empty(N)
    im = np.empty(N)
    x = np.empty(N)
    y = np.empty(N)
    for q in range(K):
        for m in range(N):
            n = N - m
            o = start[m]
            k1 = k1s[m]
            weight = 1.0 if m == 0 else 2.0
            for i in range(n):
                z = 0.5 * (W[q, i + m, i] - np.conj(W[q, i, i + m]))
                re[i] = z.real
                im[i] = z.imag
                c[i] = 2.0 * i + m - (N - 1)
            # forward (rows 0..k1-1): v_k = (c v_{k-1} - a_{k-1} v_{k-2}) / a_k;
            # backward (rows n-1..k1): v_k = (c v_{k+1} - a_{k+2} v_{k+2}) / a_{k+1}
            for back in range(2 if k1 < n else 1):
                scale = sb if back else sf
                first = b0 if back else f0
                step = -1 if back else 1
                k = n - 1 if back else 0
                for i in range(n):
                    x[i] = re[i] * scale[o + i]
                    y[i] = im[i] * scale[o + i]
                    u[i] = 0.0
                    v[i] = first[o + i]
                for j in range(n - k1 if back else k1):
                    t0 = 0.0
                    t1 = 0.0
                    if j == 0:
                        for i in range(n):
                            t0 += x[i] * v[i]
                            t1 += y[i] * v[i]
                    else:
                        inv = 1.0 / a[o + k + back]
                        ak = a[o + k + back - step]
                        for i in range(n):
                            wi = (c[i] * v[i] - ak * u[i]) * inv
                            u[i] = v[i]
                            v[i] = wi
                            t0 += x[i] * wi
                            t1 += y[i] * wi
                    out[q, m + k] += weight * (t0 * t0 + t1 * t1)
                    k += step


_degree_squares_compiled = _Kernel(_degree_squares, fastmath=True, reciprocal=True)


@attrs.frozen(eq=False)
class DiagonalTables:
    """The recurrence tables of all ``N`` diagonals (:func:`harmonic_scales`), packed: built
    once per ``N`` (O(N³/3) flops, ``5N²/2`` numbers), so that :meth:`squares_by_degree`
    only runs the product sweeps (numba required; ``N <= MAX_N``).

    Diagonal ``m``'s entries are at ``start[m] : start[m] + N - m + 1`` of ``a`` (the
    coefficients ``a_{m+k}``, ``k = 0..n``) and of ``f0``, ``b0``, ``sf``, ``sb`` (the last
    entry unused); ``k1[m]`` is its split degree.
    """

    N: int
    k1: Array = attrs.field(repr=False)
    start: Array = attrs.field(repr=False)
    a: Array = attrs.field(repr=False)
    f0: Array = attrs.field(repr=False)
    b0: Array = attrs.field(repr=False)
    sf: Array = attrs.field(repr=False)
    sb: Array = attrs.field(repr=False)

    @classmethod
    def of(cls, N: int) -> DiagonalTables:
        """The tables of ``N×N`` matrices."""
        start = np.concatenate([[0], np.cumsum(N - np.arange(N) + 1)]).astype(np.int64)
        k1 = np.empty(N, dtype=np.int64)
        packed = np.zeros((5, int(start[-1])))
        for m in range(N):
            a, f0, b0, k1[m], sf, sb = harmonic_scales(N, m)
            o, n = int(start[m]), N - m
            packed[0, o : o + n + 1] = a
            for row, values in enumerate((f0, b0, sf, sb), start=1):
                packed[row, o : o + n] = values
        return cls(N, k1, start, *packed)

    def squares_by_degree(self, W: Array) -> Array:
        """``Σ_{|m|<=l} |<T_lm, A>_F|²`` for ``l = 0..N-1`` of the skew-Hermitian part ``A``
        of each matrix of ``W`` (``(K, N, N)``, complex128): shape ``(K, N)``. One pass of
        the recurrence per diagonal and state, fused with the products: about
        ``N³/3`` entries, each a few flops."""
        out = np.zeros((W.shape[0], self.N))
        _degree_squares_compiled(
            self.N, self.k1, self.start, self.a, self.f0, self.b0, self.sf, self.sb, W, out
        )
        return out


# ------------------------------------------------------------------ Legendre functions
def legendre_start(m: int, theta: Array) -> Array:
    """``P̄_mm(cos θ)`` (Condon–Shortley phase), computed through logarithms."""
    k = np.arange(1, m + 1, dtype=float)
    log_c = 0.5 * math.log((2 * m + 1) / (4 * math.pi)) + 0.5 * float(
        np.sum(np.log((2 * k - 1) / (2 * k)))
    )
    s = np.sin(theta)
    with np.errstate(divide="ignore"):
        logp = log_c + m * np.log(s) if m else np.full(theta.shape, log_c)
    return (-1.0) ** m * np.exp(logp)


def legendre_coefficients(N: int, m: int) -> tuple[Array, Array]:
    """``α_l, β_l`` of ``P̄_lm = α_l (x P̄_{l-1,m} - β_l P̄_{l-2,m})`` at index ``k = l - m``."""
    n = N - m
    l = np.arange(m, N, dtype=float)
    alpha = np.zeros(n)
    beta = np.zeros(n)
    alpha[1:] = np.sqrt((4 * l[1:] ** 2 - 1) / (l[1:] ** 2 - m * m))
    lm1 = l[1:] - 1
    beta[1:] = np.sqrt((lm1**2 - m * m) / (4 * lm1**2 - 1))
    return alpha, beta


def _legendre_kernel(x: Array, p0: Array, alpha: Array, beta: Array, P: Array) -> None:
    n = alpha.shape[0]
    nx = x.shape[0]
    for j in range(nx):
        P[0, j] = p0[j]
    if n > 1:
        for j in range(nx):
            P[1, j] = alpha[1] * x[j] * p0[j]
    for k in range(2, n):
        al = alpha[k]
        be = beta[k]
        for j in range(nx):
            P[k, j] = al * (x[j] * P[k - 1, j] - be * P[k - 2, j])


def _legendre_rows(x: Array, p0: Array, alpha: Array, beta: Array, P: Array) -> None:
    n = alpha.shape[0]
    P[0] = p0
    if n > 1:
        P[1] = alpha[1] * x * p0
    for k in range(2, n):
        P[k] = alpha[k] * (x * P[k - 1] - beta[k] * P[k - 2])


_legendre_compiled = _Kernel(_legendre_kernel)


def _legendre_sweep(
    x: Array, p0: Array, alpha: Array, beta: Array, C: Array, acc: Array, X: Array, coef: Array
) -> None:
    """The recurrence of :func:`_legendre_kernel` with rolling rows, fused with
    ``acc[q] += C[q, k] P_k`` and ``coef[q, k] = Σ_j X[q, j] P_k[j]`` (numba)."""
    n = alpha.shape[0]
    nx = x.shape[0]
    Q = C.shape[0]
    R = X.shape[0]
    u = np.zeros(nx)
    v = p0.copy()
    w = np.empty(nx)
    for k in range(n):
        if k == 1:
            for j in range(nx):
                w[j] = alpha[1] * x[j] * v[j]
            u, v, w = v, w, u
        elif k > 1:
            al = alpha[k]
            be = beta[k]
            for j in range(nx):
                w[j] = al * (x[j] * v[j] - be * u[j])
            u, v, w = v, w, u
        for q in range(Q):
            cq = C[q, k]
            for j in range(nx):
                acc[q, j] += cq * v[j]
        for q in range(R):
            t = 0.0
            for j in range(nx):
                t += X[q, j] * v[j]
            coef[q, k] = t


_legendre_sweep_compiled = _Kernel(_legendre_sweep, fastmath=True)


def legendre_synthesis(N: int, m: int, theta: Array, C: Array) -> Array:
    """``C @ P`` with ``P = legendre_order(N, m, θ)``, fused (numba required)."""
    alpha, beta = legendre_coefficients(N, m)
    acc = np.zeros((C.shape[0], theta.size))
    empty = np.zeros((0, theta.size))
    _legendre_sweep_compiled(
        np.cos(theta),
        legendre_start(m, theta),
        alpha,
        beta,
        np.ascontiguousarray(C),
        acc,
        empty,
        np.zeros((0, N - m)),
    )
    return acc


def legendre_analysis(N: int, m: int, theta: Array, X: Array) -> Array:
    """``X @ P.T`` with ``P = legendre_order(N, m, θ)``, fused (numba required)."""
    alpha, beta = legendre_coefficients(N, m)
    coef = np.zeros((X.shape[0], N - m))
    _legendre_sweep_compiled(
        np.cos(theta),
        legendre_start(m, theta),
        alpha,
        beta,
        np.zeros((0, N - m)),
        np.zeros((0, theta.size)),
        np.ascontiguousarray(X),
        coef,
    )
    return coef


def legendre_order(N: int, m: int, theta: Array, *, compiled: bool | None = None) -> Array:
    """``P[k, j] = Y_{m+k, m}(θ_j, 0)`` for ``k = 0..N-m-1``: shape ``(N - m, len(θ))``."""
    alpha, beta = legendre_coefficients(N, m)
    P = np.empty((N - m, theta.size))
    use = have_numba() if compiled is None else compiled
    kernel = _legendre_compiled if use and have_numba() else _legendre_rows
    kernel(np.cos(theta), legendre_start(m, theta), alpha, beta, P)
    return P
