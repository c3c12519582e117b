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
are their power sums ``C_k = Σ λ_j^k (-1)^k = tr((iW)^k)`` (``C_2 = ||W||_F²``, exact where
``Σ λ_j²`` carries the eigensolver's error: :func:`casimirs_from_levels`).

The spectra need the squares ``Σ_m |ζ_lm|²`` by degree, not the coefficients:
:func:`matrix_squares_by_degree` gets them from the matrix in one compiled pass (the
harmonic recurrences fused with the products, tables built once per ``N``), 0.04–0.09
midpoint steps (h = 1/N) per state at N = 64–512; one sample of :func:`snapshot` costs
0.27–0.38 steps, 0.15–0.28 of it the eigenvalue problem of the levels, 2.5–6 complex N×N
products (``benchmarks/suites/euler_zeitlin.py``).

Everything here takes one state ``(N, N)`` or a stack ``(..., N, N)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow

from . import _recurrences as _rec
from .quantization import kappa, matrix_to_sh

Array = NDArray[Any]

#: Casimir powers stored by :meth:`EulerZeitlin.extra_diagnostics` (``tr((iW)^k)``).
CASIMIR_POWERS = (2, 3, 4, 5, 6, 8)


def _squares_by_degree(coeffs: Array) -> Array:
    """``Σ_m |c_lm|²`` for each degree ``l`` (indices ``l²..(l+1)²-1``), shape ``(..., N)``."""
    N = math.isqrt(coeffs.shape[-1]) if coeffs.ndim else 0
    if coeffs.ndim < 1 or N * N != coeffs.shape[-1] or N < 1:
        raise lieflow.InputError(f"coefficients must have shape (..., N²), got {coeffs.shape}")
    return np.add.reduceat(np.abs(coeffs) ** 2, np.arange(N) ** 2, axis=-1)


def _energy_factor(N: int, lamb: float) -> Array:
    """``(l(l+1) + F) / (2 (l(l+1))²)`` for ``l = 0..N-1`` (0 at ``l = 0``)."""
    l = np.arange(N, dtype=float)
    lam = l * (l + 1)
    return np.divide(lam + lamb, 2 * lam * lam, out=np.zeros_like(lam), where=lam > 0)


def enstrophy_spectrum(coeffs: ArrayLike) -> Array:
    """``Z(l) = ½ Σ_m |ζ_lm|²``, ``l = 0..N-1``, from vorticity coefficients ``(..., N²)``."""
    return 0.5 * _squares_by_degree(np.asarray(coeffs))


def energy_spectrum(coeffs: ArrayLike, lamb: float = 0.0) -> Array:
    r"""``E(l) = (l(l+1) + F) / (2 (l(l+1))²) Σ_m |ζ_lm|²`` (module docs), ``E(0) = 0``,
    from the coefficients of the *relative* vorticity ``ζ``, shape ``(..., N)``."""
    S = _squares_by_degree(np.asarray(coeffs))
    return S * _energy_factor(S.shape[-1], lamb)


def matrix_squares_by_degree(W: ArrayLike, tables: _rec.DiagonalTables | None = None) -> Array:
    r"""``S(l) = Σ_{|m|<=l} |ω_lm|²``, ``l = 0..N-1``, of the field ``Q^{-1}(W)`` of each
    matrix of ``W`` (``(..., N, N)``; its skew-Hermitian part, i.e. ``W`` itself in su(N)),
    without forming the coefficients: shape ``(..., N)``.

    On diagonal ``m`` the coefficients are ``ω_lm = -(i/κ) (V_m^T d_m)_{l-m}``
    (:func:`~lieflow_zeitlin.matrix_to_sh`), and for a skew-Hermitian ``W``
    ``|ω_{l,-m}| = |ω_lm|``, so only the lower diagonals are read; the rows of ``V_m`` come
    from the recurrence of :mod:`lieflow_zeitlin._recurrences`, fused with the products,
    with the tables (starting rows and column scales) built once per ``N``
    (``tables``, :class:`~lieflow_zeitlin._recurrences.DiagonalTables`; an
    :class:`~lieflow_zeitlin.EulerZeitlin` keeps them). Cost: about ``N³/3`` entries of a
    few flops each, 0.04 / 0.2 / 1.6 ms at N = 64 / 128 / 256 (one core). Without numba,
    or above ``N = 1400``, the coefficients are formed (:func:`matrix_to_sh`).
    """
    W = np.asarray(W)
    if W.ndim < 2 or W.shape[-1] != W.shape[-2]:
        raise lieflow.InputError(f"W must have shape (..., N, N), got {W.shape}")
    N = W.shape[-1]
    if tables is None and _rec.have_numba() and 2 <= N <= _rec.MAX_N:
        tables = _rec.DiagonalTables.of(N)
    if tables is None:
        return _squares_by_degree(matrix_to_sh(W))
    if tables.N != N:
        raise lieflow.InputError(f"tables for N = {tables.N} given for matrices of size {N}")
    flat = np.ascontiguousarray(W.reshape(-1, N, N), dtype=np.complex128)
    S = tables.squares_by_degree(flat) / kappa(N) ** 2
    return S.reshape(*W.shape[:-2], N)


def _state(system: Any, W: ArrayLike, what: str) -> Array:
    """``W`` validated as a state (stack) of the Euler–Zeitlin ``system``."""
    from .system import EulerZeitlin

    if not isinstance(system, EulerZeitlin):
        raise lieflow.InputError(
            f"{what} needs an EulerZeitlin system (the state's N, rotation and Lamb "
            f"parameter), got a {type(system).__name__}"
        )
    return lieflow.SU(system.N).validate(W, name="W")


def _spectra(system: Any, W: Array) -> dict[str, Array]:
    """:func:`spectra` of states ``W`` already known to be in su(N)."""
    S = matrix_squares_by_degree(system.relative(W), system.diagonal_tables)
    return {
        "energy_spectrum": S * _energy_factor(system.N, system.lamb),
        "enstrophy_spectrum": 0.5 * S,
    }


def spectra(system: Any, W: ArrayLike) -> dict[str, Array]:
    """``{"energy_spectrum": E(l), "enstrophy_spectrum": Z(l)}`` of the relative vorticity of
    the state(s) ``W`` of ``system`` (an :class:`~lieflow_zeitlin.EulerZeitlin`).

    Raises
    ------
    lieflow.InputError
        If ``system`` is not an Euler–Zeitlin system, or ``W`` is not an ``N×N`` matrix (or
        a stack of them) in su(N) for the system's ``N`` (:class:`lieflow.AlgebraError`).
    """
    return _spectra(system, _state(system, W, "spectra"))


def vorticity_levels(W: ArrayLike) -> Array:
    """The eigenvalues of the Hermitian ``-iW`` in ascending order, shape ``(..., N)``:
    the discrete vorticity distribution (each level stands for an area ``4π/N``).

    Only the lower triangle of ``-iW`` is read (:func:`numpy.linalg.eigvalsh`): for ``W``
    skew-Hermitian to roundoff ``δ`` (a run's states) the levels are those of its
    Hermitian part to ``δ``, below the eigensolver's own error ``~ N ε ||W||``.
    """
    return np.linalg.eigvalsh(-1j * np.asarray(W))


def casimirs_from_levels(
    levels: ArrayLike,
    powers: Sequence[int] = CASIMIR_POWERS,
    *,
    square_norm: ArrayLike | None = None,
) -> Array:
    """``C_k = tr((iW)^k) = Σ_j (-λ_j)^k`` from the levels ``λ`` of :func:`vorticity_levels`,
    last axis indexes ``powers``; ``C_2`` is ``square_norm`` (``||W||_F²``) when given.

    The powers ``(-λ)^1 .. (-λ)^{max k}`` come from one running product and one sum. The
    sums inherit the eigensolver's error ``~ N ε ||W||``: measured against exact traces
    (integer arithmetic on the same floats, N = 64–256), ``|ΔC_k| / ||W||_F^k`` is
    ``<= 2e-16`` for ``k >= 3`` but up to ``2e-15`` for ``C_2 = Σλ²`` (the errors of the
    ``N`` levels add up), above the drift a run should resolve; ``C_2 = ||W||_F²`` is exact
    to ``2e-16``, hence ``square_norm``.
    """
    lam = np.asarray(levels, dtype=float)
    powers = tuple(int(k) for k in powers)
    if any(k < 1 for k in powers):
        raise lieflow.InputError(f"Casimir powers must be positive integers, got {powers}")
    if not powers:
        return np.zeros((*lam.shape[:-1], 0))
    running = np.broadcast_to(-lam[..., None], (*lam.shape, max(powers)))
    sums = np.multiply.accumulate(running, axis=-1).sum(axis=-2)
    out = sums[..., [k - 1 for k in powers]]
    if square_norm is not None and 2 in powers:
        out[..., powers.index(2)] = square_norm
    return out


def _snapshot(
    system: Any, W: Array, powers: Sequence[int] = CASIMIR_POWERS, *, levels: bool = True
) -> dict[str, Array]:
    """:func:`snapshot` of states ``W`` already known to be in su(N) (without the levels and
    Casimirs unless ``levels``)."""
    out = _spectra(system, W)
    out["energy"] = out["energy_spectrum"].sum(axis=-1)
    out["enstrophy"] = out["enstrophy_spectrum"].sum(axis=-1)
    if levels:
        lam = vorticity_levels(W)
        out["vorticity_levels"] = lam
        out["casimirs"] = casimirs_from_levels(lam, powers, square_norm=system.enstrophy(W))
    return out


def snapshot(system: Any, W: ArrayLike, powers: Sequence[int] = CASIMIR_POWERS) -> dict[str, Array]:
    """All diagnostics of one state: the spectra, ``energy = Σ E(l)``,
    ``enstrophy = Σ Z(l)`` (relative vorticity, fluid units), the ``vorticity_levels`` and
    ``casimirs`` ``tr((iW)^k)`` for ``powers`` (of the state ``W = Q(q)`` itself): one
    Hermitian eigenvalue problem serves the levels and every Casimir.

    Raises
    ------
    lieflow.InputError
        As :func:`spectra`.
    """
    return _snapshot(system, _state(system, W, "snapshot"), powers)


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
