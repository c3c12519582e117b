r"""Compiled ``B`` and projection of :class:`~lieflow_vortices.PointVortices` for lieflow's
compiled engine (imported only by :meth:`PointVortices.compiled_B`, so numba stays optional).

Both follow lieflow's compiled-map convention ``f(W, params, out)`` (see
:meth:`lieflow.IsospectralSystem.compiled_B`): ``W`` and ``out`` are C-contiguous
``float64`` ``(3K, 3K)`` matrices and ``params`` are the strengths ``Γ_1..Γ_K``. They are
the numpy methods written out entry by entry: ``m_i`` is read from the skew part of the
``i``-th diagonal block (``block_vee``), so ``B(W) = B(project_stage(W))`` for every ``W``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lieflow.numba_cache import cached_njit

_INV_4PI = 1.0 / (4.0 * math.pi)


@cached_njit
def _momentum(W: Any, i: int, c: int) -> float:
    """Component ``c`` of ``m_i = vee((D - D^T)/2)``, ``D`` the ``i``-th diagonal block."""
    o = 3 * i
    if c == 0:
        return 0.5 * (W[o + 2, o + 1] - W[o + 1, o + 2])
    if c == 1:
        return 0.5 * (W[o + 0, o + 2] - W[o + 2, o + 0])
    return 0.5 * (W[o + 1, o + 0] - W[o + 0, o + 1])


@cached_njit
def _write_hat(out: Any, i: int, b0: float, b1: float, b2: float) -> None:
    o = 3 * i
    out[o + 0, o + 0] = 0.0
    out[o + 0, o + 1] = -b2
    out[o + 0, o + 2] = b1
    out[o + 1, o + 0] = b2
    out[o + 1, o + 1] = 0.0
    out[o + 1, o + 2] = -b0
    out[o + 2, o + 0] = -b1
    out[o + 2, o + 1] = b0
    out[o + 2, o + 2] = 0.0


@cached_njit
def vortex_B(W: Any, strengths: Any, out: Any) -> None:
    r"""``out = B(W) = blockdiag(hat(b_i))``,
    :math:`b_i = \frac{1}{4\pi}\sum_{j\ne i} m_j / (1 - m_i\cdot m_j/(\Gamma_i\Gamma_j))`."""
    K = strengths.shape[0]
    out[:, :] = 0.0
    for i in range(K):
        mi0, mi1, mi2 = _momentum(W, i, 0), _momentum(W, i, 1), _momentum(W, i, 2)
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        for j in range(K):
            if j == i:
                continue
            mj0, mj1, mj2 = _momentum(W, j, 0), _momentum(W, j, 1), _momentum(W, j, 2)
            gram = mi0 * mj0 + mi1 * mj1 + mi2 * mj2
            w = 1.0 / (1.0 - gram * (1.0 / (strengths[i] * strengths[j])))
            b0 += w * mj0
            b1 += w * mj1
            b2 += w * mj2
        _write_hat(out, i, _INV_4PI * b0, _INV_4PI * b1, _INV_4PI * b2)


@cached_njit
def vortex_project(W: Any, strengths: Any, out: Any) -> None:
    """``out = project(W)``: each ``m_i`` rescaled to ``|Γ_i|`` (``out`` may be ``W``)."""
    K = strengths.shape[0]
    m = np.empty((K, 3))
    for i in range(K):
        for c in range(3):
            m[i, c] = _momentum(W, i, c)
    out[:, :] = 0.0
    for i in range(K):
        r = math.sqrt(m[i, 0] * m[i, 0] + m[i, 1] * m[i, 1] + m[i, 2] * m[i, 2])
        scale = abs(strengths[i]) / r if r > 0.0 else 1.0
        _write_hat(out, i, m[i, 0] * scale, m[i, 1] * scale, m[i, 2] * scale)
