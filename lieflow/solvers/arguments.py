"""Validators of the solvers' constructor arguments (attrs validators).

A wrong type or range raises :class:`~lieflow.errors.InputError` naming the argument and
the value at construction — never a numpy ``TypeError`` from inside the first solve
(``FixedPoint(rtol="1e-3")``). Booleans are not numbers here (``max_iter=True`` is a
mistake, not 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import attrs
import numpy as np

from ..errors import InputError

Validator = Callable[[Any, "attrs.Attribute[Any]", Any], None]


def _is_real(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


def _describe(value: object) -> str:
    return f"{value!r} of type {type(value).__name__}"


def non_negative(_inst: object, attr: attrs.Attribute[Any], value: Any) -> None:
    """A finite real number ``>= 0`` (a tolerance)."""
    if not (_is_real(value) and math.isfinite(value) and value >= 0):
        raise InputError(
            f"{attr.name} must be a non-negative finite number, got {_describe(value)}; "
            f"e.g. {attr.name}=1e-12"
        )


def positive(_inst: object, attr: attrs.Attribute[Any], value: Any) -> None:
    """A finite real number ``> 0``."""
    if not (_is_real(value) and math.isfinite(value) and value > 0):
        raise InputError(f"{attr.name} must be a positive finite number, got {_describe(value)}")


def integer_at_least(minimum: int) -> Validator:
    """An integer ``>= minimum`` (an iteration count, a depth)."""

    def check(_inst: object, attr: attrs.Attribute[Any], value: Any) -> None:
        integral = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
        if not (integral and value >= minimum):
            raise InputError(f"{attr.name} must be an integer >= {minimum}, got {_describe(value)}")

    return check


def solver(_inst: object, attr: attrs.Attribute[Any], value: Any) -> None:
    """A solver instance (an object with a ``solve`` method), not a class."""
    if isinstance(value, type) or not callable(getattr(value, "solve", None)):
        hint = (
            f"an instance, e.g. {value.__name__}()"
            if isinstance(value, type)
            else "e.g. lieflow.solvers.Newton()"
        )
        raise InputError(
            f"{attr.name} must be a solver (an object with a solve method), got "
            f"{_describe(value)}; pass {hint}"
        )
