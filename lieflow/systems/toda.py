"""The periodic Toda lattice in Lax form, extended to a Lie–Poisson system on gl(n)."""

from __future__ import annotations

import attrs
import numpy as np

from ..algebras import GL, Array
from ..errors import InputError
from .base import IsospectralSystem

#: The paper's initial condition for n = 4 (eigenvalues ±1, ±sqrt 5).
PAPER_W0 = np.array(
    [[-1.0, -1.0, 0.0, 1.0], [-1.0, 1.0, 1.0, 0.0], [0.0, 1.0, -1.0, -1.0], [1.0, 0.0, -1.0, 1.0]]
)


def _at_least_three(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 3:
        raise InputError(f"the periodic Toda lattice needs n >= 3 sites, got {n!r}")
    return int(n)


@attrs.frozen(eq=False)
class PeriodicToda(IsospectralSystem):
    r"""Periodic Toda lattice on gl(n) with the paper's B map (SPEC §3, 1-based indices):

    .. math::
        B_{i,i+1} = W_{i,i+1},\ B_{i+1,i} = -W_{i+1,i},\ B_{1,n} = -W_{1,n},\ B_{n,1} = W_{n,1},

    all other entries zero, and :math:`\eta(W) = 2\,\mathrm{tr}(W^2) - \tfrac12
    \mathrm{tr}(W^T B(W))`. ``B`` is fed exactly as written (SPEC §3 explains why).
    For symmetric ``W`` the energy ``2 tr W^2`` is a spectral invariant, so isospectral
    schemes conserve it to roundoff.
    """

    n: int = attrs.field(default=4, converter=_at_least_three)
    sign: np.ndarray = attrs.field(init=False)
    linear_B = True
    casimir_powers = (1, 2, 3, 4)

    @sign.default
    def _sign(self) -> np.ndarray:
        n = self.n
        s = np.zeros((n, n))
        i = np.arange(n - 1)
        s[i, i + 1] = 1.0
        s[i + 1, i] = -1.0
        s[0, n - 1] = -1.0
        s[n - 1, 0] = 1.0
        return s

    @property
    def algebra(self) -> GL:
        return GL(self.n)

    def random_state(self, seed: int | np.random.Generator | None = None) -> Array:
        """A random symmetric matrix of unit norm (the Flaschka phase space)."""
        X = np.random.default_rng(seed).standard_normal((self.n, self.n))
        S = X + X.T
        return S / np.linalg.norm(S)

    def B(self, W: Array) -> Array:
        return W * self.sign

    @property
    def hadamard_factor(self) -> Array:
        """``S = sign``: :math:`B(W) = S \\odot W` (SPEC §3); a copy."""
        return self.sign.copy()

    def hamiltonian(self, W: Array) -> Array:
        tr_W2 = np.einsum("...ij,...ji->...", W, W)
        return 2.0 * tr_W2 - 0.5 * np.sum(W * self.B(W), axis=(-2, -1))
