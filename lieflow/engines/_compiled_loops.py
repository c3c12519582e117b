"""numba loops behind :mod:`lieflow.engines.compiled` (imported only when the compiled engine runs).

One compiled driver and per-formulation map kernels:

* :func:`_entry_point` is the chunk loop: warm-start extrapolation and trust
  (:class:`~lieflow.flows.WarmStart`), the cold retry of a failed warm solve
  (:func:`lieflow.schemes.base.solve`), the per-step phase-space projection and the
  finiteness check; :func:`_solver` is the fixed-point loop, judged by
  :func:`lieflow.solvers.fixed_point.stopping_verdict` — the same function object the numpy
  path calls, compiled here (:data:`verdict`);
* the formulations are a map (:func:`_midpoint_map`, :func:`_reduced_map`) and a step
  (:func:`_sydirk_step`: a composition of midpoint solves; :func:`_reduced_step`: the
  reduced stage form), each the numpy code path written out entry by entry.

The system enters as compiled functions passed as *arguments*, by address (an ``int64``,
:func:`address`), and called as numba's first-class function type of :func:`map_signature`
(``B(W, params, out)`` and ``project(W, params, out)``, see
:meth:`lieflow.IsospectralSystem.compiled_B`): a typed function argument keeps the loops
in numba's on-disk cache whatever the system (an untyped dispatcher argument would make
numba recompile them in every process), and an integer costs the call no Python-level
typing. ``B`` is the stage-value ``B`` of
:class:`~lieflow.schemes.base.StageProblem`, i.e. ``B(project_stage(W))``.

numba's cache tracks this file only, not the files of the functions it inlines; the entry
points (:func:`entry`: ``"sydirk_advance"``, ``"reduced_advance"``, each for the commutator
update and for the update in conjugation form) are therefore keyed by a hash of the stopping
rules' source (:data:`SHARED_KEY`), so editing a rule recompiles them.

Compile time (a user's first run compiles its entry point: issue 37 item 11): each entry
point holds one formulation, one data type, one update, one kind of product (plain loops or
BLAS, below) and one kind of algebra (skew-Hermitian or general: the functions that branch
on it are made for each, :func:`_midpoint_map_of`), so a run compiles only the code it runs;
every function between an entry point and the map is inlined into it once (one call site
each: a failed warm solve is retried by the same call to the iteration), since inlining
copies a function's code into every call site; the largest (the maps, the stopping rule's
bookkeeping) are inlined by LLVM rather than by numba (:func:`_inlined_by_llvm`).

Conventions: ``float64`` or ``complex128`` data (one compilation of the loops for each; the
complex one for skew-Hermitian algebras such as su(N), where every transpose of the real code
is a conjugate transpose); an ensemble is a ``(K, n, n)`` stack advanced trajectory by
trajectory inside each step; solves return the number of updates, negated
when the stopping rule reports a failure (the caller then hands the step to numpy).
Products of ``n×n`` matrices are plain loops up to ``n = 8`` and BLAS calls (``np.dot``
from compiled code: no Python overhead) above, in entry points of their own.

The entry points are compiled without numba's reference counting (``_nrt=False``): every
view the loops take of an array (a trajectory, a stage, a scratch matrix) otherwise costs an
atomic increment and decrement, which were 80% of the time of a so(3) midpoint step
(measured with ``perf``: 2.0 µs per step with them, 0.45 µs without; the same bits). Code
compiled that way cannot allocate, so the work arrays come from :func:`workspace`, and the
BLAS products, which need reference counting inside ``np.dot``, are a function of their
own (:func:`_gemm`) passed to the loops like a system's map (:func:`gemm`).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import inspect
import math
import types
from collections.abc import Callable
from typing import Any, NamedTuple, TypeVar, cast

import numpy as np

from .. import warm_start
from ..schemes import base, conjugation
from ..schemes.conjugation import UPDATES
from ..solvers import fixed_point

numba: Any
numba_cache: Any
try:
    numba = importlib.import_module("numba")
    numba_cache = importlib.import_module("lieflow.numba_cache")
except ImportError:  # pragma: no cover - importable without numba (doctest collection, docs)
    numba = numba_cache = None

F = TypeVar("F", bound=Callable[..., Any])

_TINY = float(np.finfo(float).tiny)
_GO, _CONVERGED, _ROUNDOFF = fixed_point.GO, fixed_point.CONVERGED, fixed_point.ROUNDOFF
#: Up to this ``n`` products are plain loops (and a skew ``B M B`` is formed as a strict
#: upper triangle of dot products); above it BLAS (``np.dot`` called from compiled code, no
#: Python overhead) is faster: 2.5x at n = 16 and 50 for ``A @ B``, up to 8x for ``A @ B^T``.
LOOP_PRODUCTS_MAX_N = 8

#: The modules whose functions and constants the entry points compile (the rules shared
#: with the numpy path, :data:`SHARED`).
SHARED_MODULES = (fixed_point, warm_start, conjugation, base)

#: Hash of the source of :data:`SHARED_MODULES`: part of the cache key of the entry points
#: (numba's cache tracks this file only), so that editing a shared rule recompiles them.
SHARED_KEY = hashlib.sha256(
    "".join(inspect.getsource(module) for module in SHARED_MODULES).encode()
).hexdigest()

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


# ------------------------------------------------------------------ the shared rules
# The rules the numpy path runs as plain Python, compiled here (the same function objects):
# the stopping rule, the warm start's trust rule, the cold retry, and the Newton–Schulz
# iteration's decisions and unitarity test of the conjugation updates.

#: :func:`lieflow.solvers.fixed_point.stopping_verdict`, compiled (the same function object):
#: cached, for calls from Python; the loops inline their own compilation of it (``_rule``).
verdict = _jit(fixed_point.stopping_verdict)
_rule = _inner(fixed_point.stopping_verdict)
_trusted_points = _inner(warm_start.trusted_points)
_retries_cold = _inner(base.retries_cold)
_schulz_step = _inner(conjugation.newton_schulz_step)
_skew_to_roundoff_rule = _inner(conjugation.skew_to_roundoff)

#: Entries of the loops' ``tolerances`` (float64): the stopping rule's
#: (:class:`~lieflow.solvers.StoppingRule`) ...
RTOL, ATOL, ROUNDOFF_FLOOR, DIVERGENCE_FACTOR = range(4)
#: ... and of their ``settings`` (int64): the stopping rule's counts and its rate test
#: (``StoppingRule.project``), then whether a failed warm-started solve is retried cold
#: (:func:`~lieflow.schemes.base.retries_cold`) and whether steps are warm-started.
MAX_ITER, PATIENCE, WINDOW, RATE_TEST, RETRY_COLD, WARM_STARTS = range(6)
#: Entries of their ``warm_counts`` (int64, updated in place): how many solutions the
#: history holds, and how many the next prediction extrapolates from
#: (:class:`~lieflow.warm_start.WarmStart`).
FILLED, TRUSTED = range(2)


def stopping_arrays(
    rule: fixed_point.StoppingRule, retry_cold: bool, warm_starts: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The loops' ``tolerances`` and ``settings`` (see :data:`RTOL`, :data:`MAX_ITER`) for
    the stopping ``rule`` of a fixed-point solve, whether a failed warm solve is retried
    cold and whether steps are warm-started (writable: the loops' type)."""
    tolerances = np.empty(4)
    tolerances[[RTOL, ATOL, ROUNDOFF_FLOOR, DIVERGENCE_FACTOR]] = (
        rule.rtol, rule.atol, rule.roundoff_floor, rule.divergence_factor,
    )  # fmt: skip
    settings = np.empty(6, dtype=np.int64)
    settings[[MAX_ITER, PATIENCE, WINDOW, RATE_TEST, RETRY_COLD, WARM_STARTS]] = (
        rule.max_iter, rule.patience, rule.window, rule.project, retry_cold, warm_starts,
    )  # fmt: skip
    return tolerances, settings


