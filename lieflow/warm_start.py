r"""Warm starts: initial guesses of an implicit step from the previous steps' solutions.

:class:`WarmStart` is the state a :class:`~lieflow.flows.SchemeFlow` carries between steps
(SPEC §5): the last few solved offsets of the scheme's unknowns, and how many of them the
next prediction extrapolates from. The compiled loops (:mod:`lieflow.engines._compiled_loops`)
update the same state in place, with the same extrapolation weights
(:func:`extrapolation_matrix`) and the same trust rule (:func:`trusted_points`: plain scalar
Python, which they compile, as they compile the stopping rule). The extrapolation itself, a
weighted sum of the kept solutions, and the prediction errors are written twice: here as
array operations (one BLAS product of a stacked history, leaf by leaf for trees, the
compiled passes of :mod:`lieflow._warm_kernel` for large NumPy states), there as loops over
the entries. The loops calling :mod:`lieflow._warm_kernel`'s passes instead was built and
measured: the same states bit for bit, but a first compiled run compiles those passes for
the loops' array types too, 6 s more for Euler–Zeitlin N = 16 Gauss-2 on an idle 2-core
machine (17 → 23 s; issue 37 asks ≤ 20 s).
"""

from __future__ import annotations

import functools
import importlib.util
import math
import operator
from collections.abc import Sequence
from typing import Any

import attrs
import numpy as np

from . import state_trees
from .backends import copy
from .errors import InputError
from .solvers.base import einsum, squared_norm

__all__ = [
    "DEFAULT_DEPTH",
    "Prediction",
    "WarmStart",
    "extrapolation_matrix",
    "extrapolation_weights",
    "trusted_points",
    "warm_depth",
]


#: How many solutions a warm start keeps by default (``warm_start=True``): extrapolation
#: of degree up to 4. Measured updates per step, two solutions (linear, lieflow before)
#: -> five: so(10) generalized rigid body T = 20, gauss4 at h = 1, 0.5, 0.25: 29.2 -> 26.3,
#: 17.1 -> 13.7, 11.0 -> 8.2 (compiled engine 2.86 -> 2.62, 3.21 -> 2.86, 4.18 -> 3.65 ms
#: end to end); midpoint at h = 0.1: 6.1 -> 3.9; Euler–Zeitlin N = 64 T = 4, gauss3 at
#: h = 1/8, 1/16: 20.3 -> 16.1, 12.4 -> 9.7; gauss4: 17.7 -> 14.3, 10.8 -> 9.2. Six would
#: gain another 2-10% of updates, but each kept solution is one more set of unknowns in
#: memory: a streamed midpoint run (tests/test_streaming.py, at most 20 states) peaks at
#: 18.9 states with five and 20.3 with six.
DEFAULT_DEPTH = 5


def extrapolation_weights(points: int) -> tuple[int, ...]:
    r"""Weights :math:`w_j` of the polynomial extrapolation from ``points`` equidistant
    values: :math:`p(k + 1) = \sum_{j < m} w_j\, \delta_{k-j}` for the polynomial
    :math:`p` of degree :math:`m - 1` through :math:`\delta_{k-m+1}, \dots, \delta_k`
    (``m = points``), :math:`w_j = (-1)^j \binom{m}{j + 1}` (Newton's backward
    differences: :math:`p(k + 1) = \sum_{i < m} \nabla^i \delta_k`).

    ``1``: ``(1,)`` (the last value); ``2``: ``(2, -1)`` (linear); ``3``: ``(3, -3, 1)``.
    """
    return tuple((-1) ** j * math.comb(points, j + 1) for j in range(points))


#: Up to this many numbers in a history (``points * size``) extrapolations are formed as
#: one product with a weight matrix (a few numpy calls whatever the depth); above it,
#: term by term (no stacked copy of the history: one temporary array per leaf).
_STACKED = 1 << 14


def _matrix(points: int) -> np.ndarray:
    C = np.zeros((points, points))
    for m in range(1, points + 1):
        C[m - 1, :m] = extrapolation_weights(m)
    C.setflags(write=False)
    return C


