"""Butcher tableaus: an immutable value object, Gauss–Legendre of any order, compositions.

Coefficients that are irrational (Gauss nodes, composition weights) are computed in 50-digit
decimal arithmetic and rounded once to float64 (GeometricIntegrators.jl does the same).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from decimal import Decimal, localcontext
from fractions import Fraction
from typing import Any

import attrs
import numpy as np

from .errors import InputError, TableauError

_DIGITS = 50
#: Orders up to this are checked tree by tree (1205 rooted trees); above it, a tableau must
#: satisfy the simplifying assumptions B(p), C(q), D(r) that prove its order, else only the
#: tree conditions up to this order are checked.
MAX_TREE_ORDER = 10


#: A rooted tree: the sorted tuple of its children (``()`` is the single vertex).
_Tree = tuple


@functools.cache
def _trees(order: int) -> tuple[_Tree, ...]:
    """The rooted trees with ``order`` vertices, each once (children sorted)."""
    if order == 1:
        return ((),)
    return tuple(sorted(_forests(order - 1)))


@functools.cache
def _forests(total: int) -> frozenset[_Tree]:
    """Multisets of rooted trees (sorted tuples) with ``total`` vertices in all."""
    if total == 0:
        return frozenset({()})
    return frozenset(
        tuple(sorted((tree, *rest)))
        for k in range(1, total + 1)
        for tree in _trees(k)
        for rest in _forests(total - k)
    )


def _order_defects(A: np.ndarray, b: np.ndarray, order: int) -> list[tuple[int, float]]:
    """``(order of tree, defect)`` for every rooted tree up to ``order`` whose condition
    ``b · Phi(t) = 1 / gamma(t)`` fails (relative to the magnitude of its terms)."""
    s = b.shape[0]
    phi: dict[_Tree, tuple[np.ndarray, np.ndarray, float]] = {}
    absA, absb = np.abs(A), np.abs(b)
    failures = []
    for n in range(1, order + 1):
        for tree in _trees(n):
            vec, mag, gamma = np.ones(s), np.ones(s), float(n)
            for child in tree:
                cv, cm, cg = phi[child]
                vec, mag, gamma = vec * (A @ cv), mag * (absA @ cm), gamma * cg
            phi[tree] = (vec, mag, gamma)
            defect = abs(float(b @ vec) - 1.0 / gamma)
            if defect > 1e-12 * max(1.0, float(absb @ mag)):
                failures.append((n, defect))
    return failures


def _simplifying_order(A: np.ndarray, b: np.ndarray, c: np.ndarray, tol: float = 1e-12) -> int:
    """The order proved by Butcher's simplifying assumptions: the largest ``p`` with B(p),
    C(q), D(r), ``p <= q + r + 1`` and ``p <= 2q + 2`` (0 if B(1) fails)."""

    def largest(check: object, limit: int = 4 * b.shape[0] + 2) -> int:
        k = 0
        while k < limit and check(k + 1):  # type: ignore[operator]
            k += 1
        return k

    def B(k: int) -> bool:
        return abs(float(b @ c ** (k - 1)) - 1.0 / k) <= tol

    def C(k: int) -> bool:
        return bool(np.max(np.abs(A @ c ** (k - 1) - c**k / k)) <= tol)

    def D(k: int) -> bool:
        return bool(np.max(np.abs((b * c ** (k - 1)) @ A - b * (1 - c**k) / k)) <= tol)

    p, q, r = largest(B), largest(C), largest(D)
    return min(p, q + r + 1, 2 * q + 2)


def one_of(*options: str) -> Callable[[Any, Any, Any], None]:
    """An attrs validator: the value must be one of ``options``, else :class:`InputError`
    naming the field, the value and the options (attrs' own ``in_`` prints a raw tuple)."""

    def check(instance: Any, attribute: Any, value: Any) -> None:
        if value not in options:
            raise InputError(
                f"{type(instance).__name__}: {attribute.name} must be one of "
                f"{', '.join(map(repr, options))}, got {value!r}. To fix: pass one of those"
            )

    return check


def _frozen_array(value: object) -> np.ndarray:
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise TableauError(
            f"tableau coefficients must be real numbers, got {value!r} ({exc}). To fix: pass "
            "A as an s×s array and b, c as length-s arrays of floats"
        ) from None
    arr.setflags(write=False)
    return arr


@attrs.frozen(eq=False)
class ButcherTableau:
    """An s-stage Runge–Kutta tableau ``(A, b, c)`` with its classical order.

    The arrays are read-only. ``c`` defaults to the row sums of ``A``.
    """

    A: np.ndarray = attrs.field(converter=_frozen_array)
    b: np.ndarray = attrs.field(converter=_frozen_array)
    order: int
    name: str
    c: np.ndarray = attrs.field(converter=_frozen_array)

    @c.default
    def _row_sums(self) -> np.ndarray:
        return np.asarray(self.A).sum(axis=1)

    def __attrs_post_init__(self) -> None:
        A, b, c = self.A, self.b, self.c
        s = b.shape[0] if b.ndim == 1 else -1
        if A.ndim != 2 or A.shape != (s, s) or c.shape != (s,):
            raise TableauError(
                f"tableau {self.name!r}: A must be s×s and b, c of length s; got "
                f"A {A.shape}, b {b.shape}, c {c.shape}"
            )
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b)) and np.all(np.isfinite(c))):
            raise TableauError(f"tableau {self.name!r} has non-finite coefficients")
        if abs(b.sum() - 1.0) > 1e-12:
            raise TableauError(
                f"tableau {self.name!r} is not consistent: sum(b) = {b.sum():.16g} != 1"
            )
        if isinstance(self.order, bool) or not isinstance(self.order, (int, np.integer)):
            raise TableauError(
                f"tableau {self.name!r}: order must be a positive integer, got {self.order!r}"
            )
        if self.order < 1:
            raise TableauError(f"tableau {self.name!r}: order must be at least 1, got {self.order}")
        self._check_order()

    def _check_order(self) -> None:
        """Refuse a claimed :attr:`order` the coefficients do not have.

        Up to :data:`MAX_TREE_ORDER`, every rooted-tree order condition up to the claimed
        order is checked, unless the simplifying assumptions B(p), C(q), D(r) already prove
        it (Gauss–Legendre of any order is proved that way). Above it, a tableau the
        simplifying assumptions do not cover is checked up to :data:`MAX_TREE_ORDER` only.
        """
        p = int(self.order)
        if _simplifying_order(self.A, self.b, self.c) >= p:
            return
        failures = _order_defects(self.A, self.b, min(p, MAX_TREE_ORDER))
        if failures:
            first, defect = failures[0]
            raise TableauError(
                f"tableau {self.name!r} claims order {p} but does not have it: it fails "
                f"{len(failures)} order condition(s), the first for a tree of order {first} "
                f"(defect {defect:.2e}), so its order is at most {first - 1}. To fix: pass "
                f"order={first - 1} (or check the coefficients)"
            )

    @property
    def stages(self) -> int:
        """Number of stages ``s``."""
        return int(self.b.shape[0])

    def symplecticity_defect(self) -> float:
        """``max_ij |b_i a_ij + b_j a_ji - b_i b_j|`` (zero for symplectic tableaus)."""
        b, A = self.b, self.A
        M = b[:, None] * A + (b[:, None] * A).T - np.outer(b, b)
        return float(np.max(np.abs(M)))

    def is_symplectic(self, tol: float = 1e-14) -> bool:
        """Whether ``b_i a_ij + b_j a_ji = b_i b_j`` for all ``i, j`` (SPEC §4)."""
        return self.symplecticity_defect() <= tol

    def require_symplectic(self, tol: float = 1e-14) -> ButcherTableau:
        """Return ``self`` or raise :class:`TableauError` if the tableau is not symplectic."""
        if not self.is_symplectic(tol):
            raise TableauError(
                f"tableau {self.name!r} is not symplectic (max |b_i a_ij + b_j a_ji - b_i b_j|"
                f" = {self.symplecticity_defect():.2e}); its isospectral descent would be "
                "wrong. Use a symplectic tableau: Gauss–Legendre (lieflow.tableaus.gauss) or "
                "a composition of midpoint steps (lieflow.tableaus.composition)"
            )
        return self

    def is_symmetric(self, tol: float = 1e-14) -> bool:
        """Whether the method is symmetric (self-adjoint): ``a_{s+1-i, s+1-j} + a_ij = b_j``."""
        A, b = self.A, self.b
        return bool(np.max(np.abs(A[::-1, ::-1] + A - b[None, :])) <= tol)

    @property
    def spectral_radius(self) -> float:
        """``rho(A)``; the fixed-point contraction rate scales with ``h rho(A)`` (SPEC §5)."""
        return float(np.max(np.abs(np.linalg.eigvals(self.A))))

    @property
    def is_diagonally_implicit(self) -> bool:
        """Whether ``A`` is lower triangular."""
        return bool(np.all(np.triu(self.A, 1) == 0))