@_inlined_by_llvm
def _judge(
    step2: float, size2: float, k: int, size0: float, res: Any, tolerances: Any, settings: Any
) -> tuple[int, float]:
    """Record the ``k``-th update, of squared norm ``step2`` to an iterate of squared norm
    ``size2`` (the :class:`~lieflow.solvers.fixed_point.IterationMonitor` bookkeeping),
    and judge it with :data:`verdict`.

    Returns the verdict's code and the (possibly updated) reference size for the growth
    test (``tolerances``, ``settings``: :func:`stopping_arrays`).
    """
    step, size = math.sqrt(step2), math.sqrt(size2)
    if not (math.isfinite(step) and math.isfinite(size)):
        return fixed_point.NON_FINITE, size0
    if k == 1:
        size0 = max(size0, size, _TINY)
    res[k - 1] = step / max(size, _TINY)
    met = step <= tolerances[ATOL] + tolerances[RTOL] * size
    code = _rule(
        res, k, met, size / size0, tolerances[RTOL], tolerances[ROUNDOFF_FLOOR],
        tolerances[DIVERGENCE_FACTOR], settings[MAX_ITER], settings[PATIENCE],
        settings[WINDOW], settings[RATE_TEST] != 0,
    )  # fmt: skip
    return code, size0


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


# ------------------------------------------------------------------ systems' maps
# Compiled forms of the built-in systems' B and projections (map_signature); ``params`` is
# the flattened factor S for the Hadamard maps.

#: How the loops evaluate ``B`` (the first entry of the ``params`` they are given; the
#: system's own ``params`` follow): through the system's map, or — for the built-in
#: Hadamard maps — the same loop inline. A call through a function pointer cannot be
#: inlined; on so(3) it cost ~165 ns of a ~900 ns midpoint step (measured).
CALL_MAP, INLINE_HADAMARD, INLINE_HADAMARD_SKEW, INLINE_HADAMARD_SYMMETRIC = 0, 1, 2, 3


@_inner
def _hadamard(W: Any, S: Any, out: Any, code: int) -> None:
    """``out = S ⊙ part(W)`` (``S`` flattened), ``part`` by ``code``: ``W`` itself
    (:data:`INLINE_HADAMARD`), its skew part ``(W - W^T)/2`` or its symmetric part
    ``(W + W^T)/2``: the Hadamard maps below, and :func:`_apply_B`'s inline form of them."""
    n = W.shape[0]
    for i in range(n):
        for j in range(n):
            if code == INLINE_HADAMARD:
                w = W[i, j]
            elif code == INLINE_HADAMARD_SKEW:
                w = 0.5 * (W[i, j] - W[j, i])
            else:
                w = 0.5 * (W[i, j] + W[j, i])
            out[i, j] = S[i * n + j] * w


@compiled_map
def hadamard_B(W: Any, params: Any, out: Any) -> None:
    """``out = S ⊙ W`` (``params = S.ravel()``): ``B`` on gl(n)."""
    _hadamard(W, params, out, INLINE_HADAMARD)


@compiled_map
def hadamard_B_skew(W: Any, params: Any, out: Any) -> None:
    """``out = S ⊙ (W - W^T)/2``: ``B`` of a stage value on so(n) (projected first)."""
    _hadamard(W, params, out, INLINE_HADAMARD_SKEW)


@compiled_map
def hadamard_B_symmetric(W: Any, params: Any, out: Any) -> None:
    """``out = S ⊙ (W + W^T)/2``: ``B`` of a stage value on the symmetric matrices."""
    _hadamard(W, params, out, INLINE_HADAMARD_SYMMETRIC)


@compiled_map
def symmetric_part(W: Any, params: Any, out: Any) -> None:
    """``out = (W + W^T)/2`` (``out`` may be ``W``; ``params`` unused)."""
    n = W.shape[0]
    for i in range(n):
        out[i, i] = W[i, i]
        for j in range(i + 1, n):
            a = 0.5 * (W[i, j] + W[j, i])
            out[i, j] = a
            out[j, i] = a


@compiled_map
def skew_hermitian_part(W: Any, params: Any, out: Any) -> None:
    """``out = (W - W^†)/2``, then, if ``params[0]``, minus its trace over ``n`` on the
    diagonal: the projection onto u(n), or su(N) (``out`` may be ``W``)."""
    n = W.shape[0]
    trace = 0.0j
    for i in range(n):
        d = 0.5 * (W[i, i] - np.conj(W[i, i]))
        out[i, i] = d
        trace += d
        for j in range(i + 1, n):
            a = 0.5 * (W[i, j] - np.conj(W[j, i]))
            out[i, j] = a
            out[j, i] = -np.conj(a)
    if params[0] != 0.0:
        trace = trace / n
        for i in range(n):
            out[i, i] -= trace


@_inner
def _apply_B(B: Any, params: Any, W: Any, out: Any) -> None:
    """``out = B(W)``: inline for the codes of :data:`CALL_MAP`, else
    ``B(W, params[1:], out)``."""
    code = int(params[0])
    S = params[1:]
    if code == CALL_MAP:
        B(W, S, out)
        return
    _hadamard(W, S, out, code)


def inline_code(function: Any) -> int:
    """The code :func:`_apply_B` evaluates ``function`` by (a built-in Hadamard map inline,
    anything else through its pointer)."""
    codes = {
        hadamard_B: INLINE_HADAMARD,
        hadamard_B_skew: INLINE_HADAMARD_SKEW,
        hadamard_B_symmetric: INLINE_HADAMARD_SYMMETRIC,
    }
    return next((c for f, c in codes.items() if f is function), CALL_MAP)


class _FunctionPointer:
    """A compiled function as the loops take it: its address, resolved once (numba's
    C-callable wrapper of the compiled ``signature``), with the function, which keeps the
    compiled code alive. The entry points take the address as an integer (:func:`address`,
    :func:`_at`)."""

    def __init__(self, function: Any, dtype: np.dtype, signature: Any = None) -> None:
        from numba.experimental.function_type import _get_wrapper_address

        self.function = function  # keeps the compiled code alive
        self.dtype = np.dtype(dtype)
        self._signature = map_signature(self.dtype) if signature is None else signature
        self.address = _get_wrapper_address(function, self._signature)

    def signature(self) -> Any:
        return self._signature


