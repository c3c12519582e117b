r"""K point vortices on the unit sphere as an isospectral Lie–Poisson system on so(3)^K.

Equations
---------
Vortex ``i`` sits at ``x_i`` on the unit sphere with strength (circulation) ``Γ_i ≠ 0``. The
point-vortex equations on the sphere of radius 1 (Bogomolov 1977; Kidambi & Newton 1998,
eq. 2.1; Newton 2001, §4.1) are

.. math::
    \dot x_i = \frac{1}{4\pi} \sum_{j\ne i} \Gamma_j\,
               \frac{x_j \times x_i}{1 - x_i\cdot x_j},

Hamiltonian (the Kirchhoff–Routh function; ``1 - x_i·x_j = |x_i - x_j|^2 / 2``)

.. math:: H = -\frac{1}{4\pi} \sum_{i<j} \Gamma_i\Gamma_j \log(1 - x_i\cdot x_j).

Isospectral form
----------------
With momenta ``m_i = Γ_i x_i`` and ``W = blockdiag(hat(m_1), ..., hat(m_K))``, write
``x_i·x_j = m_i·m_j / (Γ_iΓ_j)``, which defines ``H`` for every ``m`` (not only on the spheres
``|m_i| = |Γ_i|``). Then

.. math::
    b_i = \frac{\partial H}{\partial m_i}
        = \frac{1}{4\pi} \sum_{j\ne i} \frac{m_j}{1 - x_i\cdot x_j},\qquad
    \dot m_i = b_i \times m_i,

which is ``Γ_i`` times the vortex equation above, and since ``[hat(a), hat(c)] = hat(a × c)``
the whole system is

.. math:: \dot W = [B(W), W],\qquad B(W) = \operatorname{blockdiag}(\hat b_1, \dots, \hat b_K).

``B`` is nonlinear; its Fréchet derivative (for Newton's method) is

.. math::
    \delta b_i = \frac{1}{4\pi}\sum_{j\ne i}\Big(
        \frac{\delta m_j}{d_{ij}}
        + \frac{\delta m_i\cdot m_j + m_i\cdot\delta m_j}{\Gamma_i\Gamma_j\, d_{ij}^2}\, m_j\Big),
    \qquad d_{ij} = 1 - \frac{m_i\cdot m_j}{\Gamma_i\Gamma_j}.

Relation to lieflow's ``B = (grad eta)^†``
-------------------------------------------
lieflow writes every system as ``B(W) = (grad eta(W))^†`` with the gradient taken in the
Frobenius pairing ``<A, C> = tr(A^T C)`` (SPEC §1). Extend any ``eta`` to all real
``3K×3K`` matrices through the orthogonal projection onto so(3)^K (``m = block_vee(W)``, a
linear map). Because ``<hat(a), hat(c)> = 2 a·c``,

.. math::
    \delta\eta = \sum_i \frac{\partial\eta}{\partial m_i}\cdot\delta m_i
    = \Big\langle \tfrac12\operatorname{blockdiag}_i
      \widehat{\partial\eta/\partial m_i},\ \delta W\Big\rangle,
    \qquad
    \operatorname{grad}\eta = \tfrac12\operatorname{blockdiag}_i\widehat{\partial\eta/\partial m_i}.

With ``eta = -2H`` this is ``grad eta = -blockdiag(hat(b_i))``, and its transpose (``^† = ^T``
for real matrices; ``hat(b)^T = -hat(b)``) is exactly ``B(W)``. The factor 2 is the Frobenius
normalisation of so(3), the same that makes the rigid body's ``eta = 2T`` in lieflow
(``B = -hat(omega)``, ``dm/dt = m × omega``). The minus sign appears because the vortex
equations ``dm_i/dt = b_i × m_i = -m_i × ∂H/∂m_i`` are the Lie–Poisson equations with the
opposite sign to the rigid body's ``dm/dt = m × ∂T/∂m``. Therefore
:meth:`PointVortices.hamiltonian` returns ``eta = -2H`` (lieflow's convention: the function
whose gradient is ``B^†``), and :meth:`PointVortices.energy` returns the physical ``H``; their
relative errors are identical.

Conserved quantities: the Casimirs ``|m_i|^2 = Γ_i^2`` (each vortex stays on its sphere,
preserved to roundoff by every isospectral scheme), the energy, and the moment of vorticity
``sum_i m_i = sum_i Γ_i x_i`` (rotation symmetry).

References
----------
V. A. Bogomolov, "Dynamics of vorticity at a sphere", Fluid Dynamics 12 (1977) 863–870.
R. Kidambi and P. K. Newton, "Motion of three point vortices on a sphere", Physica D 116
(1998) 143–175.
P. K. Newton, *The N-Vortex Problem: Analytical Techniques*, Springer (2001), ch. 4.
K. Modin and M. Viviani, "Lie–Poisson methods for isospectral flows", Found. Comput. Math. 20
(2020) 889–921 (the isospectral symplectic Runge–Kutta schemes lieflow implements).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import attrs
import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow
from lieflow.backends import from_host, is_foreign_array, namespace

from .algebra import BlockSO3, block_hat, block_vee

Array = NDArray[Any]

#: ``1 - x_i·x_j`` below this counts as a collision of vortices ``i`` and ``j``
#: (chord distance ``|x_i - x_j| = sqrt(2 (1 - x_i·x_j))`` below about 1.4e-6).
COLLISION_GAP = 1e-12

_INV_4PI = 1.0 / (4.0 * math.pi)


def _frozen(a: Array) -> Array:
    a.setflags(write=False)
    return a


def _constant(table: Array, like: Any) -> Any:
    """A float64 table of the system in ``like``'s real precision: a NumPy array for NumPy
    ``like`` (float32 stays float32), else on ``like``'s device in its library."""
    if is_foreign_array(like):
        return from_host(table, like, like.dtype)
    return table.astype(np.result_type(like.dtype, np.float32), copy=False)


