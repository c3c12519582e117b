r"""Fields on the sphere ↔ su(N) matrices: the Zeitlin quantization and its inverse.

This module fixes the *orientation* of the whole plugin; the derivation is in the docs page
``euler-zeitlin.md`` ("Conventions") and is summarised here.

Sphere, bracket and Euler's equations
-------------------------------------
Points of the unit sphere are ``x = (sin θ cos φ, sin θ sin φ, cos θ)`` (colatitude ``θ``,
longitude ``φ`` increasing *eastward*), oriented by the outward normal ``n̂ = x``: the frame
``(n̂, θ̂, φ̂)`` is right-handed, ``dA = sin θ dθ ∧ dφ = dφ ∧ dz`` (``z = cos θ``). The
Poisson bracket of this area form is

.. math:: \{f, g\} = \hat n \cdot (\nabla f \times \nabla g)
          = \frac{f_\theta g_\phi - f_\phi g_\theta}{\sin\theta}
          = \partial_\phi f\, \partial_z g - \partial_z f\, \partial_\phi g,

so ``{x_a, x_b} = ε_abc x_c`` (``{x, y} = z``). The velocity of an incompressible flow with
stream function ``ψ`` is ``u = n̂ × ∇ψ`` and its vorticity ``ω = n̂ · curl u = Δψ``; then
``u · ∇ω = n̂ · (∇ψ × ∇ω) = {ψ, ω}`` and Euler's equation ``ω_t + u · ∇ω = 0`` reads

.. math:: \omega_t = -\{\psi, \omega\} = \{\omega, \psi\},\qquad \Delta\psi = \omega.

(Check: ``ω = a cos θ`` gives ``ψ = -(a/2) cos θ`` and ``u = (a/2) sin θ φ̂``: a solid-body
rotation *eastward* at angular speed ``a/2``, vorticity twice the angular speed.)

Conventions
-----------
*Spherical harmonics* are complex with the Condon–Shortley phase, as in
:func:`scipy.special.sph_harm_y`: :math:`Y_{lm}(\theta, \phi)`, orthonormal on the unit
sphere, :math:`Y_{l,-m} = (-1)^m \overline{Y_{lm}}`. A field
``f = Σ_{l<N, |m|<=l} ω_{lm} Y_{lm}`` is stored as the vector of its ``N²`` coefficients at
index :func:`lm_index` ``(l, m) = l(l+1) + m``; it is real exactly when
:math:`ω_{l,-m} = (-1)^m \overline{ω_{lm}}`.

*Matrix harmonics* :math:`T_{lm}` are the Frobenius-orthonormal eigenvectors of the
Hoppe–Yau Laplacian with eigenvalue ``-l(l+1)``, with the signs of
:func:`~lieflow_zeitlin.laplacian.harmonics` (Condon–Shortley transported by
``L_a ↔ ad S_a``), so :math:`T_{l,-m} = (-1)^m T_{lm}^T` with real entries; ``T_{lm}``,
``m >= 0``, lives on the lower diagonal ``m``.

*The quantization* is the linear bijection

.. math:: Q(f) = i\,\kappa \sum_{l<N} \sum_{|m| \le l} \omega_{lm}\, T_{lm},
          \qquad \kappa = \sqrt{N / (4\pi)},

which maps real fields onto skew-Hermitian matrices, zero-mean fields onto su(N), and
:math:`\Delta` to :math:`\Delta_N` exactly (``Δ Y_lm = -l(l+1) Y_lm``). It maps the
coordinate functions to ``Q(x_a) = i ħ S_a`` exactly, ``ħ = 2/sqrt(N²-1)``, and
``Q(L_a f) = [S_a, Q(f)]`` exactly (``L = -i x × ∇``). Since
``[Q(x_a), Q(x_b)] = (iħ)² i ε_abc S_c = -ħ ε_abc Q(x_c) = -ħ Q({x_a, x_b})``,

.. math:: \tfrac1\hbar [Q(f), Q(g)] = -Q(\{f, g\}) + O(N^{-1}),

*exactly* when ``f`` has degree 1 (``(1/ħ)[Q(z), Q(g)] = Q(∂_φ g)``). Hence Euler's
``ω_t = -{ψ, ω}`` is the matrix flow

.. math:: \dot W = \tfrac1\hbar [P, W],\qquad \Delta_N P = W,\qquad W = Q(\omega),

which is lieflow's ``dW/dt = [B(W), W]`` with ``B(W) = (1/ħ) Δ_N^{-1} W``, forward in time
(:class:`~lieflow_zeitlin.EulerZeitlin` with ``time="fluid"``). This is also quflow's
convention: ``quflow.shc2mat`` of the same field (quflow's coefficients are
``ω_lm/√(4π)``) returns the same matrix to roundoff (largest entry difference 2e-15 at
N = 5, 8, 13; quflow commit b42eede).
Before lieflow-zeitlin 0.2 the map was ``-J Q(f) J`` (``J`` the index reversal), which
satisfies the bracket relation with the opposite sign and ran Euler backwards.

The eigenvalues of ``-i Q(f)`` approximate the values of ``f`` (so ``ρ(W) ≈ max|ω|``),
while ``||Q(f)||_F² = (N/4π) ∫ f² dΩ`` exactly. Grid functions are sampled at colatitudes
``θ_j`` and longitudes ``φ_k = 2πk/n_lon`` (:class:`SphereGrid`) and transformed with
quadrature that is exact for band-limited fields; the associated Legendre functions come from
:func:`scipy.special.sph_legendre_p_all` (same normalisation and phase as ``sph_harm_y``).

Every transform here costs O(N³) flops — the size of the transform — and holds O(N²) memory:
the matrix harmonics and the Legendre functions are generated one diagonal (one order) at a
time by their three-term recurrences in ``l`` (:mod:`lieflow_zeitlin._recurrences`), compiled
with numba when it is installed (``pip install lieflow-zeitlin[fast]``) and fused with the
products for up to four fields at once (larger stacks go through BLAS). Measured on one core
of a loaded machine (``benchmarks/transforms.py``): 0.11 s / 0.14 s for ``sh_to_matrix`` /
``matrix_to_sh`` at N = 512 (the eigensolver transforms, ``method="reference"``, 1.9 s),
0.5–0.6 s at N = 1024. Stacks ``(..., N, N)`` or ``(..., N²)`` are transformed together.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

import lieflow

from . import _recurrences as _rec
from .laplacian import harmonics, matrix_size

Array = NDArray[Any]

#: Target size (in float64 values) of one chunk of associated Legendre functions.
_CHUNK_VALUES = 4_000_000


def hbar(N: int) -> float:
    """Zeitlin's ``ħ = 2/sqrt(N² - 1)`` (``Q(x_a) = i ħ S_a``)."""
    N = matrix_size(N)
    return 2.0 / math.sqrt(N * N - 1)