# --- Gauss–Legendre --------------------------------------------------------------------------


def _legendre_roots(s: int) -> list[Decimal]:
    """Roots of the shifted Legendre polynomial ``P_s(2x - 1)`` on (0, 1), ascending."""

    def p_and_dp(x: Decimal) -> tuple[Decimal, Decimal]:
        # Bonnet recurrence for P_k(t), t = 2x - 1, and the derivative in x.
        t = 2 * x - 1
        p_prev, p = Decimal(1), t
        for k in range(1, s):
            p_prev, p = p, ((2 * k + 1) * t * p - k * p_prev) / (k + 1)
        dp_dt = s * (t * p - p_prev) / (t * t - 1)
        return p, 2 * dp_dt

    roots = []
    for i in range(1, s + 1):
        # Chebyshev-like initial guess, then Newton in 50-digit arithmetic.
        guess = (1 - np.cos(np.pi * (i - 0.25) / (s + 0.5))) / 2
        x = Decimal(repr(float(guess)))
        for _ in range(100):
            p, dp = p_and_dp(x)
            dx = p / dp
            x -= dx
            if abs(dx) < Decimal(10) ** (-_DIGITS + 5):
                break
        roots.append(x)
    return sorted(roots)


def _poly_mul_linear(coeffs: list[Decimal], root: Decimal) -> list[Decimal]:
    """Multiply a polynomial (ascending coefficients) by ``(x - root)``."""
    out = [Decimal(0)] * (len(coeffs) + 1)
    for k, a in enumerate(coeffs):
        out[k + 1] += a
        out[k] -= root * a
    return out


