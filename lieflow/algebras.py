"""Matrix Lie algebras: so(n), u(n), su(N), gl(n).

Each algebra is an immutable value object that knows its matrix size, dtype, projection,
membership test, a seeded random element, the bracket and the Frobenius inner product
``<A, B> = Re tr(A^† B)`` (SPEC §1–2). All operations broadcast over leading axes, so a
stack of shape ``(..., n, n)`` is a stack of algebra elements.
"""

from __future__ import annotations

import functools
import importlib.util
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import attrs
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .backends import all_finite, device_of, is_foreign_array, is_numpy, namespace
from .errors import AlgebraError, InputError

Array = NDArray[Any]


def _array(X: ArrayLike) -> Array:
    """``X`` as an array: itself if it belongs to another array library
    (:mod:`lieflow.backends`), else ``np.asarray(X)``."""
    if type(X) is np.ndarray:  # the common case first (a projection per stage and step)
        return X
    if is_foreign_array(X):
        return X  # type: ignore[return-value]
    return np.asarray(X)


def transpose(X: Array) -> Array:
    """``X^T`` over the last two axes (a view where the library has views)."""
    return X.swapaxes(-1, -2) if is_numpy(X) else X.mT


def dagger(X: Array) -> Array:
    """Conjugate transpose of the last two axes, ``X^†`` (a view for real input)."""
    if is_numpy(X):
        Xt = X.swapaxes(-1, -2)
        return Xt.conj() if X.dtype.kind == "c" else Xt
    xp = namespace(X)
    return xp.conj(X.mT) if xp.isdtype(X.dtype, "complex floating") else X.mT


#: Side of the square blocks in which :func:`minus_dagger` pairs ``X`` with ``X^†``.
_BLOCK = 64


def minus_dagger(X: Array) -> Array:
    r"""``X - X^†`` over the last two axes (``X - X^T`` for real ``X``), a new array.

    The same subtraction ``X_ij - conj(X_ji)`` of every entry as ``X - dagger(X)`` (same
    bits), computed in ``64 × 64`` blocks into one output: a transposed operand read
    row by row strides through a new memory page per entry once a row is 4 KiB, and the
    plain expression also makes a transposed temporary (two fresh ``n²`` arrays, whose
    first touch page-faults). Measured, one thread, complex128: n = 256 1.34 → 0.28 ms,
    n = 512 4.3 → 1.7 ms, n = 1024 13.6 → 8.2 ms (a plain ``X + X``: 0.03 / 0.15 / 1.4 ms).
    Arrays of another library (:mod:`lieflow.backends`): ``X - dagger(X)``.
    """
    if type(X) is np.ndarray and X.dtype.char == "d" and X.shape[-1] <= _BLOCK:
        # the common case first (twice an update at small n): as below; one matrix's
        # transpose by ``.T`` (the same view, 0.1 µs less than ``swapaxes`` on 3×3)
        return X - (X.T if X.ndim == 2 else X.swapaxes(-1, -2)).copy()
    if not is_numpy(X):
        return X - dagger(X)
    n = X.shape[-1]
    conj = X.dtype.kind == "c"
    if n <= _BLOCK:
        # the transpose copied first: a subtraction of two contiguous operands skips the
        # strided iteration a transposed view needs (3x3 real: 1.1 -> 0.75 µs; complex
        # n = 16: 1.7 -> 1.35 µs), the same entries subtracted
        Xt = X.swapaxes(-1, -2).copy()
        if not conj:
            return X - Xt
        np.conjugate(Xt, out=Xt)
        return np.subtract(X, Xt, out=Xt)
    out = np.empty(X.shape, dtype=X.dtype)
    for i in range(0, n, _BLOCK):
        for j in range(0, n, _BLOCK):
            t = X[..., j : j + _BLOCK, i : i + _BLOCK].swapaxes(-1, -2)
            np.subtract(
                X[..., i : i + _BLOCK, j : j + _BLOCK],
                t.conj() if conj else t,
                out=out[..., i : i + _BLOCK, j : j + _BLOCK],
            )
    return out


#: Rows of the panels in which :func:`skew_matmul` forms a product's upper triangle.
_PANEL = 64


