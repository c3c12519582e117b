"""Rigid bodies: the free rigid body on so(3) and Manakov's generalized rigid body on so(n)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import attrs
import numpy as np

from ..algebras import SO, Array, minus_dagger
from ..backends import is_foreign_array, is_numpy, namespace
from ..errors import InputError
from .base import IsospectralSystem, read_only, table_like


def _positive_vector(values: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    """``values`` as a read-only float64 copy, checked positive and finite."""
    arr = np.array(values, dtype=float)
    if arr.ndim != 1 or arr.size < 2 or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise InputError(
            f"{what} must be a 1-D sequence of positive finite numbers, got {values!r}"
        )
    return read_only(arr)


def _moments(values: Sequence[float] | np.ndarray) -> np.ndarray:
    return _positive_vector(values, "moments of inertia")


def _scaled_weights(scale: float) -> Any:
    """The default of a body's field ``scale * weights`` (read-only), made once ``weights``
    is: with ``scale`` -1, -1/2 or 1/2 bit for bit ``-weights``, ``-weights / 2``,
    ``weights / 2`` (a sign and a halving are exact)."""
    return attrs.Factory(lambda body: read_only(scale * body.weights), takes_self=True)


_NEGATIVE_WEIGHTS = _scaled_weights(-1.0)
_NEGATIVE_HALF_WEIGHTS = _scaled_weights(-0.5)
_HALF_WEIGHTS = _scaled_weights(0.5)


class _Body(IsospectralSystem):
    r"""What both bodies share: ``B(W) = F \odot W`` with the constant matrix
    ``F = -weights`` (``self._factor``, and ``self._half_factor = F / 2``), the
    Hamiltonian :math:`\tfrac12 \sum_{ij} w_{ij} W_{ij}^2` and :meth:`stage_B` in one
    pass less than the composition."""

    _factor: np.ndarray
    _half_factor: np.ndarray
    _half_weights: np.ndarray
    weights: np.ndarray

    #: Whether :meth:`stage_B` may take its shortcut: the class keeps this ``B`` and the
    #: default stage projection (a subclass that overrides either gets the composition);
    #: set for each subclass when it is created.
    _stage_shortcut: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._stage_shortcut = (
            cls.B is _Body.B and cls.project_stage is IsospectralSystem.project_stage
        )

    def B(self, W: Array) -> Array:
        return W * table_like(self._factor, W)

    def stage_B(self, W: Array) -> Array:
        r"""``B(P(W))`` at a stage value ``W``, ``P(W) = (W - W^T)/2`` the so(n) stage
        projection: :math:`(W - W^T) \odot (F/2)`, one pass over ``W`` less than
        ``B(P(W))`` and the same bits (``x/2`` and ``F/2`` are exact, so both round the
        product ``(x F)/2`` once; only a subnormal ``x`` could differ). For float64 NumPy
        stages of a class that keeps this ``B`` and the default stage projection
        (:attr:`_stage_shortcut`), else the composition itself."""
        if self._stage_shortcut and type(W) is np.ndarray and W.dtype.char == "d":
            return minus_dagger(W) * self._half_factor
        return self.B(self.project_stage(W))

    @property
    def hadamard_factor(self) -> Array:
        """``S = -weights``: :math:`B(W) = S \\odot W` (SPEC §3)."""
        return -self.weights

    def hamiltonian(self, W: Array) -> Array:
        r""":math:`\eta(W) = \tfrac12 \sum_{ij} w_{ij} W_{ij}^2` as
        :math:`\sum_{ij} (w_{ij}/2) W_{ij}^2`: bit for bit the same (halving one factor of
        each product halves it exactly), one pass less."""
        if not is_numpy(W):  # another array library (lieflow.backends)
            return namespace(W).sum(W * W * table_like(self._half_weights, W), axis=(-2, -1))
        return np.einsum("...ij,...ij,ij->...", W, W, table_like(self._half_weights, W))


def _principal_moments(values: Sequence[float] | np.ndarray) -> np.ndarray:
    arr = _moments(values)
    if arr.size != 3:
        raise InputError(f"inertia needs 3 principal moments, got {arr.size}")
    return arr


@attrs.frozen(eq=False)
class GeneralizedRigidBody(_Body):
    r"""Manakov's generalized rigid body on so(n) (SPEC §3).

    Inertia map :math:`\mathcal I(\Omega) = J\Omega + \Omega J`, ``J = diag(J_1..J_n) > 0``, so

    .. math:: B(W) = -\mathcal I^{-1} W,\qquad (\mathcal I^{-1}W)_{ij} = W_{ij}/(J_i + J_j),

    and :math:`\eta(W) = \tfrac12 \sum_{ij} W_{ij}^2 / (J_i + J_j)`. Casimirs ``tr W^{2k}``.
    The default ``J`` is a small (n = 5) example.
    """

    J: np.ndarray = attrs.field(default=(1.0, 1.3, 1.7, 2.2, 2.8), converter=_moments)
    weights: np.ndarray = attrs.field(init=False)
    #: so(n), built once (``B`` and the schemes read it every iteration).
    algebra: SO = attrs.field(init=False, repr=False)
    #: ``-weights``: ``B(W) = W * factor``, bit for bit ``-W * weights``.
    _factor: np.ndarray = attrs.field(init=False, repr=False, default=_NEGATIVE_WEIGHTS)
    #: ``factor / 2`` (exact): ``B`` of the stage projection (:meth:`_Body.stage_B`).
    _half_factor: np.ndarray = attrs.field(init=False, repr=False, default=_NEGATIVE_HALF_WEIGHTS)
    #: ``weights / 2`` (exact): the Hamiltonian's weights (:meth:`_Body.hamiltonian`).
    _half_weights: np.ndarray = attrs.field(init=False, repr=False, default=_HALF_WEIGHTS)
    linear_B = True
    casimir_powers = (2, 4, 6)

    @weights.default
    def _weights(self) -> np.ndarray:
        return read_only(1.0 / (self.J[:, None] + self.J[None, :]))

    @algebra.default
    def _algebra(self) -> SO:
        return SO(self.J.size)

    def casimirs(self, W: Array) -> Array:
        """``tr W^2``, ``tr W^4``, ``tr W^6`` (those of degree up to ``n``), from two
        products instead of five: ``tr W^{2k} = sum_ij (W^k)_ij (W^k)_ji``, the three sums
        in one ``einsum`` over ``W``, ``W^2``, ``W^3`` stacked (the diagnostics evaluate
        them on every chunk of a run)."""
        if not isinstance(W, np.ndarray):  # numbers, arrays of another library
            return super().casimirs(W)
        n = self.J.size
        factors = [W[..., None, :, :]]
        if n >= 4:
            W2 = W @ W
            factors.append(W2[..., None, :, :])
            if n >= 6:
                factors.append((W2 @ W)[..., None, :, :])
        L = np.concatenate(factors, axis=-3) if len(factors) > 1 else factors[0]
        return np.einsum("...kij,...kji->...k", L, L)

    @classmethod
    def random_inertia(cls, n: int, seed: int | None = None) -> GeneralizedRigidBody:
        """A generalized rigid body with ``J_i`` drawn uniformly from [1, 2) (seeded)."""
        return cls(np.random.default_rng(seed).uniform(1.0, 2.0, size=n))


@attrs.frozen(eq=False)
class RigidBody(_Body):
    r"""The free rigid body on so(3) with principal moments of inertia ``I_1, I_2, I_3``.

    ``W = hat(m)``, ``omega_i = m_i / I_i``, ``B(W) = -hat(omega)`` (the paper's
    :math:`B(W) = -\mathcal I^{-1} W`) and :math:`\eta = m\cdot\omega` (SPEC §3). Entry
    ``(i, j)`` of ``hat(m)`` carries ``m_k`` for the index ``k`` not in ``{i, j}``, so
    ``B(W)_{ij} = -W_{ij} / I_k``.
    """

    inertia: np.ndarray = attrs.field(default=(1.0, 2.0, 3.0), converter=_principal_moments)
    weights: np.ndarray = attrs.field(init=False)
    #: so(3), built once (``B`` and the schemes read it every iteration).
    algebra: SO = attrs.field(init=False, repr=False, factory=lambda: SO(3))
    #: ``-weights``: ``B(W) = W * factor``, bit for bit ``-W * weights``.
    _factor: np.ndarray = attrs.field(init=False, repr=False, default=_NEGATIVE_WEIGHTS)
    #: ``factor / 2`` (exact): ``B`` of the stage projection (:meth:`_Body.stage_B`).
    _half_factor: np.ndarray = attrs.field(init=False, repr=False, default=_NEGATIVE_HALF_WEIGHTS)
    #: ``weights / 2`` (exact): the Hamiltonian's weights (:meth:`_Body.hamiltonian`).
    _half_weights: np.ndarray = attrs.field(init=False, repr=False, default=_HALF_WEIGHTS)
    linear_B = True
    casimir_powers = (2,)

    @weights.default
    def _weights(self) -> np.ndarray:
        inv = 1.0 / self.inertia
        w = np.zeros((3, 3))
        for i, j, k in ((0, 1, 2), (1, 2, 0), (0, 2, 1)):
            w[i, j] = w[j, i] = inv[k]
        return read_only(w)

    def casimirs(self, W: Array) -> Array:
        """``tr W^2 = sum_ij W_ij W_ji`` (``-2 |m|^2``), without a matrix product."""
        if not is_numpy(W):  # another array library (lieflow.backends)
            xp = namespace(W)
            return xp.sum(W * xp.matrix_transpose(W), axis=(-2, -1))[..., None]
        return np.einsum("...ij,...ji->...", W, W)[..., None]


def hat(m: Array) -> Array:
    """The so(3) matrix of a vector: ``hat(m) x = m × x`` (broadcasts over leading axes;
    arrays of any library)."""
    if not is_foreign_array(m):
        m = np.asarray(m)
        out = np.zeros((*m.shape[:-1], 3, 3), dtype=m.dtype)
        out[..., 0, 1], out[..., 0, 2] = -m[..., 2], m[..., 1]
        out[..., 1, 0], out[..., 1, 2] = m[..., 2], -m[..., 0]
        out[..., 2, 0], out[..., 2, 1] = -m[..., 1], m[..., 0]
        return out
    xp = namespace(m)  # another array library: no item assignment, the entries stacked
    zero = xp.zeros_like(m[..., 0])
    x, y, z = m[..., 0], m[..., 1], m[..., 2]
    rows = [(zero, -z, y), (z, zero, -x), (-y, x, zero)]
    return xp.stack([xp.stack(row, axis=-1) for row in rows], axis=-2)


def vee(W: Array) -> Array:
    """Inverse of :func:`hat` (arrays of any library)."""
    xp = namespace(W) if is_foreign_array(W) else np
    W = W if xp is not np else np.asarray(W)
    return xp.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)
