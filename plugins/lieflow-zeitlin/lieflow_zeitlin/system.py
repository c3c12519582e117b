r"""The Euler–Zeitlin equations on su(N): Euler's equations on the sphere, quantized.

.. math:: \dot W = [B(W), W],\qquad B(W) = \sigma\, \Delta_N^{-1} W,
          \qquad \sigma = 1 \text{ (default) or } 1/\hbar,

with the Hoppe–Yau Laplacian ``Δ_N`` (:mod:`lieflow_zeitlin.laplacian`) and
``ħ = 2/sqrt(N² - 1)`` (lieflow SPEC §3; Zeitlin 1991, 2004; Modin & Viviani 2020).

Bracket and time convention
---------------------------
With the quantization ``W = Q(ω)`` of :mod:`lieflow_zeitlin.quantization` (``Q(x_a) = -iħS_a``)
one has ``(1/ħ)[Q(ψ), Q(ω)] = Q({ψ, ω}) + O(1/N²)`` with
``{f, g} = ∂_φ f ∂_z g - ∂_z f ∂_φ g``. Hence

* ``hbar_scaled=False`` (default, SPEC §3): ``dW/dt = [P, W]``, ``Δ_N P = W``. This is the
  vorticity equation ``ω_t = {ψ, ω}``, ``Δψ = ω``, in the slow time ``τ = ħ t``: one unit of
  matrix time is ``ħ ≈ 2/N`` units of fluid time.
* ``hbar_scaled=True``: ``dW/dt = (1/ħ)[P, W]``: matrix time is fluid time (the convention of
  codes that scale the bracket by ``1/ħ``).

Energy and Casimirs
-------------------
The Hamiltonian is the kinetic energy

.. math:: \eta(W) = -\tfrac12 \operatorname{Re}\operatorname{tr}(W^\dagger B(W))
          = -\tfrac{\sigma}{2} \langle W, \Delta_N^{-1} W\rangle_F \;\ge\; 0,

positive because ``Δ_N`` is negative definite on su(N); then ``B = (grad η)^†`` as lieflow
requires (SPEC §1). For ``W = Q(ω)`` it *equals* ``(σ N/4π) · ½∫|∇ψ|² dΩ``, ``Δψ = ω``
(``Q`` maps ``Δ`` to ``Δ_N`` and is an isometry up to ``κ² = N/4π``).
The Casimirs are the real traces

.. math:: C_k(W) = \operatorname{tr}\big((iW)^k\big),\qquad k \in \texttt{casimir\_powers},

(``iW`` is Hermitian, with eigenvalues ``≈`` the vorticity values); ``C_2 = ||W||_F²`` is the
enstrophy (``= (N/4π) ∫ω² dΩ`` exactly). ``tr W^k`` itself is imaginary for odd ``k``, which is why
:meth:`EulerZeitlin.casimirs` overrides lieflow's default ``Re tr W^k``.
"""

from __future__ import annotations

from typing import Any

import attrs
import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

import lieflow

from .laplacian import HoppeYauLaplacian, matrix_size
from .quantization import hbar, random_vorticity

Array = NDArray[Any]

_COMPLEX = (np.dtype(np.complex128), np.dtype(np.complex64))


def _complex_dtype(value: DTypeLike) -> np.dtype:
    try:
        dt = np.dtype(value)
    except TypeError:
        raise lieflow.InputError(f"dtype must be complex128 or complex64, got {value!r}") from None
    if dt not in _COMPLEX:
        raise lieflow.InputError(f"dtype must be complex128 or complex64, got {dt}")
    return dt