def function_pointer(function: Any, dtype: np.dtype) -> Any:
    """``function`` (a numba dispatcher compiled for :func:`map_signature` of ``dtype``) in
    the form the loops take it, cheaply converted on every call.

    The maps of this module (the built-in systems' ``B`` and projections: objects that live
    as long as the process and are compiled once) are resolved once per process, like
    :func:`gemm`; any other function on every call (~15 µs), since its dispatcher could be
    recompiled."""
    if isinstance(function, _FunctionPointer) and function.dtype == dtype:
        return function
    name = getattr(getattr(function, "py_func", None), "__name__", "")
    if globals().get(name) is not function:
        return _FunctionPointer(function, dtype)
    return _module_map_pointer(function, np.dtype(dtype))


@functools.cache
def _module_map_pointer(function: Any, dtype: np.dtype) -> Any:
    """:func:`function_pointer` of one of this module's maps, made once per process."""
    return _FunctionPointer(function, dtype)


def address(pointer: Any, signature: Any) -> int:
    """The address of ``pointer`` (a :class:`_FunctionPointer`: :func:`function_pointer`,
    :func:`gemm`) for the entry points, which take their functions as integers (:func:`_at`)
    and so cannot check them: raises ``TypeError`` unless ``pointer`` is a resolved function
    of exactly ``signature`` (the type the loops call it with)."""
    if not (isinstance(pointer, _FunctionPointer) and pointer.signature() == signature):
        raise TypeError(
            f"the compiled loops take a resolved function of signature {signature}, got {pointer!r}"
        )
    return int(pointer.address)


# ------------------------------------------------------------------ formulations


#: The name of each kind of algebra in the names of the functions made for one
#: (``skew``: skew-Hermitian, so(n), u(n), su(N); else general, gl(n), symmetric).
_ALGEBRAS = {False: "general", True: "skew"}


def _midpoint_map_of(skew: bool) -> Any:
    """:func:`_midpoint_map` for skew-Hermitian algebras (``skew``) or general ones: a
    constant of the compiled code, so that the branches of the other kind are neither typed
    nor compiled (numba prunes a branch on a closure constant; issue 37 item 11)."""

    def _midpoint_map(
        W0: Any, coef: Any, x: Any, Bm: Any, BM: Any, BMB: Any, MB: Any, B: Any, params: Any,
        gemm: Any,
    ) -> tuple[float, float]:  # fmt: skip
        """One update of the midpoint map (SPEC §4.1), in place:

        ``M <- W0 + q (B M - M B) + q^2 B M B``, ``B = B(M)``, ``coef = (q, q^2)``
        (:func:`~lieflow.schemes.sydirk.midpoint_coefficients`, ``q = h/2``);
        for skew algebras ``M B = (B M)^†`` (two products per update, SPEC §4.1), and for
        small real ``n`` only half of the skew ``B M B`` is formed. The new iterate overwrites ``x``
        entry by entry once the products are formed; ``Bm``, ... ``MB`` are scratch matrices,
        ``gemm`` the products above ``n = LOOP_PRODUCTS_MAX_N`` (:func:`gemm`; ``None``: plain
        loops, :func:`_matmul`). Returns the squared norms of the update and of the new
        iterate.
        """
        n = W0.shape[0]
        q, qq = coef[0], coef[1]
        _apply_B(B, params, x, Bm)
        _matmul(Bm, x, BM, gemm)
        step2 = 0.0
        size2 = 0.0
        if skew and n <= LOOP_PRODUCTS_MAX_N and not _is_complex(x):
            # B M B is skew for skew B, M: form its strict upper triangle only (its diagonal
            # is zero in exact arithmetic) and mirror it, half a product instead of one.
            for i in range(n):
                g = W0[i, i]
                step2 += _abs2(g - x[i, i])
                size2 += _abs2(g)
                x[i, i] = g
                for j in range(i + 1, n):
                    bmb = 0.0
                    for c in range(n):
                        bmb += BM[i, c] * Bm[c, j]
                    c1 = BM[i, j] - BM[j, i]
                    g = W0[i, j] + q * c1 + qq * bmb
                    gt = W0[j, i] - q * c1 - qq * bmb
                    step2 += _abs2(g - x[i, j]) + _abs2(gt - x[j, i])
                    size2 += _abs2(g) + _abs2(gt)
                    x[i, j] = g
                    x[j, i] = gt
        else:
            _matmul(BM, Bm, BMB, gemm)
            if not skew:
                _matmul(x, Bm, MB, gemm)
            for i in range(n):
                for j in range(n):
                    mb = np.conj(BM[j, i]) if skew else MB[i, j]
                    g = W0[i, j] + q * (BM[i, j] - mb) + qq * BMB[i, j]
                    step2 += _abs2(g - x[i, j])
                    size2 += _abs2(g)
                    x[i, j] = g
        return step2, size2

    name = f"_midpoint_map_{_ALGEBRAS[skew]}"
    return _inlined_by_llvm(_renamed(_midpoint_map, name))


_midpoint_map_general, _midpoint_map_skew = (_midpoint_map_of(skew) for skew in _ALGEBRAS)


@_inner
def _commutator_add(
    W: Any, hb: float, skew: bool, M: Any, B: Any, params: Any, Bm: Any, BM: Any, MB: Any,
    gemm: Any,
) -> None:  # fmt: skip
    """``W += hb [B(M), M]`` in place (one product for skew algebras: ``M B = (B M)^†``);
    ``Bm``, ``BM``, ``MB`` are scratch matrices."""
    n = W.shape[0]
    _apply_B(B, params, M, Bm)
    _matmul(Bm, M, BM, gemm)
    if skew:
        for i in range(n):
            for j in range(n):
                MB[i, j] = np.conj(BM[j, i])
    else:
        _matmul(M, Bm, MB, gemm)
    for i in range(n):
        for j in range(n):
            W[i, j] = W[i, j] + hb * (BM[i, j] - MB[i, j])


def _reduced_map_of(skew: bool) -> Any:
    """:func:`_reduced_map` for skew-Hermitian algebras or general ones (as
    :func:`_midpoint_map_of`)."""

    def _reduced_map(
        W0: Any, coef: Any, x: Any, Wst: Any, Bs: Any, GB: Any, PB: Any, B: Any, params: Any,
        gemm: Any,
    ) -> tuple[float, float]:  # fmt: skip
        """One update of the reduced stage form (SPEC §4.5), in place (``x[0] = G``,
        ``x[1] = P``, each ``(s, n, n)``):

        ``G_i <- I + sum_j (C_G)_ij G_j B_j^†``, ``P_i <- W0 + sum_j (C_P)_ij P_j B_j``,
        ``B_j = B(G_j^† P_j)``; ``coef = (C_G; C_P)`` stacked, ``(2s, s)``
        (:func:`~lieflow.schemes.block.reduced_coefficients`: ``C_P = -hA``, ``C_G = hA``,
        or ``-hA`` for skew algebras, where ``G_j B_j`` is formed for ``G_j B_j^† = -G_j B_j``).
        ``3 s`` products per update; ``Wst``, ... ``PB`` are scratch stacks ``(s, n, n)``
        (``GB[j]`` and ``Wst[j]`` also hold the conjugates that complex data need, before they
        are overwritten; ``Wst`` and ``Bs`` then the stage sums, each entry summed in the order
        ``j = 1..s``). Returns the squared norms of the update and of the new iterate.
        """
        s, n = coef.shape[1], W0.shape[0]
        nn = n * n
        for j in range(s):
            _matmul_hn(x[0, j], x[1, j], Wst[j], GB[j], gemm)
            _apply_B(B, params, Wst[j], Bs[j])
            if skew:  # G_j B_j, whose sign goes into the coefficients below (B^† = -B)
                _matmul(x[0, j], Bs[j], GB[j], gemm)
            else:
                _matmul_nh(x[0, j], Bs[j], GB[j], Wst[j], gemm)
            _matmul(x[1, j], Bs[j], PB[j], gemm)
        # the stage sums, into Wst and Bs (free by now), over the n² entries of each matrix as
        # one flat loop (vectorised whatever n)
        GBf, PBf = GB.reshape((s, nn)), PB.reshape((s, nn))
        accG, accP = Wst.reshape((s, nn)), Bs.reshape((s, nn))
        for i in range(s):
            for e in range(nn):
                accG[i, e] = 0.0
                accP[i, e] = 0.0
            for j in range(s):
                wG, wP = coef[i, j], coef[s + i, j]
                for e in range(nn):
                    accG[i, e] += wG * GBf[j, e]
                    accP[i, e] += wP * PBf[j, e]
        step2 = 0.0
        size2 = 0.0
        for i in range(s):
            for a in range(n):
                for c in range(n):
                    gG = Wst[i, a, c] + (1.0 if a == c else 0.0)
                    gP = Bs[i, a, c] + W0[a, c]
                    step2 += _abs2(gG - x[0, i, a, c]) + _abs2(gP - x[1, i, a, c])
                    size2 += _abs2(gG) + _abs2(gP)
                    x[0, i, a, c] = gG
                    x[1, i, a, c] = gP
        return step2, size2

    name = f"_reduced_map_{_ALGEBRAS[skew]}"
    return _inlined_by_llvm(_renamed(_reduced_map, name))