def skew_matmul(X: Array, Y: Array, out: Array) -> Array:
    r"""``out = X @ Y`` (NumPy matrices or stacks, ``out`` of the product's shape and dtype)
    for a product known to be skew-Hermitian (skew-symmetric if real): the midpoint map's
    ``BMB = (BM) B`` with ``B``, ``M`` in a skew algebra, since
    ``(BMB)^† = B^† M^† B^† = -BMB``. Returns ``out``.

    From ``n = 3 · 64`` on, the rows are cut into ``p = min(n // 64, 8)`` panels and each
    panel's product is formed from its diagonal block on (the upper block triangle, ``p``
    BLAS products), the blocks below the diagonal copied as ``-(\cdot)^†`` of those above:
    ``(p + 1) / 2p`` of the flops (measured, one thread, complex128, n = 256: 2.9 → 2.1 ms,
    n = 512: 24 → 16 ms). The copied entries are the exact ``-conj`` of the computed ones,
    not the product's own roundings (they differ by roundoff, as the product of exactly
    skew factors is skew only to roundoff). Below ``3 · 64``: one product.
    """
    n = X.shape[-1]
    panels = min(n // _PANEL, 8)
    if panels < 3:
        return np.matmul(X, Y, out=out)
    conj = out.dtype.kind == "c"
    for i in range(panels):
        a, b = i * n // panels, (i + 1) * n // panels
        np.matmul(X[..., a:b, :], Y[..., :, a:], out=out[..., a:b, a:])
        if a:
            above = out[..., :a, a:b].swapaxes(-1, -2)
            np.negative(above.conj() if conj else above, out=out[..., a:b, :a])
    return out


def skew_combination(X: Array, s: Any, A: Array, Y: Array | None = None, t: Any = None) -> Array:
    r"""``((X - X^†) s + A) + Y t`` over the last two axes (``+ Y t`` only where ``Y`` is
    given), a new array: the tail of the midpoint map, ``W_0 + q (BM - MB) + q^2 BMB``
    for skew algebras (``MB = (BM)^†``), and of the commutator update,
    ``W_0 + h (C - C^†)``. ``s`` and ``t`` are real scalars (0-d arrays of ``X``'s real
    precision: :func:`lieflow.schemes.base.real_scalar`).

    The same numbers as ``D = minus_dagger(X); D *= s; D += A; D += Y * t`` (each a
    separate rounding; tested with ``np.array_equal``), which is what it computes for arrays
    of another library, operands of other shapes or dtypes than ``X``'s, small matrices
    (``n <= 64``) and without numba. NumPy float64/complex128 matrices with numba installed
    take one compiled pass (:mod:`lieflow._skew_kernel`) in place of five passes and a
    temporary (measured, one thread, complex128, n = 256: 0.56 -> 0.15-0.2 ms)."""
    fused = _fused_combination(X, s, A, Y, t, None)
    if fused is not None:
        return fused[0]
    out = minus_dagger(X)
    out *= s
    out += A
    if Y is not None:
        Y = Y * t
        out += Y
    return out


def skew_combination_norms(
    X: Array, s: Any, A: Array, Y: Array, t: Any, old: Array
) -> tuple[Array, tuple[float, float] | None]:
    """``out = skew_combination(X, s, A, Y, t)`` (the same bits) and, where its compiled
    pass computes it, ``(||out||², ||out - old||²)`` summed in that pass (the squares of
    each output row added while the row is in the cache, in the compiler's order, then the
    rows in order: the sums do not depend on anything but the numbers); ``None`` where
    ``out`` is computed otherwise (the caller then forms the norms itself). The stopping
    test of a fixed-point update reads them (``old`` its iterate) instead of two more
    passes over ``out`` and ``old`` and a temporary."""
    fused = _fused_combination(X, s, A, Y, t, old)
    if fused is None:
        return skew_combination(X, s, A, Y, t), None
    return fused


def _fused_combination(
    X: Array, s: Any, A: Array, Y: Array | None, t: Any, old: Array | None
) -> tuple[Array, tuple[float, float] | None] | None:
    """:func:`skew_combination` by its compiled pass (and the norms against ``old``, where
    given), or ``None`` where it does not apply (see :func:`skew_combination`)."""
    n = X.shape[-1]
    kernel = _skew_kernel() if type(X) is np.ndarray and n > _BLOCK else None
    if not (
        kernel is not None
        and X.dtype.char in "dD"
        and A.shape == X.shape
        and A.dtype == X.dtype
        and (Y is None or (Y.shape == X.shape and Y.dtype == X.dtype))
        and (
            old is None
            or (type(old) is np.ndarray and old.shape == X.shape and old.dtype == X.dtype)
        )
    ):
        return None
    parts = 2 if X.dtype.char == "D" else 1
    out = np.empty(X.shape, dtype=X.dtype)

    def rows(Z: Array) -> Array:  # (K, n, parts n) real numbers, a view of a copy
        Z = np.ascontiguousarray(Z)
        return (Z.view(np.float64) if parts == 2 else Z).reshape(-1, n, parts * n)

    A = rows(A)
    o = rows(out)
    sums = np.empty((o.shape[0], n, 2))
    kernel.combine(
        kernel.work_groups(X.size * parts),
        rows(X), float(s), A, A if Y is None else rows(Y), 0.0 if t is None else float(t),
        Y is not None, parts, o, o if old is None else rows(old), old is not None, sums,
    )  # fmt: skip
    if old is None:
        return out, None
    total = sums.reshape(-1, 2).sum(axis=0)
    return out, (float(total[0]), float(total[1]))


@functools.cache
def _skew_kernel() -> Any:
    """:mod:`lieflow._skew_kernel` where numba is installed, else ``None``."""
    if importlib.util.find_spec("numba") is None:
        return None
    from . import _skew_kernel

    return _skew_kernel


def frobenius_norm(X: Array) -> Array:
    """Frobenius norm over the last two axes."""
    if type(X) is np.ndarray:  # the array's own sum: np.sum's wrapper costs ~1 µs a call
        return np.sqrt((np.abs(X) ** 2).sum(axis=(-2, -1)))
    return np.sqrt(np.sum(np.abs(X) ** 2, axis=(-2, -1)))


def _relative_defect(X: Array, P: Array) -> Array:
    """``||X - P||_F / max(||X||_F, tiny)``: :meth:`LieAlgebra.distance` for ``P = P(X)``."""
    scale = np.maximum(frobenius_norm(X), np.finfo(float).tiny)
    return frobenius_norm(X - P) / scale


def _half() -> Array:
    half = np.array(0.5)
    half.setflags(write=False)
    return half


#: 0.5 as a read-only 0-d float64 array: ``Y *= _HALF`` is ``Y *= 0.5`` (the same
#: product) in about half the time for a small ``Y`` (3×3: 0.35 against 0.6 µs).
_HALF = _half()


def _halved(Y: Array) -> Array:
    """``Y / 2``, in place when ``Y`` is a (fresh) floating array."""
    if type(Y) is np.ndarray and Y.dtype.char == "d":  # float64 first (twice a step)
        Y *= _HALF
        return Y
    if not (type(Y) is np.ndarray or is_numpy(Y)) or Y.dtype.kind in "fc":
        Y *= 0.5
        return Y
    return 0.5 * Y


def _positive_int(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"matrix size n must be a positive integer, got {n!r}")
    return int(n)


@attrs.frozen
class LieAlgebra(ABC):
    """A real Lie algebra of n×n matrices, identified with its dual by the Frobenius pairing.

    Subclasses set :attr:`dtype`, :attr:`skew` and implement :meth:`project` and
    :meth:`dimension`. ``skew`` is true when every element satisfies ``X^† = -X``;
    schemes use it to halve the number of products (``M B = (B M)^†``).
    """

    n: int = attrs.field(converter=_positive_int)

    dtype: ClassVar[np.dtype] = np.dtype(np.float64)
    skew: ClassVar[bool] = False
    symbol: ClassVar[str] = "g"

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of one element, ``(n, n)``."""
        return (self.n, self.n)

    def __str__(self) -> str:
        return f"{self.symbol}({self.n})"

    @abstractmethod
    def project(self, X: ArrayLike) -> Array:
        """Orthogonal (Frobenius) projection of ``X`` onto the algebra."""

    @property
    @abstractmethod
    def dimension(self) -> int:
        """Real dimension of the algebra."""

    def distance(self, X: ArrayLike) -> Array:
        """``||X - P(X)||_F / max(||X||_F, tiny)``: relative distance from the algebra."""
        X = np.asarray(X)
        return _relative_defect(X, self.project(X))

    def contains(self, X: ArrayLike, tol: float = 1e-12) -> bool:
        """Whether every matrix in ``X`` lies in the algebra to relative tolerance ``tol``."""
        X = np.asarray(X)
        if X.shape[-2:] != self.shape:
            return False
        if np.iscomplexobj(X) and self.dtype.kind != "c" and np.any(X.imag != 0):
            return False
        return bool(np.all(self.distance(X) <= tol))

    def validate(self, X: ArrayLike, *, name: str = "W0", tol: float = 1e-12) -> Array:
        """Return ``X`` as an array of this algebra's dtype, or raise a clear error.

        Checks shape ``(..., n, n)``, dtype (complex data for a real algebra is refused),
        finiteness and membership to relative tolerance ``tol``, which is raised to
        ``64 eps`` of the data's precision (single-precision data cannot do better).
        """
        if (
            type(X) is np.ndarray
            and X.dtype.char == "d"
            and X.dtype.isnative
            and X.shape[-2:] == (self.n, self.n)
            and self.dtype.kind == "f"
        ):  # the common case (float64 data of a real algebra) in fewer passes: the checks
            # below, same result; anything it does not accept takes them one by one
            arr = X.copy()
            if all_finite(arr) and (self.project(arr) == arr).all():
                return arr
        try:
            arr = np.asarray(X)
        except Exception as exc:  # ragged nested lists etc.
            raise InputError(f"{name} could not be converted to an array: {exc}") from exc
        if arr.dtype.kind not in "biufc":
            raise InputError(f"{name} must be numeric, got dtype {arr.dtype}")
        if arr.ndim < 2 or arr.shape[-2:] != self.shape:
            raise InputError(
                f"{name} has shape {arr.shape}, but {self} needs (..., {self.n}, {self.n}); "
                f"pass an {self.n}x{self.n} matrix or a stack of them"
            )
        if arr.dtype.kind == "c" and self.dtype.kind != "c":
            if np.any(arr.imag != 0):
                raise InputError(f"{name} is complex but {self} is a real algebra; pass real data")
            arr = arr.real
        if not np.isfinite(arr).all():
            raise InputError(f"{name} contains NaN or Inf entries; pass finite values")
        arr = np.array(arr, dtype=self.working_dtype(arr.dtype), copy=True)
        # What contains() tests, on data already of this algebra's shape and kind. Data its
        # projection leaves bit for bit unchanged is at distance 0: accepted without the
        # norms (12 µs of a 3 x 3 validation; an exactly skew W0 is such data on so(n)).
        projected = self.project(arr)
        if (projected == arr).all():
            return arr
        tol = max(tol, 64 * float(np.finfo(arr.dtype).eps))
        distance = _relative_defect(arr, projected)
        if not (distance <= tol).all():
            worst = float(np.max(distance))
            raise AlgebraError(
                f"{name} is not in {self}: relative distance {worst:.2e} > {tol:.0e}. "
                f"{self._membership_hint()} Use {type(self).__name__}.project(...) to "
                "project onto the algebra."
            )
        return arr

    def _membership_hint(self) -> str:
        return ""

    def working_dtype(self, dtype: np.dtype) -> np.dtype:
        """The dtype data of ``dtype`` is computed in: single precision is kept."""
        single = np.dtype(dtype) in (np.dtype(np.float32), np.dtype(np.complex64))
        if self.dtype.kind == "c":
            return np.dtype(np.complex64 if single else np.complex128)
        return np.dtype(np.float32 if single else np.float64)

    def random(self, seed: int | np.random.Generator | None = None, scale: float = 1.0) -> Array:
        """A random element with i.i.d. normal entries before projection (seeded).

        ``seed`` is ``None``, a non-negative integer or a :class:`numpy.random.Generator`;
        anything else raises :class:`InputError`.
        """
        if not (
            seed is None
            or isinstance(seed, np.random.Generator)
            or (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0)
        ):
            raise InputError(
                f"seed must be None, a non-negative integer or a numpy Generator, got {seed!r}. "
                "To fix: pass e.g. seed=0"
            )
        if (
            isinstance(scale, bool)
            or not isinstance(scale, (int, float, np.integer, np.floating))
            or not np.isfinite(scale)
        ):
            raise InputError(
                f"scale must be a finite real number, got {scale!r}. To fix: pass e.g. scale=1.0"
            )
        rng = np.random.default_rng(seed)
        X = rng.standard_normal(self.shape)
        if self.dtype.kind == "c":
            X = X + 1j * rng.standard_normal(self.shape)
        return (scale * self.project(X)).astype(self.dtype, copy=False)

    @staticmethod
    def bracket(X: Array, Y: Array) -> Array:
        """Matrix commutator ``[X, Y] = XY - YX``."""
        return X @ Y - Y @ X

    @staticmethod
    def inner(X: Array, Y: Array) -> Array:
        """Frobenius pairing ``Re tr(X^† Y)`` over the last two axes."""
        return np.real(np.sum(np.conj(X) * Y, axis=(-2, -1)))


@attrs.frozen
class SO(LieAlgebra):
    """so(n): real skew-symmetric matrices."""

    dtype: ClassVar[np.dtype] = np.dtype(np.float64)
    skew: ClassVar[bool] = True
    symbol: ClassVar[str] = "so"

    def project(self, X: ArrayLike) -> Array:
        if type(X) is np.ndarray and X.dtype.char == "d":  # the common case first
            return _halved(minus_dagger(X))
        X = _array(X)
        if is_numpy(X) and X.dtype.kind == "c":  # (X - X^T)/2, not (X - X^†)/2
            return _halved(X - transpose(X))
        return _halved(minus_dagger(X))

    @property
    def dimension(self) -> int:
        return self.n * (self.n - 1) // 2

    def _membership_hint(self) -> str:
        return "Elements of so(n) satisfy W^T = -W."


@attrs.frozen
class U(LieAlgebra):
    """u(n): complex skew-Hermitian matrices."""

    dtype: ClassVar[np.dtype] = np.dtype(np.complex128)
    skew: ClassVar[bool] = True
    symbol: ClassVar[str] = "u"

    def project(self, X: ArrayLike) -> Array:
        return _halved(minus_dagger(_array(X)))

    @property
    def dimension(self) -> int:
        return self.n * self.n

    def _membership_hint(self) -> str:
        return "Elements of u(n) satisfy W^† = -W."


@attrs.frozen
class SU(U):
    """su(N): traceless complex skew-Hermitian matrices."""

    symbol: ClassVar[str] = "su"

    def project(self, X: ArrayLike) -> Array:
        Y = super().project(X)
        n = self.n
        if not is_numpy(Y):  # another array library: no views assumed, one subtraction
            xp = namespace(Y)
            eye = xp.eye(n, dtype=Y.dtype, device=device_of(Y))
            trace = xp.sum(Y * eye, axis=(-2, -1))
            return Y - (trace / n)[..., None, None] * eye
        return _remove_trace(np.ascontiguousarray(Y))  # (new: the reshape is a view)

    def project_skew_hermitian(self, X: Array) -> Array:
        """:meth:`project` of a NumPy ``X`` that is skew-Hermitian bit for bit
        (``X_ij = -conj(X_ji)`` for every entry, as every state a lieflow scheme that keeps
        skew symmetry returns: :attr:`lieflow.schemes.Scheme.keeps_skew`), the same bits
        in one pass over the diagonal and a copy: its skew-Hermitian part
        ``(X_ij - conj(X_ji)) / 2 = (X_ij + X_ij) / 2`` is ``X`` itself (a doubling and a
        halving, both exact below ``2^1023``, where the projection overflows to ``inf``),
        so only the trace is removed, by :meth:`project`'s operations. A new array."""
        return _remove_trace(np.array(X, order="C"))

    @property
    def dimension(self) -> int:
        return self.n * self.n - 1

    def _membership_hint(self) -> str:
        return "Elements of su(N) satisfy W^† = -W and tr W = 0."


def _remove_trace(Y: np.ndarray) -> np.ndarray:
    """``Y - (tr Y / n) I`` over the last two axes of a C-contiguous NumPy ``Y``, in place
    (the mean of each diagonal subtracted from it), returned."""
    n = Y.shape[-1]
    diagonal = Y.reshape(*Y.shape[:-2], n * n)[..., :: n + 1]  # a view
    diagonal -= diagonal.sum(axis=-1, keepdims=True) / n
    return Y


@attrs.frozen
class GL(LieAlgebra):
    """gl(n): all real n×n matrices."""

    dtype: ClassVar[np.dtype] = np.dtype(np.float64)
    skew: ClassVar[bool] = False
    symbol: ClassVar[str] = "gl"

    def project(self, X: ArrayLike) -> Array:
        return _array(X)

    @property
    def dimension(self) -> int:
        return self.n * self.n