def kappa(N: int) -> float:
    """The normalisation ``κ = sqrt(N/(4π))`` of the quantization map."""
    return math.sqrt(matrix_size(N) / (4 * math.pi))


def lm_index(l: ArrayLike, m: ArrayLike) -> Any:
    """Position ``l(l+1) + m`` of the coefficient ``ω_lm`` (``|m| <= l``)."""
    l = np.asarray(l)
    return l * (l + 1) + np.asarray(m)


def degrees_and_orders(N: int) -> tuple[Array, Array]:
    """Arrays ``(l, m)`` of length ``N²``: the degree and order of each coefficient index."""
    N = matrix_size(N)
    l = np.repeat(np.arange(N), 2 * np.arange(N) + 1)
    m = np.arange(N * N) - l * (l + 1)
    return l, m


def _size_from_coefficients(coeffs: Array) -> int:
    n2 = coeffs.shape[-1] if coeffs.ndim else 0
    N = math.isqrt(n2)
    if coeffs.ndim < 1 or N * N != n2 or N < 2:
        raise lieflow.InputError(
            f"coefficients must have shape (..., N²) with N >= 2 (index l(l+1)+m for l < N), "
            f"got shape {coeffs.shape}"
        )
    return N


Method = Literal["auto", "recurrence", "reference"]


def _use_recurrence(N: int, method: str) -> bool:
    if method not in ("auto", "recurrence", "reference"):
        raise lieflow.InputError(
            f"method must be 'auto', 'recurrence' or 'reference', got {method!r}"
        )
    if method == "recurrence" and N > _rec.MAX_N:
        raise lieflow.InputError(
            f"the recurrence transforms support N <= {_rec.MAX_N}, got N = {N}; "
            "use method='reference'"
        )
    return method == "recurrence" or (method == "auto" and N <= _rec.MAX_N)