_reduced_map_general, _reduced_map_skew = (_reduced_map_of(skew) for skew in _ALGEBRAS)


# ------------------------------------------------------------------ conjugation updates
# The compiled forms of :mod:`lieflow.schemes.conjugation` (SPEC §4.7), in the entry points
# of that update (:func:`entry`'s ``conjugation``): the same formulas, with Gauss–Jordan
# elimination in loops for the solves (compiled code here cannot allocate, so LAPACK's
# solve is not available).

_EPS64 = float(np.finfo(np.float64).eps)


@_helper
def _gauss_jordan(L: Any, R: Any) -> None:
    """``R <- L^{-1} R`` in place (``L``, ``n×n``, is destroyed): elimination with partial
    pivoting, then back substitution."""
    n, m = L.shape[0], R.shape[1]
    for k in range(n):
        p = k
        best = _abs2(L[k, k])
        for i in range(k + 1, n):
            v = _abs2(L[i, k])
            if v > best:
                best = v
                p = i
        if p != k:
            for j in range(k, n):
                t = L[k, j]
                L[k, j] = L[p, j]
                L[p, j] = t
            for j in range(m):
                t = R[k, j]
                R[k, j] = R[p, j]
                R[p, j] = t
        inv = 1.0 / L[k, k]
        for i in range(k + 1, n):
            f = L[i, k] * inv
            for j in range(k + 1, n):
                L[i, j] -= f * L[k, j]
            for j in range(m):
                R[i, j] -= f * R[k, j]
    for k in range(n - 1, -1, -1):
        inv = 1.0 / L[k, k]
        for j in range(m):
            acc = R[k, j]
            for c in range(k + 1, n):
                acc -= L[k, c] * R[c, j]
            R[k, j] = acc * inv


@_helper
def _skew_to_roundoff(B: Any) -> bool:
    """Whether ``B`` is skew-Hermitian to roundoff
    (:func:`~lieflow.schemes.conjugation.skew_to_roundoff` of its norms)."""
    n = B.shape[0]
    defect = 0.0
    size = 0.0
    for i in range(n):
        for j in range(n):
            defect += _abs2(B[i, j] + np.conj(B[j, i]))
            size += _abs2(B[i, j])
    return _skew_to_roundoff_rule(math.sqrt(defect), math.sqrt(size), _EPS64)


@_helper
def _orthonormalize(K: Any, E: Any, KE: Any, tmp: Any, gemm: Any) -> bool:
    """Newton–Schulz on ``U = I + K`` in its increment, in place:
    ``E = K + K^† + K^† K``, ``K <- K - (E + K E)/2``
    (:func:`~lieflow.schemes.conjugation.orthonormalize`, its decisions by
    :func:`~lieflow.schemes.conjugation.newton_schulz_step`); false if ``U`` is too far
    from unitary (``||E|| >= 1`` at the start)."""
    n = K.shape[0]
    last = math.inf
    for _ in range(conjugation.NEWTON_SCHULZ_STEPS):
        _matmul_hn(K, K, E, tmp, gemm)
        err2 = 0.0
        for i in range(n):
            for j in range(n):
                e = E[i, j] + K[i, j] + np.conj(K[j, i])
                E[i, j] = e
                err2 += _abs2(e)
        err = math.sqrt(err2)
        decision = _schulz_step(err, last, n, _EPS64)
        if decision == conjugation.SCHULZ_DONE:
            return True
        if decision == conjugation.SCHULZ_REFUSED:
            return False
        last = err
        _matmul(K, E, KE, gemm)
        for i in range(n):
            for j in range(n):
                K[i, j] -= 0.5 * (E[i, j] + KE[i, j])
        if decision == conjugation.SCHULZ_LAST:
            return True
    return True


def _conjugate_into_of(skew: bool) -> Any:
    """:func:`_conjugate_into` for skew-Hermitian algebras, where ``U`` is always made
    unitary (``unitary`` is not read: the Gauss–Jordan solve of the general case is not
    compiled), or general ones (as :func:`_midpoint_map_of`)."""

    def _conjugate_into(
        W: Any, K: Any, unitary: bool, s1: Any, s2: Any, s3: Any, gemm: Any
    ) -> bool:
        """``W <- U W U^{-1}``, ``U = I + K``, in place, as ``W`` plus an increment
        (:func:`~lieflow.schemes.conjugation.conjugate`): with ``unitary``, ``K`` made unitary
        and ``W += K W + W K^† + K W K^†`` (its skew-Hermitian part with ``skew``), else
        ``W += (K W - W K) U^{-1}`` by a solve with ``U^T``. ``s1``, ``s2``, ``s3``: scratch;
        false if ``U`` is too far from unitary."""
        n = W.shape[0]
        if skew or unitary:
            if not _orthonormalize(K, s1, s2, s3, gemm):
                return False
            _matmul(K, W, s1, gemm)
            if skew:
                _matmul_nh(s1, K, s2, s3, gemm)
                for i in range(n):
                    for j in range(i, n):
                        dij = s1[i, j] - np.conj(s1[j, i]) + s2[i, j]
                        dji = s1[j, i] - np.conj(s1[i, j]) + s2[j, i]
                        d = 0.5 * (dij - np.conj(dji))
                        W[i, j] = W[i, j] + d
                        if j != i:
                            W[j, i] = W[j, i] - np.conj(d)
            else:
                _matmul_nh(W, K, s3, s2, gemm)  # W K^† (real data: s2 is not touched)
                for i in range(n):
                    for j in range(n):
                        s3[i, j] += s1[i, j]
                _matmul_nh(s1, K, s2, s1, gemm)  # K W K^† (real data: s1 is not touched)
                for i in range(n):
                    for j in range(n):
                        W[i, j] = W[i, j] + (s3[i, j] + s2[i, j])
        else:
            _matmul(K, W, s1, gemm)
            _matmul(W, K, s2, gemm)
            for i in range(n):
                for j in range(n):
                    s3[i, j] = s1[j, i] - s2[j, i]  # D^T
                    s2[i, j] = K[j, i] + (1.0 if i == j else 0.0)  # U^T
            _gauss_jordan(s2, s3)  # (D U^{-1})^T = U^{-T} D^T
            for i in range(n):
                for j in range(n):
                    W[i, j] = W[i, j] + s3[j, i]
        return True

    return _helper(_renamed(_conjugate_into, f"_conjugate_into_{_ALGEBRAS[skew]}"))


