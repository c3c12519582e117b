r"""The block-diagonal Lie algebra :math:`\mathfrak{so}(3)^K \subset \mathfrak{so}(3K)`.

An element is ``W = blockdiag(hat(m_1), ..., hat(m_K))`` with ``hat(m) x = m × x``; it is
identified with the vector of momenta ``m = (m_1, ..., m_K)`` of shape ``(K, 3)``. The
Frobenius pairing of two elements is ``<W, V> = tr(W^T V) = 2 sum_i m_i · v_i``.

Only lieflow's public API is used (``lieflow.LieAlgebra``, ``lieflow.systems.hat``/``vee``,
``lieflow.backends``). Every function takes arrays of any array-API library (CuPy, PyTorch,
JAX, ``array_api_strict``: :mod:`lieflow.backends`) as well as NumPy's, and on those uses
their namespace only — no item assignment, no indexing by integer arrays, no value read on
the host — so that it also runs traced (``jax.jit``).
"""

from __future__ import annotations

from typing import Any, ClassVar

import attrs
import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow
from lieflow.backends import from_host, is_foreign_array, namespace
from lieflow.systems import hat, vee

Array = NDArray[Any]


def _block_count(K: int) -> int:
    if isinstance(K, bool) or not isinstance(K, (int, np.integer)) or K < 1:
        raise lieflow.InputError(f"the number of blocks K must be a positive integer, got {K!r}")
    return int(K)


def diagonal_blocks(W: ArrayLike, K: int) -> Array:
    """The ``K`` diagonal 3×3 blocks of ``W``, shape ``(..., K, 3, 3)`` (a copy).

    ``W`` has shape ``(..., 3K, 3K)``; leading axes broadcast.
    """
    if is_foreign_array(W):  # entries (3k + a, 3k + b) of the flattened matrices, one take
        X: Any = W
        xp = namespace(X)
        n = 3 * K
        k, a, b = np.meshgrid(np.arange(K), np.arange(3), np.arange(3), indexing="ij")
        flat = xp.reshape(X, (*X.shape[:-2], n * n))
        at = from_host(((3 * k + a) * n + 3 * k + b).ravel(), X)
        return xp.reshape(xp.take(flat, at, axis=-1), (*X.shape[:-2], K, 3, 3))
    W = np.asarray(W)
    blocks = W.reshape(*W.shape[:-2], K, 3, K, 3)
    idx = np.arange(K)
    # (..., K, K, 3, 3) view, then the K diagonal blocks (adjacent advanced indices stay put)
    return np.swapaxes(blocks, -3, -2)[..., idx, idx, :, :]


def block_vee(W: ArrayLike) -> Array:
    r"""Momenta ``m_i`` of the diagonal blocks of ``W``, shape ``(..., K, 3)``.

    Reads the skew-symmetric part of each block,
    :math:`m_i = \operatorname{vee}\big(\tfrac12 (W_{ii} - W_{ii}^T)\big)`, i.e. the vector of
    the orthogonal projection of ``W`` onto :math:`\mathfrak{so}(3)^K`. For an element of the
    algebra this is the exact inverse of :func:`block_hat`; for any other matrix it is a
    linear map, so functions of ``m`` stay differentiable on the whole matrix space.
    """
    foreign = is_foreign_array(W)
    X: Any = W if foreign else np.asarray(W)
    n = X.shape[-1]
    if X.ndim < 2 or X.shape[-2] != n or n % 3:
        raise lieflow.InputError(f"expected matrices of shape (..., 3K, 3K), got shape {X.shape}")
    D = diagonal_blocks(X, n // 3)
    Dt = namespace(D).matrix_transpose(D) if foreign else np.swapaxes(D, -1, -2)
    return 0.5 * (vee(D) - vee(Dt))


def block_hat(m: ArrayLike) -> Array:
    r"""``blockdiag(hat(m_1), ..., hat(m_K))`` for momenta ``m`` of shape ``(..., K, 3)``.

    Returns shape ``(..., 3K, 3K)``; off-diagonal 3×3 blocks are zero.
    """
    foreign = is_foreign_array(m)
    v: Any = m if foreign else np.asarray(m)
    if v.ndim < 2 or v.shape[-1] != 3:
        raise lieflow.InputError(f"expected momenta of shape (..., K, 3), got shape {v.shape}")
    *batch, K, _ = v.shape
    if foreign:  # hat(m_i) at block (i, i) of a (..., K, 3, K, 3) array by where, no scatter
        xp = namespace(v)
        out = xp.where(_diagonal_mask(K, v), hat(v)[..., :, :, None, :], 0.0)
        return xp.reshape(out, (*batch, 3 * K, 3 * K))
    out = np.zeros((*batch, K, K, 3, 3), dtype=v.dtype)
    idx = np.arange(K)
    out[..., idx, idx, :, :] = hat(v)
    return np.swapaxes(out, -3, -2).reshape(*batch, 3 * K, 3 * K)


def _diagonal_mask(K: int, like: Any) -> Any:
    """``(K, 1, K, 1)`` booleans, true at the diagonal blocks of a ``(..., K, 3, K, 3)``
    array, in ``like``'s library and on its device."""
    return from_host(np.eye(K, dtype=bool)[:, None, :, None], like)


@attrs.frozen
class BlockSO3(lieflow.LieAlgebra):
    r""":math:`\mathfrak{so}(3)^K`: block-diagonal real ``3K×3K`` matrices with skew 3×3 blocks.

    A Lie subalgebra of :math:`\mathfrak{so}(3K)` (a direct sum of K copies of
    :math:`\mathfrak{so}(3)`), dimension ``3K``. The orthogonal projection (Frobenius pairing)
    skew-symmetrizes and zeroes every off-diagonal 3×3 block:

    .. math:: P(X) = \operatorname{blockdiag}_i\big(\tfrac12 (X_{ii} - X_{ii}^T)\big).

    Parameters
    ----------
    K : int
        Number of 3×3 blocks; the matrix size is ``n = 3K``.
    """

    K: int = attrs.field(converter=_block_count)
    n: int = attrs.field(init=False)

    dtype: ClassVar[np.dtype] = np.dtype(np.float64)
    skew: ClassVar[bool] = True
    symbol: ClassVar[str] = "so(3)^"

    @n.default
    def _size(self) -> int:
        return 3 * self.K

    def __str__(self) -> str:
        return f"so(3)^{self.K}"

    def project(self, X: ArrayLike) -> Array:
        if is_foreign_array(X):  # another array library (lieflow.backends)
            xp = namespace(X)
            S = 0.5 * (X - xp.matrix_transpose(X))
            blocks = xp.reshape(S, (*S.shape[:-2], self.K, 3, self.K, 3))
            return xp.reshape(xp.where(_diagonal_mask(self.K, X), blocks, 0.0), S.shape)
        X = np.asarray(X)
        S = 0.5 * (X - np.swapaxes(X, -1, -2))
        K = self.K
        mask = np.eye(K, dtype=bool)[:, None, :, None]  # (K, 1, K, 1): keep blocks (i, i)
        blocks = S.reshape(*S.shape[:-2], K, 3, K, 3)
        P: Array = np.where(mask, blocks, 0.0).reshape(S.shape)
        return P

    @property
    def dimension(self) -> int:
        return 3 * self.K

    def _membership_hint(self) -> str:
        return (
            f"Elements of so(3)^{self.K} are block-diagonal with skew-symmetric 3×3 blocks "
            "(W = blockdiag(hat(m_1), ..., hat(m_K)))."
        )
