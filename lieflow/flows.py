r"""Flows: one step ``W(t) -> W(t + h)`` with explicit state, and their compositions.

A :class:`Flow` is what the stepping loop (:mod:`lieflow.stepping`) advances::

    state = flow.init(W0)
    W, state, stats = flow.step(W, t, h, state)

``state`` is a tree of arrays (:mod:`lieflow.state_trees`) that the flow alone reads and writes —
the warm start of an implicit scheme, nothing for an exact sub-flow — and that a
checkpoint stores leaf by leaf, so a run resumes bit-for-bit. ``stats`` is a
:class:`StepStats`. Three flows come with lieflow (compare GeometricIntegrators.jl's
integrators, ``Composition`` and ``ProjectedMethod``):

* :class:`SchemeFlow` — an ISOSyRK :class:`~lieflow.schemes.Scheme` on a system, solved by a
  :class:`~lieflow.solvers.Solver`, with warm starts (SPEC §5, :mod:`lieflow.warm_start`);
* :class:`Splitting` — a composition of flows (Lie–Trotter, Strang, symmetric compositions
  of Strang steps of higher order), e.g. a conservative isospectral step with dissipation
  and forcing;
* :class:`Projected` — a flow followed by the system's phase-space projection.

A flow written outside lieflow (an exact dissipative sub-step, a stochastic forcing) needs
only ``name``, ``init`` and ``step``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, cast

import attrs
import numpy as np

from .algebras import SO, SU, Array
from .errors import ConvergenceError, InputError
from .schemes import contraction
from .schemes.base import Scheme
from .solvers.base import Solver
from .solvers.fixed_point import FixedPoint, FrozenB
from .steps import Flow, StepStats
from .systems.base import IsospectralSystem
from .systems.shifted import CasimirShifted
from .tableaus import COMPOSITIONS, composition_weights

# WarmStart and DEFAULT_DEPTH: importable from here as before (lieflow.WarmStart too)
from .warm_start import WarmStart, warm_depth

__all__ = [
    "SPLITTINGS",
    "Flow",
    "Projected",
    "SchemeFlow",
    "Splitting",
    "StepStats",
]


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
    #: Whether a step from a state exactly on the phase space lands exactly on it, or on
    #: it up to its trace, so that :meth:`step_from_phase_space` need not project, or only
    #: remove the trace (derived once): the scheme keeps exact skew-symmetry
    #: (:attr:`~lieflow.schemes.Scheme.keeps_skew`) and the system's projection is its
    #: algebra's, so(n)'s ``(W - W^T)/2`` (``"f"``: real states land on so(n)) or su(N)'s
    #: (``"c"``: complex states land on the skew-Hermitian matrices, whose projection is
    #: :meth:`lieflow.SU.project_skew_hermitian`; a subclass of :class:`~lieflow.SU` only
    #: where its own class body sets ``projects_as_su = True``, a promise that its
    #: projection has SU's bits, as lieflow-zeitlin's compiled one has); ``""`` otherwise.
    _exact: str = attrs.field(init=False, repr=False)

    @_exact.default
    def _keeps_phase_space(self) -> str:
        # (a scheme of one's own that is not a lieflow Scheme need not say: "")
        keeps = getattr(self.scheme, "keeps_skew", False) is True
        if not keeps or type(self.system).project is not IsospectralSystem.project:
            return ""
        algebra = type(self.system.algebra)
        # su(N) itself, or a subclass that says in its own body that its projection has
        # SU's bits (a subclass inherits no such promise: it may project otherwise)
        su = algebra is SU or vars(algebra).get("projects_as_su") is True
        return "f" if algebra is SO else "c" if su else ""

    def __attrs_post_init__(self) -> None:
        warm_depth(self.warm_start)

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
        return warm_depth(self.warm_start)

    @property
    def projects_onto(self) -> IsospectralSystem:
        """The system whose projection ends each step (:class:`Projected` does not
        project again)."""
        return self.system

    def init(self, W0: Array) -> WarmStart | None:
        """An empty warm start (``None`` without warm starts)."""
        depth = self.depth
        return WarmStart.keeping(depth) if depth else None

    def step(
        self, W: Array, t: float, h: float, state: WarmStart | None
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """One step of the scheme (autonomous: ``t`` is not used)."""
        return self._step(W, h, state, False)

    def step_from_phase_space(
        self, W: Array, t: float, h: float, state: WarmStart | None
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """:meth:`step` from a state exactly on the phase space — ``project(W)`` is ``W``
        bit for bit, as every state :meth:`step` returns — with the same result: the new
        state is not projected where that would return it unchanged, a real NumPy state
        of so(n) after a scheme that keeps exact skew-symmetry
        (:attr:`~lieflow.schemes.Scheme.keeps_skew`: the midpoint rule and its
        compositions, commutator update), and a complex one of su(N) only has its trace
        removed (:meth:`lieflow.SU.project_skew_hermitian`: the projection's bits, one
        pass over ``N × N`` numbers less). The stepping loop
        (:func:`lieflow.stepping.advance`) calls it for every step after the first of a
        run. (The one exception: an entry beyond ``2^1023``, which the projection would
        overflow to ``inf``.)"""
        return self._step(W, h, state, bool(self._exact))

    def _step(
        self, W: Array, h: float, state: WarmStart | None, exact: bool
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """A step; ``exact``: ``W`` is on the phase space and the step keeps it there."""
        try:
            if state is None:
                res = self.scheme.step(W, h, self.system, self.solver, None)
                new = None
            else:
                prediction = state.predict()
                res = self.scheme.step(W, h, self.system, self.solver, prediction.guess)
                new = prediction.advance(res.warm)
        except ConvergenceError as exc:
            # a fixed-point iteration that failed: which step size would converge
            solver = self.solver
            if isinstance(solver, FixedPoint) and not isinstance(solver, FrozenB):
                raise exc.with_hint(contraction.hint(self.system, self.scheme, W, h)) from None
            raise
        W1 = res.W
        if exact and type(W1) is np.ndarray and W1.dtype.kind == self._exact:
            if self._exact == "c":  # su(N): skew-Hermitian bit for bit, the trace removed
                W1 = cast(SU, self.system.algebra).project_skew_hermitian(W1)
            return W1, new, res.stats
        return self.system.project(W1), new, res.stats


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


def _sequence(seq: Sequence[tuple[int, float]]) -> tuple[tuple[int, float], ...]:
    return tuple((int(i), float(c)) for i, c in seq)


def _flows(flows: Sequence[Flow]) -> tuple[Flow, ...]:
    return tuple(flows)


#: The splittings by name (:meth:`Splitting.named`, ``[splitting] method``).
SPLITTINGS = ("lie", "strang", *COMPOSITIONS)


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

        ``method`` names a composition of :data:`lieflow.tableaus.COMPOSITIONS`
        (``"triple_jump"``: Yoshida 1990, order 4; ``"suzuki5"``: order 4; ``"yoshida6"``:
        order 6; the coefficients of :func:`lieflow.tableaus.composition_weights`, which
        the SyDIRK schemes of the same names are made of), or gives symmetric coefficients
        ``gamma`` summing to 1 (order 2 claimed; raise it with
        ``attrs.evolve(split, order=...)`` when the coefficients are known to do better).
        """
        if isinstance(method, str):
            gammas, order = composition_weights(method)
        else:
            gammas, order = tuple(float(g) for g in method), 2
            if not np.allclose(gammas, gammas[::-1], rtol=0, atol=1e-14):
                raise InputError(f"composition coefficients must be symmetric, got {gammas}")
        seq = [sub for g in gammas for sub in _strang(len(flows), g)]
        return cls(flows, _merge(seq), order=order)

    @classmethod
    def named(cls, method: str, *flows: Flow) -> Splitting:
        """:meth:`lie`, :meth:`strang`, or :meth:`composition` with ``method`` (one of
        :data:`lieflow.tableaus.COMPOSITIONS`), by name."""
        if method == "lie":
            return cls.lie(*flows)
        if method == "strang":
            return cls.strang(*flows)
        if method in COMPOSITIONS:
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
    the state on the phase space by construction.

    One projection per step: a flow whose steps already end with that projection (a
    :class:`SchemeFlow` on the same system, or on its Casimir-shifted form; a
    :class:`Projected` onto it) is not projected again — its :attr:`projects_onto` says
    so, as any flow of one's own may."""

    flow: Flow
    system: IsospectralSystem

    def __attrs_post_init__(self) -> None:
        _check_flow(self.flow, "flow")

    @property
    def name(self) -> str:
        """``"projected(<flow>)"``."""
        return f"projected({self.flow.name})"

    @property
    def projects_onto(self) -> IsospectralSystem:
        """The system whose projection ends each step."""
        return self.system

    @property
    def projects_again(self) -> bool:
        """Whether :meth:`step` projects (``False`` when the wrapped flow's steps end with
        the same projection already)."""
        inner = getattr(self.flow, "projects_onto", None)
        return inner is None or _phase_space(inner) is not _phase_space(self.system)

    def init(self, W0: Array) -> Any:
        """The wrapped flow's state."""
        return self.flow.init(W0)

    def step(self, W: Array, t: float, h: float, state: Any) -> tuple[Array, Any, StepStats]:
        """A step of the wrapped flow, projected (once: see the class docstring)."""
        W, state, stats = self.flow.step(W, t, h, state)
        return (self.system.project(W) if self.projects_again else W), state, stats


def _phase_space(system: IsospectralSystem) -> IsospectralSystem:
    """The system whose projection ``system`` uses (a Casimir-shifted system: its base's)."""
    while isinstance(system, CasimirShifted):
        system = system.base
    return system