_conjugate_into_general, _conjugate_into_skew = (_conjugate_into_of(skew) for skew in _ALGEBRAS)


@_inner
def _cayley_into(
    W: Any, a: float, skew: bool, M: Any, B: Any, params: Any, Bm: Any, L: Any, C: Any,
    s3: Any, gemm: Any,
) -> bool:  # fmt: skip
    """The midpoint update in Cayley form in place: ``W <- C W C^{-1}``,
    ``C = (I - aB)^{-1}(I + aB) = I + K``, ``K = 2a (I - aB)^{-1} B``, ``B = B(M)``
    (:func:`~lieflow.schemes.conjugation.cayley_update`); ``Bm``, ``L``, ``C``, ``s3``
    scratch (``M`` is read only)."""
    n = W.shape[0]
    _apply_B(B, params, M, Bm)
    unitary = skew or _skew_to_roundoff(Bm)  # (skew: a constant, see _sydirk_step_of)
    for i in range(n):
        for j in range(n):
            L[i, j] = (1.0 if i == j else 0.0) - a * Bm[i, j]
            C[i, j] = (2 * a) * Bm[i, j]
    _gauss_jordan(L, C)
    if skew:
        return _conjugate_into_skew(W, C, unitary, L, Bm, s3, gemm)
    return _conjugate_into_general(W, C, unitary, L, Bm, s3, gemm)


@_inner
def _lifted_into(
    W: Any, hb: Any, skew: bool, x: Any, B: Any, params: Any, Wi: Any, Bi: Any, P: Any,
    U: Any, gemm: Any,
) -> bool:  # fmt: skip
    """The Gauss update in conjugation form in place: ``W <- U W U^{-1}``, ``U = I + K``,
    ``K = sum_i hb_i B_i G_i^†`` (held in ``U``), ``B_i = B(G_i^† P_i)``, ``x = (G, P)``
    (:func:`~lieflow.schemes.conjugation.lifted_update`); ``Wi``, ``Bi``, ``P``, ``U``
    scratch."""
    n = W.shape[0]
    for a in range(n):
        for c in range(n):
            U[a, c] = 0.0
    unitary = True
    for i in range(hb.shape[0]):
        _matmul_hn(x[0, i], x[1, i], Wi, P, gemm)
        _apply_B(B, params, Wi, Bi)
        if not skew:  # (a constant, see _reduced_step_of)
            unitary = unitary and _skew_to_roundoff(Bi)
        _matmul_nh(Bi, x[0, i], P, Wi, gemm)
        for a in range(n):
            for c in range(n):
                U[a, c] += hb[i] * P[a, c]
    if skew:
        return _conjugate_into_skew(W, U, unitary, Wi, Bi, P, gemm)
    return _conjugate_into_general(W, U, unitary, Wi, Bi, P, gemm)


# ------------------------------------------------------------------ the one driver


def _solver(fmap: Any) -> Any:
    """The fixed-point solve of the map ``fmap`` (:func:`_midpoint_map` or
    :func:`_reduced_map`, of one kind of algebra): one source for every formulation,
    compiled once per map (the map is a closure variable, i.e. a direct call, not a value
    passed at run time)."""

    def solve(
        W0: Any, coef: Any, x: Any, xf: Any, x0f: Any, pred: Any, solved: Any, off: int,
        guessing: bool, m0: Any, m1: Any, m2: Any, m3: Any, B: Any, params: Any, gemm: Any,
        res: Any, tolerances: Any, settings: Any,
    ) -> int:  # fmt: skip
        """Fixed-point iteration ``x <- fmap(x)`` until the stopping rule stops it, from the
        warm guess ``x0 + pred[off:]`` (when ``guessing``), and once more from the cold
        guess ``x0`` if that fails and :func:`~lieflow.schemes.base.retries_cold` says so
        (where ``settings`` allow it); on success ``solved[off:] = x - x0`` (the offsets a
        warm start keeps) and the updates of both attempts are returned, else a negative
        number. ``xf``, ``x0f``: flat views of ``x`` and the cold guess."""
        m = xf.size
        total = 0
        warm = guessing
        while True:  # the warm attempt (when guessing), then the cold one if it failed
            for e in range(m):
                xf[e] = x0f[e] + pred[off + e] if warm else x0f[e]
            size0 = _norm(xf)
            k = 0
            code = _GO
            while code == _GO:
                step2, size2 = fmap(W0, coef, x, m0, m1, m2, m3, B, params, gemm)
                k += 1
                code, size0 = _judge(step2, size2, k, size0, res, tolerances, settings)
            total += k
            converged = code == _CONVERGED or code == _ROUNDOFF
            if not (settings[RETRY_COLD] != 0 and _retries_cold(converged, warm)):
                break
            warm = False
        if not converged:
            return -1
        for e in range(m):
            solved[off + e] = xf[e] - x0f[e]
        return total

    return _inner(solve, f"_solve_{fmap.__name__}")


#: The solves of each formulation, by kind of algebra (``skew``).
_solve_midpoint = {False: _solver(_midpoint_map_general), True: _solver(_midpoint_map_skew)}
_solve_reduced = {False: _solver(_reduced_map_general), True: _solver(_reduced_map_skew)}


@_inner
def _sydirk_views(work: Any, scratch: Any) -> Any:
    """Views of the work arrays for :func:`_sydirk_step`, made once per chunk: the iterate
    ``x`` and the sub-step's start ``x0`` (``n×n``, and flat), four scratch matrices."""
    x, x0 = work[0, 0, 0], work[1, 0, 0]
    m0, m1, m2, m3 = scratch[1, 0], scratch[2, 0], scratch[3, 0], scratch[4, 0]
    return x, x0, x.reshape(x.size), x0.reshape(x0.size), m0, m1, m2, m3


