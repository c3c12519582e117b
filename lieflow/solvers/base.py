"""The contract between schemes and nonlinear solvers.

A scheme states its implicit equation as an :class:`ImplicitProblem`: an unknown ``x``, a
fixed-point map ``F`` whose fixed point is the solution, the map's derivative (for Newton) and
a frozen-B map (the Cayley-type quasi-Newton iteration of SPEC §5). A :class:`Solver` finds
the fixed point and returns a :class:`SolveResult`; it never knows which scheme called it.

Unknowns have shape ``batch + core``: the trailing ``core_ndim`` axes form one unknown and
leading axes index independent problems (an ensemble of initial conditions). Norms are
Frobenius norms per problem; a solve has converged when every problem in the batch has.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import attrs
import numpy as np

from ..algebras import Array
from ..backends import numpy_c_function, vdot


@runtime_checkable
class ImplicitProblem(Protocol):
    """An implicit equation ``x = F(x)`` posed by a scheme for one step."""

    @property
    def x0(self) -> Array:
        """Initial guess (cold: the ``h = 0`` solution; warm: extrapolated from the last step)."""
        ...

    @property
    def core_ndim(self) -> int:
        """How many trailing axes of ``x`` make up one unknown."""
        ...

    def map(self, x: Array) -> Array:
        """The fixed-point map ``F(x)``; a new array."""
        ...

    def map_derivative(self, x: Array, dx: Array) -> Array:
        """Fréchet derivative ``F'(x)[dx]`` (Newton solves ``(I - F'(x)) d = F(x) - x``)."""
        ...

    def frozen_map(self, x: Array) -> Array:
        """Frozen-B map: evaluate ``B`` at ``x`` and solve the then-linear equation exactly."""
        ...


@attrs.frozen
class SolveResult:
    """Outcome of one nonlinear solve.

    Attributes
    ----------
    x : ndarray
        The last iterate (the solution if ``converged``).
    converged : bool
        Whether the stopping rule was met.
    iterations : int
        Updates performed (map evaluations for fixed-point iterations, linear solves for
        Newton). The paper counts one fewer for fixed-point iteration (SPEC §5).
    residuals : tuple of float
        Relative update (or residual) norm after each iteration, max over the batch.
    reason : str
        ``"converged"``, ``"roundoff"`` (stagnated at roundoff below ``roundoff_floor``:
        accepted), ``"max_iterations"``, ``"stalled"``, ``"diverged"`` or ``"non_finite"``.
    solver : str
        Name of the solver that produced ``x``.
    """

    x: Array = attrs.field(repr=False)
    converged: bool
    iterations: int
    residuals: tuple[float, ...]
    reason: str
    solver: str


@runtime_checkable
class Solver(Protocol):
    """Anything with a ``name`` and ``solve(problem) -> SolveResult``."""

    @property
    def name(self) -> str: ...

    def solve(self, problem: ImplicitProblem) -> SolveResult: ...


#: ``einsum(subscripts, *operands)`` as :func:`numpy.einsum` computes it (a constant:
#: its C function, ``optimize=False``, the default; :func:`~lieflow.backends.numpy_c_function`).
einsum: Callable[..., Any] = numpy_c_function("c_einsum", np.einsum)


#: Up to this many numbers a sum of squares is a dot product (BLAS ``dot``: 0.45 µs on a
#: 3×3 matrix against 1.4 µs for ``einsum``; single-threaded at this size, so its result
#: does not depend on the number of threads); above it, ``einsum``'s plain loop.
DOT_SIZE = 4096


def sum_of_squares(x: Array) -> Any:
    """``||x||_F^2`` of a whole array as a NumPy scalar of ``x``'s real precision: a dot
    product of the raveled array (real and imaginary parts as two reals) for up to
    :data:`DOT_SIZE` numbers, else a plain sum of squares (``einsum``, no BLAS call,
    whose threading overhead dominates for small arrays). The two may differ in the last
    bits (they add the squares in different orders). Neither warns where squares of
    finite entries overflow (the dot product is :func:`~lieflow.backends.vdot`: the BLAS
    ``dot`` of ``ndarray.dot``, without its floating-point error check)."""
    flat = x.ravel() if isinstance(x, np.ndarray) else np.ascontiguousarray(x).reshape(-1)
    if flat.dtype.kind == "c":
        flat = flat.view(flat.real.dtype)
    if flat.size <= DOT_SIZE:
        return vdot(flat, flat)
    return einsum("i,i->", flat, flat)


def squared_norm(x: Array) -> float:
    """:func:`sum_of_squares` as a Python float."""
    if type(x) is np.ndarray and x.dtype.kind == "f" and x.size <= DOT_SIZE:
        flat = x.ravel()  # the common case inline: one problem's update, a few µs a call
        return float(vdot(flat, flat))
    return float(sum_of_squares(x))


def batch_norm(x: Array, core_ndim: int) -> Array:
    """Frobenius norm over the trailing ``core_ndim`` axes (shape: the batch shape).

    A plain sum of squares (``einsum``): no BLAS call, whose threading overhead dominates
    for small matrices.
    """
    flat = np.ascontiguousarray(x).reshape(*x.shape[: x.ndim - core_ndim], -1)
    if flat.dtype.kind == "c":
        flat = flat.view(flat.real.dtype)
    return np.sqrt(einsum("...i,...i->...", flat, flat))