def _integral(coeffs: list[Decimal], upper: Decimal) -> Decimal:
    return sum((a * upper ** (k + 1) / (k + 1) for k, a in enumerate(coeffs)), Decimal(0))


@functools.cache
def gauss(s: int) -> ButcherTableau:
    r"""The s-stage Gauss–Legendre collocation tableau, order ``2s`` (SPEC §4.6).

    Nodes ``c_i`` are the roots of the shifted Legendre polynomial; with the Lagrange
    basis :math:`\ell_j` on the nodes, :math:`a_{ij} = \int_0^{c_i} \ell_j` and
    :math:`b_j = \int_0^1 \ell_j`.

    Built once per ``s`` (a tableau is an immutable value: frozen, read-only arrays), as
    are the other named tableaus of this module.
    """
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1:
        raise TableauError(f"Gauss–Legendre needs a positive integer number of stages, got {s!r}")
    s = int(s)
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        c = _legendre_roots(s)
        A = [[Decimal(0)] * s for _ in range(s)]
        b = [Decimal(0)] * s
        for j in range(s):
            basis = [Decimal(1)]
            denom = Decimal(1)
            for m in range(s):
                if m != j:
                    basis = _poly_mul_linear(basis, c[m])
                    denom *= c[j] - c[m]
            basis = [a / denom for a in basis]
            b[j] = _integral(basis, Decimal(1))
            for i in range(s):
                A[i][j] = _integral(basis, c[i])
        return ButcherTableau(
            A=[[float(a) for a in row] for row in A],
            b=[float(x) for x in b],
            c=[float(x) for x in c],
            order=2 * s,
            name=f"gauss{s}",
        )


# --- compositions of the midpoint rule (symplectic DIRK) -------------------------------------


def composition(weights: Sequence[float], order: int, name: str) -> ButcherTableau:
    """The symplectic DIRK tableau of a composition of midpoint steps (SPEC §4.2).

    A step of size ``h`` is midpoint steps of sizes ``b_1 h, ..., b_s h``; the tableau has
    ``a_ij = b_j`` for ``j < i`` and ``a_ii = b_i / 2``.
    """
    try:
        b = np.asarray(weights, dtype=float)
    except (TypeError, ValueError):
        b = np.empty((0,))
    if b.ndim != 1 or b.size < 1:
        raise TableauError(
            f"composition weights must be a non-empty 1-D sequence of numbers, got {weights!r}"
        )
    A = np.tril(np.broadcast_to(b, (b.size, b.size)), -1) + np.diag(b / 2)
    return ButcherTableau(A=A, b=b, order=order, name=name)