def _vector(points: int) -> np.ndarray:
    w = np.array(extrapolation_weights(points), dtype=float)
    w.setflags(write=False)
    return w


#: :func:`extrapolation_weights` (as tuples and as read-only float64 vectors) and
#: :func:`extrapolation_matrix` up to 16 points (read-only constants: building them costs
#: more than a small step's extrapolation).
_WEIGHTS = tuple(extrapolation_weights(m) for m in range(17))
_VECTORS = tuple(_vector(m) for m in range(17))
_MATRICES = tuple(_matrix(m) for m in range(17))


def extrapolation_matrix(points: int) -> np.ndarray:
    """The ``(points, points)`` matrix whose row ``m - 1`` holds the weights of the
    extrapolation from ``m`` points (:func:`extrapolation_weights`, zero-padded),
    ``m = 1 .. points``; read-only."""
    return _MATRICES[points] if points < len(_MATRICES) else _matrix(points)


def trusted_points(errors: Any, filled: int, depth: int) -> int:
    """How many kept solutions the next prediction extrapolates from (SPEC §5): the number
    of points whose prediction of the step's solution was closest, fewer among equals, plus
    one if that was all ``filled`` of them and ``depth`` keeps more (the history is still
    filling).

    ``errors[m]`` is the squared error ``||solved - p_m||^2`` of the prediction from ``m``
    points, ``m = 0 .. filled`` (``p_0 = 0``: the cold guess); a NaN error is never the
    closest. One source for both engines: :meth:`WarmStart.advance` calls it on a list, and
    the compiled loops (:mod:`lieflow.engines._compiled_loops`) compile this very function on an
    array;
    hence scalars and indexing only.
    """
    best = 0
    for m in range(1, filled + 1):
        if errors[m] < errors[best]:
            best = m
    if best == filled and best < depth:
        best += 1
    return best


def _weights(points: int) -> tuple[int, ...]:
    return _WEIGHTS[points] if points < len(_WEIGHTS) else extrapolation_weights(points)


def _stacked(history: Sequence[Any]) -> np.ndarray | None:
    """The history as one ``(points, size)`` array if it is small and made of arrays."""
    first = history[0]
    if not (isinstance(first, np.ndarray) and first.size * len(history) <= _STACKED):
        return None
    shape = first.shape
    for x in history:
        if not (isinstance(x, np.ndarray) and x.shape == shape):
            return None
    # np.stack's values without its Python layers: arrays of one shape end to end
    if first.ndim:
        return np.concatenate(history).reshape(len(history), -1)
    return np.array(history).reshape(len(history), -1)


@functools.cache
def _kernel() -> Any:
    """:mod:`lieflow._warm_kernel` where numba is installed, else ``None``."""
    if importlib.util.find_spec("numba") is None:
        return None
    from . import _warm_kernel

    return _warm_kernel


def _flat(arrays: Sequence[Any]) -> tuple[tuple[Any, ...], int] | None:
    """Flat real views of ``arrays`` and how many reals a number is (2: complex), where
    the compiled passes (:mod:`lieflow._warm_kernel`) take them: C-contiguous float64 or
    complex128 NumPy arrays of one shape and dtype, more than :data:`_STACKED` numbers
    each (smaller ones cost microseconds either way), numba installed; else ``None``."""
    first = arrays[0]
    if not (type(first) is np.ndarray and first.dtype.char in "dD" and first.size > _STACKED):
        return None
    for x in arrays:
        if not (
            type(x) is np.ndarray
            and x.shape == first.shape
            and x.dtype == first.dtype
            and x.flags.c_contiguous
        ):
            return None
    if _kernel() is None:
        return None
    parts = 2 if first.dtype.char == "D" else 1
    return tuple(x.reshape(-1).view(np.float64) for x in arrays), parts


