r"""Step updates that are isospectral for *any* iterate of the stage equations (SPEC §4.7).

The commutator update ``W1 = W0 + h sum_i b_i [B(W_i), W_i]`` of every formulation is
isospectral only at the fixed point of the stage equations. The updates here write the same
``W1`` as a conjugation ``W1 = U W0 U^{-1}`` by a matrix ``U`` built from the current iterate,
so the spectrum of ``W0`` is kept whatever the iterate, and they equal the commutator update
when the stage equations are solved (derivations: ``docs/theory.md``, *Updates that are
isospectral for any iterate*):

* :func:`cayley_update` — a midpoint step (each sub-step of a SyDIRK composition):
  ``U = (I - a B)^{-1} (I + a B)``, ``a = h/2``, ``B = B(M)`` at the iterate ``M``;
* :func:`lifted_update` — a Gauss (any symplectic tableau) step: ``U = g1^†`` with
  ``g1 = I + h sum_j b_j G_j B_j^†`` of the lifted system, ``W1 = g1^† W0 g1^{-†}``
  (``p1 g1^† = W0`` is a bilinear invariant every symplectic Runge–Kutta method keeps);
  :func:`frozen_stage_conjugator` forms ``g1^†`` from the stage values' ``B_j`` alone (the
  block and Modin–Viviani forms, which do not carry ``G``).

When every ``B`` is skew-Hermitian — always on a skew-Hermitian algebra (``so(n)``,
``u(n)``, ``su(N)``: ``B`` is an element of it, skew-Hermitian up to the roundoff of its own
evaluation), and where it is so to ``16 eps`` on others (the Toda lattice on its symmetric
phase space) — ``U`` is unitary: it is made unitary to roundoff by Newton–Schulz
(:func:`orthonormalize`) and ``W1 = U W0 U^†``. Otherwise ``W1 = U W0 U^{-1}`` (a
similarity: still isospectral), by a linear solve.

Every function takes and returns arrays of any array-API library (NumPy, CuPy, torch, ...)
and uses only ``@``, ``+ - *``, ``eye``, ``where``, ``linalg.solve`` and
``linalg.vector_norm`` of the array's own namespace, so one source serves CPU and GPU. On
NumPy arrays the decisions (unitary or not, when Newton–Schulz stops) are made on the host;
on arrays of another library they are arrays themselves — a fixed number
(:data:`STATIC_NEWTON_SCHULZ_STEPS`) of Newton–Schulz updates, each applied only where the
NumPy rule would still iterate, and ``where`` between the unitary and the similarity
update — so that the functions run traced (``jax.jit``) with no value read on the host. A
conjugator the NumPy path refuses (:class:`~lieflow.errors.ConvergenceError`) comes back
as NaN there: the step is then reported as not finite.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..backends import device_of, identity, namespace
from ..errors import ConvergenceError

Array = Any

#: The step updates a scheme offers: ``"commutator"`` (SPEC §4.1–4.5, isospectral at the
#: fixed point) and ``"conjugation"`` (this module, isospectral for any iterate).
UPDATES = ("commutator", "conjugation")

#: Newton–Schulz steps allowed before :func:`orthonormalize` gives up (each at least
#: squares the distance from unitarity once it is below 1/2: two or three suffice).
NEWTON_SCHULZ_STEPS = 12

#: Newton–Schulz updates on arrays of another library (:func:`orthonormalize`), a static
#: count: from ``||E|| <= 3e-3`` (stage equations solved to ``rtol`` leave ``||E||`` of
#: order ``rtol``) three updates reach roundoff (``3e-3 -> 7e-6 -> 4e-11 -> 1e-21``); a
#: conjugator that needs more comes back as NaN (the NumPy path iterates on).
STATIC_NEWTON_SCHULZ_STEPS = 3


def _dagger(xp: Any, X: Array) -> Array:
    """``X^†`` over the last two axes."""
    Xt = xp.matrix_transpose(X)
    return xp.conj(Xt) if xp.isdtype(X.dtype, "complex floating") else Xt


def _matrix_norms(xp: Any, X: Array) -> Array:
    """Frobenius norm of each matrix of a stack (shape: the stack's)."""
    return xp.linalg.vector_norm(X, axis=(-2, -1))


def _eps(xp: Any, X: Array) -> float:
    return float(xp.finfo(X.dtype).eps)


#: A ``B`` is skew-Hermitian to roundoff when ``||B + B^†|| <= UNITARY_TOLERANCE eps ||B||``
#: (:func:`skew_to_roundoff`).
UNITARY_TOLERANCE = 16
_TINY = float(np.finfo(float).tiny)


def skew_to_roundoff(defect: float, size: float, eps: float) -> bool:
    """Whether a ``B`` with ``||B + B^†|| = defect`` and ``||B|| = size`` is skew-Hermitian
    to roundoff (machine epsilon ``eps``), so that the conjugators built from it are
    unitary. One source for both engines: :func:`is_unitary_generator` calls it with NumPy
    norms and the compiled loops (:mod:`lieflow.engines._compiled_loops`) compile it; scalars
    only."""
    return defect <= UNITARY_TOLERANCE * eps * max(size, _TINY)


def is_unitary_generator(B: Array, xp: Any | None = None) -> Any:
    """Whether every ``B`` of the stack is skew-Hermitian to roundoff
    (:func:`skew_to_roundoff` of the largest norms): a bool for NumPy arrays, a 0-d boolean
    array (not read on the host) for arrays of another library."""
    xp = namespace(B) if xp is None else xp
    defect = xp.max(_matrix_norms(xp, B + _dagger(xp, B)))
    size = xp.max(_matrix_norms(xp, B))
    if xp is np:
        return skew_to_roundoff(float(defect), float(size), _eps(xp, B))
    return defect <= UNITARY_TOLERANCE * _eps(xp, B) * xp.maximum(size, _TINY)


#: What :func:`newton_schulz_step` decides before an update of :func:`orthonormalize`:
#: stop (``U`` is unitary to roundoff, or no longer improves), refuse (too far from
#: unitary), the last update (it takes ``||E||`` to roundoff), or an update and go on.
SCHULZ_DONE, SCHULZ_REFUSED, SCHULZ_LAST, SCHULZ_GO = range(4)


def newton_schulz_step(err: float, last: float, n: int, eps: float) -> int:
    """The decision of :func:`orthonormalize` at ``||E||_F = err`` (``last``: the value
    before the previous update, ``inf`` at the start) for ``n×n`` matrices of machine
    epsilon ``eps``: :data:`SCHULZ_DONE` when ``err <= sqrt(n) eps`` or ``err`` stopped
    decreasing, :data:`SCHULZ_REFUSED` when ``err >= 1`` at the start,
    :data:`SCHULZ_LAST` when the update takes ``||E||`` to roundoff (``err^2 <= eps``),
    else :data:`SCHULZ_GO`. One source for both engines: :func:`orthonormalize` calls it
    and the compiled loops (:mod:`lieflow.engines._compiled_loops`) compile it; scalars and ``math``
    only."""
    if err <= math.sqrt(n) * eps or err >= last:
        return SCHULZ_DONE
    if err >= 1.0 and last == math.inf:
        return SCHULZ_REFUSED
    if err * err <= eps:
        return SCHULZ_LAST
    return SCHULZ_GO


def orthonormalize(K: Array, xp: Any | None = None) -> Array:
    r"""``U = I + K`` replaced by the nearest unitary matrix (its polar factor), by
    Newton–Schulz, returned as its increment ``K`` (so that a small ``K`` keeps its
    relative accuracy):

    .. math:: U \leftarrow U\,(3I - U^\dagger U)/2 = U\,(I - E/2),\qquad
              E = U^\dagger U - I = K + K^\dagger + K^\dagger K,

    i.e. :math:`K \leftarrow K - (E + KE)/2`, which converges quadratically to the polar
    factor when ``||E|| < 1`` (Higham, *Functions of Matrices*, SIAM 2008, §8.3): the next
    ``||E||`` is about ``(3/4) ||E||^2``. Stops after the update that takes ``||E||_F``
    below roundoff (``||E||^2 <= eps``), or when ``||E||_F <= sqrt(n) eps`` (or stops
    decreasing) before an update; raises :class:`~lieflow.errors.ConvergenceError` if
    ``U`` is too far from unitary for the iteration (``||E|| >= 1``: the stage equations
    were not solved to any useful accuracy).
    """
    xp = namespace(K) if xp is None else xp
    if xp is not np:
        return _orthonormalize_static(K, xp)
    eps, n = _eps(xp, K), K.shape[-1]
    last = math.inf
    for _ in range(NEWTON_SCHULZ_STEPS):
        Kh = _dagger(xp, K)
        E = K + Kh + Kh @ K
        err = float(xp.max(_matrix_norms(xp, E)))
        decision = newton_schulz_step(err, last, n, eps)
        if decision == SCHULZ_DONE:
            return K
        if decision == SCHULZ_REFUSED:
            raise ConvergenceError(
                f"the step's conjugator is far from unitary (||U^† U - I|| = {err:.2e} >= 1; "
                "solve the stage equations more accurately: a smaller rtol)",
                solver="newton_schulz",
                iterations=0,
                residuals=(err,),
            )
        last = err
        K = K - 0.5 * (E + K @ E)
        if decision == SCHULZ_LAST:
            return K
    return K


def _orthonormalize_static(K: Array, xp: Any) -> Array:
    """:func:`orthonormalize` on arrays of another library, with no value read on the host:
    :data:`STATIC_NEWTON_SCHULZ_STEPS` updates, each kept only where the NumPy rule would
    still iterate (its stops as 0-d boolean arrays); NaN where the NumPy rule raises
    (``||E|| >= 1`` at the start) or iterates beyond the static count."""
    eps = _eps(xp, K)
    floor = math.sqrt(K.shape[-1]) * eps

    def update(K: Array) -> tuple[Array, Array]:
        """``E``'s norm and the Newton–Schulz update of ``K``."""
        Kh = _dagger(xp, K)
        E = K + Kh + Kh @ K
        return xp.max(_matrix_norms(xp, E)), K - 0.5 * (E + K @ E)

    err, new = update(K)
    go = err > floor  # the NumPy loop's first checks: done already, or refused
    refused = go & (err >= 1.0)
    for _ in range(1, STATIC_NEWTON_SCHULZ_STEPS):
        K = xp.where(go, new, K)
        active = go & (err * err > eps)  # the update did not take ||E|| to roundoff
        last = err
        err, new = update(K)
        go = active & (err > floor) & (err < last)  # above the floor, still decreasing
    K = xp.where(go, new, K)
    active = go & (err * err > eps)
    return xp.where(refused | active, K * math.nan, K)


def conjugate(K: Array, W0: Array, unitary: Any, skew: bool, xp: Any | None = None) -> Array:
    r"""``W1 = U W0 U^{-1}`` for ``U = I + K``, formed as ``W0`` plus an increment computed
    from ``K`` (the roundoff of the products is then relative to the step's change, not to
    ``W0``, as in the commutator update):

    * ``unitary``: ``U`` made unitary (:func:`orthonormalize`), and
      ``W1 = W0 + (K W0 + W0 K^† + K W0 K^†)`` (``= U W0 U^†``); for ``skew`` (``W0`` in a
      skew-Hermitian algebra) ``W0 K^† = -(K W0)^†`` and the increment's skew-Hermitian
      part is taken, so that ``W1`` is in the algebra exactly;
    * otherwise ``W1 = W0 + (K W0 - W0 K) U^{-1}`` (``= U W0 U^{-1}``), ``U^{-1}`` applied
      by a linear solve with ``U^T``.

    ``unitary`` is a bool, or a 0-d boolean array (:func:`is_unitary_generator` of arrays of
    another library): then both are formed and ``where`` picks one, nothing is read on the
    host.
    """
    xp = namespace(K, W0) if xp is None else xp
    if skew or (isinstance(unitary, (bool, np.bool_)) and unitary):
        return _unitary_conjugate(K, W0, skew, xp)
    if isinstance(unitary, (bool, np.bool_)):
        return _similarity(K, W0, xp)
    # a 0-d boolean array (another library: not read on the host): both, then where
    return xp.where(unitary, _unitary_conjugate(K, W0, skew, xp), _similarity(K, W0, xp))


def _unitary_conjugate(K: Array, W0: Array, skew: bool, xp: Any) -> Array:
    """:func:`conjugate` with ``U = I + K`` made unitary."""
    K = orthonormalize(K, xp)
    Kh = _dagger(xp, K)
    KW = K @ W0
    if skew:
        D = KW - _dagger(xp, KW) + KW @ Kh
        return W0 + 0.5 * (D - _dagger(xp, D))
    return W0 + (KW + W0 @ Kh + KW @ Kh)


def _similarity(K: Array, W0: Array, xp: Any) -> Array:
    """:func:`conjugate` with ``U = I + K`` as it is: ``W0 + (K W0 - W0 K) U^{-1}``."""
    D = K @ W0 - W0 @ K
    U = identity(K.shape[-1], K) + K
    return W0 + xp.matrix_transpose(xp.linalg.solve(xp.matrix_transpose(U), xp.matrix_transpose(D)))


def cayley(B: Array, a: float, xp: Any | None = None) -> Array:
    r"""The Cayley transform ``C = (I - aB)^{-1}(I + aB)`` as its increment
    ``K = C - I = 2a (I - aB)^{-1} B``, by one solve with ``n`` right-hand sides. ``C`` is
    unitary (to roundoff) when ``B`` is skew-Hermitian."""
    xp = namespace(B) if xp is None else xp
    eye = identity(B.shape[-1], B)
    return xp.linalg.solve(eye - a * B, (2 * a) * B)


def cayley_update(W0: Array, B: Array, a: float, skew: bool) -> Array:
    r"""The midpoint update in conjugation form (SPEC §4.7):

    .. math:: W_1 = C W_0 C^{-1},\qquad C = (I - a\tilde B)^{-1}(I + a\tilde B),\qquad a = h/2,

    with ``B`` = :math:`\tilde B = B(M)` at any iterate ``M``. At the fixed point
    :math:`W_0 = (I - a\tilde B) M (I + a\tilde B)` it equals
    :math:`(I + a\tilde B) M (I - a\tilde B) = W_0 + h[\tilde B, M]`, the commutator update.
    ``skew``: ``W0`` lies in a skew-Hermitian algebra."""
    xp = namespace(W0, B)
    return conjugate(cayley(B, a, xp), W0, skew or is_unitary_generator(B, xp), skew, xp)


def lifted_update(W0: Array, Gdag: Array, B: Array, hb: Array, skew: bool) -> Array:
    r"""The Gauss (any symplectic tableau) update in conjugation form (SPEC §4.7):

    .. math:: U = g_1^\dagger = I + h\sum_j b_j B_j G_j^\dagger,\qquad W_1 = U W_0 U^{-1},

    from the lifted stage values ``Gdag`` (:math:`G_j^\dagger`, shape ``(..., s, n, n)``),
    their ``B_j`` (same shape) and the weights ``hb`` (:math:`h b_j`, a NumPy vector). At
    the fixed point :math:`p_1 g_1^\dagger = W_0` and this is :math:`g_1^\dagger p_1`, the
    commutator update. With skew-Hermitian ``B_j`` the lifted :math:`g_1` is unitary at the
    fixed point and is made unitary exactly otherwise (:func:`orthonormalize`)."""
    xp = namespace(W0, Gdag, B)
    K = _weighted_sum(xp, hb, B @ Gdag)
    return conjugate(K, W0, skew or is_unitary_generator(B, xp), skew, xp)


def frozen_stage_conjugator(B: Array, A: Array, h: float) -> Array:
    r"""The lifted stage values :math:`G_i^\dagger` for the stages' ``B_i`` (shape
    ``(..., s, n, n)``): the solution of the linear stage equations
    :math:`G_i^\dagger = I + h\sum_j a_{ij} B_j G_j^\dagger`, i.e. one dense solve
    :math:`(I - hA\mathbf B)\,[G_1^\dagger; \dots; G_s^\dagger] = [I; \dots; I]` of size
    ``sn`` (blocks :math:`a_{ij} B_j`). At the fixed point of any formulation these are the
    lifted system's :math:`G_i^\dagger`; for any skew-Hermitian ``B_j`` the
    :math:`g_1` they give is unitary (it preserves the quadratic invariant
    :math:`g g^\dagger` of :math:`\dot g = g B^\dagger`)."""
    xp = namespace(B)
    *batch, s, n, _ = B.shape
    coef = xp.asarray(np.asarray(A) * h, dtype=xp.finfo(B.dtype).dtype, device=device_of(B))
    blocks = coef[:, :, None, None] * B[..., None, :, :, :]  # (..., i, j, a, c) = h a_ij B_j
    k = len(batch)
    dense = xp.reshape(
        xp.permute_dims(blocks, (*range(k), k, k + 2, k + 1, k + 3)), (*batch, s * n, s * n)
    )
    eye_n = identity(B.shape[-1], B)
    rhs = xp.reshape(xp.broadcast_to(eye_n, (*batch, s, n, n)), (*batch, s * n, n))
    eye = xp.eye(s * n, dtype=B.dtype, device=device_of(B))
    return xp.reshape(xp.linalg.solve(eye - dense, rhs), (*batch, s, n, n))


def _weighted_sum(xp: Any, weights: Array, X: Array) -> Array:
    """``sum_j weights[j] X[..., j, :, :]``."""
    out = float(weights[0]) * X[..., 0, :, :]
    for j in range(1, X.shape[-3]):
        out = out + float(weights[j]) * X[..., j, :, :]
    return out
