r"""Flows: one step ``W(t) -> W(t + h)`` with explicit state, and their compositions.

A :class:`Flow` is what the driver (:mod:`lieflow.driver`) advances::

    state = flow.init(W0)
    W, state, stats = flow.step(W, t, h, state)

``state`` is a tree of arrays (:mod:`lieflow.tree`) that the flow alone reads and writes —
the warm start of an implicit scheme, nothing for an exact sub-flow — and that a
checkpoint stores leaf by leaf, so a run resumes bit-for-bit. ``stats`` is a
:class:`StepStats`. Three flows come with lieflow (compare GeometricIntegrators.jl's
integrators, ``Composition`` and ``ProjectedMethod``):

* :class:`SchemeFlow` — an ISOSyRK :class:`~lieflow.schemes.Scheme` on a system, solved by a
  :class:`~lieflow.solvers.Solver`, with warm starts (SPEC §5);
* :class:`Splitting` — a composition of flows (Lie–Trotter, Strang, symmetric compositions
  of Strang steps of higher order), e.g. a conservative isospectral step with dissipation
  and forcing;
* :class:`Projected` — a flow followed by the system's phase-space projection.

A flow written outside lieflow (an exact dissipative sub-step, a stochastic forcing) needs
only ``name``, ``init`` and ``step``.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import attrs
import numpy as np

from . import tree
from .algebras import Array
from .backends import copy
from .errors import InputError
from .schemes.base import Scheme
from .solvers.base import Solver, einsum, squared_norm
from .solvers.fixed_point import FixedPoint
from .systems.base import IsospectralSystem

__all__ = [
    "DEFAULT_DEPTH",
    "Flow",
    "Projected",
    "SchemeFlow",
    "Splitting",
    "StepStats",
    "WarmStart",
    "extrapolation_matrix",
    "extrapolation_weights",
]


@attrs.frozen
class StepStats:
    """What one step of a flow cost.

    Attributes
    ----------
    iterations : int
        Nonlinear-solver updates (summed over the sub-steps of a composition; 0 for an
        explicit or exact flow).
    solver : str
        Name of the solver that finished the (last implicit sub-)step; ``""`` if none.
    residual : float
        The largest last relative update of the step's solves (0 if none).
    """

    iterations: int = 0
    solver: str = ""
    residual: float = 0.0


@runtime_checkable
class Flow(Protocol):
    """One step of an evolution ``W(t) -> W(t + h)``, with state carried between steps."""

    @property
    def name(self) -> str:
        """A short name (used in files and reports)."""
        ...

    def init(self, W0: Array) -> Any:
        """The state before the first step from ``W0`` (a tree of arrays, or ``None``)."""
        ...

    def step(self, W: Array, t: float, h: float, state: Any) -> tuple[Array, Any, StepStats]:
        """Advance ``W`` from time ``t`` by ``h``; return the new ``W``, state and stats."""
        ...


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


def _combine(weights: Sequence[int], history: Sequence[Any], stack: Any = None) -> Any:
    """``sum_j weights[j] * history[j]`` leaf by leaf (the history's arrays are never
    written). ``stack``: :func:`_stacked` of a history that ``history`` begins, if the
    caller has it (its first ``len(weights)`` rows are used)."""
    m = len(weights)
    if m == 1 and isinstance(history[0], np.ndarray):
        return history[0].copy()
    if stack is None:
        stack = _stacked(history[:m])
    if stack is not None:
        w = _VECTORS[m] if m < len(_VECTORS) else np.array(weights, dtype=float)
        dtype = stack.real.dtype
        if w.dtype != dtype:
            w = w.astype(dtype)
        return (w @ stack[:m]).reshape(history[0].shape)

    def leaf(*xs: Any) -> Any:
        acc = weights[0] * xs[0] if weights[0] != 1 else copy(xs[0])
        for w, x in zip(weights[1:], xs[1:], strict=False):
            acc += w * x
        return acc

    return tree.map_leaves(leaf, *history[:m])


def _prediction_errors(solved: Any, history: Sequence[Any], stack: Any = None) -> list[float]:
    """``||solved - p_m||^2`` for the extrapolations ``p_m`` from ``m = 1 .. len(history)``
    points. ``stack``: :func:`_stacked` of ``history``, if the caller has it."""
    if stack is None:
        stack = _stacked(history)
    if stack is not None and isinstance(solved, np.ndarray) and solved.shape == history[0].shape:
        C = extrapolation_matrix(len(history))
        if stack.real.dtype != C.dtype:
            C = C.astype(stack.real.dtype)
        E = solved.reshape(1, -1) - C @ stack
        if E.dtype.kind == "c":
            E = E.view(E.real.dtype)
        errors: list[float] = einsum("ij,ij->i", E, E).tolist()
        return errors
    return [
        tree.sum_of_squares(tree.map_leaves(operator.sub, solved, _combine(_weights(m), history)))
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

    The offsets may be one array or any tree of arrays (:mod:`lieflow.tree`); extrapolation
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


def _advanced(state: WarmStart, solved: Any, history: list[Any], stack: Any) -> WarmStart:
    """:meth:`WarmStart.advance` given ``state``'s history and, if the caller has it, its
    :func:`_stacked` form ``stack`` (one stacking per step serves the guess and this)."""
    best = 0
    best_error = (
        squared_norm(solved) if isinstance(solved, np.ndarray) else tree.sum_of_squares(solved)
    )
    if history:
        for m, error in enumerate(_prediction_errors(solved, history, stack), start=1):
            if error < best_error:
                best, best_error = m, error
    if best == len(history) and best < state.depth:
        best += 1
    return state.replaced([solved, *history], best)


def _warm_depth(warm_start: bool | int) -> int:
    """Solutions kept for ``SchemeFlow.warm_start`` (0: no warm starts)."""
    if isinstance(warm_start, (bool, np.bool_)):
        return DEFAULT_DEPTH if warm_start else 0
    if isinstance(warm_start, (int, np.integer)) and warm_start >= 0:
        return int(warm_start)
    raise InputError(
        f"warm_start must be True, False or the number of solutions to keep (>= 0), "
        f"got {warm_start!r}"
    )


@attrs.frozen(eq=False)
class SchemeFlow:
    """A :class:`~lieflow.schemes.Scheme` on a system as a :class:`Flow`.

    Each step solves the scheme's implicit equation with ``solver`` (warm-started from the
    previous steps when ``warm_start``, SPEC §5) and maps the new state onto the system's
    phase space (:meth:`~lieflow.IsospectralSystem.project`: a change at roundoff level for
    a converged step, which keeps defects from accumulating over long runs). The state is
    a :class:`WarmStart` (``None`` without warm starts).

    ``warm_start``: ``True`` (keep :data:`DEFAULT_DEPTH` solutions and extrapolate from as
    many as help), ``False`` (cold starts), or how many solutions to keep (``2``: at most
    linear extrapolation, e.g. to save memory on very large states: each kept solution
    costs one set of the scheme's unknowns).
    """

    system: IsospectralSystem
    scheme: Scheme
    solver: Solver = attrs.field(factory=FixedPoint)
    warm_start: bool | int = True

    def __attrs_post_init__(self) -> None:
        _warm_depth(self.warm_start)

    @property
    def name(self) -> str:
        """The scheme's name."""
        return self.scheme.name

    @property
    def order(self) -> int:
        """The scheme's order."""
        return self.scheme.order

    @property
    def depth(self) -> int:
        """How many solutions the warm start keeps (0: no warm starts)."""
        return _warm_depth(self.warm_start)

    def init(self, W0: Array) -> WarmStart | None:
        """An empty warm start (``None`` without warm starts)."""
        depth = self.depth
        return WarmStart.keeping(depth) if depth else None

    def step(
        self, W: Array, t: float, h: float, state: WarmStart | None
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """One step of the scheme (autonomous: ``t`` is not used)."""
        if state is None:
            res = self.scheme.step(self.system, W, h, self.solver, None)
            new = None
        else:
            # state.guess() and state.advance(...), with the history stacked once for both
            history = state.history()
            stack = _stacked(history) if history else None
            m = min(int(state.trusted), len(history))
            guess = _combine(_weights(m), history, stack) if m > 0 else None
            res = self.scheme.step(self.system, W, h, self.solver, guess)
            new = _advanced(state, res.warm, history, stack)
        return (
            self.system.project(res.W),
            new,
            StepStats(res.iterations, res.solver, res.residual),
        )


def _check_flow(flow: object, what: str) -> None:
    if not isinstance(flow, Flow):
        raise InputError(
            f"{what} must be a Flow (name, init(W0), step(W, t, h, state)), got "
            f"{type(flow).__name__}; wrap a scheme as lieflow.SchemeFlow(system, scheme)"
        )


def _strang(m: int, g: float) -> list[tuple[int, float]]:
    """Sub-steps of one Strang step of size ``g h`` of ``m`` flows (the last one inner)."""
    outer = [(i, g / 2) for i in range(m - 1)]
    return [*outer, (m - 1, g), *outer[::-1]]


def _merge(sequence: Sequence[tuple[int, float]]) -> tuple[tuple[int, float], ...]:
    """Join consecutive sub-steps of the same flow (their sizes add up)."""
    out: list[tuple[int, float]] = []
    for i, c in sequence:
        if out and out[-1][0] == i:
            out[-1] = (i, out[-1][1] + c)
        else:
            out.append((i, c))
    return tuple(out)


#: Symmetric compositions of a second-order symmetric step (Strang): coefficients
#: ``gamma_k`` of ``S(gamma_m h) ... S(gamma_1 h)`` and the order reached.
#: ``triple_jump``: Yoshida (1990), Suzuki (1990), order 4;
#: ``suzuki5``: Suzuki's five-stage fractal, order 4 (smaller error constant).
_COMPOSITIONS: dict[str, tuple[tuple[float, ...], int]] = {
    "triple_jump": (
        (
            1 / (2 - 2 ** (1 / 3)),
            -(2 ** (1 / 3)) / (2 - 2 ** (1 / 3)),
            1 / (2 - 2 ** (1 / 3)),
        ),
        4,
    ),
    "suzuki5": (
        (
            1 / (4 - 4 ** (1 / 3)),
            1 / (4 - 4 ** (1 / 3)),
            1 - 4 / (4 - 4 ** (1 / 3)),
            1 / (4 - 4 ** (1 / 3)),
            1 / (4 - 4 ** (1 / 3)),
        ),
        4,
    ),
}


def _sequence(seq: Sequence[tuple[int, float]]) -> tuple[tuple[int, float], ...]:
    return tuple((int(i), float(c)) for i, c in seq)


def _flows(flows: Sequence[Flow]) -> tuple[Flow, ...]:
    return tuple(flows)


#: The splittings by name (:meth:`Splitting.named`, ``[splitting] method``).
SPLITTINGS = ("lie", "strang", *_COMPOSITIONS)


@attrs.frozen(eq=False)
class Splitting:
    r"""A composition of flows: ``Φ_h = φ^{(i_m)}_{c_m h} ∘ ... ∘ φ^{(i_1)}_{c_1 h}``.

    Parameters
    ----------
    flows : sequence of Flow
        The flows composed (e.g. an isospectral :class:`SchemeFlow` and a dissipative
        sub-flow).
    sequence : sequence of (int, float)
        The sub-steps in the order they are taken: which flow (an index into ``flows``)
        and its step as a fraction of ``h``. Each flow's fractions must add up to 1 (the
        composition is then consistent, order >= 1). Build the usual ones with
        :meth:`lie`, :meth:`strang` and :meth:`composition`.
    order : int
        The composition's order as a splitting method (1 for Lie–Trotter, 2 for Strang),
        given the sub-flows are exact or at least that accurate.

    Notes
    -----
    Every sub-flow sees its own clock: the ``j``-th sub-step of flow ``i`` starts at
    ``t + h (c_1 + ... + c_{j-1})`` summed over flow ``i``'s earlier sub-steps, which is
    the standard time-stepping of splittings of non-autonomous flows. Each sub-step has its
    own state slot (a tuple entry), so a warm start of a Strang half step is predicted from
    the same half step of the previous steps. Negative fractions (compositions of order
    > 2) run a sub-flow backwards; for a dissipative flow that is ill-posed in the limit,
    so prefer Strang there.
    """

    flows: tuple[Flow, ...] = attrs.field(converter=_flows)
    sequence: tuple[tuple[int, float], ...] = attrs.field(converter=_sequence)
    order: int = 1

    def __attrs_post_init__(self) -> None:
        if not self.flows:
            raise InputError("a Splitting needs at least one flow")
        for k, flow in enumerate(self.flows):
            _check_flow(flow, f"flows[{k}]")
        totals = [0.0] * len(self.flows)
        for i, c in self.sequence:
            if not 0 <= i < len(self.flows):
                raise InputError(
                    f"sub-step of flow {i}: there are only {len(self.flows)} flows "
                    f"(indices 0..{len(self.flows) - 1})"
                )
            if not math.isfinite(c):
                raise InputError(f"sub-step fractions must be finite, got {c!r}")
            totals[i] += c
        for i, total in enumerate(totals):
            if abs(total - 1.0) > 1e-12:
                raise InputError(
                    f"the sub-steps of flow {i} ({self.flows[i].name}) add up to {total!r} h, "
                    "not h: the composition would not be consistent"
                )

    @classmethod
    def lie(cls, *flows: Flow) -> Splitting:
        """Lie–Trotter splitting ``φ^{(m)}_h ∘ ... ∘ φ^{(1)}_h`` (``flows[0]`` runs
        first), order 1."""
        return cls(flows, [(i, 1.0) for i in range(len(flows))], order=1)

    @classmethod
    def strang(cls, *flows: Flow) -> Splitting:
        """Strang splitting, order 2: half steps of ``flows[0], ..., flows[-2]``, a full
        step of ``flows[-1]``, then the half steps in reverse order. With two flows:
        ``φ^A_{h/2} ∘ φ^B_h ∘ φ^A_{h/2}``. Put the costly flow (an implicit scheme) last:
        it then runs once per step."""
        return cls(flows, _strang(len(flows), 1.0), order=2)

    @classmethod
    def composition(cls, *flows: Flow, method: str | Sequence[float] = "triple_jump") -> Splitting:
        r"""A symmetric composition :math:`S_{\gamma_m h} \circ \dots \circ S_{\gamma_1 h}`
        of Strang steps :math:`S = ` :meth:`strang` ``(*flows)``, adjacent sub-steps of the
        same flow merged (Hairer, Lubich & Wanner, *Geometric Numerical Integration*,
        §II.4 and §V.3).

        ``method`` is ``"triple_jump"`` (Yoshida 1990, order 4), ``"suzuki5"`` (order 4),
        or symmetric coefficients ``gamma`` summing to 1 (order 2 claimed; raise it with
        ``attrs.evolve(split, order=...)`` when the coefficients are known to do better).
        """
        if isinstance(method, str):
            if method not in _COMPOSITIONS:
                raise InputError(
                    f"unknown composition {method!r}; choose one of {sorted(_COMPOSITIONS)} "
                    "or give the coefficients"
                )
            gammas, order = _COMPOSITIONS[method]
        else:
            gammas, order = tuple(float(g) for g in method), 2
            if not np.allclose(gammas, gammas[::-1], rtol=0, atol=1e-14):
                raise InputError(f"composition coefficients must be symmetric, got {gammas}")
        seq = [sub for g in gammas for sub in _strang(len(flows), g)]
        return cls(flows, _merge(seq), order=order)

    @classmethod
    def named(cls, method: str, *flows: Flow) -> Splitting:
        """:meth:`lie`, :meth:`strang`, or :meth:`composition` with ``method``
        (``"triple_jump"``, ``"suzuki5"``), by name."""
        if method == "lie":
            return cls.lie(*flows)
        if method == "strang":
            return cls.strang(*flows)
        if method in _COMPOSITIONS:
            return cls.composition(*flows, method=method)
        raise InputError(f"unknown splitting {method!r}; choose one of {', '.join(SPLITTINGS)}")

    @property
    def name(self) -> str:
        """``"splitting(<flows>)"``."""
        return f"splitting({', '.join(f.name for f in self.flows)})"

    def init(self, W0: Array) -> tuple[Any, ...]:
        """One state per sub-step."""
        return tuple(self.flows[i].init(W0) for i, _ in self.sequence)

    def step(
        self, W: Array, t: float, h: float, state: tuple[Any, ...]
    ) -> tuple[Array, tuple[Any, ...], StepStats]:
        """Take the sub-steps in order, each flow on its own clock."""
        clock = [t] * len(self.flows)
        states: list[Any] = []
        iterations, solver, residual = 0, "", 0.0
        for (i, c), sub in zip(self.sequence, state, strict=True):
            W, sub, stats = self.flows[i].step(W, clock[i], c * h, sub)
            clock[i] += c * h
            states.append(sub)
            iterations += stats.iterations
            if stats.solver:
                solver, residual = stats.solver, max(residual, stats.residual)
        return W, tuple(states), StepStats(iterations, solver, residual)


@attrs.frozen(eq=False)
class Projected:
    """``flow`` followed by ``system``'s phase-space projection
    (:meth:`~lieflow.IsospectralSystem.project`), e.g. after a sub-flow that does not keep
    the state on the phase space by construction."""

    flow: Flow
    system: IsospectralSystem

    def __attrs_post_init__(self) -> None:
        _check_flow(self.flow, "flow")

    @property
    def name(self) -> str:
        """``"projected(<flow>)"``."""
        return f"projected({self.flow.name})"

    def init(self, W0: Array) -> Any:
        """The wrapped flow's state."""
        return self.flow.init(W0)

    def step(self, W: Array, t: float, h: float, state: Any) -> tuple[Array, Any, StepStats]:
        """A step of the wrapped flow, projected."""
        W, state, stats = self.flow.step(W, t, h, state)
        return self.system.project(W), state, stats
