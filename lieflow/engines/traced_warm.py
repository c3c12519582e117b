r"""The warm start (:class:`~lieflow.warm_start.WarmStart`) as fixed-shape arrays, for a traced
engine: what a compiled loop carries from step to step.

:class:`~lieflow.warm_start.WarmStart` keeps the last solutions in a tuple that fills up, and
chooses with Python comparisons how many of them the next prediction extrapolates from. A
program traced once for every step (``jax.lax.while_loop``) needs the same rule on arrays of
fixed shape:

* ``history`` ``(depth, *shape)``: the solved offsets :math:`\delta_k, \delta_{k-1}, \dots`,
  most recent first, zero where not yet filled; ``count`` of them filled;
* ``trusted``: how many points the next prediction uses.

:func:`predict` is :meth:`WarmStart.predict <lieflow.warm_start.WarmStart.predict>`'s guess,
:math:`\sum_{j<m} w^{(m)}_j \delta_{k-j}` with :math:`m = \min(\text{trusted}, \text{count})`
and the weights of :func:`~lieflow.warm_start.extrapolation_matrix` (the cold guess, zero
offsets, for :math:`m = 0`). :func:`advance` is :meth:`WarmStart.advance
<lieflow.warm_start.WarmStart.advance>`: the errors :math:`\|\delta - p_m\|^2` of every
prediction the history allowed (:math:`p_0 = 0`), the first smallest chosen (ties: fewer
points), one point more when that used all there were and the depth allows. The two agree to
roundoff (tests); the extrapolation weights are the same constants.

Every function takes the array namespace ``xp`` of its arrays and uses its standard
operations only, so it runs eagerly on any array library and traced by ``jax.jit``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from ..algebras import Array
from ..warm_start import WarmStart, extrapolation_matrix

__all__ = ["History", "advance", "from_warm_start", "predict"]


class History(NamedTuple):
    """A warm start as arrays (a JAX pytree): ``history`` ``(depth, *shape)``, most recent
    first; ``count`` solutions filled; ``trusted`` points the next prediction uses (0-d
    integer arrays)."""

    history: Any
    count: Any
    trusted: Any


def from_warm_start(
    state: WarmStart, shape: tuple[int, ...], dtype: Any, xp: Any, device: Any = None
) -> History:
    """``state`` as a :class:`History` of ``xp`` arrays (on ``device``) whose solutions
    have ``shape`` and ``dtype``. The kept solutions are copied (from the host if they are
    NumPy arrays, as a checkpoint's are)."""
    depth = state.depth
    kept = state.history()[:depth]
    rows = [xp.asarray(_host_or_same(x, xp), dtype=dtype, device=device) for x in kept]
    zeros = xp.zeros(shape, dtype=dtype, device=device)
    rows += [zeros] * (depth - len(rows))
    return History(
        xp.stack([xp.reshape(r, shape) for r in rows]),
        xp.asarray(len(kept), dtype=xp.int64, device=device),
        xp.asarray(int(state.trusted), dtype=xp.int64, device=device),
    )


def _host_or_same(x: Any, xp: Any) -> Any:
    """``x`` as ``xp.asarray`` can take it: NumPy arrays go through a contiguous copy."""
    return np.ascontiguousarray(x) if isinstance(x, np.ndarray) else x


def predict(state: History, xp: Any) -> Array:
    """The initial guess (offsets) of the next step: the extrapolation from
    ``min(trusted, count)`` points, zero for none."""
    depth = state.history.shape[0]
    weights = _weights(depth, xp)  # (depth + 1, depth): row m, m points
    m = xp.minimum(state.trusted, state.count)
    w = xp.take(weights, xp.reshape(m, (1,)), axis=0)[0]
    return xp.tensordot(xp.astype(w, state.history.dtype), state.history, axes=1)


def advance(state: History, solved: Array, xp: Any) -> History:
    """The state after a step whose solved offsets are ``solved``."""
    hist = state.history
    depth = hist.shape[0]
    weights = _weights(depth, xp)
    predictions = xp.tensordot(xp.astype(weights, hist.dtype), hist, axes=1)  # p_0 .. p_depth
    diff = solved[None, ...] - predictions
    axes = tuple(range(1, diff.ndim))
    errors = xp.sum(xp.real(diff * xp.conj(diff)), axis=axes)  # (depth + 1,)
    points = xp.arange(depth + 1, dtype=xp.int64)
    # predictions from more points than there were are not candidates; nan loses
    errors = xp.where((points <= state.count) & ~xp.isnan(errors), errors, xp.inf)
    best = xp.astype(xp.argmin(errors), xp.int64)  # the first smallest: ties, fewer points
    best = xp.where((best == state.count) & (best < depth), best + 1, best)
    shifted = xp.concat([solved[None, ...], hist[: depth - 1]], axis=0)
    return History(shifted, xp.minimum(state.count + 1, depth), best)


def _weights(depth: int, xp: Any) -> Array:
    """:func:`~lieflow.warm_start.extrapolation_matrix` with a zero row 0 (no points): row
    ``m`` holds the weights of the extrapolation from ``m`` points, a float64 array of
    ``xp`` (a constant of a traced program)."""
    table = np.zeros((depth + 1, depth))
    table[1:] = extrapolation_matrix(depth)
    return xp.asarray(table)
