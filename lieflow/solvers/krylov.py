"""Restarted GMRES on arrays of any library, with its loops passed in: one source for eager
arrays (NumPy, CuPy, ...) and traced ones (``jax.jit``).

Every array operation goes through the namespace of the right-hand side
(:func:`lieflow.backends.namespace`) with static shapes: the Krylov basis is a
``(restart + 1, N)`` array whose unused rows are zero, new rows and columns are written by
``where`` against an index vector (no item assignment), and the two loops — the Arnoldi
steps of a cycle and the restart cycles — are ``while_loop(cond, body, state)`` calls with
the contract of ``jax.lax.while_loop``. :func:`host_while_loop` (the default) runs them as
Python loops, reading each condition on the host; a compiled caller passes
``jax.lax.while_loop``. On NumPy arrays, whose loop counter is on the host anyway, the
basis is written in place and only its rows built so far are read (the cost of SciPy's
``gmres``, which this replaces); the numbers are the same.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..backends import device_of, identity, is_numpy, namespace

Array = Any
#: ``while_loop(cond, body, state)``: ``body`` applied while ``cond(state)`` holds
#: (``jax.lax.while_loop``'s contract); ``state`` is a tuple of arrays.
WhileLoop = Callable[[Callable[[Any], Any], Callable[[Any], Any], Any], Any]


def host_while_loop(cond: Callable[[Any], Any], body: Callable[[Any], Any], state: Any) -> Any:
    """``jax.lax.while_loop``'s contract as a Python loop: ``body`` while ``cond(state)``,
    each condition read on the host (for device arrays: a synchronisation per pass)."""
    while bool(cond(state)):
        state = body(state)
    return state


def _zeros(shape: tuple[int, ...], like: Array) -> Array:
    if is_numpy(like):
        return np.zeros(shape, dtype=like.dtype)
    return namespace(like).zeros(shape, dtype=like.dtype, device=device_of(like))


def _arange(n: int, like: Array) -> Array:
    if is_numpy(like):
        return np.arange(n)
    return namespace(like).arange(n, device=device_of(like))


def _cast(mask: Array, like: Array) -> Array:
    """A boolean array as 0/1 in ``like``'s dtype."""
    if is_numpy(mask):
        return mask.astype(like.dtype)
    return namespace(mask).astype(mask, like.dtype)


def _orthogonalize(V: Array, w: Array, j: Any) -> tuple[Array, Array]:
    """``w`` made orthogonal to the basis rows ``V[:j+1]`` by classical Gram–Schmidt
    applied twice, and its coefficients ``h`` (a vector of ``V``'s row count, zero below
    row ``j``). NumPy arrays (``j`` known on the host): the rows built so far only; other
    libraries: all rows (those not built yet are zero, and so are their coefficients)."""
    if is_numpy(V):
        rows = int(j) + 1
        Vj = V[:rows]
        h = Vj @ w
        w = w - h @ Vj
        h2 = Vj @ w
        w = w - h2 @ Vj
        out = np.zeros(V.shape[0], dtype=V.dtype)
        out[:rows] = h + h2
        return w, out
    h = V @ w
    w = w - h @ V
    h2 = V @ w
    return w - h2 @ V, h + h2


def _basis(rows: int, like: Array) -> Array:
    """Room for ``rows`` basis vectors like ``like``: zeros (rows not built yet must be zero
    for :func:`_orthogonalize`), uninitialised for NumPy (whose rows are read only once
    built)."""
    if is_numpy(like):
        return np.empty((rows, like.shape[0]), dtype=like.dtype)
    return _zeros((rows, like.shape[0]), like)


def _combine(y: Array, V: Array, j: Any) -> Array:
    """``sum_i y_i V[i]`` over the ``j`` rows built (``y`` is zero beyond them)."""
    if is_numpy(V):
        used = int(j)
        return y[:used] @ V[:used]
    return y @ V[: y.shape[0], :]


def _set_row(V: Array, i: Any, v: Array) -> Array:
    """``V`` with row ``i`` replaced by ``v``: in place for NumPy (``V`` is GMRES's own
    array), by ``where`` against the row index otherwise (no item assignment)."""
    if is_numpy(V):
        V[int(i)] = v
        return V
    xp = namespace(V)
    return xp.where((_arange(V.shape[0], V) == i)[:, None], v[None, :], V)


def _norm(v: Array) -> Array:
    """Euclidean norm of a real vector, a 0-d array."""
    xp = namespace(v)
    return xp.sqrt(xp.sum(v * v))