def _combine(weights: Sequence[int], history: Sequence[Any], stack: Any = None) -> Any:
    """``sum_j weights[j] * history[j]`` leaf by leaf (the history's arrays are never
    written). ``stack``: :func:`_stacked` of a history that ``history`` begins, if the
    caller has it (its first ``len(weights)`` rows are used). Large NumPy histories: one
    compiled pass with the same roundings (:func:`lieflow._warm_kernel.extrapolate`)."""
    m = len(weights)
    if m == 1 and isinstance(history[0], np.ndarray):
        return history[0].copy()
    flat = _flat(history[:m]) if stack is None else None
    if flat is not None:
        out = np.empty_like(history[0])
        w = _VECTORS[m] if m < len(_VECTORS) else np.array(weights, dtype=float)
        o = out.reshape(-1).view(np.float64)
        _kernel().extrapolate(_kernel().work_groups(o.size), w, flat[0], flat[1], o)
        return out
    if stack is None:
        stack = _stacked(history[:m])
    if stack is not None:
        w = _VECTORS[m] if m < len(_VECTORS) else np.array(weights, dtype=float)
        dtype = stack.real.dtype
        if w.dtype != dtype:
            w = w.astype(dtype)
        # ndarray.dot: the BLAS product of @ (the same bits) without the ufunc layers
        return w.dot(stack[:m]).reshape(history[0].shape)

    def leaf(*xs: Any) -> Any:
        acc = weights[0] * xs[0] if weights[0] != 1 else copy(xs[0])
        for w, x in zip(weights[1:], xs[1:], strict=False):
            acc += w * x
        return acc

    return state_trees.map_leaves(leaf, *history[:m])


def _prediction_errors(solved: Any, history: Sequence[Any], stack: Any = None) -> list[float]:
    """``||solved - p_m||^2`` for the extrapolations ``p_m`` from ``m = 1 .. len(history)``
    points. ``stack``: :func:`_stacked` of ``history``, if the caller has it."""
    if len(history) == 1 and isinstance(solved, np.ndarray):  # one point: the last solution
        last = history[0]
        if isinstance(last, np.ndarray) and last.shape == solved.shape:
            return [squared_norm(solved - last)]
    if stack is None:
        stack = _stacked(history)
    if stack is not None and isinstance(solved, np.ndarray) and solved.shape == history[0].shape:
        C = extrapolation_matrix(len(history))
        if stack.real.dtype != C.dtype:
            C = C.astype(stack.real.dtype)
        E = solved.reshape(1, -1) - C.dot(stack)
        if E.dtype.kind == "c":
            E = E.view(E.real.dtype)
        errors: list[float] = einsum("ij,ij->i", E, E).tolist()
        return errors
    return [
        state_trees.sum_of_squares(
            state_trees.map_leaves(operator.sub, solved, _combine(_weights(m), history))
        )
        for m in range(1, len(history) + 1)
    ]


