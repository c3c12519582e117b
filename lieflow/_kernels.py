"""numba loops behind :mod:`lieflow.compiled` (imported only when the compiled engine runs).

Every loop here is the numpy code path written out entry by entry for a system with
``B(W) = S ⊙ W``: same maps, same update, same stopping rule, same warm starts, so that the
two engines agree to roundoff and take the same iterations (up to one, where roundoff moves a
relative update across the tolerance). Products of ``n×n`` matrices are plain loops up to
``n = 8`` and BLAS calls (``np.dot`` from compiled code: no Python overhead) above.

Conventions: real ``float64`` data only; an ensemble is a ``(K, n, n)`` stack advanced
trajectory by trajectory inside each step; the solvers return the number of updates, negated
when the stopping rule reports a failure (the caller then hands the step to numpy).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np

numba: Any
try:
    numba = importlib.import_module("numba")
except ImportError:  # pragma: no cover - importable without numba (doctest collection, docs)
    numba = None

F = TypeVar("F", bound=Callable[..., Any])

_TINY = float(np.finfo(float).tiny)
_GO, _ACCEPT, _FAIL = 0, 1, 2
#: Up to this ``n`` a skew ``B M B`` is formed as a strict upper triangle of dot products,
#: and products are plain loops; above it BLAS (``np.dot`` called from compiled code, no
#: Python overhead) is faster: 2.5x at n = 16 and 50 for ``A @ B``, up to 8x for ``A @ B^T``.
_SMALL = 8


def _jit(func: F) -> F:
    """``numba.njit`` with an on-disk cache where one can be written.

    numba writes its cache next to the module, or, when the package directory is read-only,
    to a per-user cache directory; if neither is possible, decoration raises
    ``RuntimeError`` and we compile in memory on every first call instead. Without numba
    the plain function is returned (so the module imports) and
    :func:`lieflow.compiled.kernels` raises ``ImportError``.
    """
    if numba is None:  # pragma: no cover - lieflow.compiled.kernels() refuses this case
        return func
    try:
        return cast(F, numba.njit(cache=True, error_model="numpy")(func))
    except RuntimeError:  # pragma: no cover - no writable cache location
        return cast(F, numba.njit(error_model="numpy")(func))


@_jit
def _matmul(A: Any, B: Any, out: Any) -> None:
    """``out = A @ B``: unrolled for ``n = 3``, in ``i, k, j`` order (vectorisable) up to
    ``_SMALL``, else BLAS."""
    n = A.shape[0]
    if n > _SMALL:
        np.dot(A, B, out)
        return
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


@_jit
def _matmul_tn(A: Any, B: Any, out: Any) -> None:
    """``out = A^T @ B`` (:func:`_matmul` on the transposed view)."""
    _matmul(A.T, B, out)


@_jit
def _matmul_nt(A: Any, B: Any, out: Any) -> None:
    """``out = A @ B^T`` (:func:`_matmul` on the transposed view)."""
    _matmul(A, B.T, out)


@_jit
def _verdict(res: Any, k: int, met: bool, growth: float, rule: Any, irule: Any) -> int:
    """:meth:`lieflow.solvers.StoppingRule.verdict` on the relative updates ``res[:k]``.

    ``_ACCEPT`` for ``"converged"`` and ``"roundoff"``, ``_FAIL`` for every other stop,
    ``_GO`` to iterate on.
    """
    rtol, floor, divergence = rule[0], rule[2], rule[3]
    max_iter, patience, window, project = irule[0], irule[1], irule[2], irule[3]
    r = res[k - 1]
    if not (math.isfinite(r) and math.isfinite(growth)):
        return _FAIL
    if met:
        return _ACCEPT
    if growth > divergence:
        return _FAIL
    best_at = 0
    for i in range(1, k):
        if res[i] < res[best_at]:
            best_at = i
    best = res[best_at]
    if k - 1 - best_at >= patience:
        return _ACCEPT if best <= floor else _FAIL
    if project != 0 and k > window and best > floor:
        earlier = res[0]
        for i in range(1, k - window):
            earlier = min(earlier, res[i])
        if earlier > 0.0:
            rate = (best / earlier) ** (1.0 / window)
            if rate >= 1.0:
                return _FAIL
            if rate > 0.0 and k + math.log(max(rtol, floor) / best) / math.log(rate) > max_iter:
                return _FAIL
    if k >= max_iter:  # at the cap, an update at roundoff is accepted (as StoppingRule)
        return _ACCEPT if r <= floor else _FAIL
    return _GO


@_jit
def _judge(
    step2: float, size2: float, k: int, size0: float, res: Any, rule: Any, irule: Any
) -> tuple[int, float]:
    """Record the ``k``-th update, of squared norm ``step2`` to an iterate of squared norm
    ``size2`` (the :class:`IterationMonitor` bookkeeping), and judge it.

    Returns the verdict and the (possibly updated) reference size for the growth test.
    """
    step, size = math.sqrt(step2), math.sqrt(size2)
    if not (math.isfinite(step) and math.isfinite(size)):
        return _FAIL, size0
    if k == 1:
        size0 = max(size0, size, _TINY)
    res[k - 1] = step / max(size, _TINY)
    met = step <= rule[1] + rule[0] * size
    return _verdict(res, k, met, size / size0, rule, irule), size0


@_jit
def _norm(x: Any) -> float:
    xf = x.reshape(x.size)
    acc = 0.0
    for i in range(xf.size):
        acc += xf[i] * xf[i]
    return math.sqrt(acc)


@_jit
def _midpoint_solve(
    W0: Any, S: Any, q: float, skew: bool, x: Any, scratch: Any, res: Any, rule: Any, irule: Any
) -> int:
    """Fixed-point iteration of the midpoint map (SPEC §4.1) from the guess in ``x``:

    ``M <- W0 + q (B M - M B) + q^2 B M B``, ``B = S ⊙ M``, ``q = h/2``;
    for skew algebras ``M B = (B M)^T`` (two products per iteration, SPEC §4.1), and for
    small ``n`` only half of the skew ``B M B`` is formed. The new iterate overwrites ``x``
    entry by entry once the products are formed; on acceptance ``x`` holds the solution.
    """
    n = W0.shape[0]
    B, BM, BMB, MB = scratch[1], scratch[2], scratch[3], scratch[4]
    qq = q * q
    size0 = _norm(x)
    k = 0
    while True:
        for i in range(n):
            for j in range(n):
                B[i, j] = S[i, j] * x[i, j]
        _matmul(B, x, BM)
        step2 = 0.0
        size2 = 0.0
        if skew and n <= _SMALL:
            # B M B is skew for skew B, M: form its strict upper triangle only (its diagonal
            # is zero in exact arithmetic) and mirror it, half a product instead of one.
            for i in range(n):
                g = W0[i, i]
                d = g - x[i, i]
                step2 += d * d
                size2 += g * g
                x[i, i] = g
                for j in range(i + 1, n):
                    bmb = 0.0
                    for c in range(n):
                        bmb += BM[i, c] * B[c, j]
                    c1 = BM[i, j] - BM[j, i]
                    g = W0[i, j] + q * c1 + qq * bmb
                    gt = W0[j, i] - q * c1 - qq * bmb
                    d = g - x[i, j]
                    dt = gt - x[j, i]
                    step2 += d * d + dt * dt
                    size2 += g * g + gt * gt
                    x[i, j] = g
                    x[j, i] = gt
        else:
            _matmul(BM, B, BMB)
            if not skew:
                _matmul(x, B, MB)
            for i in range(n):
                for j in range(n):
                    mb = BM[j, i] if skew else MB[i, j]
                    g = W0[i, j] + q * (BM[i, j] - mb) + qq * BMB[i, j]
                    d = g - x[i, j]
                    step2 += d * d
                    size2 += g * g
                    x[i, j] = g
        k += 1
        verdict, size0 = _judge(step2, size2, k, size0, res, rule, irule)
        if verdict == _ACCEPT:
            return k
        if verdict == _FAIL:
            return -k


@_jit
def _commutator_add(
    W: Any, S: Any, hb: float, skew: bool, M: Any, B: Any, BM: Any, MB: Any
) -> None:
    """``W += hb [S ⊙ M, M]`` in place (one product for skew algebras); ``B``, ``BM``,
    ``MB`` are scratch matrices."""
    n = W.shape[0]
    for i in range(n):
        for j in range(n):
            B[i, j] = S[i, j] * M[i, j]
    _matmul(B, M, BM)
    if skew:
        for i in range(n):
            for j in range(n):
                MB[i, j] = BM[j, i]
    else:
        _matmul(M, B, MB)
    for i in range(n):
        for j in range(n):
            W[i, j] = W[i, j] + hb * (BM[i, j] - MB[i, j])


@_jit
def _predict(last: Any, prev: Any, has_prev: bool, out: Any) -> None:
    """The warm-start prediction ``2 last - prev`` (``last`` alone after one step), 1-D."""
    for i in range(out.size):
        out[i] = 2.0 * last[i] - prev[i] if has_prev else last[i]


@_jit
def _commit(solved: Any, last: Any, prev: Any, flags: Any, diff2: float, norm2: float) -> None:
    """:meth:`WarmStart.advance` for the whole stack (warm arrays flattened to ``(K, m)``)."""
    flags[2] = 1 if flags[0] == 0 or math.sqrt(diff2) < math.sqrt(norm2) else 0
    K, m = last.shape
    for kk in range(K):
        for i in range(m):
            if flags[0] != 0:
                prev[kk, i] = last[kk, i]
            last[kk, i] = solved[kk, i]
    if flags[0] != 0:
        flags[1] = 1
    flags[0] = 1


@_jit
def _distance2(a: Any, b: Any) -> tuple[float, float]:
    """``||a - b||^2`` and ``||a||^2`` of 1-D arrays."""
    d2 = 0.0
    n2 = 0.0
    for i in range(a.size):
        d = a[i] - b[i]
        d2 += d * d
        n2 += a[i] * a[i]
    return d2, n2


@_jit
def sydirk_advance(
    W: Any,
    S: Any,
    b: Any,
    h: float,
    skew: bool,
    rule: Any,
    irule: Any,
    last: Any,
    prev: Any,
    flags: Any,
    states: Any,
    iters: Any,
) -> int:
    """Advance the stack ``W`` (``(K, n, n)``) by up to ``states.shape[0]`` steps of the
    composition of midpoint steps with fractions ``b`` (SPEC §4.2).

    ``last``/``prev`` (``(K, s n n)``: the ``(K, s, n, n)`` offsets, flattened) and
    ``flags = (has_last, has_prev, trusted)`` are the warm-start state, updated in place
    after every completed step. ``irule`` holds
    ``(max_iter, patience, window, project, retry_cold, use_warm)``. Writes each step's states
    and its iteration count (max over the stack) and returns how many steps completed; fewer
    than asked means the next step failed and nothing of it was committed.
    """
    K, n, s = W.shape[0], W.shape[1], b.shape[0]
    retry_cold, use_warm = irule[4] != 0, irule[5] != 0
    solved = np.empty((K, s * n * n))
    pred = np.empty(s * n * n)
    x = np.empty((n, n))
    scratch = np.empty((5, n, n))
    res = np.empty(irule[0])
    for step in range(states.shape[0]):
        has_last, has_prev = flags[0] != 0, flags[1] != 0
        guessing = use_warm and has_last and flags[2] != 0
        diff2 = 0.0
        norm2 = 0.0
        most = 0
        for kk in range(K):
            if has_last:
                _predict(last[kk], prev[kk], has_prev, pred)
            Wc = states[step, kk]  # the state, advanced in place through the sub-steps
            cur = W[kk] if step == 0 else states[step - 1, kk]
            for a in range(n):
                for c in range(n):
                    Wc[a, c] = cur[a, c]
            total = 0
            for i in range(s):
                q = 0.5 * (b[i] * h)
                its = -1
                if guessing:
                    for a in range(n):
                        for c in range(n):
                            x[a, c] = Wc[a, c] + pred[(i * n + a) * n + c]
                    its = _midpoint_solve(Wc, S, q, skew, x, scratch, res, rule, irule)
                    if its < 0:
                        total -= its
                        if not retry_cold:
                            return step
                if its < 0:
                    for a in range(n):
                        for c in range(n):
                            x[a, c] = Wc[a, c]
                    its = _midpoint_solve(Wc, S, q, skew, x, scratch, res, rule, irule)
                    if its < 0:
                        return step
                total += its
                for a in range(n):
                    for c in range(n):
                        solved[kk, (i * n + a) * n + c] = x[a, c] - Wc[a, c]
                _commutator_add(Wc, S, 2.0 * q, skew, x, scratch[1], scratch[2], scratch[4])
            for a in range(n):
                for c in range(n):
                    if not math.isfinite(Wc[a, c]):
                        return step
            d2, n2 = _distance2(solved[kk], pred)
            norm2 += n2
            if has_last:
                diff2 += d2
            most = max(most, total)
        _commit(solved, last, prev, flags, diff2, norm2)
        iters[step] = most
    return states.shape[0]


@_jit
def _reduced_solve(
    W0: Any,
    S: Any,
    hA: Any,
    skew: bool,
    x: Any,
    scratch: Any,
    res: Any,
    rule: Any,
    irule: Any,
) -> int:
    """Fixed-point iteration of the reduced stage form (SPEC §4.5) from the guess in ``x``
    (``x[0] = G``, ``x[1] = P``, each ``(s, n, n)``):

    ``G_i <- I + h sum_j a_ij G_j B_j^T``, ``P_i <- W0 - h sum_j a_ij P_j B_j``,
    ``B_j = S ⊙ (G_j^T P_j)``; for skew algebras ``B^T = -B``. ``3 s`` products per
    iteration. The new iterate overwrites ``x`` once the products are formed; on
    acceptance ``x`` holds the solution.
    """
    s, n = hA.shape[0], W0.shape[0]
    Wst, Bs, GB, PB = scratch[0], scratch[1], scratch[2], scratch[3]
    size0 = _norm(x)
    k = 0
    while True:
        for j in range(s):
            _matmul_tn(x[0, j], x[1, j], Wst[j])
            for a in range(n):
                for c in range(n):
                    Bs[j, a, c] = S[a, c] * Wst[j, a, c]
            if skew:
                _matmul(x[0, j], Bs[j], GB[j])
                for a in range(n):
                    for c in range(n):
                        GB[j, a, c] = -GB[j, a, c]
            else:
                _matmul_nt(x[0, j], Bs[j], GB[j])
            _matmul(x[1, j], Bs[j], PB[j])
        step2 = 0.0
        size2 = 0.0
        for i in range(s):
            for a in range(n):
                for c in range(n):
                    accG = 0.0
                    accP = 0.0
                    for j in range(s):
                        accG += hA[i, j] * GB[j, a, c]
                        accP += hA[i, j] * -PB[j, a, c]
                    gG = accG + (1.0 if a == c else 0.0)
                    gP = accP + W0[a, c]
                    dG = gG - x[0, i, a, c]
                    dP = gP - x[1, i, a, c]
                    step2 += dG * dG + dP * dP
                    size2 += gG * gG + gP * gP
                    x[0, i, a, c] = gG
                    x[1, i, a, c] = gP
        k += 1
        verdict, size0 = _judge(step2, size2, k, size0, res, rule, irule)
        if verdict == _ACCEPT:
            return k
        if verdict == _FAIL:
            return -k


@_jit
def _reduced_update(W0: Any, S: Any, hb: Any, skew: bool, x: Any, out: Any, scratch: Any) -> None:
    """``out = W0 + sum_i h b_i [B_i, W_i]``, ``W_i = G_i^T P_i``, ``B_i = S ⊙ W_i``."""
    Wi, Bi, BW, WB = scratch[0, 0], scratch[1, 0], scratch[2, 0], scratch[3, 0]
    out[:, :] = W0
    for i in range(hb.shape[0]):
        _matmul_tn(x[0, i], x[1, i], Wi)
        _commutator_add(out, S, hb[i], skew, Wi, Bi, BW, WB)


@_jit
def reduced_advance(
    W: Any,
    S: Any,
    hA: Any,
    hb: Any,
    skew: bool,
    rule: Any,
    irule: Any,
    last: Any,
    prev: Any,
    flags: Any,
    states: Any,
    iters: Any,
) -> int:
    """As :func:`sydirk_advance`, for the reduced stage form of a symplectic tableau with
    coefficients ``hA = h A``, ``hb = h b``; warm state ``(K, 2, s, n, n)`` (offsets of
    ``G`` from ``I`` and of ``P`` from ``W0``)."""
    K, n, s = W.shape[0], W.shape[1], hb.shape[0]
    retry_cold, use_warm = irule[4] != 0, irule[5] != 0
    m = s * n * n
    solved = np.empty((K, 2 * m))
    pred = np.empty(2 * m)
    x = np.empty((2, s, n, n))
    scratch = np.empty((5, s, n, n))
    res = np.empty(irule[0])
    for step in range(states.shape[0]):
        has_last, has_prev = flags[0] != 0, flags[1] != 0
        guessing = use_warm and has_last and flags[2] != 0
        diff2 = 0.0
        norm2 = 0.0
        most = 0
        for kk in range(K):
            W0 = W[kk] if step == 0 else states[step - 1, kk]
            if has_last:
                _predict(last[kk], prev[kk], has_prev, pred)
            total = 0
            its = -1
            if guessing:
                for i in range(s):
                    for a in range(n):
                        for c in range(n):
                            e = (i * n + a) * n + c
                            x[0, i, a, c] = (1.0 if a == c else 0.0) + pred[e]
                            x[1, i, a, c] = W0[a, c] + pred[m + e]
                its = _reduced_solve(W0, S, hA, skew, x, scratch, res, rule, irule)
                if its < 0:
                    total -= its
                    if not retry_cold:
                        return step
            if its < 0:
                for i in range(s):
                    for a in range(n):
                        for c in range(n):
                            x[0, i, a, c] = 1.0 if a == c else 0.0
                            x[1, i, a, c] = W0[a, c]
                its = _reduced_solve(W0, S, hA, skew, x, scratch, res, rule, irule)
                if its < 0:
                    return step
            total += its
            for i in range(s):
                for a in range(n):
                    for c in range(n):
                        e = (i * n + a) * n + c
                        solved[kk, e] = x[0, i, a, c] - (1.0 if a == c else 0.0)
                        solved[kk, m + e] = x[1, i, a, c] - W0[a, c]
            out = states[step, kk]
            _reduced_update(W0, S, hb, skew, x, out, scratch)
            for a in range(n):
                for c in range(n):
                    if not math.isfinite(out[a, c]):
                        return step
            d2, n2 = _distance2(solved[kk], pred)
            norm2 += n2
            if has_last:
                diff2 += d2
            most = max(most, total)
        _commit(solved, last, prev, flags, diff2, norm2)
        iters[step] = most
    return states.shape[0]
