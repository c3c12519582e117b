r"""Dissipation and forcing for the Euler–Zeitlin system, as lieflow flows.

The conservative part of a forced-dissipative run is the isospectral step of
:class:`~lieflow_zeitlin.EulerZeitlin`; everything else enters as a separate sub-flow,
composed with it by :class:`lieflow.flows.Splitting` (Lie–Trotter, Strang, ...), so the
conservative step stays isospectral. The sub-flows here act on the *anomaly*
``X = W - Q(f)`` of the state (``Q(f)`` the planetary vorticity, zero without rotation):
with ``X = Q((Δ - F)ψ)`` and ``Δ``, ``Δ - F`` sharing eigenvectors, damping ``X`` degree by
degree damps the stream function, the relative vorticity and the potential-vorticity
anomaly alike.

=====================================  ===============================  ===================
flow                                   equation (fluid time)            sub-step
=====================================  ===============================  ===================
:class:`Viscosity`                     ``ζ_t = ν Δζ``                   exact, or CN O(N²)
:class:`Hyperviscosity`                ``ζ_t = (-1)^{p+1} ν Δ^p ζ``     exact
:class:`LinearDrag`                    ``ζ_t = -μ ζ``                   exact, O(N²)
:class:`StochasticForcing`             ``dζ = σ dB_t`` (degrees l1..l2)  exact (additive)
=====================================  ===============================  ===================

*Exact* sub-steps use the eigenbasis of the Hoppe–Yau Laplacian: ``Δ_N T_lm = -l(l+1) T_lm``
(:func:`~lieflow_zeitlin.laplacian.harmonics`), so ``exp(τ ν Δ_N)`` multiplies the degree-``l``
part by ``exp(-ν l(l+1) τ)``; applied diagonal by diagonal (``x -> V_m (g ⊙ V_m^T x)``)
this costs O(N³) flops, about two thirds of one complex ``N × N`` product, with the
``≈ N³/3`` eigenvector entries computed once per ``N`` (by the recurrence of
:mod:`lieflow_zeitlin._recurrences`, 0.1 s at N = 512) and cached up to N = 512 (360 MB);
above, they are generated diagonal by diagonal at every sub-step (O(N²) memory, about
0.4 s more per sub-step at N = 1024). Crank–Nicolson
(``method="crank_nicolson"``) solves ``(I - τνΔ_N/2) X_1 = (I + τνΔ_N/2) X_0`` with the
shifted O(N²) tridiagonal solver (:class:`~lieflow_zeitlin.HoppeYauLaplacian` with
``shift = 2/(τν)``): degree ``l`` is multiplied by ``(1 - τνλ/2)/(1 + τνλ/2)``,
``λ = l(l+1)``, second-order accurate and unconditionally stable.

Time: every rate is per unit of *fluid* time; a sub-step of length ``h`` in the system's
time lasts ``τ = h · system.fluid_time_unit`` (``ħ h`` in matrix time).

Every flow has the signature of :class:`lieflow.flows.Flow`: ``name``, ``init(W0)``
(``None``: these flows keep no state) and ``step(W, t, h, state) -> (W, state, stats)``.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import NDArray

import lieflow
from lieflow.flows import StepStats

from . import _recurrences as _rec
from .laplacian import HoppeYauLaplacian, harmonics
from .quantization import kappa
from .system import EulerZeitlin

Array = NDArray[Any]

__all__ = [
    "Hyperviscosity",
    "LinearDrag",
    "StochasticForcing",
    "Viscosity",
    "degree_multiplier",
]


#: Above this N the eigenbasis is not cached (it would hold N³/3 numbers: 360 MB at 512)
#: but generated diagonal by diagonal at every call by the recurrence (O(N²) memory).
CACHE_MAX_N = 512


def _basis_generator(N: int) -> Any:
    """``(m, V_m)`` of :func:`harmonics`: by the recurrence where it applies (about 20x
    faster than the eigensolver), else by the eigensolver."""
    if N <= _rec.MAX_N:
        return _rec.harmonics_by_recurrence(N)
    return harmonics(N)


@functools.lru_cache(maxsize=4)
def _eigenbasis(N: int) -> tuple[Array, ...]:
    """``V_m`` for ``m = 0..N-1`` (:func:`harmonics`), read-only: O(N³/3) memory."""
    out: list[Array] = [np.empty(0)] * N
    for m, V in _basis_generator(N):
        V = np.ascontiguousarray(V)
        V.setflags(write=False)
        out[m] = V
    return tuple(out)


def _bases(N: int) -> Any:
    """The ``V_m`` in order ``m = 0..N-1``: cached up to :data:`CACHE_MAX_N`, else generated
    (``m = N-1..0``, paired with their ``m``)."""
    if N <= CACHE_MAX_N:
        return enumerate(_eigenbasis(N))
    return _basis_generator(N)


@functools.lru_cache(maxsize=4)
def _diagonal_indices(N: int) -> tuple[Array, ...]:
    """Flat indices of diagonal ``m`` of an ``N × N`` matrix: row 0 the lower diagonal
    (entries ``(i+m, i)``), row 1 the upper one (``(i, i+m)``); one row for ``m = 0``."""
    out = []
    for m in range(N):
        i = np.arange(N - m)
        idx = np.stack([(i + m) * N + i, i * N + i + m]) if m else (i * N + i)[None, :]
        idx.setflags(write=False)
        out.append(idx)
    return tuple(out)


def degree_multiplier(X: Array, g: Array) -> Array:
    r"""``Σ_lm g_l <T_lm, X> T_lm``: multiply the degree-``l`` part of ``X`` by ``g[l]``.

    ``X`` has shape ``(..., N, N)`` (any matrices; the expansion in the orthonormal matrix
    harmonics is complete), ``g`` shape ``(N,)``. Diagonal ``±m`` holds the degrees
    ``l = m..N-1`` with the eigenvectors ``V_m`` of :func:`harmonics`, so the map is
    ``x -> V_m (g[m:] ⊙ (V_m^T x))`` on both diagonals ``±m`` at once: O(N³) flops and
    ``5N`` numpy calls in all.
    """
    X = np.asarray(X)
    N = X.shape[-1]
    g = np.asarray(g, dtype=float)
    if g.shape != (N,):
        raise lieflow.InputError(f"need one multiplier per degree, shape ({N},), got {g.shape}")
    batch = X.shape[:-2]
    flat = X.reshape(-1, N * N)
    out = np.empty(flat.shape, dtype=np.result_type(X.dtype, np.complex64))
    indices = _diagonal_indices(N)
    for m, V in _bases(N):
        idx = indices[m]
        coefficients = flat[:, idx] @ V  # (K, 1 or 2, N-m): coefficients of degrees m..N-1
        coefficients *= g[m:]
        out[:, idx] = coefficients @ V.T
    return out.reshape(*batch, N, N)


def _nonnegative(name: str, value: object) -> float:
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        out = math.nan
    if not (math.isfinite(out) and out >= 0):
        raise lieflow.InputError(f"{name} must be finite and >= 0, got {value!r}")
    return out


def _viscosity(value: object) -> float:
    return _nonnegative("viscosity nu", value)


def _hyperviscosity(value: object) -> float:
    return _nonnegative("hyperviscosity nu", value)


def _drag(value: object) -> float:
    return _nonnegative("drag mu", value)


def _amplitude(value: object) -> float:
    return _nonnegative("forcing amplitude", value)


def _system(_inst: object, _attr: attrs.Attribute, value: object) -> None:
    if not isinstance(value, EulerZeitlin):
        raise lieflow.InputError(
            f"system must be an EulerZeitlin system, got {type(value).__name__}"
        )


def _anomaly_parts(system: EulerZeitlin, W: Array) -> tuple[Array, Array]:
    """``(X, offset)`` with ``W = X + offset``, ``offset = Q(f)`` (zero without rotation)."""
    W = np.asarray(W)
    offset = system.planetary.astype(np.result_type(W.dtype, np.complex64), copy=False)
    return W - offset, offset


@attrs.frozen(eq=False)
class _DegreeDamping:
    """Exact sub-step ``X -> Σ exp(-τ r_l) X_l`` for per-degree rates ``r_l`` (fluid time)."""

    system: EulerZeitlin = attrs.field(validator=_system)

    def rates(self) -> Array:
        """Decay rate of each degree ``l = 0..N-1`` per unit fluid time."""
        raise NotImplementedError  # pragma: no cover

    @property
    def name(self) -> str:
        """The flow's name."""
        return type(self).__name__.lower()

    def init(self, W0: Array) -> None:
        """No state."""
        return None

    def factors(self, h: float) -> Array:
        """The multiplier of each degree over a step ``h`` (system time)."""
        tau = float(h) * self.system.fluid_time_unit
        return np.exp(-tau * self.rates())

    def step(self, W: Array, t: float, h: float, state: None) -> tuple[Array, None, StepStats]:
        """``W -> Q(f) + Σ_l e^{-τ r_l} (W - Q(f))_l`` (exact)."""
        X, offset = _anomaly_parts(self.system, W)
        out = degree_multiplier(X, self.factors(h)) + offset
        return out.astype(np.asarray(W).dtype, copy=False), None, StepStats(0, "", 0.0)