@attrs.frozen
class WarmStart:
    r"""Initial guesses from the previous steps' solutions (SPEC §5), as explicit state.

    The unknowns of consecutive steps, as offsets :math:`\delta_k` from their ``h = 0``
    values, are smooth functions of the step's initial value :math:`W_k`, which moves
    slowly (at the rate :math:`\|[B, W]\|/\|W\|` of the flow, not the rate
    :math:`\|B\|` at which the lifted unknowns rotate within a step). The next offsets are
    therefore predicted by polynomial extrapolation in the step index from the last
    :math:`m` solutions (:func:`extrapolation_weights`),

    .. math:: \delta_{k+1}^{(0)} = \sum_{j<m} (-1)^j \binom{m}{j+1}\, \delta_{k-j}
              = \sum_{i<m} \nabla^i \delta_k ,

    error :math:`O((h\omega)^m)` for a flow of frequency :math:`\omega` (the cold guess
    :math:`\delta = 0` is :math:`m = 0`; ``m = 2`` is linear extrapolation). Each update
    of the fixed-point iteration gains a factor ``rho`` (its contraction rate), so a guess
    ``10^d`` times closer saves about ``d / log10(1/rho)`` updates.

    The number of points :math:`m` (``trusted``) is chosen by what worked: after each step
    the predictions of every order the history allows (``m = 0`` included) are compared
    with the solution found, and the next step uses the best one — one more point if the
    best used all there were (the history is still filling). A prediction that is worse
    than the cold guess is never used, so at large ``h`` (where a step changes ``W`` a
    lot) this falls back to cold starts by itself.

    Considered and measured, not used: the standard predictor of collocation methods
    (Hairer & Wanner, *Solving ODEs II*, §IV.8), extrapolating the previous step's
    collocation polynomial to the new stage times. In the reduced stage form (SPEC §4.5)
    the stage values are those of the lifted system :math:`(g, p)` started at
    :math:`(I, W_k)`; with Lagrange polynomials :math:`L_j` on the nodes
    :math:`0, c_1, \dots, c_s`, the new stages are
    :math:`G_i^{(0)} = g_1^{-1} u_g(1 + c_i)`, :math:`P_i^{(0)} = g_1^\dagger u_p(1 + c_i)`,
    :math:`u(\theta) = \sum_j L_j(\theta) Y_j`, :math:`g_1 = u_g(1)` (the left
    action :math:`(g, p) \mapsto (Ug, U^{-\dagger}p)` maps solutions to solutions and
    keeps :math:`W = g^\dagger p`, so it moves the extrapolated stages into the new step's
    frame). It extrapolates the fast rotation :math:`g \approx e^{-tB}` by a polynomial and
    was no better than linear extrapolation of the offsets (so(10), gauss4, h = 1, 0.5,
    0.25: 28, 16, 10 updates per step against 29, 17, 11; gauss3 and Euler–Zeitlin:
    worse, e.g. gauss3 at h = 1/8 on Euler–Zeitlin N = 64: 24 against 21).

    Attributes
    ----------
    last : array or tree of arrays, optional
        The last step's solved offsets :math:`\delta_k` (``None`` before the first step).
    previous : tuple, array or None
        The earlier solutions :math:`\delta_{k-1}, \delta_{k-2}, \dots`, most recent first:
        a tuple of fixed length ``depth - 1`` whose entries are ``None`` until filled (its
        length fixes how many solutions are kept); a bare array or ``None`` keeps one
        (``depth = 2``, the state of lieflow before higher-order extrapolation).
    trusted : int
        How many solutions the next prediction extrapolates from (0: the cold guess).
        ``True``/``False`` (older checkpoints) read as 1 and 0.

    The offsets may be one array or any tree of arrays (:mod:`lieflow.state_trees`); extrapolation
    is leaf by leaf and errors are measured on the norm of the whole tree.
    """

    last: Any = attrs.field(default=None, repr=False)
    previous: Any = attrs.field(default=None, repr=False)
    trusted: int = 1

    @classmethod
    def keeping(cls, depth: int) -> WarmStart:
        """An empty warm start that keeps the last ``depth >= 1`` solutions."""
        if depth < 1:
            raise InputError(f"a warm start keeps at least one solution, got depth {depth}")
        return cls(None, (None,) * (depth - 1), 1)

    @property
    def depth(self) -> int:
        """How many solutions are kept."""
        return len(self.previous) + 1 if isinstance(self.previous, tuple) else 2

    def history(self) -> list[Any]:
        """The kept solutions, most recent first (``[]`` before the first step)."""
        if self.last is None:
            return []
        if isinstance(self.previous, tuple):
            older = [p for p in self.previous if p is not None]
        else:
            older = [] if self.previous is None else [self.previous]
        return [self.last, *older]

    def prediction(self, points: int | None = None) -> Any:
        """The extrapolation from the last ``points`` solutions (default ``trusted``, at
        most as many as are kept); ``None`` for the cold guess."""
        history = self.history()
        m = min(int(self.trusted) if points is None else points, len(history))
        return _combine(_weights(m), history) if m > 0 else None

    def guess(self) -> Any:
        """The initial guess to use: :meth:`prediction`, or ``None`` (cold)."""
        return self.prediction()

    def predict(self) -> Prediction:
        """:meth:`guess` and what :meth:`Prediction.advance` needs after the solve (the
        history stacked once for both: one step's worth of :meth:`guess` and
        :meth:`advance`, with the same results)."""
        last, previous = self.last, self.previous
        if type(last) is np.ndarray and type(previous) is tuple and not previous:
            # one solution kept (warm_start=1): the guess is a copy of it, or cold
            return Prediction(self, last.copy() if int(self.trusted) else None, [last], None)
        history = self.history()
        # one solution: nothing to stack (its prediction is a copy, its error one norm)
        stack = _stacked(history) if len(history) > 1 else None
        m = min(int(self.trusted), len(history))
        guess = _combine(_weights(m), history, stack) if m > 0 else None
        return Prediction(self, guess, history, stack)

    def advance(self, solved: Any) -> WarmStart:
        """The state after a step whose solved offsets are ``solved``: ``solved`` joins the
        history, and ``trusted`` becomes the number of points whose prediction of
        ``solved`` was closest (ties: fewer points), plus one if that was all of them and
        one more is kept from now on."""
        return _advanced(self, solved, self.history(), None)

    def replaced(self, history: Sequence[Any], trusted: int) -> WarmStart:
        """A warm start of the same depth (and form) holding ``history`` (most recent
        first; the oldest beyond the depth are dropped) and ``trusted``."""
        last = history[0] if history else None
        if isinstance(self.previous, tuple):
            older = list(history[1 : len(self.previous) + 1])
            previous: Any = (*older, *(None,) * (len(self.previous) - len(older)))
        else:
            previous = history[1] if len(history) > 1 else None
        return WarmStart(last, previous, trusted)