def _grid_recurrence(method: str) -> bool:
    """Legendre functions by recurrence (any N) unless ``method == "reference"``."""
    _use_recurrence(2, method)  # validates the name
    return method != "reference"


#: Up to this many real rows (4 per field) a product runs fused with the compiled recurrence;
#: above, the basis of the diagonal is built and multiplied by BLAS.
_FUSED_ROWS = 16


def _harmonic_product(N: int, m: int, X: Array, *, analysis: bool) -> Array:
    """``X @ V_m`` (analysis) or ``X @ V_m.T`` (synthesis) for real ``X`` of shape ``(Q, n)``."""
    if _rec.have_numba() and X.shape[0] <= _FUSED_ROWS:
        if analysis:
            return _rec.harmonic_analysis(N, m, X)
        return _rec.harmonic_synthesis(N, m, X)
    Vt, k1, sf, sb = _rec.harmonic_diagonal(N, m)
    n = N - m
    if analysis:
        Y = np.empty((X.shape[0], n))
        Y[:, :k1] = (X * sf) @ Vt[:k1].T
        Y[:, k1:] = (X * sb) @ Vt[k1:n].T
        return Y
    out: Array = (X[:, :k1] @ Vt[:k1]) * sf
    if k1 < n:
        out += (X[:, k1:] @ Vt[k1:n]) * sb
    return out


def _legendre_product(N: int, m: int, theta: Array, X: Array, *, analysis: bool) -> Array:
    """``X @ P.T`` (analysis, ``X``: ``(Q, n_lat)``) or ``X @ P`` (synthesis, ``(Q, n)``) with
    ``P = P̄_{m+k, m}(θ_j)``, real ``X``."""
    if _rec.have_numba() and X.shape[0] <= _FUSED_ROWS:
        if analysis:
            return _rec.legendre_analysis(N, m, theta, X)
        return _rec.legendre_synthesis(N, m, theta, X)
    P = _rec.legendre_order(N, m, theta)
    return X @ P.T if analysis else X @ P


def sh_to_matrix(
    coeffs: ArrayLike, *, dtype: DTypeLike = np.complex128, method: Method = "auto"
) -> Array:
    r"""The matrix ``W = Q(f)`` of the field with coefficients ``coeffs`` (module docs).

    Parameters
    ----------
    coeffs : array_like, shape (..., N²)
        Spherical-harmonic coefficients ``ω_lm`` at index ``l(l+1) + m``, ``l < N``.
    dtype : complex dtype
        dtype of the result.
    method : {"auto", "recurrence", "reference"}
        ``"recurrence"``: the matrix harmonics one diagonal at a time by their three-term
        recurrence in ``l`` (:mod:`lieflow_zeitlin._recurrences`; O(N³) flops, O(N²)
        memory, compiled with numba when installed), for ``N <= 1400``; ``"reference"``:
        one tridiagonal eigenproblem per diagonal (:func:`harmonics`, about 10x slower);
        ``"auto"`` (default): the recurrence where it applies.

    Returns
    -------
    ndarray, shape (..., N, N)
        ``i κ Σ ω_lm T_lm``; skew-Hermitian if the field is real, traceless if ``ω_00 = 0``.
    """
    c = np.asarray(coeffs)
    N = _size_from_coefficients(c)
    batch = c.shape[:-1]
    out = np.zeros((*batch, N, N), dtype=dtype)
    factor = 1j * kappa(N)
    if not _use_recurrence(N, method):
        for m, V in harmonics(N):
            l = np.arange(m, N)
            i = np.arange(N - m)
            out[..., i + m, i] = factor * (c[..., lm_index(l, m)] @ V.T)
            if m:
                out[..., i, i + m] = (factor * (-1) ** m) * (c[..., lm_index(l, -m)] @ V.T)
        return out
    K = math.prod(batch)
    c2 = c.reshape(K, N * N).astype(np.complex128, copy=False)
    flat = out.reshape(K, N * N)
    for m in range(N):
        n = N - m
        l = np.arange(m, N)
        i = np.arange(n)
        parts = [c2[:, lm_index(l, m)]]
        if m:
            parts.append(c2[:, lm_index(l, -m)] * (-1) ** m)
        X = np.concatenate([np.concatenate([p.real, p.imag]) for p in parts])
        Y = _harmonic_product(N, m, X, analysis=False)
        for q, index in enumerate([(i + m) * N + i, i * N + i + m][: len(parts)]):
            flat[:, index] = factor * (
                Y[2 * q * K : (2 * q + 1) * K] + 1j * Y[(2 * q + 1) * K : (2 * q + 2) * K]
            )
    return out


