r"""Total angular momentum, the first integral ``γ = ‖L‖ / √C₂``, and random initial
vorticity with a prescribed ``γ`` (Modin & Viviani, J. Fluid Mech. 884:A22, 2020).

Continuous definitions (unit sphere, ``R = 1``; conventions of
:mod:`lieflow_zeitlin.quantization`)
---------------------------------------------------------------------------------------------

.. math::
    L_a = \int_{S^2} x_a\,\omega\,d\Omega \quad(a = 1, 2, 3),\qquad
    C_2 = \int_{S^2} \omega^2\,d\Omega,\qquad
    \gamma = \frac{\|L\|}{\sqrt{C_2}} .

``L`` is the fluid's total angular momentum ``∫ x × u dΩ`` (for ``u = n̂ × ∇ψ``,
``x × u = -∇ψ`` and ``∫∇ψ dΩ = 2∫ψ x dΩ``, which the degree-1 relation ``ψ_1 = -ω_1/2``
turns into ``∫ x ω dΩ``). Only the degree-1 part ``ω_1`` of ``ω`` contributes (the ``x_a``
span degree 1), and ``∫ x_a x_b dΩ = (4π/3) δ_ab``, so ``‖L‖² = (4π/3) ∫ω_1² dΩ`` and, by
Parseval,

.. math:: 0 \le \gamma = \sqrt{4\pi/3}\,\sqrt{\int\omega_1^2 / \int\omega^2}
          \le \gamma_{\max} = \sqrt{4\pi/3} \approx 2.0466,

with ``γ = 0`` exactly when ``ω`` has no degree-1 part and ``γ = γ_max`` exactly when it has
nothing else (a solid-body rotation). Both ``L`` and ``C_2`` are conserved by Euler's
equations, hence ``γ`` is (Modin & Viviani's first integral; the paper writes
``γ = ‖L‖/(R√C₂)`` on a sphere of radius ``R``).

Discrete definitions on su(N)
-----------------------------
With ``W = Q(ω)`` (``Q`` is linear, exact on degree 1 with ``Q(x_a) = iħ S_a``, and an
isometry up to ``κ² = N/4π``: ``⟨Q(f), Q(g)⟩_F = (N/4π) ∫ f g dΩ``), the same integrals of
``Q^{-1}(W)`` are, *exactly*,

.. math::
    L_a(W) = \frac{4\pi}{N}\langle Q(x_a), W\rangle_F
           = \frac{4\pi\hbar}{N}\,\operatorname{Im}\operatorname{tr}(S_a W),\qquad
    C_2(W) = \frac{4\pi}{N}\,\|W\|_F^2 .

``L(W)`` is (up to the factor) Zeitlin's SU(2) momentum map, the projection of ``W`` onto
``span{iS_a}``; the matrix flow conserves it exactly (``tr(S_a[P, ΔP]) = 0`` because
``Δ_N`` is self-adjoint and commutes with ``ad S_a``), and so does every isospectral
midpoint step at its fixed point. ``C_2(W)`` is the plugin's enstrophy Casimir
``tr((iW)²) = ‖W‖_F²`` times ``4π/N``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow

from .laplacian import matrix_size, spin_matrices
from .quantization import degrees_and_orders, hbar, random_sh, sh_to_matrix

Array = NDArray[Any]

#: The largest ``γ`` of any field: ``√(4π/3)``, reached by pure degree-1 vorticity.
GAMMA_MAX = math.sqrt(4 * math.pi / 3)

__all__ = [
    "GAMMA_MAX",
    "angular_momentum",
    "enstrophy_integral",
    "gamma",
    "random_vorticity_gamma",
    "solid_body_rotation",
]


def _square(W: ArrayLike) -> Array:
    W = np.asarray(W)
    if W.ndim < 2 or W.shape[-1] != W.shape[-2]:
        raise lieflow.InputError(f"W must have shape (..., N, N), got {W.shape}")
    return W


def angular_momentum(W: ArrayLike) -> Array:
    r"""Total angular momentum ``L_a = ∫ x_a ω dΩ`` of ``ω = Q^{-1}(W)``, shape ``(..., 3)``.

    Computed as ``(4πħ/N) Im tr(S_a W)`` (module docs), exact for any ``W``: the
    degree-1 content of the field. ``W = Q(a·x)`` (solid-body rotation with vorticity
    ``a·x``) gives ``L = (4π/3) a``.
    """
    W = _square(W)
    N = matrix_size(W.shape[-1])
    S = np.stack(spin_matrices(N))  # (3, N, N)
    # tr(S_a W) = Σ_ij (S_a)_ij W_ji
    traces = np.einsum("aij,...ji->...a", S, W)
    return (4 * math.pi * hbar(N) / N) * traces.imag


def enstrophy_integral(W: ArrayLike) -> Array:
    """``C_2 = ∫ ω² dΩ = (4π/N) ‖W‖_F²`` of ``ω = Q^{-1}(W)``, shape ``W.shape[:-2]``."""
    W = _square(W)
    N = matrix_size(W.shape[-1])
    return (4 * math.pi / N) * np.sum(np.abs(W) ** 2, axis=(-2, -1))


def gamma(W: ArrayLike) -> Array:
    r"""Modin & Viviani's first integral ``γ = ‖L‖ / √C₂`` of ``ω = Q^{-1}(W)`` (unit
    sphere), in ``[0, √(4π/3)]``; shape ``W.shape[:-2]``.

    Raises
    ------
    lieflow.InputError
        ``W`` is zero (``γ`` is undefined for a fluid at rest).
    """
    W = _square(W)
    c2 = enstrophy_integral(W)
    if np.any(c2 == 0):
        raise lieflow.InputError("gamma is undefined for W = 0 (a fluid at rest)")
    return np.asarray(np.linalg.norm(angular_momentum(W), axis=-1) / np.sqrt(c2))


def solid_body_rotation(W: ArrayLike) -> Array:
    r"""Angular velocity ``Ω = 3L/(8π)`` of the solid-body part ``ω_1 = 2Ω · x`` of
    ``ω = Q^{-1}(W)``, shape ``(..., 3)``.

    Since ``L`` is conserved, ``ω_1`` is a steady rotation of the whole fluid; in the frame
    that turns with it the same flow is Euler's equation on a sphere rotating at ``Ω``
    with ``W`` its absolute vorticity (``EulerZeitlin(rotation=Ω_z)`` when ``Ω`` is along
    ``z``: then ``B(W) = Δ_N^{-1}(W - Q(2Ω_z cos θ))/ħ`` has no solid-body part, which is
    what makes large ``γ`` stiff for a fixed-point iteration in the inertial frame).
    """
    return (3 / (8 * math.pi)) * angular_momentum(W)


def _band(N: int, degrees: Sequence[int]) -> tuple[int, int]:
    try:
        lo, hi = (int(d) for d in degrees)
    except (TypeError, ValueError):
        lo = hi = -1
    if isinstance(degrees, (str, bytes)) or not 2 <= lo <= hi < N:
        raise lieflow.InputError(
            f"degrees must be a pair (l_min, l_max) with 2 <= l_min <= l_max < N = {N}, got "
            f"{degrees!r}. To fix: pass e.g. degrees=(2, {min(10, N - 1)}); degree 1 is set "
            "by gamma"
        )
    return lo, hi


def random_vorticity_gamma(
    N: int,
    gamma: float,
    seed: int | np.random.Generator | None = None,
    *,
    degrees: Sequence[int] = (2, 10),
    rms: float = 1.0,
    axis: Sequence[float] | None = None,
) -> Array:
    r"""A seeded random smooth vorticity matrix in su(N) with ``γ(W) = gamma`` and
    root-mean-square vorticity ``rms`` (``C_2 = 4π rms²``).

    The field is ``ω = ω_1 + ω_r``:

    * ``ω_r``: i.i.d. standard complex normal coefficients ``ω_lm`` in the band
      ``l_min <= l <= l_max`` (``degrees``; real for ``m = 0``, completed so that the field is
      real) — a flat enstrophy spectrum over a few intermediate degrees, the recipe of
      Dritschel, Qi & Marston (2015) — scaled to ``∫ω_r² dΩ = C_2 (1 - 3γ²/4π)``;
    * ``ω_1 = b · x``, the solid-body rotation with angular momentum ``L = (4π/3) b``,
      ``‖L‖ = γ √C₂``, about a uniformly random axis (so ``∫ω_1² dΩ = 3‖L‖²/4π``).

    Both parts come from one generator seeded by ``seed`` (the axis drawn first), so the
    fields of one seed at different ``gamma`` share their shape and axis: an ensemble over
    ``gamma × seed`` compares like with like.

    Parameters
    ----------
    N : int
        Matrix size (``degrees`` must be ``< N``).
    gamma : float
        ``0 <= gamma <= √(4π/3)`` (:data:`GAMMA_MAX`; zero: no angular momentum).
    seed : int, Generator or None
        Seed of the random field.
    degrees : (int, int)
        The band ``(l_min, l_max)`` of ``ω_r``, ``2 <= l_min <= l_max < N``.
    rms : float
        Root-mean-square vorticity ``√(C_2/4π) > 0`` (sets the time unit; ``γ`` does not
        depend on it).
    axis : 3 floats, optional
        Direction of ``L`` (default: uniformly random, drawn from the generator either way
        so that ``ω_r`` does not depend on it). ``axis = (0, 0, 1)`` puts the solid-body
        part on the ``z`` axis, where :func:`solid_body_rotation` gives the rotation rate of
        the frame that co-rotates with it.

    Returns
    -------
    ndarray, shape (N, N), complex128
        Skew-Hermitian and traceless; ``gamma(W)`` equals ``gamma`` to roundoff.
    """
    N = matrix_size(N)
    lo, hi = _band(N, degrees)
    g = float(gamma)
    if not (math.isfinite(g) and 0 <= g <= GAMMA_MAX * (1 + 1e-12)):
        raise lieflow.InputError(
            f"gamma must be in [0, sqrt(4 pi/3) = {GAMMA_MAX:.6f}] (its largest value, a "
            f"solid-body rotation), got {gamma!r}"
        )
    if not (math.isfinite(rms) and rms > 0):
        raise lieflow.InputError(f"rms must be finite and positive, got {rms!r}")
    g = min(g, GAMMA_MAX)
    rng = np.random.default_rng(seed)
    drawn = rng.standard_normal(3)
    direction = drawn if axis is None else np.asarray(axis, dtype=float)
    if direction.shape != (3,) or not np.all(np.isfinite(direction)) or not direction.any():
        raise lieflow.InputError(f"axis must be a nonzero vector of 3 finite numbers, got {axis!r}")
    direction = direction / np.linalg.norm(direction)
    c2 = 4 * math.pi * rms**2
    coeffs = random_sh(N, hi, rng)
    l, _ = degrees_and_orders(N)
    coeffs[l < lo] = 0.0
    rest = 1.0 - (g / GAMMA_MAX) ** 2  # share of C_2 outside degree 1
    coeffs *= math.sqrt(c2 * rest / float(np.sum(np.abs(coeffs) ** 2)))
    W = sh_to_matrix(coeffs)
    b = (3 / (4 * math.pi)) * g * math.sqrt(c2) * direction  # L = (4π/3) b, ‖L‖ = γ √C₂
    S = spin_matrices(N)
    W += 1j * hbar(N) * sum(ba * Sa for ba, Sa in zip(b, S, strict=True))  # Q(b·x), exact
    diag = np.einsum("ii->i", W)  # remove the roundoff trace of the l >= 1 harmonics
    diag -= np.mean(diag)
    return W
