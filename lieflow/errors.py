"""The lieflow exception hierarchy.

Every error lieflow raises on purpose is a :class:`LieflowError`; each message says what was
wrong and what to do about it.
"""

from __future__ import annotations

import reprlib
from collections.abc import Sequence
from typing import Any

_SHORT = reprlib.Repr()
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = _SHORT.maxset = 8
_SHORT.maxstring = _SHORT.maxother = 80
_SHORT.maxlevel = 4


def quote(value: Any) -> str:
    """``repr(value)`` cut short for an error message: at most 8 items of a list, tuple or
    dict and 80 characters of a string (``...`` marks what was left out), so that a message
    quoting a user's 100 000-entry parameter list stays one readable line."""
    return _SHORT.repr(value)


def shorten(text: object, limit: int = 1000) -> str:
    """``str(text)`` with its middle cut out if it is longer than ``limit`` characters (the
    start names the problem, the end says what to do; both are kept)."""
    text = str(text)
    if len(text) <= limit:
        return text
    keep = (limit - 40) // 2
    return f"{text[:keep]} ... [{len(text) - 2 * keep} characters left out] ... {text[-keep:]}"


def with_fix(message: object, fix: str) -> str:
    """``message`` and what to do about it, said once: a wrapped error's own "To fix: ..."
    (the more specific advice) if it has one, else ``fix``.

    Examples
    --------
    >>> with_fix("W0 is not symmetric. To fix: pass (W0 + W0.T) / 2", "give another W0")
    'W0 is not symmetric. To fix: pass (W0 + W0.T) / 2.'
    >>> with_fix("steps is missing", "add steps = 100")
    'steps is missing. To fix: add steps = 100.'
    """
    problem, said, own = str(message).strip().partition(" To fix: ")
    return f"{problem.rstrip().rstrip('.')}. To fix: {(own if said else fix).rstrip('.')}."


def without_fix(message: object) -> str:
    """``message`` without its "To fix: ..." advice (to quote a wrapped error whose advice
    does not apply where it is quoted)."""
    return str(message).strip().partition(" To fix: ")[0].rstrip().rstrip(".")


class LieflowError(Exception):
    """Base class of every error raised by lieflow."""


class InputError(LieflowError, ValueError):
    """An argument has the wrong shape, dtype or value (NaN/Inf, h <= 0, ...)."""


class AlgebraError(InputError):
    """A matrix is not an element of the Lie algebra it is supposed to belong to."""


class TableauError(LieflowError, ValueError):
    """A Butcher tableau is malformed or not symplectic."""


class RegistryError(LieflowError, KeyError):
    """An unknown or duplicate name in the system / scheme / solver registry."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else ""


class PluginError(LieflowError):
    """A plugin failed to import or registered something invalid."""


class ConvergenceError(LieflowError):
    """The nonlinear solver did not converge.

    Attributes
    ----------
    reason : str
        ``"max_iterations"``, ``"stalled"``, ``"diverged"`` or ``"non_finite"``.
    solver : str
        Name of the solver that gave up.
    iterations : int
        Updates performed before giving up.
    residuals : tuple of float
        Relative update norms, one per iteration.
    step, t : int or None, float or None
        Step index and time of the failed step (filled in by :func:`lieflow.integrate`).
    hint : str or None
        What the failed step says about a step size that converges (a fixed-point
        iteration's estimated contraction, :func:`lieflow.schemes.contraction.hint`).
    """

    def __init__(
        self,
        reason: str,
        *,
        solver: str,
        iterations: int,
        residuals: Sequence[float],
        step: int | None = None,
        t: float | None = None,
        hint: str | None = None,
    ) -> None:
        self.reason = reason
        self.solver = solver
        self.iterations = iterations
        self.residuals = tuple(float(r) for r in residuals)
        self.step = step
        self.t = t
        self.hint = hint
        super().__init__(self._message())

    def at(self, step: int, t: float) -> ConvergenceError:
        """The same failure, located at step index ``step`` and time ``t``."""
        return self._with(step=step, t=t)

    def with_hint(self, hint: str | None) -> ConvergenceError:
        """The same failure with ``hint`` (the message ends with it); itself for ``None``."""
        return self if hint is None else self._with(hint=hint)

    def _with(self, **changes: Any) -> ConvergenceError:
        fields: dict[str, Any] = dict(solver=self.solver, iterations=self.iterations,
                                      residuals=self.residuals, step=self.step, t=self.t,
                                      hint=self.hint)  # fmt: skip
        fields.update(changes)
        return ConvergenceError(self.reason, **fields)

    def _message(self) -> str:
        where = "" if self.step is None else f" at step {self.step} (t = {self.t:.6g})"
        last = f"{self.residuals[-1]:.3e}" if self.residuals else "n/a"
        advice = {
            "max_iterations": "raise max_iter, loosen rtol, or reduce the step size h",
            "stalled": (
                "the iteration stopped contracting, or contracts too slowly to reach rtol "
                "within max_iter: reduce h, raise max_iter, or use a solver that converges "
                "for stiff steps (lieflow.solvers.Newton or 'auto')"
            ),
            "diverged": (
                "h times the Lipschitz constant of the map is too large for fixed-point "
                "iteration: reduce h, or use lieflow.solvers.Newton / FrozenB / 'auto'"
            ),
            "non_finite": "the iterate became NaN/Inf: reduce h or check the system's B map",
        }.get(self.reason, "reduce h or change the solver")
        hint = "" if self.hint is None else f" {self.hint}"
        return (
            f"{self.solver} did not converge{where}: {self.reason} after {self.iterations} "
            f"iterations, last relative update {last}. To fix: {advice}.{hint}"
        )