def matrix_to_sh(W: ArrayLike, *, method: Method = "auto") -> Array:
    r"""Coefficients ``ω_lm`` of the field ``f = Q^{-1}(W)``: the exact inverse of
    :func:`sh_to_matrix` (``ω_lm = -(i/κ) <T_lm, W>_F``).

    Parameters
    ----------
    W : array_like, shape (..., N, N)
    method : {"auto", "recurrence", "reference"}
        As for :func:`sh_to_matrix`.

    Returns
    -------
    ndarray, shape (..., N²), complex128
    """
    W = np.asarray(W)
    if W.ndim < 2 or W.shape[-1] != W.shape[-2]:
        raise lieflow.InputError(f"W must have shape (..., N, N), got {W.shape}")
    N = matrix_size(W.shape[-1])
    batch = W.shape[:-2]
    out = np.zeros((*batch, N * N), dtype=np.complex128)
    factor = -1j / kappa(N)
    if not _use_recurrence(N, method):
        for m, V in harmonics(N):
            l = np.arange(m, N)
            lower = np.diagonal(W, offset=-m, axis1=-2, axis2=-1)
            out[..., lm_index(l, m)] = factor * (lower @ V)
            if m:
                upper = np.diagonal(W, offset=m, axis1=-2, axis2=-1)
                out[..., lm_index(l, -m)] = (factor * (-1) ** m) * (upper @ V)
        return out
    K = math.prod(batch)
    flat = W.reshape(K, N * N)
    res = out.reshape(K, N * N)
    for m in range(N):
        n = N - m
        l = np.arange(m, N)
        i = np.arange(n)
        diagonals = [flat[:, (i + m) * N + i]]
        if m:
            diagonals.append(flat[:, i * N + i + m] * (-1) ** m)
        X = np.concatenate([np.concatenate([d.real, d.imag]) for d in diagonals])
        Y = _harmonic_product(N, m, X.astype(np.float64, copy=False), analysis=True)
        for q, mm in enumerate([m, -m][: len(diagonals)]):
            res[:, lm_index(l, mm)] = factor * (
                Y[2 * q * K : (2 * q + 1) * K] + 1j * Y[(2 * q + 1) * K : (2 * q + 2) * K]
            )
    return out