def _degrees(N: int) -> Array:
    l = np.arange(N, dtype=float)
    return l * (l + 1)


@functools.lru_cache(maxsize=8)
def _shifted(N: int, a: float) -> HoppeYauLaplacian:
    """``(I - aΔ_N)^{-1} = (-1/a)(Δ_N - 1/a)^{-1}`` as a shifted, scaled solver."""
    return HoppeYauLaplacian(N, scale=-1.0 / a, shift=1.0 / a)


@attrs.frozen(eq=False)
class Viscosity(_DegreeDamping):
    r"""Viscosity ``ζ_t = ν Δζ``: degree ``l`` decays as ``exp(-ν l(l+1) t)``.

    Parameters
    ----------
    system : EulerZeitlin
        The system whose states this flow advances (for ``N``, ``Q(f)`` and the time unit).
    nu : float
        Kinematic viscosity ``ν >= 0`` (unit sphere, fluid time).
    method : {"exact", "crank_nicolson"}
        ``"exact"`` (default): multiply degree ``l`` by ``exp(-ν l(l+1) τ)`` in the
        eigenbasis of ``Δ_N``, O(N³). ``"crank_nicolson"``: one shifted tridiagonal solve,
        O(N²), factor ``(1 - νλτ/2)/(1 + νλτ/2)`` (second order; damps the highest degrees
        less strongly than the exact step).
    """

    nu: float = attrs.field(converter=_viscosity, kw_only=True)
    method: Literal["exact", "crank_nicolson"] = attrs.field(default="exact", kw_only=True)

    @method.validator
    def _check_method(self, _attr: attrs.Attribute, value: str) -> None:
        if value not in ("exact", "crank_nicolson"):
            raise lieflow.InputError(f'method must be "exact" or "crank_nicolson", got {value!r}')

    @property
    def name(self) -> str:
        """``"viscosity"``."""
        return "viscosity"

    def rates(self) -> Array:
        """``ν l(l+1)``."""
        return self.nu * _degrees(self.system.N)

    def factors(self, h: float) -> Array:
        """Exact ``exp(-νλτ)`` or Crank–Nicolson ``(1 - νλτ/2)/(1 + νλτ/2)`` per degree."""
        if self.method == "exact":
            return super().factors(h)
        a = 0.5 * float(h) * self.system.fluid_time_unit * self.nu * _degrees(self.system.N)
        return (1 - a) / (1 + a)

    def step(self, W: Array, t: float, h: float, state: None) -> tuple[Array, None, StepStats]:
        """One exact or Crank–Nicolson viscous sub-step of length ``h``."""
        if self.method == "exact" or self.nu == 0 or h == 0:
            return super().step(W, t, h, state)
        W = np.asarray(W)
        X, offset = _anomaly_parts(self.system, W)
        a = 0.5 * float(h) * self.system.fluid_time_unit * self.nu
        if a < 0:
            raise lieflow.InputError(
                "a Crank–Nicolson viscous step needs h > 0 (a composition with negative "
                'sub-steps needs method="exact")'
            )
        N = self.system.N
        trace = np.trace(X, axis1=-2, axis2=-1)[..., None, None] / N
        rhs = X + a * HoppeYauLaplacian(N).apply(X)
        out = _shifted(N, a).solve(rhs) + trace * np.eye(N) + offset
        return out.astype(W.dtype, copy=False), None, StepStats(0, "", 0.0)