def _sydirk_step_of(conjugation: bool, skew: bool) -> Any:
    """:func:`_sydirk_step` for one update (SPEC §4.7) on one kind of algebra (``skew``:
    skew-Hermitian): both are constants of the compiled code, so the other update and the
    other kind's branches are neither typed nor compiled (numba prunes a branch on a closure
    constant, in the functions it inlines too)."""
    solve = _solve_midpoint[skew]

    def _sydirk_step(
        cur: Any, out: Any, pred: Any, solved: Any, guessing: bool, coefficients: Any,
        weights: Any, x: Any, x0: Any, xf: Any, x0f: Any, m0: Any, m1: Any, m2: Any, m3: Any,
        B: Any, params: Any, gemm: Any, res: Any, tolerances: Any, settings: Any,
    ) -> int:  # fmt: skip
        """One step of a composition of midpoint steps (SPEC §4.2) of sizes ``weights``
        (``h b_i``; ``coefficients[i]``: their
        :func:`~lieflow.schemes.sydirk.midpoint_coefficients`) from ``cur`` into ``out``;
        ``solved``/``pred``: the ``(s, n, n)`` offsets, flattened."""
        n = cur.shape[0]
        nn = n * n
        for a in range(n):
            for c in range(n):
                out[a, c] = cur[a, c]
        total = 0
        for i in range(weights.shape[0]):
            for a in range(n):
                for c in range(n):
                    x0[a, c] = out[a, c]
            its = solve(
                x0, coefficients[i], x, xf, x0f, pred, solved, i * nn, guessing, m0, m1, m2,
                m3, B, params, gemm, res, tolerances, settings,
            )  # fmt: skip
            if its < 0:
                return -1
            total += its
            if conjugation:
                a = coefficients[i, 0]  # the Cayley transform's h/2
                if not _cayley_into(out, a, skew, x, B, params, m0, m1, m2, m3, gemm):
                    return -1
            else:
                _commutator_add(out, weights[i], skew, x, B, params, m0, m1, m3, gemm)
        return total

    return _inner(_sydirk_step, f"_sydirk_step_{UPDATES[conjugation]}_{_ALGEBRAS[skew]}")


@_inner
def _reduced_views(work: Any, scratch: Any) -> Any:
    """Views of the work arrays for :func:`_reduced_step`, made once per chunk: the
    unknowns ``x = (G, P)`` and the cold guess ``x0 = (I, W0)`` (and flat), four scratch
    stacks."""
    x, x0 = work[0], work[1]
    xf, x0f = x.reshape(x.size), x0.reshape(x0.size)
    return x, x0, xf, x0f, scratch[0], scratch[1], scratch[2], scratch[3]


def _reduced_step_of(conjugation: bool, skew: bool) -> Any:
    """:func:`_reduced_step` for one update on one kind of algebra (as
    :func:`_sydirk_step_of`)."""
    solve = _solve_reduced[skew]

    def _reduced_step(
        cur: Any, out: Any, pred: Any, solved: Any, guessing: bool, coefficients: Any,
        weights: Any, x: Any, x0: Any, xf: Any, x0f: Any, m0: Any, m1: Any, m2: Any, m3: Any,
        B: Any, params: Any, gemm: Any, res: Any, tolerances: Any, settings: Any,
    ) -> int:  # fmt: skip
        """One step of the reduced stage form of a symplectic tableau (SPEC §4.5) from
        ``cur`` into ``out``: unknowns ``(G, P)``, cold guess ``(I, cur)``; ``coefficients``:
        :func:`~lieflow.schemes.block.reduced_coefficients`, ``weights = h b``;
        ``solved``/``pred``: the ``(2, s, n, n)`` offsets, flattened.
        ``out = cur + sum_i hb_i [B(W_i), W_i]``, ``W_i = G_i^† P_i``."""
        s, n = weights.shape[0], cur.shape[0]
        for i in range(s):
            for a in range(n):
                for c in range(n):
                    x0[0, i, a, c] = 1.0 if a == c else 0.0
                    x0[1, i, a, c] = cur[a, c]
        its = solve(cur, coefficients, x, xf, x0f, pred, solved, 0, guessing, m0, m1, m2, m3,
                    B, params, gemm, res, tolerances, settings)  # fmt: skip
        if its < 0:
            return -1
        Wi, Bi, BW, WB = m0[0], m1[0], m2[0], m3[0]
        for a in range(n):
            for c in range(n):
                out[a, c] = cur[a, c]
        if conjugation:
            lifted = _lifted_into(out, weights, skew, x, B, params, Wi, Bi, BW, WB, gemm)
            return its if lifted else -1
        for i in range(s):
            _matmul_hn(x[0, i], x[1, i], Wi, WB, gemm)
            _commutator_add(out, weights[i], skew, Wi, B, params, Bi, BW, WB, gemm)
        return its

    return _inner(_reduced_step, f"_reduced_step_{UPDATES[conjugation]}_{_ALGEBRAS[skew]}")


@_helper
def _predict(history: Any, kk: int, points: int, extrapolation: Any, out: Any) -> None:
    """The warm-start prediction from the last ``points`` solutions of trajectory ``kk``
    (:meth:`WarmStart.prediction <lieflow.warm_start.WarmStart.prediction>`):
    ``out = sum_j extrapolation[points - 1, j] history[j, kk]``, 1-D."""
    m = out.size
    w0 = extrapolation[points - 1, 0]
    for e in range(m):
        out[e] = w0 * history[0, kk, e]
    for j in range(1, points):
        w = extrapolation[points - 1, j]
        for e in range(m):
            out[e] += w * history[j, kk, e]


@_helper
def _commit(
    solved: Any, history: Any, warm_counts: Any, extrapolation: Any, acc: Any, err2: Any
) -> None:
    """:meth:`WarmStart.advance <lieflow.warm_start.WarmStart.advance>` for the whole stack:
    the squared errors of the predictions of ``solved`` from ``0 .. filled`` points (summed
    over the stack), the number of points trusted next by
    :func:`~lieflow.warm_start.trusted_points`, and ``solved`` into the history
    (``(depth, K, m)``, most recent first)."""
    depth, K, m = history.shape
    filled = warm_counts[FILLED]
    for u in range(filled + 1):
        err2[u] = 0.0
    for kk in range(K):
        for e in range(m):
            err2[0] += _abs2(solved[kk, e])
        for u in range(1, filled + 1):
            _predict(history, kk, u, extrapolation, acc)
            for e in range(m):
                err2[u] += _abs2(solved[kk, e] - acc[e])
    warm_counts[TRUSTED] = _trusted_points(err2, filled, depth)
    for j in range(depth - 1, 0, -1):
        for kk in range(K):
            for e in range(m):
                history[j, kk, e] = history[j - 1, kk, e]
    for kk in range(K):
        for e in range(m):
            history[0, kk, e] = solved[kk, e]
    warm_counts[FILLED] = min(filled + 1, depth)