def _swap(x: Any) -> Any:
    """``x`` with its last two axes swapped (arrays of any library)."""
    return namespace(x).matrix_transpose(x) if is_foreign_array(x) else np.swapaxes(x, -1, -2)


def _strengths(values: Sequence[float] | ArrayLike) -> Array:
    try:
        arr = np.array(values, dtype=float)
    except (TypeError, ValueError):
        raise lieflow.InputError(
            f"strengths must be a 1-D sequence of non-zero finite numbers, got {values!r}"
        ) from None
    if arr.ndim != 1:
        raise lieflow.InputError(
            f"strengths must be a 1-D sequence (one circulation per vortex), got shape {arr.shape}"
        )
    if arr.size < 2:
        raise lieflow.InputError(
            f"point vortices need at least K = 2 vortices to move, got {arr.size} strength(s)"
        )
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise lieflow.InputError(f"strength of vortex {bad} is {arr[bad]}; pass finite numbers")
    if np.any(arr == 0):
        bad = int(np.flatnonzero(arr == 0)[0])
        raise lieflow.InputError(
            f"strength of vortex {bad} is zero: a vortex of zero circulation has no momentum "
            "m = Γ x to follow (it is a passive tracer); remove it or give it Γ ≠ 0"
        )
    return _frozen(arr)


def random_positions(
    K: int,
    seed: int | np.random.Generator | None = None,
    *,
    min_distance: float = 0.0,
    max_tries: int = 1000,
) -> Array:
    """``K`` points uniformly distributed on the unit sphere, shape ``(K, 3)`` (seeded).

    Normalised standard normal vectors from ``numpy.random.default_rng(seed)``. With
    ``min_distance > 0``, whole configurations are redrawn until every chord distance
    ``|x_i - x_j|`` is at least ``min_distance`` (close pairs rotate fast and make the implicit
    equations stiff); :class:`lieflow.InputError` after ``max_tries`` draws.
    """
    if isinstance(K, bool) or not isinstance(K, (int, np.integer)) or K < 1:
        raise lieflow.InputError(f"K must be a positive integer, got {K!r}")
    if not (math.isfinite(min_distance) and 0.0 <= min_distance < 2.0):
        raise lieflow.InputError(
            f"min_distance is a chord length on the unit sphere, in [0, 2); got {min_distance!r}"
        )
    rng = np.random.default_rng(seed)
    off = ~np.eye(int(K), dtype=bool)
    for _ in range(max(int(max_tries), 1)):
        x = rng.standard_normal((int(K), 3))
        x /= np.linalg.norm(x, axis=-1, keepdims=True)
        chord2 = 2.0 * (1.0 - x @ x.T)
        if min_distance == 0.0 or np.all(chord2[off] >= min_distance**2):
            return x
    raise lieflow.InputError(
        f"no configuration of {K} points with all distances >= {min_distance} found in "
        f"{max_tries} draws; lower min_distance"
    )