def _fejer_weights(n: int) -> Array:
    r"""Fejér's first rule on ``x_j = cos θ_j``, ``θ_j = (j + 1/2)π/n``: weights for
    ``∫_{-1}^{1} g(x) dx``, exact for polynomials of degree ``< n`` (Fejér 1933):
    ``w_j = (2/n) [1 - 2 Σ_{k=1}^{⌊n/2⌋} cos(2kθ_j) / (4k² - 1)]``."""
    theta = (np.arange(n) + 0.5) * np.pi / n
    k = np.arange(1, n // 2 + 1)
    s = np.cos(2 * np.outer(theta, k)) / (4 * k * k - 1)
    return (2.0 / n) * (1 - 2 * s.sum(axis=1))


@functools.lru_cache(maxsize=8)
def _gauss_legendre(n: int) -> tuple[Array, Array]:
    """numpy's Gauss–Legendre rule (0.5 s at n = 1024), cached; read-only arrays."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def _positive(_inst: object, attr: attrs.Attribute, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise lieflow.InputError(f"{attr.name} must be a positive integer, got {value!r}")


@attrs.frozen(eq=False)
class SphereGrid:
    r"""A latitude–longitude grid with a quadrature rule for ``∫ f dΩ``.

    Colatitudes ``θ_j`` (north to south) are Gauss–Legendre nodes in ``cos θ``
    (``kind="gauss"``) or the equiangular midpoints ``(j + 1/2)π/n_lat``
    (``kind="equiangular"``, Fejér's first rule); longitudes are ``φ_k = 2πk/n_lon``.
    The quadrature ``Σ_jk w_j (2π/n_lon) f(θ_j, φ_k)`` integrates ``Y_lm conj(Y_l'm')``
    exactly for ``l, l' < N`` if ``n_lon >= 2N - 1`` and ``n_lat >= N`` (Gauss) or
    ``n_lat >= 2N - 1`` (equiangular); :meth:`for_size` builds such a grid.
    """

    nlat: int = attrs.field(validator=_positive)
    nlon: int = attrs.field(validator=_positive)
    kind: Literal["gauss", "equiangular"] = attrs.field(
        default="gauss", validator=attrs.validators.in_(("gauss", "equiangular"))
    )
    theta: Array = attrs.field(init=False, repr=False)
    weights: Array = attrs.field(init=False, repr=False)

    @theta.default
    def _theta(self) -> Array:
        if self.kind == "gauss":
            x, _ = _gauss_legendre(self.nlat)
            t = np.arccos(x[::-1])
        else:
            t = (np.arange(self.nlat) + 0.5) * np.pi / self.nlat
        t.setflags(write=False)
        return t

    @weights.default
    def _weights(self) -> Array:
        if self.kind == "gauss":
            w = _gauss_legendre(self.nlat)[1][::-1].copy()
        else:
            w = _fejer_weights(self.nlat)
        w.setflags(write=False)
        return w

    @classmethod
    def for_size(
        cls, N: int, kind: Literal["gauss", "equiangular"] = "gauss", oversample: int = 1
    ) -> SphereGrid:
        """The smallest grid (times ``oversample``) on which degrees ``< N`` are exact."""
        N = matrix_size(N)
        nlat = N if kind == "gauss" else 2 * N - 1
        return cls(oversample * nlat, oversample * 2 * N, kind)

    @property
    def phi(self) -> Array:
        """Longitudes ``2πk/n_lon`` in radians, shape ``(n_lon,)``."""
        return 2 * np.pi * np.arange(self.nlon) / self.nlon

    @property
    def lat(self) -> Array:
        """Latitudes ``90° - θ`` in degrees (north to south)."""
        return 90.0 - np.degrees(self.theta)

    @property
    def lon(self) -> Array:
        """Longitudes in degrees, ``[0, 360)``."""
        return np.degrees(self.phi)

    def exact_for(self, N: int) -> bool:
        """Whether analysis of fields of degree ``< N`` on this grid is exact."""
        need_lat = N if self.kind == "gauss" else 2 * N - 1
        return self.nlat >= need_lat and self.nlon >= 2 * N - 1

    def integrate(self, f: ArrayLike) -> Array:
        """``∫ f dΩ`` by the grid's quadrature, over the last two axes ``(n_lat, n_lon)``."""
        f = np.asarray(f)
        return (2 * np.pi / self.nlon) * np.einsum("...jk,j->...", f, self.weights)


def _legendre_chunks(N: int, theta: Array) -> Any:
    """Yield ``(slice, P)`` with ``P[l, m, j] = Y_lm(θ_j, 0)`` for ``0 <= m <= l < N``."""
    from scipy.special import sph_legendre_p_all  # 0.1 s to import: on first use

    chunk = max(1, _CHUNK_VALUES // (N * (2 * N - 1)))
    for start in range(0, theta.size, chunk):
        sl = slice(start, min(start + chunk, theta.size))
        P = sph_legendre_p_all(N - 1, N - 1, theta[sl])[0]  # (N, 2N-1, c), m < 0 at the end
        yield sl, P[:, :N, :]


def _nonnegative_table(coeffs: Array, N: int) -> Array:
    """``ω_lm`` for ``m >= 0`` as a ``(..., l, m)`` table (zero where ``m > l``)."""
    l, m = np.tril_indices(N)
    table = np.zeros((*coeffs.shape[:-1], N, N), dtype=np.complex128)
    table[..., l, m] = coeffs[..., lm_index(l, m)]
    return table


def _legendre_sums(table: Array, theta: Array, N: int) -> Array:
    """``F[..., j, m] = Σ_l table[..., l, m] P̄_lm(θ_j)`` by recurrence, one order at a time."""
    batch = table.shape[:-2]
    K = math.prod(batch)
    t2 = table.reshape(K, N, N)
    F = np.zeros((K, theta.size, N), dtype=np.complex128)
    for m in range(N):
        block = t2[:, m:, m]
        Y = _legendre_product(N, m, theta, np.concatenate([block.real, block.imag]), analysis=False)
        F[:, :, m] = Y[:K] + 1j * Y[K:]
    return F.reshape(*batch, theta.size, N)


def sh_to_grid(coeffs: ArrayLike, grid: SphereGrid, *, method: Method = "auto") -> Array:
    r"""Values of the *real* field ``f = Σ ω_lm Y_lm`` on ``grid``, shape ``(..., n_lat, n_lon)``.

    Uses the coefficients with ``m >= 0``; those with ``m < 0`` are taken to be
    :math:`(-1)^m \overline{ω_{l,|m|}}` (a real field). Exact on any grid (longitudes are
    summed with an FFT, frequencies folded if ``n_lon < 2N - 1``). ``method``:
    ``"recurrence"`` (Legendre functions by their recurrence, one order at a time, O(N²)
    memory), ``"reference"`` (:func:`scipy.special.sph_legendre_p_all` in chunks) or
    ``"auto"`` (the recurrence).
    """
    c = np.asarray(coeffs)
    N = _size_from_coefficients(c)
    table = _nonnegative_table(c, N)
    batch = c.shape[:-1]
    spectrum = np.zeros((*batch, grid.nlat, grid.nlon), dtype=np.complex128)
    chunks: Any = (
        [(slice(None), None)] if _grid_recurrence(method) else _legendre_chunks(N, grid.theta)
    )
    for sl, P in chunks:
        if P is None:
            F = _legendre_sums(table, grid.theta, N)
        else:
            F = np.einsum("...lm,lmj->...jm", table, P)  # F[..., j, m] = Σ_l ω_lm P_lm(θ_j)
        F[..., 1:] *= 2.0  # f = Re(F_0 + 2 Σ_{m>0} F_m e^{imφ})
        for start in range(0, N, grid.nlon):  # fold frequencies m >= n_lon onto m mod n_lon
            part = F[..., start : start + grid.nlon]
            spectrum[..., sl, : part.shape[-1]] += part
    return np.fft.ifft(spectrum, axis=-1).real * grid.nlon


def grid_to_sh(f: ArrayLike, grid: SphereGrid, N: int, *, method: Method = "auto") -> Array:
    r"""Coefficients ``ω_lm`` (``l < N``) of the real field sampled as ``f`` on ``grid``.

    The L² projection onto degrees ``< N`` by the grid's quadrature: an FFT in longitude,
    then ``ω_lm = Σ_j w_j Y_lm(θ_j, 0) · (2π/n_lon) Σ_k f_jk e^{-imφ_k}``; ``ω_{l,-m}``
    is set to :math:`(-1)^m \overline{ω_{lm}}` so that the field is exactly real. Exact
    (a round trip with :func:`sh_to_grid` reproduces the coefficients to roundoff) when
    ``grid.exact_for(N)``; otherwise :class:`lieflow.InputError` is raised.

    Parameters
    ----------
    f : array_like, shape (..., n_lat, n_lon)
        Real samples.
    grid : SphereGrid
    N : int
        Number of degrees to keep (the matrix size of the quantization).
    method : {"auto", "recurrence", "reference"}
        As for :func:`sh_to_grid`.
    """
    N = matrix_size(N)
    f = np.asarray(f)
    if f.ndim < 2 or f.shape[-2:] != (grid.nlat, grid.nlon):
        raise lieflow.InputError(
            f"f has shape {f.shape}; the grid needs (..., {grid.nlat}, {grid.nlon})"
        )
    if np.iscomplexobj(f):
        raise lieflow.InputError("grid_to_sh transforms real fields; pass real samples")
    if not grid.exact_for(N):
        raise lieflow.InputError(
            f"a {grid.kind} grid of {grid.nlat}×{grid.nlon} cannot resolve degree {N - 1}: "
            f"use SphereGrid.for_size({N}, {grid.kind!r}) or a finer grid"
        )
    spectrum = np.fft.rfft(f, axis=-1)[..., :N] * (2 * np.pi / grid.nlon)  # (..., j, m)
    spectrum = spectrum * grid.weights[:, None]
    table = np.zeros((*f.shape[:-2], N, N), dtype=np.complex128)
    if _grid_recurrence(method):
        K = math.prod(f.shape[:-2])
        s2 = spectrum.reshape(K, grid.nlat, N)
        t2 = table.reshape(K, N, N)
        for order in range(N):
            block = s2[:, :, order]
            Y = _legendre_product(
                N, order, grid.theta, np.concatenate([block.real, block.imag]), analysis=True
            )
            t2[:, order:, order] = Y[:K] + 1j * Y[K:]
    else:
        for sl, P in _legendre_chunks(N, grid.theta):
            table += np.einsum("lmj,...jm->...lm", P, spectrum[..., sl, :])
    l, m = np.tril_indices(N)
    out = np.zeros((*f.shape[:-2], N * N), dtype=np.complex128)
    values = table[..., l, m]
    out[..., lm_index(l, m)] = values
    negative = m > 0
    out[..., lm_index(l[negative], -m[negative])] = (-1.0) ** m[negative] * np.conj(
        values[..., negative]
    )
    out[..., lm_index(l[~negative], 0)] = values[..., ~negative].real
    return out


def matrix_to_grid(W: ArrayLike, grid: SphereGrid, *, method: Method = "auto") -> Array:
    """The real field ``Q^{-1}(W)`` of a skew-Hermitian ``W`` on ``grid``,
    shape ``(..., n_lat, n_lon)``."""
    return sh_to_grid(matrix_to_sh(W, method=method), grid, method=method)


def grid_to_matrix(
    f: ArrayLike,
    grid: SphereGrid,
    N: int,
    *,
    dtype: DTypeLike = np.complex128,
    method: Method = "auto",
) -> Array:
    """The skew-Hermitian matrix ``Q(f)`` of the real field sampled on ``grid``, projected
    onto degrees ``< N`` (:func:`grid_to_sh`); the mean (``l = 0``) is kept, subtract it
    (or ``tr W/N``) for su(N)."""
    return sh_to_matrix(grid_to_sh(f, grid, N, method=method), dtype=dtype, method=method)


def random_sh(
    N: int,
    degree: int,
    seed: int | np.random.Generator | None = None,
    rms: float = 1.0,
) -> Array:
    r"""Coefficients of a seeded random smooth real field with zero mean.

    ``ω_lm`` for ``1 <= l <= min(degree, N-1)`` are i.i.d. standard complex normals
    (real for ``m = 0``) completed by :math:`ω_{l,-m} = (-1)^m \overline{ω_{lm}}`; all
    others are zero. The result is scaled so that the field's root-mean-square over the
    sphere, ``sqrt(Σ|ω_lm|² / 4π)``, equals ``rms``.
    """
    N = matrix_size(N)
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or degree < 1:
        raise lieflow.InputError(f"degree must be a positive integer, got {degree!r}")
    if not (math.isfinite(rms) and rms >= 0):
        raise lieflow.InputError(f"rms must be finite and non-negative, got {rms!r}")
    L = min(int(degree), N - 1)
    rng = np.random.default_rng(seed)
    l, m = np.tril_indices(L + 1)
    keep = l >= 1
    l, m = l[keep], m[keep]
    values = rng.standard_normal(l.size) + 1j * rng.standard_normal(l.size)
    values = np.where(m == 0, values.real * math.sqrt(2), values) / math.sqrt(2)
    out = np.zeros(N * N, dtype=np.complex128)
    out[lm_index(l, m)] = values
    pos = m > 0
    out[lm_index(l[pos], -m[pos])] = (-1.0) ** m[pos] * np.conj(values[pos])
    norm = math.sqrt(float(np.sum(np.abs(out) ** 2)) / (4 * math.pi))
    return out * (rms / norm) if norm > 0 else out


def random_vorticity(
    N: int,
    degree: int = 8,
    seed: int | np.random.Generator | None = None,
    rms: float = 1.0,
    *,
    dtype: DTypeLike = np.complex128,
) -> Array:
    """A seeded random smooth vorticity matrix in su(N): ``Q`` of :func:`random_sh`.

    Band-limited to degrees ``1..degree`` with a flat spectrum, root-mean-square vorticity
    ``rms``; exactly skew-Hermitian (by construction) and traceless (the roundoff trace of
    the ``l >= 1`` harmonics is removed).
    """
    W = sh_to_matrix(random_sh(N, degree, seed, rms), dtype=dtype)
    diag = np.einsum("ii->i", W)  # a writable view of the diagonal
    diag -= np.mean(diag)
    return W