class LoopArguments(NamedTuple):
    """The arguments of an entry point (:func:`entry`), by name and in order: the loops'
    interface. The loops read the inputs and write ``states``, ``iterations`` and the warm
    start (``history``, ``warm_counts``) in place, and return how many steps they took.

    Attributes
    ----------
    start : ndarray
        The states the chunk starts from, ``(K, n, n)`` (``K`` trajectories).
    coefficients : ndarray
        The formulation's stage coefficients, ``float64``: rows ``(q, q^2)`` per sub-step
        of a midpoint composition (:func:`~lieflow.schemes.sydirk.midpoint_coefficients`),
        ``(C_G; C_P)`` of the reduced form (:func:`~lieflow.schemes.block.reduced_coefficients`).
    weights : ndarray
        ``h b``: the sub-steps' sizes, or the stage weights of the update.
    B, project, gemm : int
        Addresses of the system's compiled ``B``, of its compiled projection (``B``'s when
        there is none: not called) and of the BLAS product (:func:`address`; ``0`` for
        the entry points of plain-loop products, which do not read it).
    B_params, project_params : ndarray
        Their ``params``; ``B_params`` led by :func:`inline_code`.
    projecting : bool
        Whether each new state is mapped by ``project``.
    tolerances, settings : ndarray
        The stopping rule and the step's switches (:func:`stopping_arrays`).
    history : ndarray
        The warm start's kept solutions, ``(depth, K, m)``, most recent first (updated).
    extrapolation : ndarray
        :func:`~lieflow.warm_start.extrapolation_matrix` of ``depth`` points.
    warm_counts : ndarray
        ``(filled, trusted)`` of the warm start (:data:`FILLED`, :data:`TRUSTED`; updated).
    states : ndarray
        Out: the states after each step, ``(steps, K, n, n)``.
    iterations : ndarray
        Out: fixed-point updates per step (max over the stack), ``(steps,)``.
    workspace, real_workspace : ndarray
        The work arrays (:func:`workspace`): the loops allocate nothing.
    """

    start: np.ndarray
    coefficients: np.ndarray
    weights: np.ndarray
    B: int
    B_params: np.ndarray
    project: int
    project_params: np.ndarray
    projecting: bool
    tolerances: np.ndarray
    settings: np.ndarray
    history: np.ndarray
    extrapolation: np.ndarray
    warm_counts: np.ndarray
    states: np.ndarray
    iterations: np.ndarray
    gemm: int
    workspace: np.ndarray
    real_workspace: np.ndarray


def _at(signature_of: Callable[[np.dtype], Any]) -> Any:
    """An intrinsic ``f(address, like)``: the compiled function at ``address`` (an
    ``int64``: a :class:`_FunctionPointer`'s :attr:`~_FunctionPointer.address`) as a value of
    the first-class function type of ``signature_of(like.dtype)`` — the value numba unboxes
    from a :class:`_FunctionPointer` argument (the address in its C-callable slot, the
    others null), made in compiled code: the entry points take the addresses as integers,
    which their dispatcher types without Python (a function object is typed by a Python
    call per argument and call, ~4 µs each)."""

    def at(typingctx: Any, address: Any, like: Any) -> Any:
        from numba.core import cgutils
        from numba.np.numpy_support import as_dtype

        if not isinstance(address, numba.types.Integer):
            return None
        ftype = numba.types.FunctionType(signature_of(as_dtype(like.dtype)))

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            value = cgutils.create_struct_proxy(ftype)(context, builder)
            pointer = context.get_value_type(numba.types.voidptr)
            value.c_addr = builder.inttoptr(args[0], pointer)
            value.py_addr = cgutils.get_null_value(pointer)
            value.jit_addr = cgutils.get_null_value(pointer)
            return value._getvalue()

        return ftype(address, like), codegen

    return numba.extending.intrinsic(at)


def linked_function(symbol: str, function: Any, signature: Any) -> Any:
    """``function`` (a numba dispatcher, compiled for ``signature`` with its C wrapper: not
    :func:`_helper`'s options) under the linker's name ``symbol``, for compiled code to call
    through the intrinsic returned, ``f(like)``, which gives that function as a value of
    numba's first-class function type of ``signature`` (``like``: any value, unused but for
    typing).

    A compiled function that calls another by name has numba link the callee's code into
    its own and optimize and generate it again (a second compilation of the callee's code,
    in every caller: issue 37 item 11). Called through its symbol, the callee's code is
    compiled once; the caller's code (also as loaded from numba's disk cache) holds only the
    symbol, which the linker resolves in each process to the address registered here (as
    numba's own runtime functions are), so no process-local address is stored anywhere.
    Register before any function that calls it is compiled or loaded."""
    from llvmlite import binding
    from numba.experimental.function_type import _get_wrapper_address

    if signature.args not in function.overloads:
        function.compile(signature)
    binding.add_symbol(symbol, _get_wrapper_address(function, signature))

    def at(typingctx: Any, like: Any) -> Any:
        from llvmlite import ir
        from numba.core import cgutils

        ftype = numba.types.FunctionType(signature)

        def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
            declared = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), []), symbol
            )
            value = cgutils.create_struct_proxy(ftype)(context, builder)
            pointer = context.get_value_type(numba.types.voidptr)
            value.c_addr = builder.bitcast(declared, pointer)
            value.py_addr = cgutils.get_null_value(pointer)
            value.jit_addr = cgutils.get_null_value(pointer)
            return value._getvalue()

        return ftype(like), codegen

    return numba.extending.intrinsic(at)


if numba is not None:
    _map_at = _at(map_signature)
    _product_at = _at(lambda dtype: _PRODUCT_SIGNATURES[np.dtype(dtype)])


#: The steps of each formulation, update and kind of algebra, and the views of the work
#: arrays they take: ``(sydirk, conjugation, skew) -> (step, views)`` (:func:`_entry_point`).
_STEPS = {
    (sydirk, conjugation, skew): (
        (_sydirk_step_of if sydirk else _reduced_step_of)(conjugation, skew),
        _sydirk_views if sydirk else _reduced_views,
    )
    for sydirk in (True, False)
    for conjugation in (False, True)
    for skew in _ALGEBRAS
}