@attrs.frozen(eq=False)
class PointVortices(lieflow.IsospectralSystem):
    r"""K point vortices on the unit sphere, an isospectral system on so(3)^K ⊂ so(3K).

    ``W = blockdiag(hat(Γ_1 x_1), ..., hat(Γ_K x_K))`` and
    ``B(W) = blockdiag(hat(b_1), ..., hat(b_K))`` with
    :math:`b_i = \partial H/\partial m_i = \frac{1}{4\pi}\sum_{j\ne i} m_j/(1 - x_i\cdot x_j)`;
    see the module docstring for the derivation, the sign conventions and the relation
    ``B = (grad eta)^†`` with ``eta = -2H``.

    Every method broadcasts over leading axes (``W`` of shape ``(..., 3K, 3K)``) and is
    vectorised over vortices: ``B`` costs two small matrix products (the ``K×K`` Gram matrix
    ``m m^T`` and ``w m``) plus ``O(K^2)`` elementwise work.

    Parameters
    ----------
    strengths : sequence of float
        Circulations ``Γ_1..Γ_K``, non-zero and finite, ``K >= 2``.

    Examples
    --------
    >>> import lieflow as lf
    >>> system = PointVortices(strengths=(1.0, 1.0, 1.0, -1.0))
    >>> W0 = system.random_initial_condition(seed=0)
    >>> sol = lf.integrate(system, lf.schemes.get("gauss3"), W0, h=0.05, steps=20)
    >>> bool(sol.casimir_drift.max() < 1e-13)
    True
    """

    strengths: Array = attrs.field(default=(1.0, 1.0, 1.0, -1.0), converter=_strengths)
    # read-only K×K constants (defaults run in this order): the off-diagonal mask, and
    # 1/(Γ_iΓ_j) and Γ_iΓ_j with zero diagonal
    _offdiag: Array = attrs.field(init=False, repr=False)
    _inv_gg: Array = attrs.field(init=False, repr=False)
    _gg: Array = attrs.field(init=False, repr=False)

    linear_B = False

    @_offdiag.default
    def _make_offdiag(self) -> Array:
        return _frozen(1.0 - np.eye(self.strengths.size))

    @_inv_gg.default
    def _make_inv_gg(self) -> Array:
        return _frozen(self._offdiag / np.outer(self.strengths, self.strengths))

    @_gg.default
    def _make_gg(self) -> Array:
        return _frozen(self._offdiag * np.outer(self.strengths, self.strengths))

    # ---------------------------------------------------------------- structure
    @property
    def K(self) -> int:
        """Number of vortices."""
        return int(self.strengths.size)

    @property
    def algebra(self) -> BlockSO3:
        """so(3)^K, block-diagonal ``3K×3K`` skew matrices."""
        return BlockSO3(self.K)

    @property
    def name(self) -> str:
        return f"PointVortices(K={self.K})"

    # ---------------------------------------------------------------- phase space
    def project(self, W: Array) -> Array:
        r"""Nearest point of the phase space, the product of spheres ``|m_i| = |Γ_i|``.

        Projects onto so(3)^K (``m = block_vee(W)``, skew part of the diagonal blocks),
        then rescales each momentum to its radius, ``m_i ← |Γ_i| m_i/|m_i|`` (a zero
        ``m_i`` has no nearest point and is left alone). O(K) after the O(n²) read-out;
        keeps the precision of ``W``. Not linear: stage values of a step are *not* on the
        spheres, so they are projected with :meth:`project_stage` (onto so(3)^K) instead.
        """
        if is_foreign_array(W):  # another array library (lieflow.backends)
            m = block_vee(W)
            xp = namespace(m)
            r = xp.linalg.vector_norm(m, axis=-1, keepdims=True)
            radius = from_host(np.abs(self.strengths)[:, None], m, m.dtype)
            return block_hat(m * xp.where(r > 0, radius / xp.where(r > 0, r, 1.0), 1.0))
        W = np.asarray(W)
        m = block_vee(W)
        r = np.linalg.norm(m, axis=-1, keepdims=True)
        radius = np.abs(self.strengths).astype(m.dtype)[:, None]
        scale = np.where(r > 0, radius / np.where(r > 0, r, 1), 1).astype(m.dtype)
        P: Array = block_hat(m * scale)
        return P

    def project_stage(self, W: Array) -> Array:
        """Orthogonal projection onto so(3)^K, the linear span of the phase space."""
        return self.algebra.project(W)

    def compiled_B(self, shift: float = 0.0) -> tuple[Any, Array] | None:
        """``B`` compiled with numba for lieflow's compiled engine (``engine="compiled"``):
        ``(vortex_B, strengths)``, see :meth:`lieflow.IsospectralSystem.compiled_B`;
        ``None`` with a Casimir shift (``shift != 0``: such runs use the numpy engine)."""
        if shift != 0.0:
            return None
        from ._compiled import vortex_B

        return vortex_B, np.ascontiguousarray(self.strengths, dtype=np.float64)

    def compiled_project(self) -> tuple[Any, Array] | None:
        """:meth:`project` compiled: the compiled engine puts every vortex back on its
        sphere after each step, as the numpy path does."""
        from ._compiled import vortex_project

        return vortex_project, np.ascontiguousarray(self.strengths, dtype=np.float64)

    # ---------------------------------------------------------------- dynamics
    def _pair_terms(self, m: Array) -> tuple[Array, Array]:
        """``d_ij = 1 - m_i·m_j/(Γ_iΓ_j)`` (1 on the diagonal) and ``w_ij = 1/d_ij`` (0 on it)."""
        gram = m @ _swap(m)
        d = 1.0 - gram * _constant(self._inv_gg, m)  # float32 states stay float32
        return d, _constant(self._offdiag, m) / d

    def B(self, W: Array) -> Array:
        r"""``B(W) = blockdiag(hat(b_i))``, :math:`b_i = \frac{1}{4\pi}\sum_{j\ne i} w_{ij} m_j`,
        ``w_ij = 1/(1 - x_i·x_j)``; ``m = block_vee(W)`` (the projection onto so(3)^K)."""
        m = block_vee(W)
        _, w = self._pair_terms(m)
        return block_hat(_INV_4PI * (w @ m))

    def B_derivative(self, W: Array, dW: Array) -> Array:
        r"""Exact Fréchet derivative ``B'(W)[dW]`` (see the module docstring).

        With ``dm = block_vee(dW)`` and ``dG = dm m^T + m dm^T``:
        ``dw_ij = w_ij^2 dG_ij / (Γ_iΓ_j)`` and ``db = (dw m + w dm) / 4π``.
        """
        m, dm = block_vee(W), block_vee(dW)
        _, w = self._pair_terms(m)
        dm_mT = dm @ _swap(m)
        dgram = dm_mT + _swap(dm_mT)
        dw = (w * w) * dgram * _constant(self._inv_gg, w)
        return block_hat(_INV_4PI * (dw @ m + w @ dm))

    def hamiltonian(self, W: Array) -> Array:
        r"""lieflow's ``eta = -2H``, the function with ``B = (grad eta)^†``; shape ``W.shape[:-2]``.

        :math:`\eta = \frac{1}{2\pi}\sum_{i<j}\Gamma_i\Gamma_j\log(1 - x_i\cdot x_j)`.
        """
        d, _ = self._pair_terms(block_vee(W))
        xp = namespace(d)
        # sum over i != j counts each pair twice; log d_ii = log 1 = 0
        eta: Array = _INV_4PI * xp.sum(_constant(self._gg, d) * xp.log(d), axis=(-2, -1))
        return eta

    def energy(self, W: Array) -> Array:
        r"""The physical Hamiltonian
        :math:`H = -\frac{1}{4\pi}\sum_{i<j}\Gamma_i\Gamma_j\log(1 - x_i\cdot x_j) = -\eta/2`."""
        return -0.5 * self.hamiltonian(W)

    def moment_of_vorticity(self, W: Array) -> Array:
        """``sum_i Γ_i x_i = sum_i m_i``, shape ``(..., 3)``: conserved by rotation symmetry."""
        m = block_vee(W)
        total: Array = namespace(m).sum(m, axis=-2)
        return total

    # ---------------------------------------------------------------- invariants
    def casimirs(self, W: Array) -> Array:
        """``|m_i|^2`` for each vortex, shape ``(..., K)``; equal to ``Γ_i^2`` on the phase space.

        ``|m_i|^2 = -tr(hat(m_i)^2) / 2``: one quadratic Casimir per so(3) factor.
        """
        m = block_vee(W)
        norms2: Array = namespace(m).sum(m * m, axis=-1)
        return norms2

    @property
    def casimir_powers(self) -> tuple[int, ...]:  # type: ignore[override]
        """Degree of each Casimir in :meth:`casimirs`: all ``K`` are quadratic."""
        return (2,) * self.K

    def casimir_scale(self, W0: Array) -> Array:
        """``|m_i(0)|^2`` (``= Γ_i^2``) per vortex, so that the drift is relative and
        dimensionless: ``|C_i(W_k) - C_i(W_0)| / C_i(W_0)``."""
        return np.maximum(self.casimirs(np.asarray(W0)), np.finfo(float).tiny)

    # ---------------------------------------------------------------- states
    def validate(self, W0: ArrayLike, tol: float = 1e-12) -> Array:
        """Check an initial condition and return it as a fresh array.

        Besides membership in so(3)^K (:class:`lieflow.AlgebraError` otherwise), each block
        must carry ``|m_i| = |Γ_i|`` to relative tolerance ``max(tol, 64 eps)`` — a unit
        position times the vortex's strength — and no two vortices may coincide
        (``1 - x_i·x_j > COLLISION_GAP``). Violations raise :class:`lieflow.InputError` naming
        the vortex; build valid states with :meth:`initial_condition`.
        """
        W = self.algebra.validate(W0, name="W0", tol=tol)
        m = block_vee(W)
        norms = np.linalg.norm(m, axis=-1)
        absg = np.abs(self.strengths)
        rel = np.abs(norms - absg) / absg
        limit = max(tol, 64 * float(np.finfo(W.dtype).eps))
        if np.any(rel > limit):
            i = int(np.argwhere(rel > limit)[0][-1])
            worst = float(np.max(rel[..., i]))
            raise lieflow.InputError(
                f"W0: vortex {i} has |m_{i}| off by a relative {worst:.2e} from "
                f"|Γ_{i}| = {absg[i]:g} (tolerance {limit:.0e}); each block must be "
                "hat(Γ_i x_i) with |x_i| = 1. Build W0 with "
                "PointVortices.initial_condition(positions)"
            )
        d, _ = self._pair_terms(m)
        close = (d <= COLLISION_GAP) & (self._offdiag > 0)
        if np.any(close):
            i, j = (int(v) for v in np.argwhere(close)[0][-2:])
            raise lieflow.InputError(
                f"W0: vortices {i} and {j} coincide (1 - x_{i}·x_{j} = "
                f"{float(np.min(d[..., i, j])):.1e}); the vortex equations are singular there"
            )
        return W

    def initial_condition(self, positions: ArrayLike) -> Array:
        """``W0 = blockdiag(hat(Γ_i x_i))`` from positions of shape ``(..., K, 3)``.

        Each position is normalised onto the unit sphere (it must be finite and non-zero);
        the result passes :meth:`validate` unless two vortices coincide.
        """
        x = np.asarray(positions, dtype=float)
        if x.ndim < 2 or x.shape[-2:] != (self.K, 3):
            raise lieflow.InputError(
                f"positions have shape {x.shape}, but {self.K} vortices need (..., {self.K}, 3)"
            )
        if not np.all(np.isfinite(x)):
            raise lieflow.InputError("positions contain NaN or Inf entries; pass finite values")
        r = np.linalg.norm(x, axis=-1, keepdims=True)
        if np.any(r == 0):
            i = int(np.argwhere(r[..., 0] == 0)[0][-1])
            raise lieflow.InputError(
                f"position of vortex {i} is the zero vector; it has no direction on the sphere"
            )
        return block_hat(self.strengths[:, None] * (x / r))

    def positions(self, W: ArrayLike) -> Array:
        """Unit positions ``x_i = m_i / Γ_i``, shape ``(..., K, 3)``."""
        return block_vee(W) / self.strengths[:, None]

    def random_initial_condition(
        self, seed: int | np.random.Generator | None = None, *, min_distance: float = 0.0
    ) -> Array:
        """:meth:`initial_condition` of :func:`random_positions` (uniform on the sphere,
        seeded; optionally no two vortices closer than ``min_distance``)."""
        return self.initial_condition(random_positions(self.K, seed, min_distance=min_distance))

    def random_state(
        self, seed: int | np.random.Generator | None = None, *, min_distance: float = 0.5
    ) -> Array:
        """A seeded random valid state with no two vortices closer than ``min_distance``.

        lieflow's generic "random initial condition of this system" (used by the test suite
        for every registered system): vortices uniform on the sphere, rejected until well
        separated so that moderate steps (``h <= 0.1``) keep the implicit equations
        non-stiff. Same as ``random_initial_condition(seed, min_distance=0.5)``.
        """
        return self.random_initial_condition(seed, min_distance=min_distance)
