"""How the compiled engine's loops are compiled, and the primitives they are made of:
numba's decorators, the signatures, real or complex arithmetic and the matrix products
(imported with :mod:`lieflow.engines._compiled_loops`, only when the compiled engine runs).

* the decorators: :func:`_jit` (an on-disk cache: the systems' maps, :func:`compiled_map`,
  and the BLAS product :func:`_gemm`), :func:`_inner` (no cache, inlined by numba),
  :func:`_helper` (no cache, compiled on their own), :func:`_inlined_by_llvm` (no cache,
  inlined by LLVM) and :func:`_renamed` (a name of its own for each function a factory
  makes); the signatures of a system's map (:func:`map_signature`) and of the BLAS product,
  for the data types :data:`DTYPES`;
* real or complex: :func:`_is_complex` (a constant of the compiled code), :func:`_abs2`,
  :func:`_finite`;
* the products: :func:`_matmul`, :func:`_matmul_hn`, :func:`_matmul_nh` (by plain loops,
  :func:`_loops`, or by BLAS, :func:`_gemm`), and :func:`_norm`.

Conventions: ``float64`` or ``complex128`` data (one compilation of the loops for each; the
complex one for skew-Hermitian algebras such as su(N), where every transpose of the real code
is a conjugate transpose). Products of ``n×n`` matrices are plain loops up to ``n = 8``
(:data:`LOOP_PRODUCTS_MAX_N`) and BLAS calls (``np.dot`` from compiled code: no Python
overhead) above, in entry points of their own; the BLAS products, which need reference
counting inside ``np.dot``, are a function of their own (:func:`_gemm`) passed to the loops
like a system's map (:func:`lieflow.engines._compiled_loops.gemm`), since the entry points
are compiled without it.

Compile time (issue 37 item 11): every function between an entry point and the map is
inlined into it once (one call site each), since inlining copies a function's code into
every call site; the largest (the maps, the stopping rule's bookkeeping) are inlined by LLVM
rather than by numba (:func:`_inlined_by_llvm`).

Only the functions of :func:`_jit` have a cache of their own; everything else here is
compiled into the entry points, whose cache key hashes the source of this module
(:data:`lieflow.engines._compiled_loops.SHARED_KEY`).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np

numba: Any
numba_cache: Any
try:
    numba = importlib.import_module("numba")
    numba_cache = importlib.import_module("lieflow.numba_cache")
except ImportError:  # pragma: no cover - importable without numba (doctest collection, docs)
    numba = numba_cache = None

F = TypeVar("F", bound=Callable[..., Any])

#: Up to this ``n`` products are plain loops (and a skew ``B M B`` is formed as a strict
#: upper triangle of dot products); above it BLAS (``np.dot`` called from compiled code, no
#: Python overhead) is faster: 2.5x at n = 16 and 50 for ``A @ B``, up to 8x for ``A @ B^T``.
LOOP_PRODUCTS_MAX_N = 8

#: The data types the loops are compiled for.
DTYPES = (np.dtype(np.float64), np.dtype(np.complex128))


def _signature(dtype: np.dtype) -> Any:
    mat = numba.from_dtype(dtype)[:, ::1]
    return numba.types.void(mat, numba.types.float64[::1], mat)


def _product_signature(dtype: np.dtype) -> Any:
    mat = numba.from_dtype(dtype)[:, ::1]
    return numba.types.void(mat, mat, mat, numba.types.boolean, numba.types.boolean)


#: The signatures of :func:`map_signature` and of :func:`_gemm`, made once (numba types are
#: immutable; making one costs ~80 µs, and numba asks for a function argument's on every
#: call of the loops).
_SIGNATURES = {} if numba is None else {dtype: _signature(dtype) for dtype in DTYPES}
_PRODUCT_SIGNATURES = {} if numba is None else {d: _product_signature(d) for d in DTYPES}


def map_signature(dtype: np.dtype) -> Any:
    """Signature of a system's compiled map for data of ``dtype`` (one of :data:`DTYPES`):
    ``f(W, params, out)`` writes into ``out`` (``W``, ``out``: C-contiguous ``(n, n)`` of
    that dtype; ``params``: ``float64`` 1-D)."""
    return _SIGNATURES[np.dtype(dtype)]


def _jit(func: F) -> F:
    """``numba.njit`` with an on-disk cache in the user's cache directory
    (:func:`lieflow.numba_cache.cached_njit`), or in memory where none can be written.
    Without numba the plain function is returned (so the module imports) and
    :func:`lieflow.engines.compiled.kernels` raises ``ImportError``.
    """
    if numba is None:  # pragma: no cover - lieflow.engines.compiled.kernels() refuses this case
        return func
    return cast(F, numba_cache.cached_njit(func, error_model="numpy"))


def _renamed(func: F, name: str) -> F:
    """``func`` under the name ``name`` (qualified name too): numba's symbol and cache names
    are the qualified name and the argument types, so each function a factory makes (below)
    needs a name of its own."""
    func.__name__ = func.__qualname__ = name
    return func


def _inner(func: F, name: str | None = None) -> F:
    """``numba.njit`` without a cache, for the functions between an entry point and the
    shared rules: they are compiled into the entry points (whose cache is keyed by
    :data:`SHARED_KEY`), never loaded from a cache of their own that could hold an old rule.

    They are inlined by numba (``inline="always"``): as separate calls, the generic driver
    and solve cost twice the time per step of hand-inlined loops (so(3) midpoint, measured).
    ``name`` renames a function made by a factory: numba's symbol names are the qualified
    name, the argument types and a per-process counter, so two closures of one factory with
    the same argument types could meet under one symbol in code loaded from the cache."""
    if name is not None:
        func = _renamed(func, name)
    if numba is None:  # pragma: no cover
        return func
    return cast(F, numba.njit(error_model="numpy", inline="always")(func))


def _helper(func: F) -> F:
    """``numba.njit`` without a cache, for the helpers of the loops: numba links a function
    loaded from its own cache as machine code, which cannot be inlined into a caller, so the
    loops would call ``_matmul`` and friends instead of inlining them whenever they are
    recompiled (a new stopping rule) while the helpers' cache is still valid.

    Only compiled code calls them, so numba makes neither of its wrappers for them (the
    Python one, ``no_cpython_wrapper``, and the C one, ``no_cfunc_wrapper``), code that a
    first run would otherwise compile for each helper (issue 37 item 11)."""
    if numba is None:  # pragma: no cover
        return func
    return cast(F, numba.njit(**_HELPER_OPTIONS)(func))


#: numba's options of :func:`_helper` (and of the overloads of the products); explicitly
#: not ``forceinline``, which a function compiled while another is compiling would
#: otherwise take from it (numba's flags are inherited where not set).
_HELPER_OPTIONS = {
    "error_model": "numpy", "no_cpython_wrapper": True, "no_cfunc_wrapper": True,
    "forceinline": False,
}  # fmt: skip


def _inlined_by_llvm(func: F) -> F:
    """``numba.njit`` for the large functions the loops call in their innermost loop (the
    maps, the stopping rule's bookkeeping): compiled on their own once, without a cache or
    wrappers (as :func:`_helper`), and inlined by LLVM (``forceinline``: LLVM's
    ``alwaysinline``) into the code that calls them, rather than by numba as :func:`_inner`.

    Numba inlines a function by copying its code block by block together with the whole
    scope of its variables, at every level of nesting (the map into the solve, the solve
    into the step, the step into the entry point), so the cost grows with the square of
    the inlined code; the maps and the stopping rule were most of it (a first so(3)
    midpoint run: 2.7 s of numba's inlining before, 0.9 s after, issue 37 item 11). The
    same code runs: LLVM inlines them where numba did, and the loops' states are the same
    bits (``benchmarks/compile_time.py --save``)."""
    if numba is None:  # pragma: no cover
        return func
    return cast(F, numba.njit(**{**_HELPER_OPTIONS, "forceinline": True})(func))


def compiled_map(func: F) -> F:
    """``func(W, params, out)`` as a system's compiled map (what
    :meth:`~lieflow.IsospectralSystem.compiled_B` may return): jitted with a disk cache,
    compiled for :func:`map_signature` of the data's dtype when
    :func:`lieflow.engines.compiled.plan`
    first asks for it (not at import, so that importing this module stays cheap)."""
    return _jit(func)


# ------------------------------------------------------------------ real or complex


def _is_complex(x: Any) -> bool:
    """Whether ``x`` (an array or a scalar) is complex: a constant of the compiled code."""
    return bool(np.iscomplexobj(x))


if numba is not None:

    @numba.extending.overload(_is_complex, inline="always")
    def _is_complex_compiled(x: Any) -> Any:
        answer = isinstance(getattr(x, "dtype", x), numba.types.Complex)

        def constant(x: Any) -> bool:  # the stub's signature, annotations included
            return answer

        return constant


@_helper
def _abs2(z: Any) -> float:
    """``|z|²`` (``z * z`` for real ``z``); a real number for every ``z``, so that both
    branches type alike (numba types the branch it does not take, too)."""
    if _is_complex(z):
        return z.real * z.real + z.imag * z.imag
    return z.real * z.real


@_helper
def _finite(z: Any) -> bool:
    """Whether ``z`` is finite (both parts of a complex number)."""
    return math.isfinite(z.real) and math.isfinite(z.imag)


# ------------------------------------------------------------------ products


@_jit
def _gemm(A: Any, B: Any, out: Any, transpose_a: bool, transpose_b: bool) -> None:
    """``out = op(A) @ op(B)`` by BLAS (``np.dot``), ``op(X) = X^T`` where its flag is set
    (the loops set one at most): the products of the loops above ``n = LOOP_PRODUCTS_MAX_N``.

    Compiled on its own, with numba's reference counting (``np.dot`` needs it), and handed
    to the loops — compiled without it — as a function argument (:func:`gemm`).
    """
    if transpose_a:
        np.dot(A.T, B, out)
    elif transpose_b:
        np.dot(A, B.T, out)
    else:
        np.dot(A, B, out)


@_helper
def _loops(A: Any, B: Any, out: Any) -> None:
    """``out = A @ B`` in plain loops: unrolled for ``n = 3``, else in ``i, k, j`` order
    (vectorisable)."""
    n = A.shape[0]
    if n == 3:
        for i in range(3):
            a0, a1, a2 = A[i, 0], A[i, 1], A[i, 2]
            out[i, 0] = a0 * B[0, 0] + a1 * B[1, 0] + a2 * B[2, 0]
            out[i, 1] = a0 * B[0, 1] + a1 * B[1, 1] + a2 * B[2, 1]
            out[i, 2] = a0 * B[0, 2] + a1 * B[1, 2] + a2 * B[2, 2]
        return
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.0
        for k in range(n):
            a = A[i, k]
            for j in range(n):
                out[i, j] += a * B[k, j]


@_helper
def _conj_into(A: Any, out: Any) -> None:
    """``out = conj(A)``, entry by entry."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = np.conj(A[i, j])


# The products of the loops: by ``gemm`` (the BLAS product, :func:`gemm`) in the entry
# points above ``n = LOOP_PRODUCTS_MAX_N``, by :func:`_loops` in those of the smaller ``n``,
# which pass ``None`` for ``gemm``. Each is a stub with the formula in numpy and its
# compiled form an overload: numba types and compiles only the form of the type of
# ``gemm`` (it cannot prune a branch on a function argument that is not ``None``), so a
# run compiles no BLAS call or no loops it does not run.


def _matmul(A: Any, B: Any, out: Any, gemm: Any) -> None:
    """``out = A @ B`` (compiled: by ``gemm``, or :func:`_loops` where it is ``None``)."""
    np.dot(A, B, out)


def _matmul_hn(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> None:
    """``out = A^† @ B``: the product with the transpose of ``A``, or of its conjugate
    (compiled: written into the scratch matrix ``tmp``) for complex data."""
    np.dot(A.conj().T, B, out)


def _matmul_nh(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> None:
    """``out = A @ B^†`` (as :func:`_matmul_hn`)."""
    np.dot(A, B.conj().T, out)


def _by_products(gemm: Any, loops: F, blas: F) -> F:
    """The compiled form of a product for the type of ``gemm``: ``loops`` for ``None``,
    else ``blas``."""
    return loops if isinstance(gemm, numba.types.NoneType) else blas


if numba is not None:

    @numba.extending.overload(_matmul, jit_options=_HELPER_OPTIONS)
    def _matmul_compiled(A: Any, B: Any, out: Any, gemm: Any) -> Any:
        def loops(A: Any, B: Any, out: Any, gemm: Any) -> None:
            _loops(A, B, out)

        def blas(A: Any, B: Any, out: Any, gemm: Any) -> None:
            gemm(A, B, out, False, False)

        return _by_products(gemm, loops, blas)

    @numba.extending.overload(_matmul_hn, jit_options=_HELPER_OPTIONS)
    def _matmul_hn_compiled(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> Any:
        conj = isinstance(A.dtype, numba.types.Complex)  # a constant: numba prunes on it

        def loops(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> None:
            if conj:
                _conj_into(A, tmp)
                A = tmp
            _loops(A.T, B, out)

        def blas(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> None:
            if conj:
                _conj_into(A, tmp)
                A = tmp
            gemm(A, B, out, True, False)

        return _by_products(gemm, loops, blas)

    @numba.extending.overload(_matmul_nh, jit_options=_HELPER_OPTIONS)
    def _matmul_nh_compiled(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> Any:
        conj = isinstance(B.dtype, numba.types.Complex)

        def loops(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> None:
            if conj:
                _conj_into(B, tmp)
                B = tmp
            _loops(A, B.T, out)

        def blas(A: Any, B: Any, out: Any, tmp: Any, gemm: Any) -> None:
            if conj:
                _conj_into(B, tmp)
                B = tmp
            gemm(A, B, out, False, True)

        return _by_products(gemm, loops, blas)


@_helper
def _norm(xf: Any) -> float:
    """Euclidean norm of a 1-D array."""
    acc = 0.0
    for i in range(xf.size):
        acc += _abs2(xf[i])
    return math.sqrt(acc)