def _order(value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise lieflow.InputError(f"hyperviscosity order p must be an integer >= 1, got {value!r}")
    return int(value)


@attrs.frozen(eq=False)
class Hyperviscosity(_DegreeDamping):
    r"""Hyperviscosity ``ζ_t = (-1)^{p+1} ν Δ^p ζ``: degree ``l`` decays as
    ``exp(-ν (l(l+1))^p t)`` (exact sub-step; ``p = 1`` is :class:`Viscosity`).

    Parameters
    ----------
    system : EulerZeitlin
    nu : float
        ``ν >= 0``; a common choice damps the largest degree ``N-1`` at a rate ``r``:
        ``ν = r / ((N-1)N)^p``.
    order : int
        ``p >= 1`` (default 2).
    """

    nu: float = attrs.field(converter=_hyperviscosity, kw_only=True)
    order: int = attrs.field(default=2, converter=_order, kw_only=True)

    @property
    def name(self) -> str:
        """``"hyperviscosity"``."""
        return "hyperviscosity"

    def rates(self) -> Array:
        """``ν (l(l+1))^p``."""
        return self.nu * _degrees(self.system.N) ** self.order


@attrs.frozen(eq=False)
class LinearDrag(_DegreeDamping):
    """Linear (Rayleigh/Ekman) drag ``ζ_t = -μ ζ``: ``X -> e^{-μτ} X``, exact, O(N²).

    Parameters
    ----------
    system : EulerZeitlin
    mu : float
        Drag rate ``μ >= 0`` per unit fluid time.
    """

    mu: float = attrs.field(converter=_drag, kw_only=True)

    @property
    def name(self) -> str:
        """``"drag"``."""
        return "drag"

    def rates(self) -> Array:
        """``μ`` for every degree."""
        return np.full(self.system.N, self.mu)

    def step(self, W: Array, t: float, h: float, state: None) -> tuple[Array, None, StepStats]:
        """``W -> Q(f) + e^{-μτ}(W - Q(f))``."""
        W = np.asarray(W)
        X, offset = _anomaly_parts(self.system, W)
        decay = math.exp(-float(h) * self.system.fluid_time_unit * self.mu)
        return (decay * X + offset).astype(W.dtype, copy=False), None, StepStats(0, "", 0.0)


def _seed(value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise lieflow.InputError(f"seed must be a non-negative integer, got {value!r}")
    return int(value)


def _band(_inst: Any, _attr: attrs.Attribute, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise lieflow.InputError(f"forcing degrees must be integers, got {value!r}")


#: The forcing's padded eigenvectors (:func:`_forcing_plan`) hold at most this many numbers
#: per block of diagonals (32 MB); a wide band at large N takes several blocks.
FORCING_BLOCK = 1 << 22


@functools.lru_cache(maxsize=8)
def _forcing_plan(N: int, l1: int, l2: int) -> tuple[tuple[Array, ...], ...]:
    """What :meth:`StochasticForcing.noise` needs to build ``Q(η)`` in a few numpy calls,
    in blocks of consecutive diagonals ``m`` (one block unless the band is wide), each
    ``(basis, real, imag, scale, lower, upper)``, row ``j`` for diagonal ``m``, padded to
    ``count = l2 - l1 + 1`` degrees and ``N`` entries: the eigenvectors ``V_m`` of the
    forced degrees ``(rows, N, count)``; indices into ``η`` (index ``modes``: zero) of the
    real and imaginary parts of ``ω_lm`` (``m = 0``: ``η`` itself; ``m > 0``:
    ``(a + ib)/√2`` from the next ``2 count`` numbers, in the order they are drawn); their
    scale; the flat indices of diagonal ``-m`` (``(i + m, i)``) and ``+m`` (``m > 0``),
    ``N²`` for padding. Read-only."""
    count = l2 - l1 + 1
    modes = (l2 + 1) ** 2 - l1**2
    per_block = max(1, FORCING_BLOCK // (N * count))
    eigenbasis = _eigenbasis(N)
    blocks = []
    pos = 0
    for first in range(0, l2 + 1, per_block):
        ms = range(first, min(first + per_block, l2 + 1))
        rows = len(ms)
        basis = np.zeros((rows, N, count))
        real = np.full((rows, count), modes)
        imag = np.full((rows, count), modes)
        scale = np.ones((rows, 1))
        lower = np.full((rows, N), N * N)
        upper = np.full((rows, N), N * N)
        for j, m in enumerate(ms):
            lo = max(l1, m)
            k = l2 - lo + 1
            basis[j, : N - m, :k] = eigenbasis[m][:, lo - m : l2 - m + 1]
            i = np.arange(N - m)
            lower[j, : N - m] = (i + m) * N + i
            real[j, :k] = np.arange(pos, pos + k)
            pos += k
            if m:
                upper[j, : N - m] = i * N + i + m
                imag[j, :k] = np.arange(pos, pos + k)
                pos += k
                scale[j] = 1 / math.sqrt(2)
        block = (basis, real, imag, scale, lower, upper)
        for x in block:
            x.setflags(write=False)
        blocks.append(block)
    return tuple(blocks)


@attrs.frozen(eq=False)
class StochasticForcing:
    r"""Additive white-in-time noise in the degrees ``l1 <= l <= l2``.

    .. math:: d\zeta = \sigma \sum_{l=l_1}^{l_2} \sum_{|m| \le l} Y^{\mathbb R}_{lm}\,
              d\beta_{lm}(t),

    ``Y^R_lm`` the real orthonormal spherical harmonics and ``β_lm`` independent standard
    Brownian motions (fluid time). A sub-step of length ``h`` (fluid time ``τ``) adds
    ``σ √τ Q(η)``, ``η`` with independent standard normal real coefficients, which is the
    exact increment. The noise of a sub-step starting at ``t`` comes from
    ``np.random.default_rng([seed, k])`` with ``k = round(t/h)``: no generator state is
    carried between steps, so a run is reproducible from its seed and a resumed run draws
    exactly the noise the uninterrupted one would have (in a Strang splitting the forcing
    sub-steps start at distinct multiples of their own length).

    Parameters
    ----------
    system : EulerZeitlin
    amplitude : float
        ``σ >= 0``.
    l1, l2 : int
        Forced degrees, ``1 <= l1 <= l2 <= N-1`` (``l = 0`` would leave su(N)).
    seed : int
        Non-negative seed.

    Notes
    -----
    The forcing injects field enstrophy ``Z = ½∫ζ² dΩ`` at the rate
    :attr:`enstrophy_rate` ``= ½ σ² n``, ``n = (l2+1)² - l1²`` forced modes; the matrix
    enstrophy ``||W||_F² = (N/4π)∫ζ²`` grows by ``(N/4π) σ² n`` per unit fluid time
    (in expectation). Euler's flow conserves ``||W||_F`` and a drag ``μ`` removes
    ``2μ||W||²``, so with drag alone (no rotation) the statistically steady enstrophy is
    ``E||W||_F² = (N/4π) σ² n / (2μ)`` — whatever the nonlinear transfer does.
    """

    system: EulerZeitlin = attrs.field(validator=_system)
    amplitude: float = attrs.field(converter=_amplitude, kw_only=True)
    l1: int = attrs.field(validator=_band, kw_only=True)
    l2: int = attrs.field(validator=_band, kw_only=True)
    seed: int = attrs.field(converter=_seed, kw_only=True)

    def __attrs_post_init__(self) -> None:
        N = self.system.N
        if not 1 <= self.l1 <= self.l2 <= N - 1:
            raise lieflow.InputError(
                f"forced degrees need 1 <= l1 <= l2 <= N-1 = {N - 1}, got l1 = {self.l1}, "
                f"l2 = {self.l2}"
            )

    @property
    def name(self) -> str:
        """``"forcing"``."""
        return "forcing"

    @property
    def modes(self) -> int:
        """Number of forced real modes, ``(l2+1)² - l1²``."""
        return (self.l2 + 1) ** 2 - self.l1**2

    @property
    def enstrophy_rate(self) -> float:
        """Injection rate of ``½∫ζ² dΩ`` per unit fluid time, ``½ σ² n``."""
        return 0.5 * self.amplitude**2 * self.modes

    def init(self, W0: Array) -> None:
        """No state (the noise is a function of ``(seed, t, h)``)."""
        return None

    def noise(self, t: float, h: float) -> Array:
        """``Q(η)`` of the sub-step ``[t, t + h]``: ``η`` with i.i.d. standard normal real
        coefficients in degrees ``l1..l2``, drawn from ``default_rng([seed, round(t/h)])``."""
        if not (math.isfinite(h) and h > 0):
            raise lieflow.InputError(f"stochastic forcing needs a step h > 0, got {h!r}")
        k = round(float(t) / float(h))
        if k < 0:
            raise lieflow.InputError(f"stochastic forcing needs t >= 0, got t = {t!r}")
        rng = np.random.default_rng([self.seed, k])
        N = self.system.N
        z = rng.standard_normal(self.modes)
        zz = np.append(z, 0.0)  # index ``modes``: the padding
        factor = 1j * kappa(N)
        out = np.zeros(N * N + 1, dtype=np.complex128)  # the last entry takes the padding
        for basis, real, imag, scale, lower, upper in _forcing_plan(N, self.l1, self.l2):
            # real and imaginary parts of ω_lm (row: diagonal m, column: degree l)
            parts = np.stack([zz[real], zz[imag]], axis=-1) * scale[..., None]
            values = basis @ parts  # V_m ω_m, real and imaginary parts, all m at once
            out[lower] = factor * (values[..., 0] + 1j * values[..., 1])
            out[upper] = factor * (values[..., 0] - 1j * values[..., 1])  # V_m conj(ω_m)
        return out[:-1].reshape(N, N)

    def step(self, W: Array, t: float, h: float, state: None) -> tuple[Array, None, StepStats]:
        """``W -> W + σ √τ Q(η_k)``."""
        W = np.asarray(W)
        tau = float(h) * self.system.fluid_time_unit
        if self.amplitude == 0:
            return W.copy(), None, StepStats(0, "", 0.0)
        out = W + (self.amplitude * math.sqrt(tau)) * self.noise(t, h)
        return out.astype(W.dtype, copy=False), None, StepStats(0, "", 0.0)
