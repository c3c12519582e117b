r"""How fast the fixed-point iteration of a scheme's stage equations contracts, estimated from
the state: what a step that diverged says about a step size that converges.

Near the solution the stage map of a tableau ``A`` acts on an error ``δ`` of the stages as

.. math:: \delta_i \mapsto h \sum_j a_{ij}\,\big([B_j, \delta_j] + [B'(W_j)\delta_j, W_j]\big)
          + O(h^2)

(SPEC §4; the midpoint rule: ``a = 1/2``). For the stiff, grid-scale part of ``δ`` the first
term dominates (the second is smoothing where ``B`` is, as Euler–Zeitlin's inverse
Laplacian), and with every ``B_j ≈ B(W)`` the linear map is ``h A ⊗ ad_B``, whose spectral
radius is ``h ρ(A) ρ(ad_B)``. The eigenvalues of ``ad_B`` are the differences
``λ_j - λ_k`` of those of ``B``, so ``ρ(ad_B) = s``, the diameter of ``B``'s spectrum (for a
skew-Hermitian ``B``, the spread ``λ_max - λ_min`` of ``iB``'s eigenvalues). Hence

.. math:: \rho \approx h\, \rho(A)\, s, \qquad h_{\max} \approx \frac{1}{\rho(A)\, s},

with ``ρ(A)`` the spectral radius of the tableau's coefficient matrix (a composition of
midpoint steps: ``max_i |b_i| / 2``, its triangular ``A``'s largest diagonal entry; Gauss–
Legendre with ``s`` stages: the largest modulus of ``A``'s eigenvalues). Measured on the smooth
Euler–Zeitlin field of ``benchmarks.device`` (N = 64–256, h = 1/128–1/16), the iteration
converged wherever ``h ρ(A) s < 0.9`` and failed from about ``1.0``–``1.4`` on: the estimate
is conservative by at most that factor.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..algebras import Array
from ..backends import to_numpy

__all__ = ["hint", "spectral_diameter", "step_size_limit"]


def spectral_diameter(B: Array, skew: bool) -> float:
    """``max |λ_j - λ_k|`` over the eigenvalues of ``B`` (a stack: the largest over it):
    ``λ_max - λ_min`` of the Hermitian ``iB`` for a skew(-Hermitian) ``B``; for any other
    ``B`` the diameter of its (complex) spectrum."""
    B = np.asarray(to_numpy(B))
    B = B.reshape(-1, *B.shape[-2:])
    if skew:
        real = np.linalg.eigvalsh(1j * B)
        return float(np.max(real[:, -1] - real[:, 0]))
    ev = np.linalg.eigvals(B)
    return float(np.max(np.abs(ev[:, :, None] - ev[:, None, :])))


def step_size_limit(system: Any, scheme: Any, W: Array) -> tuple[float, float, float] | None:
    """``(h_max, ρ(A), s)``: the step size below which the fixed-point iteration of
    ``scheme``'s stage equations contracts at ``W`` (module docstring), the tableau's
    spectral radius and ``B(W)``'s spectral diameter; ``None`` for a scheme without a
    tableau or a ``B`` whose spectrum cannot be computed."""
    tableau = getattr(scheme, "tableau", None)
    A = getattr(tableau, "A", None)
    if A is None:
        return None
    try:
        rho = float(np.max(np.abs(np.linalg.eigvals(np.asarray(A, dtype=float)))))
        s = spectral_diameter(system.B(W), bool(system.algebra.skew))
    except (np.linalg.LinAlgError, ValueError, TypeError, AttributeError):
        return None
    if not (rho > 0 and s > 0 and np.isfinite(s)):
        return None
    return 1.0 / (rho * s), rho, s


def hint(system: Any, scheme: Any, W: Array, h: float) -> str | None:
    """The sentence a failed fixed-point step adds to its error: the estimated contraction
    per update at ``h`` and the step size below which it converges (``None`` where no
    estimate exists)."""
    limit = step_size_limit(system, scheme, W)
    if limit is None:
        return None
    h_max, rho, s = limit
    return (
        f"Estimated from the state: the fixed point contracts by about h ρ(A) s = "
        f"{h * rho * s:.3g} per update at h = {h:.6g} (ρ(A) = {rho:.3g} of the tableau, "
        f"s = {s:.4g} the spread of B(W)'s eigenvalues), so it converges for h below about "
        f"{h_max:.3g}: try h = {_round_down(h_max / 2):.6g} or less."
    )


def _round_down(x: float) -> float:
    """The largest ``2^-k`` not above ``x`` (a step size that divides unit time), or ``x``
    itself when it is at least 1."""
    if x >= 1:
        return x
    return float(2.0 ** np.floor(np.log2(x)))
