"""The periodic Toda lattice in Flaschka's Lax form: symmetric states in gl(n)."""

from __future__ import annotations

from typing import Any

import attrs
import numpy as np
from numpy.typing import ArrayLike

from ..algebras import GL, Array, transpose
from ..backends import is_foreign_array, is_numpy, namespace
from ..errors import InputError
from .base import IsospectralSystem, read_only, table_like

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
    r"""Periodic Toda lattice in Flaschka's Lax form (SPEC §3), states symmetric ``n×n``.

    The paper's map (1-based indices; ``gl_gradient=False``, the default):

    .. math::
        B_{i,i+1} = W_{i,i+1},\ B_{i+1,i} = -W_{i+1,i},\ B_{1,n} = -W_{1,n},\ B_{n,1} = W_{n,1},

    all other entries zero, i.e. ``B(W) = S ⊙ W`` with the skew sign pattern ``S``, and
    :math:`\eta(W) = 2\,\mathrm{tr}(W^2) - \tfrac12 \mathrm{tr}(W^T B(W))` (fed exactly as
    written; SPEC §3 explains why).

    **Phase space.** The symmetric matrices: for symmetric ``W``, ``B(W)`` is skew, the
    flow is isospectral by orthogonal conjugation and stays symmetric. :meth:`project`
    is the symmetric part ``(W + W^T)/2``. The symmetric subspace is *transversally
    unstable* under the paper's ``B`` (an asymmetry of 1e-12 grows about 0.1 per unit
    time in the exact flow), so integrators project every new state back onto it.

    **Where it is Lie–Poisson.** The paper's ``B`` is *not* a gradient on gl(n): the map
    ``W ↦ B(W)^T`` is anti-self-adjoint for the Frobenius pairing, so no ``η`` on gl(n)
    has ``(∇η)^T = B``, and the isospectral scheme with this ``B`` is not a Poisson map of
    gl(n)*. On symmetric ``W`` however ``B(W) = (∇\tilde\eta(W))^T`` with

    .. math:: \tilde\eta(W) = -\tfrac12 \mathrm{tr}(W^T B(W)) = -\tfrac12\sum_{ij} S_{ij}W_{ij}^2,

    the gradient taken in all of gl(n). ``η̃`` is the gl(n) Hamiltonian of the *gradient
    extension* ``B̃(W) = (∇η̃)^T = S ⊙ W^T`` (``gl_gradient=True``), which agrees with the
    paper's ``B`` on symmetric matrices. With ``B̃`` the scheme is a Lie–Poisson map of
    gl(n)* (tested by finite differences of the Poisson tensor), it maps symmetric
    matrices to symmetric matrices, and there it is the paper's map (the stage values are
    symmetric at the fixed point, where ``B̃ = B``). So on the symmetric phase space the
    paper's scheme is the restriction of a gl(n) Lie–Poisson integrator with Hamiltonian
    ``η̃``. The paper's ``η = η̃ + 2 tr W²`` differs from ``η̃`` by a Casimir of gl(n):
    the same continuous flow, but a different discrete map (``B + 4W``; its fixed point
    diverges at ``h = 0.1``). ``η̃`` vanishes on symmetric matrices; the paper's ``η``
    equals ``2 tr W²`` there, a spectral invariant, so every isospectral scheme conserves
    it to roundoff and the Toda energy plot measures roundoff, not order.

    Parameters
    ----------
    n : int
        Number of sites, ``>= 3``.
    gl_gradient : bool
        Use the gradient extension ``B̃(W) = S ⊙ W^T = (∇η̃)^T`` instead of the paper's
        ``B``; the phase space is then all of gl(n) (a Lie–Poisson
        system there), and :meth:`project` is the identity. Same trajectories from
        symmetric initial data. Not supported by the compiled engine.
    """

    n: int = attrs.field(default=4, converter=_at_least_three)
    gl_gradient: bool = attrs.field(default=False, validator=attrs.validators.instance_of(bool))
    sign: np.ndarray = attrs.field(init=False)
    #: gl(n), built once (the schemes read it every iteration).
    algebra: GL = attrs.field(init=False, repr=False)
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
        return read_only(s)

    @property
    def name(self) -> str:
        return "PeriodicToda(gl_gradient=True)" if self.gl_gradient else "PeriodicToda"

    @algebra.default
    def _algebra(self) -> GL:
        return GL(self.n)

    def project(self, W: Array) -> Array:
        """The symmetric part ``(W + W^T)/2`` (the identity with ``gl_gradient=True``)."""
        W = W if is_foreign_array(W) else np.asarray(W)
        if self.gl_gradient:
            return W
        if not is_numpy(W):  # another array library (lieflow.backends)
            return 0.5 * (W + transpose(W))
        out = W + W.swapaxes(-1, -2)
        if out.dtype.kind not in "fc":  # integer data: a float result
            return 0.5 * out
        out *= 0.5  # in place: the bits of 0.5 * (W + W^T), one temporary fewer
        return out

    def project_stage(self, W: Array) -> Array:
        """Same as :meth:`project`: the symmetric matrices are a linear space."""
        return self.project(W)

    def validate(self, W0: ArrayLike, tol: float = 1e-12) -> Array:
        """Check an initial condition and return it as a fresh array.

        Besides membership in gl(n) (:class:`lieflow.AlgebraError` otherwise), ``W0`` must
        be symmetric — the phase space; the scheme would otherwise integrate its symmetric
        part, silently — to relative tolerance ``max(tol, 64 eps)`` in the Frobenius
        norm: ``||W0 - W0^T|| / (2 ||W0||)`` (:meth:`phase_space_distance`). Any ``W0``
        with ``gl_gradient=True``, whose phase space is all of gl(n).

        Raises
        ------
        InputError
            If ``W0`` is not symmetric.
        """
        W = self.algebra.validate(W0, name="W0", tol=tol)
        if self.gl_gradient:
            return W
        limit = max(tol, 64 * float(np.finfo(W.real.dtype).eps))
        distance = float(np.max(self.phase_space_distance(W), initial=0.0))
        if distance > limit:
            raise InputError(
                f"W0: the periodic Toda lattice needs a symmetric W0 (Flaschka's phase "
                f"space), but its antisymmetric part has relative size {distance:.2e} "
                f"(tolerance {limit:.0e}). To fix: pass a symmetric matrix, e.g. "
                "(W0 + W0.T) / 2, or set gl_gradient=True (in a configuration: [system] "
                "params = { gl_gradient = true }) for the flow on all of gl(n)"
            )
        return W

    def random_state(self, seed: int | np.random.Generator | None = None) -> Array:
        """A random symmetric matrix of unit norm (the Flaschka phase space)."""
        X = np.random.default_rng(seed).standard_normal((self.n, self.n))
        S = X + X.T
        return S / np.linalg.norm(S)

    def B(self, W: Array) -> Array:
        if self.gl_gradient:
            return transpose(W) * table_like(self.sign, W)
        return W * table_like(self.sign, W)

    @property
    def hadamard_factor(self) -> Array | None:
        """``S = sign``: :math:`B(W) = S \\odot W` (SPEC §3); a copy. ``None`` for the
        gradient extension (``B̃(W) = S ⊙ W^T`` is not of that form)."""
        return None if self.gl_gradient else self.sign.copy()

    def compiled_B(self, shift: float = 0.0) -> tuple[Any, Array] | None:
        """``S ⊙ (W + W^T)/2`` compiled: ``B`` of the symmetric part of a stage value.

        ``None`` for the gradient extension, and with a Casimir shift: ``B - cW`` is not
        skew, so the stage values are not symmetric, and the loops' commutator update uses
        the stage value where the numpy path uses its symmetric part."""
        if self.gl_gradient or shift != 0.0:
            return None
        return "hadamard_B_symmetric", self.sign.ravel().copy()  # lieflow's own, by name

    def compiled_project(self) -> tuple[Any, Array] | None:
        """The symmetric part, compiled: the compiled engine symmetrizes every step."""
        if self.gl_gradient:
            return None
        return "symmetric_part", np.zeros(0)

    def hamiltonian(self, W: Array) -> Array:
        """The paper's ``η(W) = 2 tr W² - ½ tr(W^T B(W))`` (``= 2 tr W²`` on symmetric W),
        for both variants: ``η = η̃ + 2 tr W²`` (:meth:`gradient_hamiltonian` plus a
        Casimir), so its relative error is a meaningful diagnostic where ``η̃ = 0``."""
        if is_foreign_array(W):  # another array library (lieflow.backends)
            tr_W2 = namespace(W).sum(W * transpose(W), axis=(-2, -1))
        else:
            W = np.asarray(W)
            tr_W2 = np.einsum("...ij,...ji->...", W, W)
        return 2.0 * tr_W2 + self.gradient_hamiltonian(W)

    def gradient_hamiltonian(self, W: Array) -> Array:
        r"""``η̃(W) = -½ Σ S_ij W_ij²``: the gl(n) function whose gradient gives ``B``.

        ``(∇η̃(W))^T = S ⊙ W^T``, which is the paper's ``B(W)`` for symmetric ``W`` (and
        the extension's ``B̃`` everywhere). Zero on symmetric matrices; it differs from the
        paper's ``η`` by the gl(n) Casimir ``2 tr W²``.
        """
        W = W if is_foreign_array(W) else np.asarray(W)
        xp = namespace(W)
        out: Array = -0.5 * xp.sum(W * W * table_like(self.sign, W), axis=(-2, -1))
        return out