def _decimal_root(x: int, k: int) -> Decimal:
    return Decimal(x) ** (Decimal(1) / Decimal(k))


def _triple_jump() -> tuple[Decimal, ...]:
    x = 1 / (2 - _decimal_root(2, 3))
    return (x, 1 - 2 * x, x)


def _suzuki5() -> tuple[Decimal, ...]:
    p = 1 / (4 - _decimal_root(4, 3))
    return (p, p, 1 - 4 * p, p, p)


def _yoshida6() -> tuple[Decimal, ...]:
    w1 = Decimal("-1.17767998417887100694641568096")
    w2 = Decimal("0.235573213359358133684793182979")
    w3 = Decimal("0.784513610477557263819497633866")
    w0 = 1 - 2 * (w1 + w2 + w3)
    return (w3, w2, w1, w0, w1, w2, w3)


#: Symmetric compositions :math:`S_{\gamma_m h} \circ \dots \circ S_{\gamma_1 h}` of a
#: symmetric second-order step :math:`S`, by name: the weights (in 50-digit arithmetic) and
#: the order reached (Hairer, Lubich & Wanner, *Geometric Numerical Integration*, §V.3).
#: ``triple_jump``: Yoshida (1990), Suzuki (1990), order 4; ``suzuki5``: Suzuki's
#: five-stage fractal, order 4 (smaller error constant); ``yoshida6``: Yoshida's 7-stage
#: solution A, order 6. The same coefficients make the SyDIRK schemes (compositions of
#: midpoint steps, :func:`triple_jump`, ...) and the splittings of flows
#: (:meth:`lieflow.Splitting.composition`).
_COMPOSITIONS: dict[str, tuple[Callable[[], tuple[Decimal, ...]], int]] = {
    "triple_jump": (_triple_jump, 4),
    "suzuki5": (_suzuki5, 4),
    "yoshida6": (_yoshida6, 6),
}

#: The names of :func:`composition_weights`.
COMPOSITIONS = tuple(_COMPOSITIONS)


@functools.cache
def composition_weights(name: str) -> tuple[tuple[float, ...], int]:
    """The weights ``gamma`` (rounded once to float64) and the order of the symmetric
    composition ``name`` (one of :data:`COMPOSITIONS`)."""
    if name not in _COMPOSITIONS:
        raise InputError(f"unknown composition {name!r}; choose one of {', '.join(COMPOSITIONS)}")
    weights, order = _COMPOSITIONS[name]
    with localcontext() as ctx:
        ctx.prec = _DIGITS
        return tuple(float(w) for w in weights()), order


@functools.cache
def triple_jump() -> ButcherTableau:
    """Triple jump, order 4: ``b = (x, 1 - 2x, x)``, ``x = 1 / (2 - 2^{1/3})``."""
    return composition(*composition_weights("triple_jump"), "triple_jump")


@functools.cache
def suzuki5() -> ButcherTableau:
    """Suzuki's 5-stage composition, order 4.

    ``b = (p, p, 1 - 4p, p, p)`` with ``p = 1 / (4 - 4^{1/3})``.
    """
    return composition(*composition_weights("suzuki5"), "suzuki5")


@functools.cache
def yoshida6() -> ButcherTableau:
    """Yoshida's 7-stage order-6 composition (solution A), the paper's 7s-SyDIRK (SPEC §4.2)."""
    return composition(*composition_weights("yoshida6"), "sydirk7")


@functools.cache
def midpoint() -> ButcherTableau:
    """The implicit midpoint rule, ``A = [1/2]``, ``b = [1]``, order 2."""
    return composition([1.0], 2, "midpoint")


def radau_iia2() -> ButcherTableau:
    """Radau IIA with 2 stages (order 3): *not* symplectic; kept as a negative example."""
    return ButcherTableau(
        A=[[float(Fraction(5, 12)), float(Fraction(-1, 12))], [0.75, 0.25]],
        b=[0.75, 0.25],
        order=3,
        name="radau_iia2",
    )
