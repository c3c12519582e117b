r"""Many tridiagonal systems at once by parallel cyclic reduction, in array-API operations.

The systems run down axis ``-2`` of an array ``Y`` of shape ``(..., R, C)``: for every column
``c`` (and every leading index) ``a_r y_{r-1} + b_r y_r + a_{r+1} y_{r+1} = f_r`` with the
symmetric coefficients ``b`` (diagonal) and ``a`` (coupling of row ``r`` to row ``r-1``;
``a = 0`` decouples the rows, so one column can hold several systems stacked).

Parallel cyclic reduction (Hockney & Jesshope, *Parallel Computers 2*, 1988, §5.4; Zhang,
Cohen & Owens, PPoPP 2010) eliminates, at level ``j`` with stride ``s = 2^j``, the couplings
to rows ``r ± s`` from every row at once:

.. math::
    k^-_r = a_r / b_{r-s},\quad k^+_r = c_r / b_{r+s},\qquad
    f_r \leftarrow f_r - k^-_r f_{r-s} - k^+_r f_{r+s},

    a_r \leftarrow -k^-_r a_{r-s},\quad c_r \leftarrow -k^+_r c_{r+s},\quad
    b_r \leftarrow b_r - k^-_r c_{r-s} - k^+_r a_{r+s}

(``c_r`` the coupling to the row below; terms outside ``0..R-1`` vanish). After
``ceil(log2 R)`` levels every row is decoupled and ``y = f / b``. The multipliers depend only
on the matrix, so they are computed once on the host (:meth:`CyclicReduction.build`) and a
solve is ``2 ceil(log2 R)`` shifted multiply–subtracts over the whole array plus one
scaling: vector operations of any array library, no scatter, no per-system loop, ``O(R C
log R)`` work. For a symmetric negative (or positive) definite matrix every reduced system is
a Schur complement of a symmetric permutation of it, hence definite too: no pivoting is needed
and the ``b`` never vanish.

Accuracy. The multipliers are computed in extended precision (``numpy.longdouble``, 64-bit
mantissa on x86-64) and rounded to float64 once: computed in float64, the cancellations in
``b`` accumulate over the levels, and on the Hoppe–Yau systems (condition ``~N²``) the solve
lost ``5e-13`` / ``6e-12`` relative at N = 256 / 1024 against an extended-precision solve;
with extended-precision multipliers ``2e-15`` at both (the numpy engine's sequential sweeps,
whose factors are computed the same way: ``2e-15`` too, ``2e-13`` before). Where
``longdouble`` is plain double (some ARM and Windows builds) the float64 figures apply.
"""

from __future__ import annotations

from typing import Any

import attrs
import numpy as np
from numpy.typing import NDArray

from lieflow.backends import device_of, from_host, is_traced, namespace

Array = NDArray[Any]


def _down(x: Array, s: int) -> Array:
    """Row ``r`` of the result is row ``r - s`` of ``x`` (zero for ``r < s``), host numpy."""
    out = np.zeros_like(x)
    out[s:] = x[:-s]
    return out


def _up(x: Array, s: int) -> Array:
    """Row ``r`` of the result is row ``r + s`` of ``x`` (zero for ``r >= R - s``)."""
    out = np.zeros_like(x)
    out[:-s] = x[s:]
    return out


@attrs.frozen(eq=False)
class CyclicReduction:
    """The multipliers of parallel cyclic reduction for fixed tridiagonal matrices (module
    docs): ``lower[j]``/``upper[j]`` are ``k^-``/``k^+`` of level ``j`` (shape ``(levels, R,
    C)``), ``inverse`` is ``scale / b`` after the last level. Host float64 arrays; a solve
    copies them once to the device and precision of its input (:meth:`on`)."""

    lower: Array = attrs.field(repr=False)
    upper: Array = attrs.field(repr=False)
    inverse: Array = attrs.field(repr=False)
    _placed: dict[tuple[str, str, str], tuple[Any, ...]] = attrs.field(
        init=False, factory=dict, repr=False
    )

    @classmethod
    def build(cls, b: Array, a: Array, scale: float = 1.0) -> CyclicReduction:
        """The multipliers for diagonal ``b`` and coupling ``a`` (``a[r]`` couples rows
        ``r - 1`` and ``r``; ``a[0]`` is ignored), both ``(R, C)``; the solve returns
        ``scale`` times the solution."""
        b = np.array(b, dtype=np.longdouble)
        a = np.array(a, dtype=np.longdouble)
        a[0] = 0
        c = _up(a, 1)  # coupling to the row below
        R = b.shape[0]
        lower, upper = [], []
        s = 1
        while s < R:
            below, above = _down(b, s), _up(b, s)  # zero outside the rows: no coupling
            km = a / np.where(below == 0, 1, below)
            kp = c / np.where(above == 0, 1, above)
            b = b - km * _down(c, s) - kp * _up(a, s)
            a, c = -km * _down(a, s), -kp * _up(c, s)
            lower.append(km)
            upper.append(kp)
            s *= 2
        levels = len(lower)
        shape = (levels, *b.shape)
        return cls(
            np.array(lower, dtype=float).reshape(shape),
            np.array(upper, dtype=float).reshape(shape),
            np.asarray(scale / b, dtype=float),
        )

    @property
    def levels(self) -> int:
        """``ceil(log2 R)``."""
        return int(self.lower.shape[0])

    def on(self, like: Any, real_dtype: Any) -> tuple[Any, ...]:
        """``(lower, upper, inverse)`` as arrays of ``like``'s library and device in
        ``real_dtype``, copied from the host on first use and kept with this object — except
        while ``like`` is traced (``jax.jit``): the program then holds them as constants of
        its own, which must not outlive the trace."""
        xp = namespace(like)
        key = (xp.__name__, str(device_of(like)), str(real_dtype))
        placed = self._placed.get(key)
        if placed is None:
            placed = tuple(
                from_host(x, like, real_dtype) for x in (self.lower, self.upper, self.inverse)
            )
            if not is_traced(like):
                self._placed[key] = placed
        return placed

    def solve(self, Y: Any, lower: Any, upper: Any, inverse: Any) -> Any:
        """The solutions for the right-hand sides ``Y`` (``(..., R, C)``, any array library;
        the multipliers from :meth:`on`). A new array; ``Y`` is not modified."""
        xp = namespace(Y)
        R = Y.shape[-2]
        lead = Y.shape[:-2]
        s = 1
        for j in range(self.levels):
            pad = xp.zeros((*lead, s, Y.shape[-1]), dtype=Y.dtype, device=device_of(Y))
            down = xp.concat([pad, Y[..., : R - s, :]], axis=-2)
            up = xp.concat([Y[..., s:, :], pad], axis=-2)
            Y = Y - lower[j, ...] * down - upper[j, ...] * up
            s *= 2
        return Y * inverse
