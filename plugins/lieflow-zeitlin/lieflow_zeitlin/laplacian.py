r"""The Hoppe–Yau Laplacian on su(N): application, O(N²) inverse, quantized harmonics.

Spin matrices and index convention
----------------------------------
Rows and columns are indexed by ``i = 0..N-1`` ↔ the spin-``s`` weight ``μ = i - s``
(ascending), ``s = (N-1)/2``. The Hermitian spin matrices are

.. math:: S_3 = \operatorname{diag}(i - s),\qquad (S_+)_{i,i-1} = \sqrt{i(N-i)},\qquad
          S_- = S_+^T,\quad S_1 = \tfrac12(S_+ + S_-),\quad S_2 = \tfrac1{2i}(S_+ - S_-),

so ``[S_1, S_2] = i S_3`` (cyclically) and ``Σ_a S_a² = s(s+1) I`` (:func:`spin_matrices`).
The raising matrix ``S_+`` is *lower* triangular. This is the index order of quflow
(Modin & Viviani): with it the quantization of :mod:`lieflow_zeitlin.quantization` gives the
same matrix as quflow for the same field (``Q(x_a) = iħ S_a``). Reversing the index order
(``J S_a J``, ``J`` the exchange matrix) gives the descending convention ``S_3 = diag(s - i)``
of many physics texts; ``Δ_N`` below is the same in both.

The Laplacian
-------------
The Hoppe–Yau Laplacian (Hoppe 1982; Hoppe & Yau 1998) is minus the adjoint Casimir,

.. math:: \Delta_N P = -\sum_{a=1}^{3} [S_a, [S_a, P]].

Expanding the double commutators with the ladder matrices (lieflow SPEC §3) shows that it maps
every diagonal ``m = j - k`` of ``P`` to itself and is tridiagonal there: with ``P_i`` the
``i``-th entry ``P_{i+m, i}`` of diagonal ``m >= 0`` (``i = 0..N-m-1``),

.. math::
    (\Delta_N P)_i = -\big[(N-1)(2i+1+m) - 2i(i+m)\big] P_i + e_i P_{i-1} + e_{i+1} P_{i+1},
    \qquad e_i = \sqrt{i (N-i) (i+m) (N-i-m)}.

``Δ_N`` has real coefficients and commutes with transposition and with ``P -> J P J``
(the tridiagonal matrices are persymmetric), so diagonal ``-m`` (entries ``P_{i, i+m}``)
carries the same tridiagonal matrix. Its spectrum is ``-l(l+1)``, ``l = 0..N-1``, with
multiplicity ``2l+1``: on diagonal ``±m`` the eigenvalues are ``-l(l+1)`` for
``l = |m|..N-1`` (the eigenvector of degree ``l`` on the lower diagonal ``m >= 0`` is the
quantized spherical harmonic ``T_{l,m}``, on the upper one ``T_{l,-m}``, see
:func:`harmonics`). The kernel is spanned by the identity (``l = 0``), so on su(N) ``Δ_N``
is invertible; the shifted operator ``Δ_N - F`` (``F > 0``, the quasi-geostrophic model)
is invertible on all matrices and keeps the same eigenvectors.

Solving ``Δ_N P = W`` in O(N²): the packed layout
-------------------------------------------------
Copy the ``N²`` entries of ``W`` (row-major) into a zero buffer of ``N(N+1)`` entries and read
it as an ``N × (N+1)`` matrix ``Y``. Since ``i(N+1) + q = iN + (i+q)``,

.. math:: Y_{i,q} = W_{i, i+q}\ (i + q < N),\qquad Y_{i,q} = W_{i+1, i+q-N}\ (i + q \ge N),

so column ``q`` of ``Y`` holds diagonal ``-q`` of ``W`` followed by diagonal ``N+1-q`` (and
one zero pad): every column is two of the ``2N-1`` independent tridiagonal systems stacked,
decoupled where they meet. One vectorised Thomas sweep down the rows of ``Y`` therefore
solves all of them at once, for every matrix of a batch, without gathering diagonals. The
``m = 0`` system (column 0) is singular; it is *pinned* by adding ``-1/2`` to its first
diagonal entry (lieflow SPEC §3), which makes every system negative definite so that the
``LDL^T`` factorisation needs no pivoting; the trace is removed before and after the solve,
which makes :meth:`HoppeYauLaplacian.solve` the pseudo-inverse ``Δ_N^+`` (exact inverse on
su(N)). With a shift ``F > 0`` every system, ``m = 0`` included, is negative definite
as it stands and nothing is pinned (the identity is an eigenvector of ``Δ_N - F``, so the
traceless part of the solution is still that of the traceless part of ``W``).

To cut the Python overhead of ``2N`` row operations, the sweeps are *partitioned*: rows are
split into ``≈ √N`` blocks of ``≈ √N`` rows; the recurrences run inside all blocks at once,
then along the block boundaries, and a final broadcast adds each block's dependence on its
predecessor (the coefficients of that dependence are products of the ``LDL^T`` multipliers,
precomputed). That is ``O(√N)`` numpy calls per solve instead of ``O(N)``; complex data are
processed as interleaved real arrays so that every call is a same-type real ufunc. (LAPACK
``?pttrs`` on the concatenated block-diagonal system was measured no faster: it needs a
transposed copy in and out, and its sweep is sequential.) With numba installed
(``lieflow-zeitlin[fast]``) the same sweeps run as compiled loops, entry by entry in the
same order and without fused multiply–adds, so they give the same bits (tested) about five
times faster (a batch of four N = 64 matrices: 60 µs instead of 320 µs per solve).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from typing import Any

import attrs
import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow
from lieflow.backends import device_of, is_foreign_array, is_numpy, namespace

from ._recurrences import _Kernel, have_numba, work_groups
from .cyclic_reduction import CyclicReduction
from .projection import remove_trace, skew_part_into, su_project

#: ``range`` here; ``numba.prange`` in a split kernel's parallel build
#: (:class:`lieflow.numba_cache.SplitKernel`).
prange = range

Array = NDArray[Any]

#: Added to the first diagonal entry of the singular ``m = 0`` block (SPEC §3).
PIN = -0.5


def matrix_size(N: int) -> int:
    """``N`` as an int, or :class:`lieflow.InputError` unless it is an integer ``>= 2``."""
    if isinstance(N, bool) or not isinstance(N, (int, np.integer)) or N < 2:
        raise lieflow.InputError(f"the matrix size N must be an integer >= 2, got {N!r}")
    return int(N)


def spin_matrices(N: int) -> tuple[Array, Array, Array]:
    r"""The Hermitian spin-``(N-1)/2`` matrices ``(S_1, S_2, S_3)`` of the module convention.

    ``S_3 = diag(i - s)``, ``(S_+)_{i,i-1} = sqrt(i (N-i))`` (lower), ``S_± = S_1 ± i S_2``;
    ``[S_1, S_2] = i S_3`` and ``S_1² + S_2² + S_3² = s(s+1) I`` with ``s = (N-1)/2``.
    Dense ``N×N`` complex arrays (for checks and small examples; the Laplacian never forms
    them).
    """
    N = matrix_size(N)
    i = np.arange(1, N)
    Sp = np.zeros((N, N), dtype=complex)
    Sp[i, i - 1] = np.sqrt(i * (N - i))
    Sm = Sp.T.copy()
    S3 = np.diag(np.arange(N) - (N - 1) / 2).astype(complex)
    return 0.5 * (Sp + Sm), (Sp - Sm) / 2j, S3


def _coefficients(N: int, m: Array, k: Array) -> tuple[Array, Array]:
    r"""The one source of the Hoppe–Yau coefficients (SPEC §3): for entry ``k`` of diagonal
    ``m >= 0`` (arrays of the same shape, floats), the diagonal
    ``-[(N-1)(2k+1+m) - 2k(k+m)]`` and the coupling ``e_k = sqrt(k (N-k) (k+m) (N-k-m))``
    of entry ``k`` to entry ``k-1`` (zero for ``k = 0``; ``nan``-free wherever
    ``0 <= k < N-m``, which callers mask)."""
    d = -((N - 1) * (2 * k + 1 + m) - 2 * k * (k + m))
    e = np.sqrt(np.maximum(k * (N - k) * (k + m) * (N - k - m), 0.0))
    return d, e


def tridiagonal(N: int, m: int) -> tuple[Array, Array]:
    r"""The tridiagonal matrix of ``Δ_N`` on diagonal ``±m``: ``(diagonal, off-diagonal)``.

    Diagonal ``-[(N-1)(2i+1+m) - 2i(i+m)]`` for ``i = 0..N-|m|-1`` and off-diagonal
    ``e_i = sqrt(i (N-i) (i+m) (N-i-m))`` for ``i = 1..N-|m|-1`` (SPEC §3). Unpinned (for
    ``m = 0`` the matrix is singular with kernel ``(1, ..., 1)``).
    """
    N = matrix_size(N)
    m = abs(int(m))
    if m >= N:
        raise lieflow.InputError(f"diagonal m must satisfy |m| < N = {N}, got {m}")
    d, e = _coefficients(N, np.full(N - m, float(m)), np.arange(N - m, dtype=float))
    return d, e[1:]


def _packed_coefficients(N: int) -> tuple[Array, Array, Array]:
    """``Δ_N`` in the packed ``(N, N+1)`` layout (module docs): diagonal ``d``, the coupling
    ``e`` of each row to the row above (zero where systems meet and on pads) and the mask of
    non-pad entries (``d = 0`` on pads); the values are those of :func:`_coefficients`."""
    i = np.arange(N, dtype=float)[:, None]
    q = np.arange(N + 1, dtype=float)[None, :]
    first = i < N - q  # diagonal -q, entry index i
    second = (i >= N - q) & (i <= N - 2)  # diagonal N+1-q, entry index i - (N-q)
    m = np.where(first, q, N + 1 - q)
    k = np.where(first, i, i - (N - q))
    valid = first | second
    d, e = _coefficients(N, m, k)
    return np.where(valid, d, 0.0), np.where(valid & (k > 0), e, 0.0), valid


@attrs.frozen(eq=False)
class _BlockedFactor:
    """``LDL^T`` factors of the pinned packed Laplacian, arranged for the partitioned sweeps.

    All arrays have shape ``(nb, b, width)`` with ``width = 2(N+1)`` (real and imaginary parts
    interleaved, matching a complex buffer viewed as real) in one floating-point precision.
    ``lower[r]`` multiplies row ``r-1`` in the forward sweep, ``upper[r]`` row ``r+1`` in the
    backward sweep; ``carry_fwd`` / ``carry_bwd`` are the products of multipliers that carry a
    block's boundary value into its successor / predecessor; ``dinv`` is ``scale / D``.

    The factors are computed in extended precision (``numpy.longdouble``, a 64-bit mantissa
    on x86-64) and rounded once to the working precision. Computed in float64, the pivots
    ``D_r = d_r - e_r² / D_{r-1}`` of the nearly singular pinned ``m = 0`` system (and of the
    small-``m`` ones, condition ``~N²``) lose digits by cancellation: the solve was off by
    ``1.3e-14`` / ``1.1e-13`` relative at N = 64 / 256 against exact rational arithmetic on
    the ``m = 0`` system; with extended-precision factors ``6e-16`` / ``1.8e-15``.
    """

    lower: Array
    upper: Array
    carry_fwd: Array
    carry_bwd: Array
    dinv: Array
    #: ``lower``, ``carry_fwd``, ``carry_bwd`` and ``dinv`` as one ``(4, nb, b, width)``
    #: stack: what the compiled sweeps read (:func:`_sweep_loops`; ``upper`` is ``lower``
    #: one row on, ``upper[r] = lower[r + 1]``, which they read instead).
    compact: Array

    @classmethod
    def build(cls, N: int, block: int, scale: float, shift: float, dtype: type) -> _BlockedFactor:
        d_packed, e_packed, valid = _packed_coefficients(N)
        d_packed = d_packed - shift
        C = N + 1
        nb = -(-N // block)
        R = nb * block
        ext = np.longdouble  # factors in extended precision, rounded once (see the class)
        d = np.ones((R, C), dtype=ext)
        e = np.zeros((R, C), dtype=ext)
        d[:N] = np.where(valid, d_packed, 1.0)  # pads solve as the identity
        e[:N] = e_packed
        if shift == 0:
            d[0, 0] += PIN  # the singular m = 0 system; Δ_N - F (F > 0) is regular
        D = np.empty((R, C), dtype=ext)
        lower = np.zeros((R, C), dtype=ext)
        D[0] = d[0]
        for r in range(1, R):  # setup only: O(N) vectorised steps
            lower[r] = e[r] / D[r - 1]
            D[r] = d[r] - lower[r] * e[r]
        upper = np.zeros((R, C), dtype=ext)
        upper[:-1] = lower[1:]
        L4 = lower.reshape(nb, block, C)
        U4 = upper.reshape(nb, block, C)
        fwd = np.empty((nb, block, C), dtype=ext)
        bwd = np.empty((nb, block, C), dtype=ext)
        fwd[:, 0] = -L4[:, 0]
        for r in range(1, block):
            fwd[:, r] = -L4[:, r] * fwd[:, r - 1]
        bwd[:, block - 1] = -U4[:, block - 1]
        for r in range(block - 2, -1, -1):
            bwd[:, r] = -U4[:, r] * bwd[:, r + 1]

        def interleave(a: Array) -> Array:
            out: Array = np.repeat(a.reshape(nb, block, C), 2, axis=-1).astype(dtype)
            out.setflags(write=False)
            return out

        compact = np.stack([interleave(a) for a in (L4, fwd, bwd, scale / D)])
        compact.setflags(write=False)  # (its rows are the fields: views)
        return cls(compact[0], interleave(U4), compact[1], compact[2], compact[3], compact)


def _sweep(Y: Array, L: Array, U: Array, F: Array, G: Array, dinv: Array) -> None:
    """The partitioned ``LDL^T`` sweeps (module docs) in place on ``Y`` (``(K, nb, b, width)``,
    real, the packed right-hand sides of ``K`` matrices) with the factors of
    :class:`_BlockedFactor` (``L = lower``, ``U = upper``, ``F``/``G`` the carries): row
    operations vectorised over the batch, the blocks and the columns."""
    K, nb, b, width = Y.shape
    tmp = np.empty((K, nb, width), dtype=Y.dtype)
    row = tmp[:, 0]
    # forward substitution with the unit lower factor, inside every block at once
    for r in range(1, b):
        np.multiply(L[:, r], Y[:, :, r - 1], out=tmp)
        np.subtract(Y[:, :, r], tmp, out=Y[:, :, r])
    # ... along the block boundaries (last row of each block), then into the blocks
    for j in range(1, nb):
        np.multiply(F[j, b - 1], Y[:, j - 1, b - 1], out=row)
        np.add(Y[:, j, b - 1], row, out=Y[:, j, b - 1])
    if nb > 1 and b > 1:
        Y[:, 1:, : b - 1] += F[1:, : b - 1] * Y[:, :-1, b - 1 : b]
    Y *= dinv
    # backward substitution with the unit upper factor, the same way round
    for r in range(b - 2, -1, -1):
        np.multiply(U[:, r], Y[:, :, r + 1], out=tmp)
        np.subtract(Y[:, :, r], tmp, out=Y[:, :, r])
    for j in range(nb - 2, -1, -1):
        np.multiply(G[j, 0], Y[:, j + 1, 0], out=row)
        np.add(Y[:, j, 0], row, out=Y[:, j, 0])
    if nb > 1 and b > 1:
        Y[:, :-1, 1:] += G[:-1, 1:] * Y[:, 1:, 0:1]


def _sweep_loops(groups: int, Y: Array, factors: Array) -> None:
    """:func:`_sweep` as explicit loops, compiled with numba when it is installed: the same
    operations on every entry (no fused multiply–adds) with the same operands, hence the
    same bits, without the ``O(√N)`` numpy calls (~10× faster at N = 64). ``factors``:
    :attr:`_BlockedFactor.compact` (``lower``, ``carry_fwd``, ``carry_bwd``, ``dinv``;
    ``upper[r]`` is ``lower[r + 1]``).

    Two passes over ``Y`` instead of seven: block by block, the forward substitution inside
    the block, its last row's boundary update from the previous block's last row (kept
    before the scaling), the carry into its other rows, the scaling by ``dinv`` and the
    backward substitution inside the block, while the block is in the cache; then, from
    the last block back, the backward boundary update and its carry. Each entry sees the
    operations of :func:`_sweep` in its order, with the same operands. The columns (each
    its own recurrences) of all matrices are split into ``groups`` runs of consecutive
    columns (one per thread where ``groups > 1``: the same numbers)."""
    K, nb, b, width = Y.shape
    L = factors[0]
    F = factors[1]
    G = factors[2]
    dinv = factors[3]
    total = K * width
    for g in prange(groups):
        prev = np.empty(width, dtype=Y.dtype)
        pos = g * total // groups
        stop = (g + 1) * total // groups
        while pos < stop:  # the columns [c0, c1) of matrix k
            k = pos // width
            # unsigned column bounds: numba then indexes without the check for negative
            # indices, which would keep the loops from being vectorized
            c0 = np.uint64(pos - k * width)
            c1 = np.uint64(min(width, pos - k * width + stop - pos))
            pos += int(c1 - c0)
            for j in range(nb):
                X = Y[k, j]
                for r in range(1, b):
                    for c in range(c0, c1):
                        X[r, c] = X[r, c] - L[j, r, c] * X[r - 1, c]
                if j > 0:
                    for c in range(c0, c1):
                        X[b - 1, c] = X[b - 1, c] + F[j, b - 1, c] * prev[c]
                    for r in range(b - 1):
                        for c in range(c0, c1):
                            X[r, c] = X[r, c] + F[j, r, c] * prev[c]
                for c in range(c0, c1):
                    prev[c] = X[b - 1, c]
                for r in range(b):
                    for c in range(c0, c1):
                        X[r, c] = X[r, c] * dinv[j, r, c]
                for r in range(b - 2, -1, -1):
                    for c in range(c0, c1):
                        X[r, c] = X[r, c] - L[j, r + 1, c] * X[r + 1, c]
            for j in range(nb - 2, -1, -1):
                X = Y[k, j]
                Z = Y[k, j + 1, 0]
                for c in range(c0, c1):
                    X[0, c] = X[0, c] + G[j, 0, c] * Z[c]
                for r in range(1, b):
                    for c in range(c0, c1):
                        X[r, c] = X[r, c] + G[j, r, c] * Z[c]


#: The sweeps' parallel build, for more than one group of columns (numba's threads,
#: :class:`lieflow.numba_cache.SplitKernel`); one group runs :func:`sweep_kernel`'s build.
_sweep_split = _Kernel(_sweep_loops, split=True)


@functools.cache
def sweep_kernel(real: str) -> Any:
    """:func:`_sweep_loops` compiled for one group (serial; numba installed; with the on-disk
    cache of :func:`lieflow.numba_cache.cached_njit`) for data of the real type ``real`` (a
    dtype character: ``"d"`` float64, ``"f"`` float32), made and compiled on first use.

    Compiled once, for its one signature: ``groups``, ``Y`` writable, the factors' stack
    typed read-only. The numpy path passes the read-only :attr:`_BlockedFactor.compact`,
    the compiled ``B`` of the engine (:func:`lieflow_zeitlin._compiled.zeitlin_B`) a
    writable view of its ``params``, which numba converts to the read-only type; compiled
    on first call, the two would compile the loops twice (1.2 s of a first compiled
    Euler–Zeitlin run, issue 37 item 11). A function of its argument alone (cached)."""
    import numba

    from lieflow.numba_cache import cached_njit

    t = numba.from_dtype(np.dtype(real))
    factors = numba.types.Array(t, 4, "C", readonly=True)
    signature = numba.types.void(numba.int64, t[:, :, :, ::1], factors)
    return cached_njit(_sweep_loops, signature=signature, nogil=True)


def _remove_mean(rows: Array) -> None:
    """``rows -= rows.mean(axis=-1, keepdims=True)`` with ``mean``'s arithmetic (the sum,
    then a division by the count as an ``intp``, cast back: the same bits, also in single
    precision) without its Python layers (~3 µs a call)."""
    mean = np.add.reduce(rows, axis=-1, keepdims=True)
    np.true_divide(mean, np.intp(rows.shape[-1]), out=mean, casting="unsafe")
    rows -= mean


def _default_block(N: int) -> int:
    return max(2, round(math.sqrt(N)))


@attrs.frozen(eq=False)
class HoppeYauLaplacian:
    r"""The Hoppe–Yau Laplacian ``Δ_N = -Σ_a ad_{S_a}²`` on ``N×N`` matrices (module docs),
    optionally shifted: the operator is ``L = Δ_N - shift · I``.

    Parameters
    ----------
    N : int
        Matrix size (``>= 2``); spin ``s = (N-1)/2``.
    scale : float
        :meth:`solve` returns ``scale · L^+ W`` (the Euler–Zeitlin system uses
        ``scale = 1/ħ`` in fluid time); :meth:`apply` is unaffected.
    shift : float, keyword-only
        ``F >= 0`` in ``L = Δ_N - F`` (default 0): the Lamb parameter of the
        quasi-geostrophic model, or ``2/(νh)`` in a Crank–Nicolson viscous step. Eigenvalues
        ``-l(l+1) - F``; same eigenvectors as ``Δ_N``.
    block : int, optional
        Rows per block of the partitioned Thomas sweeps (default ``round(√N)``).

    Notes
    -----
    Construction costs O(N²) time and memory (two precisions of the factors are kept, so
    complex64 input is solved in single precision without conversions). Instances are
    immutable and safe to share.
    """

    N: int = attrs.field(converter=matrix_size)
    scale: float = attrs.field(default=1.0, converter=float)
    shift: float = attrs.field(default=0.0, converter=float, kw_only=True)
    block: int = attrs.field(kw_only=True)
    _double: _BlockedFactor = attrs.field(init=False, repr=False)
    _single: _BlockedFactor = attrs.field(init=False, repr=False)
    _d: Array = attrs.field(init=False, repr=False)
    _e: Array = attrs.field(init=False, repr=False)
    _reduction: dict[str, CyclicReduction] = attrs.field(init=False, factory=dict, repr=False)

    @block.default
    def _block_default(self) -> int:
        return _default_block(self.N)

    @block.validator
    def _check_block(self, _attr: attrs.Attribute, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise lieflow.InputError(f"block must be a positive integer, got {value!r}")

    @_double.default
    def _double_default(self) -> _BlockedFactor:
        if not (math.isfinite(self.scale) and self.scale != 0):
            raise lieflow.InputError(f"scale must be finite and non-zero, got {self.scale!r}")
        if not (math.isfinite(self.shift) and self.shift >= 0):
            raise lieflow.InputError(
                f"shift must be finite and >= 0 (Δ_N - shift is then negative definite), "
                f"got {self.shift!r}"
            )
        return _BlockedFactor.build(self.N, self.block, self.scale, self.shift, np.float64)

    @_single.default
    def _single_default(self) -> _BlockedFactor:
        return _BlockedFactor.build(self.N, self.block, self.scale, self.shift, np.float32)

    @_d.default
    def _d_default(self) -> Array:
        d, _, valid = _packed_coefficients(self.N)
        return np.where(valid, d - self.shift, 0.0)

    @_e.default
    def _e_default(self) -> Array:
        return _packed_coefficients(self.N)[1]

    # ------------------------------------------------------------------ application
    def _check(self, X: ArrayLike, name: str) -> Array:
        X = X if is_foreign_array(X) else np.asarray(X)
        if X.ndim < 2 or X.shape[-2:] != (self.N, self.N):
            raise lieflow.InputError(
                f"{name} has shape {X.shape}; the N = {self.N} Laplacian needs (..., {self.N}, "
                f"{self.N})"
            )
        return X

    def apply(self, P: ArrayLike) -> Array:
        r"""``(Δ_N - shift) P`` with ``Δ_N P = -Σ_a [S_a, [S_a, P]]``, in O(N²), broadcasting
        over leading axes."""
        P = self._check(P, "P")
        N, C = self.N, self.N + 1
        batch = P.shape[:-2]
        dtype = np.result_type(P.dtype, np.complex64)
        Y = np.zeros((*batch, N * C), dtype=dtype)
        Y[..., : N * N] = P.reshape(*batch, N * N)
        Y = Y.reshape(*batch, N, C)
        out = self._d * Y
        out[..., 1:, :] += self._e[1:] * Y[..., :-1, :]
        out[..., :-1, :] += self._e[1:] * Y[..., 1:, :]
        return out.reshape(*batch, N * C)[..., : N * N].reshape(P.shape)

    def solve(self, W: ArrayLike, skew_part: bool = False) -> Array:
        r"""``scale · L^+ W``: the traceless ``P`` with ``L P = scale · (W - (tr W/N) I)``,
        ``L = Δ_N - shift``.

        ``skew_part``: solve for the su(N) projection of ``W`` instead,
        ``solve(su_project(W))`` bit for bit (:func:`~lieflow_zeitlin.projection.su_project`),
        the projection formed directly in the solve's buffer (one ``N × N`` array and two
        passes over it less) where numba is installed and ``W`` is a complex128 NumPy
        array; else it is that composition.

        One partitioned Thomas sweep over the packed layout (module docs) solves the
        ``2N-1`` tridiagonal systems of all matrices of the batch at once: O(N²) work,
        compiled loops (numba) or ``O(√N)`` numpy calls, one fresh output buffer.
        complex64 input is solved in single precision, anything else in double precision
        (real input gives complex output).
        Linear in ``W`` (the trace is projected out, not assumed zero), so it is also the
        derivative needed by Newton's method.
        """
        W = self._check(W, "W")
        fused = skew_part and is_numpy(W) and W.dtype == np.complex128 and have_numba()
        if skew_part and not fused:
            W = su_project(W, lieflow.SU(self.N).project)
        if not is_numpy(W):
            return self._solve_arrays(W)
        single = W.dtype in (np.dtype(np.complex64), np.dtype(np.float32))
        factor = self._single if single else self._double
        dtype = np.complex64 if single else np.complex128
        real = np.float32 if single else np.float64
        N, C = self.N, self.N + 1
        nb, b = factor.lower.shape[:2]
        batch = W.shape[:-2]
        K = math.prod(batch)
        buf = np.empty((K, nb * b * C), dtype=dtype)
        diag = buf[:, : N * N : C]
        if fused:  # su_project's operations, into the buffer
            rows = np.ascontiguousarray(W).reshape(K, N, N).view(real)
            skew_part_into(rows, buf[:, : N * N].view(real).reshape(K, N, 2 * N))
            remove_trace(diag, N)
        else:
            buf[:, : N * N] = W.reshape(K, N * N)
        buf[:, N * N :] = 0
        _remove_mean(diag)
        Y = buf.view(real).reshape(K, nb, b, 2 * C)
        if have_numba():
            groups = work_groups(Y.size)
            sweep = sweep_kernel(np.dtype(real).char) if groups == 1 else _sweep_split
            sweep(groups, Y, factor.compact)
        else:
            _sweep(Y, factor.lower, factor.upper, factor.carry_fwd, factor.carry_bwd, factor.dinv)
        _remove_mean(diag)
        return buf[:, : N * N].reshape(*batch, N, N)

    def cyclic_reduction(self) -> CyclicReduction:
        """The pinned packed systems of :meth:`solve` (module docs) as multipliers of
        parallel cyclic reduction (:mod:`~lieflow_zeitlin.cyclic_reduction`), built on first
        use (O(N² log N) host work) and kept.

        The singular ``m = 0`` system is pinned by ``-N`` instead of :data:`PIN`: any
        non-zero pin ``p`` gives the same result once the trace is removed (for a traceless
        right-hand side ``f`` the pinned solution is ``x - x_0 (1, ..., 1)``, ``x`` the
        traceless solution), and ``-N`` keeps the pinned matrix's smallest eigenvalue
        ``O(1)`` rather than ``O(1/N)``, which cyclic reduction (unlike the sequential
        sweep) needs to stay at roundoff: measured on the ``m = 0`` system against exact
        rational arithmetic, ``-1/2`` loses 1.6e-11 at N = 256, ``-N`` 3e-13."""
        held = self._reduction.get("packed")
        if held is None:
            d, e, valid = _packed_coefficients(self.N)
            b = np.where(valid, d - self.shift, 1.0)  # pads solve as the identity
            if self.shift == 0:
                b[0, 0] -= self.N  # see the docstring
            held = self._reduction["packed"] = CyclicReduction.build(b, e, self.scale)
        return held

    def _solve_arrays(self, W: Any) -> Any:
        r""":meth:`solve` for arrays of any array-API library (CuPy, PyTorch, JAX,
        ``array_api_strict``; NumPy arrays take the sweeps): the same packed layout, the trace
        removed before and after, and all ``2N - 1`` systems of every matrix of the batch
        solved at once by parallel cyclic reduction — ``2⌈log₂ N⌉ + 1`` vector operations over
        the whole ``(..., N, N+1)`` array, reshapes and slices only (no gather, no scatter)."""
        xp = namespace(W)
        single = W.dtype in (xp.complex64, xp.float32)
        cdtype, rdtype = (xp.complex64, xp.float32) if single else (xp.complex128, xp.float64)
        N, C = self.N, self.N + 1
        batch = tuple(W.shape[:-2])
        device = device_of(W)
        reduction = self.cyclic_reduction()
        lower, upper, inverse = reduction.on(W, rdtype)
        first = xp.astype(xp.arange(C, device=device) == 0, rdtype)  # column 0: diagonal m = 0
        flat = xp.reshape(xp.astype(W, cdtype), (*batch, N * N))
        pad = xp.zeros((*batch, N), dtype=cdtype, device=device)
        Y = xp.reshape(xp.concat([flat, pad], axis=-1), (*batch, N, C))
        Y = Y - (xp.sum(Y[..., :, 0], axis=-1) / N)[..., None, None] * first
        X = reduction.solve(Y, lower, upper, inverse)
        X = X - (xp.sum(X[..., :, 0], axis=-1) / N)[..., None, None] * first
        return xp.reshape(xp.reshape(X, (*batch, N * C))[..., : N * N], (*batch, N, N))

    # ------------------------------------------------------------------ spectrum
    def eigenvalues(self) -> Array:
        """``-l(l+1) - shift`` for every coefficient index ``l(l+1)+m`` (length ``N²``)."""
        l = np.repeat(np.arange(self.N), 2 * np.arange(self.N) + 1)
        return -(l * (l + 1)).astype(float) - self.shift

    def harmonics(self) -> Iterator[tuple[int, Array]]:
        """The quantized spherical harmonics of size ``N``: see :func:`harmonics`."""
        return harmonics(self.N)

    def harmonic(self, l: int, m: int) -> Array:
        r"""The dense matrix harmonic :math:`T_{l,m}` (unit Frobenius norm, real entries;
        lower diagonal ``m`` for ``m >= 0``, upper diagonal ``|m|`` for ``m < 0``).

        O(N³) time (it runs :meth:`harmonics` down to ``|m|``): for checks and examples.
        """
        N = self.N
        if not (0 <= abs(m) <= l < N):
            raise lieflow.InputError(f"need |m| <= l < N = {N}, got l = {l}, m = {m}")
        for mm, V in harmonics(N):
            if mm == abs(m):
                T = np.zeros((N, N))
                i = np.arange(N - mm)
                v = V[:, l - mm]
                if m >= 0:
                    T[i + mm, i] = v
                else:
                    T[i, i + mm] = (-1) ** mm * v
                return T
        raise AssertionError("unreachable")  # pragma: no cover


def harmonics(N: int) -> Iterator[tuple[int, Array]]:
    r"""Quantized spherical harmonics, one diagonal at a time: ``(m, V_m)`` for
    ``m = N-1, N-2, ..., 0``.

    ``V_m`` is the real orthogonal ``(N-m)×(N-m)`` eigenvector matrix of the tridiagonal
    ``Δ_N`` on diagonal ``m``; column ``l - m`` (``l = m..N-1``) has eigenvalue
    ``-l(l+1)`` and, placed on the *lower* diagonal ``m`` (entries ``(i+m, i)``), is the
    Frobenius-normalised matrix harmonic :math:`T_{l,m}`; :math:`T_{l,-m} = (-1)^m
    T_{l,m}^T` lives on the upper diagonal. Signs follow the Condon–Shortley convention of
    :math:`Y_{lm}`, transported to matrices by ``L_a ↔ ad S_a`` (``L = -i x × ∇``, the
    spin matrices of :func:`spin_matrices`):

    * :math:`T_{l,l}` is a positive multiple of :math:`(-1)^l S_+^l` (as
      :math:`Y_{ll} ∝ (-1)^l (x+iy)^l`);
    * :math:`[S_-, T_{l,m}] = \sqrt{(l+m)(l-m+1)}\, T_{l,m-1}` (as
      :math:`L_- Y_{lm} = \sqrt{(l+m)(l-m+1)} Y_{l,m-1}`).

    The second rule fixes the sign of every column from the previous diagonal through an
    overlap that equals ``±sqrt((l+m)(l-m+1)) >= 1`` exactly, so it is robust at any
    ``N`` (unlike reading the sign of one entry, which underflows for large ``N``).
    Each diagonal costs one ``eigh_tridiagonal`` (O((N-m)²)); only two ``V`` are held
    at a time, so memory is O(N²).
    """
    from scipy.linalg import eigh_tridiagonal  # 0.1 s to import: on first use

    N = matrix_size(N)
    prev: Array | None = None
    for m in range(N - 1, -1, -1):
        d, e = tridiagonal(N, m)
        if N - m == 1:
            V = np.ones((1, 1))
        else:
            _, V = eigh_tridiagonal(-d, -e)  # ascending l(l+1): column k <-> l = m + k
        # l = m: all entries share one sign (Perron vector); make it (-1)^m
        if (V[:, 0].sum() < 0) != (m % 2 == 1):
            V[:, 0] *= -1
        if prev is not None:
            ladder = _lower_ladder(N, m + 1, prev)  # [S_-, T_{l,m+1}] on diagonal m
            overlap = np.einsum("il,il->l", V[:, 1:], ladder)
            V[:, 1:] *= np.where(overlap < 0, -1.0, 1.0)
        yield m, V
        prev = V


def _lower_ladder(N: int, m: int, V: Array) -> Array:
    r"""``[S_-, T]`` restricted to the lower diagonal ``m-1`` for the columns ``T`` of ``V``
    on the lower diagonal ``m``: with ``(S_-)_{j-1,j} = sqrt(j(N-j))``,
    ``u_j = sqrt((j+m)(N-j-m)) v_j - sqrt(j(N-j)) v_{j-1}``, ``j = 0..N-m`` (with
    ``v_{-1} = v_{N-m} = 0``); O((N-m)²)."""
    n = N - m
    j = np.arange(n + 1, dtype=float)[:, None]
    u = np.zeros((n + 1, V.shape[1]))
    u[:-1] += np.sqrt((j[:-1] + m) * (N - j[:-1] - m)) * V
    u[1:] -= np.sqrt(j[1:] * (N - j[1:])) * V
    return u