def _degree(value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise lieflow.InputError(f"random_degree must be a positive integer, got {value!r}")
    return int(value)


@attrs.frozen
class VorticityAlgebra(lieflow.SU):
    """su(N) whose :meth:`random` draws a *smooth* vorticity field instead of white noise.

    Identical to :class:`lieflow.SU` (projection, membership, bracket, inner product) except
    for the random element, which is :func:`~lieflow_zeitlin.random_vorticity`: band-limited
    to degrees ``1..degree``, root-mean-square vorticity ``scale``. A run configuration's
    ``[initial] random = true`` therefore starts a smooth flow. ``precision`` is the dtype of
    random elements (complex128 or complex64).
    """

    degree: int = attrs.field(default=8, converter=_degree, kw_only=True)
    precision: np.dtype = attrs.field(
        default=np.dtype(np.complex128), converter=_complex_dtype, kw_only=True
    )

    def random(self, seed: int | np.random.Generator | None = None, scale: float = 1.0) -> Array:
        """A seeded random smooth vorticity matrix with root-mean-square vorticity ``scale``."""
        return random_vorticity(self.n, self.degree, seed, rms=scale, dtype=self.precision)


@attrs.frozen(eq=False)
class EulerZeitlin(lieflow.IsospectralSystem):
    r"""Euler's equations on the sphere, Zeitlin's su(N) model (module docs for conventions).

    Parameters
    ----------
    N : int
        Matrix size (``>= 2``; default 8, a test size: real runs use 64–512). The
        quantization resolves spherical-harmonic degrees ``l < N``.
    dtype : {"complex128", "complex64"}
        Precision of the states this system makes (random initial conditions). ``B`` works
        in the precision of its argument (complex64 in single, anything else in double).
    hbar_scaled : bool
        Scale the bracket by ``1/ħ`` (matrix time = fluid time); default ``False``
        (``dW/dt = [P, W]``, SPEC §3).
    random_degree : int
        Band limit of :meth:`algebra`'s random elements (smooth random initial vorticity).

    Notes
    -----
    ``B(W) = σ Δ_N^{-1} W`` costs one O(N²) partitioned tridiagonal sweep over all diagonals
    of all matrices of a batch (:meth:`HoppeYauLaplacian.solve`); ``B`` is linear
    (``linear_B = True``), so Newton's method needs nothing more. For ``W`` outside su(N)
    (Newton directions) ``B`` is the pseudo-inverse: the trace is projected out.
    """

    N: int = attrs.field(default=8, converter=matrix_size)
    dtype: np.dtype = attrs.field(default=np.dtype(np.complex128), converter=_complex_dtype)
    hbar_scaled: bool = attrs.field(default=False, validator=attrs.validators.instance_of(bool))
    random_degree: int = attrs.field(default=8, converter=_degree)
    laplacian: HoppeYauLaplacian = attrs.field(init=False, repr=False)

    linear_B = True
    casimir_powers = (2, 3, 4)

    @laplacian.default
    def _laplacian(self) -> HoppeYauLaplacian:
        return HoppeYauLaplacian(self.N, scale=self.bracket_scale)

    @property
    def bracket_scale(self) -> float:
        """``σ``: ``1/ħ`` if ``hbar_scaled`` else ``1``."""
        return 1.0 / hbar(self.N) if self.hbar_scaled else 1.0

    @property
    def algebra(self) -> VorticityAlgebra:
        """su(N) (random elements are smooth vorticity fields)."""
        return VorticityAlgebra(self.N, degree=self.random_degree, precision=self.dtype)

    def B(self, W: Array) -> Array:
        r"""``σ Δ_N^{-1} W`` (stream matrix ``P``), broadcasting over leading axes."""
        return self.laplacian.solve(W)

    def hamiltonian(self, W: Array) -> Array:
        r"""Kinetic energy ``-½ Re tr(W^† B(W)) >= 0``, shape ``W.shape[:-2]``."""
        W = np.asarray(W)
        P = self.B(W)
        return -0.5 * np.real(np.sum(np.conj(W) * P, axis=(-2, -1)))

    def casimirs(self, W: Array) -> Array:
        r"""``tr((iW)^k)`` for ``k`` in :attr:`casimir_powers` (real), last axis indexes k.

        Uses ``tr(A^k) = Σ_ij (A^a)_ij (A^b)_ji`` with ``a = ⌊k/2⌋``, ``b = ⌈k/2⌉``, so
        ``k <= 4`` costs a single matrix product.
        """
        A = 1j * np.asarray(W)
        powers = [k for k in self.casimir_powers if k <= self.N]
        if not powers:
            return np.zeros((*A.shape[:-2], 0))
        top = (max(powers) + 1) // 2
        stack = [np.broadcast_to(np.eye(self.N), A.shape), A]
        for _ in range(2, top + 1):
            stack.append(stack[-1] @ A)
        out = [
            np.real(np.sum(stack[k // 2] * np.swapaxes(stack[k - k // 2], -1, -2), axis=(-2, -1)))
            for k in powers
        ]
        return np.stack(out, axis=-1)

    def enstrophy(self, W: ArrayLike) -> Array:
        """``||W||_F² = tr((iW)²)`` (the ``k = 2`` Casimir)."""
        W = np.asarray(W)
        return np.sum(np.abs(W) ** 2, axis=(-2, -1))