@attrs.frozen(eq=False)
class Prediction:
    """The initial guess of a step (:meth:`WarmStart.predict`) and what turns the step's
    solution into the next warm start (:meth:`advance`).

    Attributes
    ----------
    state : WarmStart
        The warm start the guess came from.
    guess : array, tree of arrays or None
        The initial guess (``None``: cold).
    """

    state: WarmStart
    guess: Any = attrs.field(repr=False)
    _history: list[Any] = attrs.field(repr=False)
    _stack: Any = attrs.field(repr=False)

    def advance(self, solved: Any) -> WarmStart:
        """:meth:`WarmStart.advance` of :attr:`state` with the step's solved offsets."""
        return _advanced(self.state, solved, self._history, self._stack)


def _advanced(state: WarmStart, solved: Any, history: list[Any], stack: Any) -> WarmStart:
    """:meth:`WarmStart.advance` given ``state``'s history and, if the caller has it, its
    :func:`_stacked` form ``stack`` (one stacking per step serves the guess and this)."""
    previous = state.previous
    if type(previous) is tuple and not previous and len(history) == 1:
        last = history[0]
        if type(solved) is np.ndarray and type(last) is np.ndarray and last.shape == solved.shape:
            # one solution kept (warm_start=1), as below without the stacking
            errors = [squared_norm(solved), squared_norm(solved - last)]
            return WarmStart(solved, (), trusted_points(errors, 1, 1))
    flat = _flat([solved, *history]) if history and stack is None else None
    if flat is not None:  # one compiled pass over the solution and the history
        sums = np.empty(len(history) + 1)
        views = flat[0]
        C = extrapolation_matrix(len(history))
        _kernel().errors(_kernel().work_groups(views[0].size), views[0], views[1:], C, sums)
        best = trusted_points(sums.tolist(), len(history), state.depth)
        return state.replaced([solved, *history], best)
    errors = [
        squared_norm(solved)
        if isinstance(solved, np.ndarray)
        else state_trees.sum_of_squares(solved)
    ]
    if history:
        errors += _prediction_errors(solved, history, stack)
    best = trusted_points(errors, len(history), state.depth)
    return state.replaced([solved, *history], best)


def warm_depth(warm_start: bool | int) -> int:
    """How many solutions a ``warm_start`` option keeps (:class:`~lieflow.SchemeFlow`,
    :func:`lieflow.integrate`): ``True`` -> :data:`DEFAULT_DEPTH`, ``False`` -> 0 (no warm
    starts), an int ``>= 0`` -> itself."""
    if isinstance(warm_start, (bool, np.bool_)):
        return DEFAULT_DEPTH if warm_start else 0
    if isinstance(warm_start, (int, np.integer)) and warm_start >= 0:
        return int(warm_start)
    raise InputError(
        f"warm_start must be True, False or the number of solutions to keep (>= 0), "
        f"got {warm_start!r}"
    )
