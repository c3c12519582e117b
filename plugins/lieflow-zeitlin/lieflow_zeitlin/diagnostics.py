r"""Diagnostics of 2D turbulence on the sphere: spectra by degree, Casimirs, the vorticity
distribution, and time averages.

Definitions (fluid units, on the unit sphere; ``ζ = Δψ`` the relative vorticity with
coefficients ``ζ_lm``, ``F`` the Lamb parameter, ``ψ_lm = -ζ_lm / l(l+1)``)

.. math::
    Z(l) = \tfrac12 \sum_{|m|\le l} |\zeta_{lm}|^2, \qquad
    E(l) = \tfrac12 \sum_{|m|\le l} \big(l(l+1) + F\big)\,|\psi_{lm}|^2
         = \frac{l(l+1) + F}{2\,(l(l+1))^2} \sum_m |\zeta_{lm}|^2,

so that by Parseval ``Σ_l Z(l) = Z = ½∫ζ² dΩ`` (the enstrophy) and
``Σ_l E(l) = E = ½∫(|∇ψ|² + Fψ²) dΩ`` (the energy; for ``F = 0``,
``E(l) = Z(l) / (l(l+1))``). ``E`` equals the system's Hamiltonian times ``4π/(σN)``
(:class:`~lieflow_zeitlin.EulerZeitlin`, whose ``||W||_F²`` enstrophy is ``(N/4π)∫q²``, of
the *potential* vorticity). Degree 0 carries no energy and, for a state in su(N), no
enstrophy.

The *vorticity distribution* is the spectrum of the isospectral variable: the eigenvalues
``λ_1 <= ... <= λ_N`` of the Hermitian ``-iW`` approximate the values of ``q`` (each one
standing for an area ``4π/N``), and isospectral schemes keep them to roundoff; the Casimirs
are their power sums ``C_k = Σ λ_j^k (-1)^k = tr((iW)^k)``.

Everything here takes one state ``(N, N)`` or a stack ``(..., N, N)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow

from .quantization import matrix_to_sh

Array = NDArray[Any]

#: Casimir powers stored by :meth:`EulerZeitlin.extra_diagnostics` (``tr((iW)^k)``).
CASIMIR_POWERS = (2, 3, 4, 5, 6, 8)


def _squares_by_degree(coeffs: Array) -> Array:
    """``Σ_m |c_lm|²`` for each degree ``l`` (indices ``l²..(l+1)²-1``), shape ``(..., N)``."""
    N = math.isqrt(coeffs.shape[-1]) if coeffs.ndim else 0
    if coeffs.ndim < 1 or N * N != coeffs.shape[-1] or N < 1:
        raise lieflow.InputError(f"coefficients must have shape (..., N²), got {coeffs.shape}")
    return np.add.reduceat(np.abs(coeffs) ** 2, np.arange(N) ** 2, axis=-1)


def enstrophy_spectrum(coeffs: ArrayLike) -> Array:
    """``Z(l) = ½ Σ_m |ζ_lm|²``, ``l = 0..N-1``, from vorticity coefficients ``(..., N²)``."""
    return 0.5 * _squares_by_degree(np.asarray(coeffs))


def energy_spectrum(coeffs: ArrayLike, lamb: float = 0.0) -> Array:
    r"""``E(l) = (l(l+1) + F) / (2 (l(l+1))²) Σ_m |ζ_lm|²`` (module docs), ``E(0) = 0``,
    from the coefficients of the *relative* vorticity ``ζ``, shape ``(..., N)``."""
    S = _squares_by_degree(np.asarray(coeffs))
    l = np.arange(S.shape[-1], dtype=float)
    lam = l * (l + 1)
    factor = np.divide(lam + lamb, 2 * lam * lam, out=np.zeros_like(lam), where=lam > 0)
    return S * factor


def spectra(system: Any, W: ArrayLike) -> dict[str, Array]:
    """``{"energy_spectrum": E(l), "enstrophy_spectrum": Z(l)}`` of the relative vorticity of
    the state(s) ``W`` of ``system`` (an :class:`~lieflow_zeitlin.EulerZeitlin`).

    Raises
    ------
    lieflow.InputError
        If ``system`` is not an Euler–Zeitlin system, or ``W`` is not an ``N×N`` matrix (or
        a stack of them) in su(N) for the system's ``N`` (:class:`lieflow.AlgebraError`).
    """
    from .system import EulerZeitlin

    if not isinstance(system, EulerZeitlin):
        raise lieflow.InputError(
            f"spectra needs an EulerZeitlin system (the state's N, rotation and Lamb "
            f"parameter), got a {type(system).__name__}"
        )
    W = lieflow.SU(system.N).validate(W, name="W")
    coeffs = matrix_to_sh(system.relative(W))
    return {
        "energy_spectrum": energy_spectrum(coeffs, system.lamb),
        "enstrophy_spectrum": enstrophy_spectrum(coeffs),
    }


def vorticity_levels(W: ArrayLike) -> Array:
    """The eigenvalues of the Hermitian ``-iW`` in ascending order, shape ``(..., N)``:
    the discrete vorticity distribution (each level stands for an area ``4π/N``)."""
    A = -1j * np.asarray(W)
    A = 0.5 * (A + np.conj(np.swapaxes(A, -1, -2)))  # exactly Hermitian
    return np.linalg.eigvalsh(A)


def casimirs_from_levels(levels: ArrayLike, powers: Sequence[int] = CASIMIR_POWERS) -> Array:
    """``C_k = tr((iW)^k) = Σ_j (-λ_j)^k`` from the levels ``λ`` of :func:`vorticity_levels`,
    last axis indexes ``powers``."""
    lam = np.asarray(levels, dtype=float)
    powers = tuple(int(k) for k in powers)
    if any(k < 1 for k in powers):
        raise lieflow.InputError(f"Casimir powers must be positive integers, got {powers}")
    return np.stack([np.sum((-lam) ** k, axis=-1) for k in powers], axis=-1)


def snapshot(system: Any, W: ArrayLike, powers: Sequence[int] = CASIMIR_POWERS) -> dict[str, Array]:
    """All diagnostics of one state: the spectra, ``energy = Σ E(l)``,
    ``enstrophy = Σ Z(l)`` (relative vorticity, fluid units), the ``vorticity_levels`` and
    ``casimirs`` ``tr((iW)^k)`` for ``powers`` (of the state ``W = Q(q)`` itself)."""
    out = spectra(system, W)
    out["energy"] = out["energy_spectrum"].sum(axis=-1)
    out["enstrophy"] = out["enstrophy_spectrum"].sum(axis=-1)
    levels = vorticity_levels(W)
    out["vorticity_levels"] = levels
    out["casimirs"] = casimirs_from_levels(levels, powers)
    return out


def running_mean(values: ArrayLike, axis: int = 0) -> Array:
    """Cumulative means along ``axis``: row ``k`` is the mean of rows ``0..k`` (the running
    time average of samples taken at a fixed interval)."""
    v = np.asarray(values, dtype=float)
    count = np.arange(1, v.shape[axis] + 1, dtype=float)
    shape = [1] * v.ndim
    shape[axis] = -1
    return np.cumsum(v, axis=axis) / count.reshape(shape)


def time_mean(t: ArrayLike, values: ArrayLike, t_start: float | None = None) -> Array:
    """Mean of the samples ``values`` (rows at times ``t``) with ``t >= t_start`` (all rows
    by default): the time average over a statistically steady window."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(values, dtype=float)
    sel = np.ones(t.shape, bool) if t_start is None else t >= t_start
    if not sel.any():
        raise lieflow.InputError(f"no samples at t >= {t_start} (last sample at t = {t[-1]})")
    return np.asarray(v[sel].mean(axis=0))