def gmres(
    apply: Callable[[Array], Array],
    b: Array,
    *,
    rtol: Any,
    restart: int = 50,
    cycles: int = 20,
    while_loop: WhileLoop = host_while_loop,
) -> Array:
    r"""Solve ``A x = b`` for a real vector ``b`` of length ``N`` by restarted GMRES
    (Saad & Schultz, SIAM J. Sci. Stat. Comput. 7 (1986) 856–869), matrix-free:
    ``apply(v)`` is ``A v``.

    Each cycle builds an orthonormal basis ``V`` of the Krylov space of the residual ``r``
    by Arnoldi steps (classical Gram–Schmidt applied twice, which keeps ``V`` orthonormal to
    working precision: Giraud, Langou & Rozložník, Comput. Math. Appl. 50 (2005) 1069),
    reduces the Hessenberg matrix ``H`` to triangular form ``R = Q H`` by Givens rotations
    as it grows (``Q`` kept as a ``(k+1)×(k+1)`` product), so that the least-squares
    residual :math:`\min_y \|\beta e_1 - H y\| = \beta |Q_{j+1,0}|` is known after every
    step, and ends when it is at most ``rtol ||b||`` or after ``restart`` steps (at most
    ``N``); then ``x += V^T y`` with ``R y = \beta Q e_1`` and the true residual is
    computed afresh. At most ``cycles`` cycles; returns the last ``x`` (converged or not, as
    SciPy's ``gmres`` does with ``maxiter``). ``rtol`` may be a float or a 0-d array.

    Static shapes throughout (no item assignment, no value read on the host but by
    ``while_loop``): traced by passing ``while_loop=jax.lax.while_loop``.
    """
    xp = namespace(b)
    n = b.shape[0]
    k = max(1, min(int(restart), n))
    rows = _arange(k + 1, b)
    cols = rows[:k]
    eye = identity(k + 1, b)
    target = rtol * _norm(b)

    def arnoldi_going(state: tuple[Any, ...]) -> Any:
        j, _V, _v, _Q, _R, _beta, res = state
        return (j < k) & (res > target)

    def arnoldi(state: tuple[Any, ...]) -> tuple[Any, ...]:
        j, V, v, Q, R, beta, _res = state
        w, h = _orthogonalize(V, apply(v), j)
        hn = _norm(w)
        next_row = rows == j + 1
        v = w / xp.where(hn > 0, hn, 1.0)  # a breakdown (hn = 0) ends the cycle: res = 0
        V = _set_row(V, j + 1, v)
        t = Q @ xp.where(next_row, hn, h)  # column j of H, the rotations so far applied
        this_row = rows == j
        a = xp.sum(xp.where(this_row, t, 0.0))  # t[j] and t[j + 1]
        c = xp.sum(xp.where(next_row, t, 0.0))
        rho = xp.sqrt(a * a + c * c)
        safe = xp.where(rho > 0, rho, 1.0)
        cos = xp.where(rho > 0, a / safe, 1.0)
        sin = c / safe
        # the rotation [cos sin; -sin cos] of rows j, j + 1 zeroes t[j + 1]: t[j] becomes
        # rho, and Q takes the rotation (two rows changed)
        R = xp.where(
            (cols == j)[None, :], xp.where(this_row, rho, t * _cast(rows < j, b))[:, None], R
        )
        qj = xp.sum(xp.where(this_row[:, None], Q, 0.0), axis=0)
        qj1 = xp.sum(xp.where(next_row[:, None], Q, 0.0), axis=0)
        Q = xp.where(this_row[:, None], (cos * qj + sin * qj1)[None, :], Q)
        Q = xp.where(next_row[:, None], (cos * qj1 - sin * qj)[None, :], Q)
        res = xp.abs(beta * xp.sum(xp.where(next_row, Q[:, 0], 0.0)))
        return j + 1, V, v, Q, R, beta, res

    def cycling(state: tuple[Any, ...]) -> Any:
        count, _x, _r, rnorm = state
        return (count < cycles) & (rnorm > target)

    def cycle(state: tuple[Any, ...]) -> tuple[Any, ...]:
        count, x, r, beta = state
        v = r / xp.where(beta > 0, beta, 1.0)
        V = _set_row(_basis(k + 1, b), rows[0], v)
        R = _zeros((k + 1, k), b)
        j, V, _v, Q, R, _beta, _res = while_loop(
            arnoldi_going, arnoldi, (rows[0], V, v, eye, R, beta, beta)
        )
        # R y = beta Q e_1 on the j columns built; the unused ones made the identity (and
        # a zero pivot, A singular on the Krylov space, made one: y stays finite)
        used = cols < j
        Rk = xp.where(used[None, :], R[:k, :], 0.0)
        pivots = xp.sum(Rk * eye[:k, :k], axis=-1)
        Rk = Rk + eye[:k, :k] * _cast(xp.logical_or(~used, pivots == 0), b)[None, :]
        g = xp.where(used, beta * Q[:k, 0], 0.0)
        y = xp.linalg.solve(Rk, g[:, None])[:, 0]
        x = x + _combine(y, V, j)
        r = b - apply(x)
        return count + 1, x, r, _norm(r)

    state = (rows[0], _zeros((n,), b), b, _norm(b))
    return while_loop(cycling, cycle, state)[1]