def _entry_point(key: str, sydirk: bool, conjugation: bool, blas: bool, skew: bool) -> Any:
    """The entry point of one formulation (``sydirk``: a composition of midpoint steps, else
    the reduced stage form), update, kind of product (``blas``: the BLAS product
    :func:`gemm`, for ``n > LOOP_PRODUCTS_MAX_N``; else plain loops, :func:`_loops`, and
    the product's address is not read) and kind of algebra (``skew``: skew-Hermitian,
    ``M B = (B M)^†``; a run of the other kind compiles none of its branches, e.g. a
    conjugation update on su(N) no Gauss–Jordan solve): the chunk loop over the steps of
    :data:`_STEPS` (:func:`_sydirk_step_of` or :func:`_reduced_step_of`, with views of the
    work arrays from :func:`_sydirk_views` or :func:`_reduced_views`). It takes the
    :class:`LoopArguments`, the system's maps and the product by address (``int64``, see
    :func:`_at`).

    One source for all: the step, the views and the kind of product are the globals
    ``_step``, ``_views`` and ``_blas`` of the function, which is made with a namespace of
    its own (this module's globals and those three; numba prunes the branch on ``_blas`` it
    does not take, so a run types and compiles only the products it calls), so that numba
    compiles the loop as the entry point itself rather than inlining it into one (numba's
    inlining deep-copies the inlined code block by block, a cost that grows with the square
    of its size: about a fifth of the CPU time of a first so(3) run, measured with
    ``benchmarks/compile_time.py``). Its closure holds
    ``key`` (:data:`SHARED_KEY`) alone, which numba's cache key hashes (with the bytecode),
    so that editing a shared rule recompiles it; the name (one cache file per entry point)
    tells them apart."""

    def advance(
        start: Any, coefficients: Any, weights: Any, B_address: Any, B_params: Any,
        project_address: Any, project_params: Any, projecting: bool, tolerances: Any,
        settings: Any, history: Any, extrapolation: Any, warm_counts: Any, states: Any,
        iterations: Any, gemm_address: Any, workspace: Any, real_workspace: Any,
    ) -> int:  # fmt: skip
        """Advance the stack ``start`` (``(K, n, n)``) by up to ``states.shape[0]`` steps of
        ``_step``. Writes each step's states and its iteration count (max over the stack)
        and returns how many steps completed; fewer than asked means the next step failed
        and nothing of it was committed.
        """
        key  # noqa: B018 - part of the cache key
        B = _map_at(B_address, start)
        project = _map_at(project_address, start)
        # _blas: a global of the entry point's own namespace (see above), pruned
        if _blas:  # type: ignore[name-defined] # noqa: F821
            gemm = _product_at(gemm_address, start)
        else:
            gemm = None
        K, n, s = start.shape[0], start.shape[1], weights.shape[0]
        warm = settings[WARM_STARTS] != 0
        depth, m = history.shape[0], history.shape[2]
        # the work arrays, carved out as workspace() sizes them
        solved = workspace[: K * m].reshape((K, m))
        pred = workspace[K * m : K * m + m]
        acc = workspace[K * m + m : K * m + 2 * m]
        o = K * m + 2 * m
        work = workspace[o : o + 4 * s * n * n].reshape((2, 2, s, n, n))
        scratch = workspace[o + 4 * s * n * n : o + 9 * s * n * n].reshape((5, s, n, n))
        err2 = real_workspace[: depth + 1]
        res = real_workspace[depth + 1 : depth + 1 + settings[MAX_ITER]]
        # _views and _step: globals of the entry point's own namespace (see above)
        parts = _views(work, scratch)  # type: ignore[name-defined] # noqa: F821
        x, x0, xf, x0f, m0, m1, m2, m3 = parts
        for step in range(states.shape[0]):
            points = min(warm_counts[FILLED], warm_counts[TRUSTED])
            guessing = warm and points > 0
            most = 0
            for kk in range(K):
                if guessing:
                    _predict(history, kk, points, extrapolation, pred)
                cur = start[kk] if step == 0 else states[step - 1, kk]
                out = states[step, kk]
                total = _step(  # type: ignore[name-defined] # noqa: F821
                    cur, out, pred, solved[kk], guessing, coefficients, weights, x, x0, xf,
                    x0f, m0, m1, m2, m3, B, B_params, gemm, res, tolerances, settings,
                )  # fmt: skip
                if total < 0:
                    return step
                if projecting:
                    project(out, project_params, out)
                for a in range(n):
                    for c in range(n):
                        if not _finite(out[a, c]):
                            return step
                most = max(most, total)
            if warm:
                _commit(solved, history, warm_counts, extrapolation, acc, err2)
            iterations[step] = most
        return states.shape[0]

    step, views = _STEPS[sydirk, conjugation, skew]
    name = f"{'sydirk' if sydirk else 'reduced'}_advance{'_conjugation' if conjugation else ''}"
    name += ("_blas" if blas else "") + ("_skew" if skew else "")
    namespace = {**globals(), "_step": step, "_views": views, "_blas": blas}
    made = types.FunctionType(advance.__code__, namespace, name, None, advance.__closure__)
    made.__qualname__ = name  # one cache file per entry point
    return made


def _entry_signature(dtype: np.dtype) -> Any:
    """numba's signature of an entry point for data of ``dtype``: the types of
    :class:`LoopArguments`, by name."""
    t = numba.types
    f8, i8, d = t.float64, t.int64, numba.from_dtype(dtype)
    types = {
        "start": d[:, :, ::1], "coefficients": f8[:, ::1], "weights": f8[::1], "B": i8,
        "B_params": f8[::1], "project": i8, "project_params": f8[::1],
        "projecting": t.boolean, "tolerances": f8[::1], "settings": i8[::1],
        "history": d[:, :, ::1], "extrapolation": f8[:, ::1], "warm_counts": i8[::1],
        "states": d[:, :, :, ::1], "iterations": i8[::1], "gemm": i8, "workspace": d[::1],
        "real_workspace": f8[::1],
    }  # fmt: skip
    return t.int64(*(types[name] for name in LoopArguments._fields))


def _compile_entry(func: F, dtype: np.dtype) -> F:
    """An entry point compiled for its one signature for data of ``dtype`` (loaded from the
    disk cache if there)."""
    if numba is None:  # pragma: no cover
        return func
    # without reference counting (see the module's docstring) where this numba has the
    # (private) option; with it the same loops are correct, only slower; called from
    # Python only (no C wrapper)
    options: dict[str, Any] = {"error_model": "numpy", "no_cfunc_wrapper": True}
    cpu = importlib.import_module("numba.core.cpu")
    if hasattr(getattr(cpu, "CPUTargetOptions", None), "_nrt"):
        options["_nrt"] = False
    return cast(F, numba_cache.cached_njit(func, signature=_entry_signature(dtype), **options))


def gemm(dtype: np.dtype) -> Any:
    """:func:`_gemm` for data of ``dtype``, compiled (or loaded from the disk cache) on first
    use, as the loops take it (an address, like a system's map)."""
    return _gemm_pointer(np.dtype(dtype))


@functools.cache
def _gemm_pointer(dtype: np.dtype) -> Any:
    signature = _PRODUCT_SIGNATURES[dtype]
    cast(Any, _gemm).compile(signature)  # a numba dispatcher (_jit)
    return _FunctionPointer(_gemm, dtype, signature)


def workspace(
    dtype: np.dtype, K: int, m: int, s: int, n: int, depth: int, max_iter: int
) -> tuple[np.ndarray, np.ndarray]:
    """The work arrays of the loops (``workspace``, ``real_workspace`` of
    :class:`LoopArguments`), which allocate nothing themselves: ``solved (K, m)``,
    ``pred (m)``, ``acc (m)``, ``work (2, 2, s, n, n)`` and ``scratch (5, s, n, n)`` end to
    end in ``dtype``, then ``err2 (depth + 1)`` and the residual history ``res (max_iter)``
    in float64; ``m``: one trajectory's warm offsets, ``depth``: the history's length."""
    return (
        np.zeros(K * m + 2 * m + 9 * s * n * n, dtype=dtype),
        np.zeros(depth + 1 + max_iter),
    )


def entry(
    name: str,
    dtype: np.dtype = DTYPES[0],
    conjugation: bool = False,
    blas: bool = False,
    skew: bool = False,
) -> Any:
    """The entry point ``name`` (``"sydirk_advance"`` or ``"reduced_advance"``) for data of
    ``dtype`` (one of :data:`DTYPES`), the update in conjugation form or not, products by
    BLAS (``blas``: for ``n > LOOP_PRODUCTS_MAX_N``, :func:`gemm`) or by plain loops and a
    skew-Hermitian algebra (``skew``) or not, compiled (or loaded from the disk cache) on
    first use, so that importing this module (as :func:`lieflow.engines.compiled.plan` does
    to check a system's maps) loads no loops, and a run compiles and loads only the loop of
    its own formulation, data type, update, products and kind of algebra."""
    if name not in ("sydirk_advance", "reduced_advance"):
        raise ValueError(f"no entry point {name!r}")
    return _entry(name, np.dtype(dtype), bool(conjugation), bool(blas), bool(skew))


@functools.cache
def _entry(name: str, dtype: np.dtype, conjugation: bool, blas: bool, skew: bool) -> Any:
    """:func:`entry`, compiled once per process and key."""
    source = _entry_point(SHARED_KEY, name == "sydirk_advance", conjugation, blas, skew)
    return _compile_entry(source, dtype)
