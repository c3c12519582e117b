r"""The Euler–Zeitlin equations on su(N): Euler's equations on the (rotating) sphere and the
global quasi-geostrophic model, quantized.

Continuous model
----------------
With the conventions of :mod:`lieflow_zeitlin.quantization` (outward normal, ``u = n̂ × ∇ψ``,
``{f, g} = n̂ · (∇f × ∇g)``), the equivalent-barotropic quasi-geostrophic equation on a
sphere rotating at rate ``Ω`` about ``z`` is

.. math:: q_t = -\{\psi, q\},\qquad q = \Delta\psi - F\psi + f,\qquad f = 2\Omega\cos\theta,

with the Lamb parameter ``F >= 0``. ``F = 0`` is Euler's equation on the rotating sphere for
the absolute vorticity ``q = ω + f``; ``F = Ω = 0`` is Euler's equation ``ω_t = -{ψ, ω}``.
Since ``{ψ, q} = u · ∇q``, ``q`` is transported: every ``∫ g(q) dΩ`` is conserved.

Matrix model
------------
With ``W = Q(q)`` (the isospectral variable), ``F_f = Q(f) = 2Ω · iħ S_3`` (exact: ``f`` has
degree 1) and ``L = Δ_N - F`` (shifted Hoppe–Yau Laplacian),

.. math:: \dot W = [B(W), W],\qquad B(W) = \sigma P,\qquad
          P = L^{-1}(W - F_f) = Q(\psi),\qquad \sigma = 1/\hbar \text{ or } 1,

because ``(1/ħ)[Q(f), Q(g)] = -Q({f, g}) + O(1/N)`` (:mod:`~lieflow_zeitlin.quantization`).
``B`` is affine when ``Ω != 0``; its derivative (Newton) is ``σ L^{-1}``.

Time unit (summary of the docs page "Euler–Zeitlin", section "The time unit")
-----------------------------------------------------------------------------
* ``time="fluid"`` (default): ``σ = 1/ħ``, ``ħ = 2/sqrt(N² - 1)``. ``t`` is the fluid's time:
  a vorticity ``ω`` turns fluid at angular speed ``ω/2``, a rotation rate ``Ω`` is in
  radians per unit ``t``, viscosities and drags are per unit ``t``.
* ``time="matrix"``: ``σ = 1``, ``dW/dt = [P, W]`` (lieflow SPEC §3). One unit of this matrix
  time is ``ħ ≈ 2/N`` units of fluid time; all physical parameters (``Ω``, ``F``, and the
  rates of :mod:`lieflow_zeitlin.dissipation`) keep their fluid-time meaning.

Energy and Casimirs
-------------------
The Hamiltonian is the energy

.. math:: \eta(W) = -\tfrac12 \operatorname{Re}\operatorname{tr}\big((W - F_f)^\dagger B(W)\big)
          = -\tfrac{\sigma}{2} \langle W - F_f, L^{-1}(W - F_f)\rangle_F \;\ge\; 0,

so that ``grad η = -σ P`` and ``B = (grad η)^†`` as lieflow requires (SPEC §1). For
``W = Q(q)`` it *equals* ``(σ N/4π) · ½∫(|∇ψ|² + Fψ²) dΩ`` (``Q`` maps ``Δ`` to ``Δ_N`` and is
an isometry up to ``κ² = N/4π``). The Casimirs are the real traces

.. math:: C_k(W) = \operatorname{tr}\big((iW)^k\big),\qquad k \in \texttt{casimir\_powers},

(``iW`` is Hermitian, with eigenvalues ``≈ -q`` values); ``C_2 = ||W||_F²`` is the
enstrophy of ``q`` (``= (N/4π) ∫q² dΩ`` exactly). ``tr W^k`` itself is imaginary for odd
``k``, which is why :meth:`EulerZeitlin.casimirs` overrides lieflow's default ``Re tr W^k``.

Users think in relative vorticity ``ζ = Δψ``: :meth:`EulerZeitlin.from_relative` and
:meth:`EulerZeitlin.relative` convert (``q = ζ - FΔ^{-1}ζ + f``).
"""

from __future__ import annotations

import functools
import math
from typing import Any, ClassVar, Literal

import attrs
import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

import lieflow
from lieflow.backends import from_host, is_foreign_array, is_numpy, namespace
from lieflow.underflow import TAU

from . import _recurrences as _rec
from . import traces
from .laplacian import HoppeYauLaplacian, matrix_size
from .projection import su_project
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

    #: Its projection has :class:`lieflow.SU`'s bits (tested), so a step that keeps skew
    #: symmetry only has its trace removed (:class:`lieflow.SchemeFlow`).
    projects_as_su: ClassVar[bool] = True

    degree: int = attrs.field(default=8, converter=_degree, kw_only=True)
    precision: np.dtype = attrs.field(
        default=np.dtype(np.complex128), converter=_complex_dtype, kw_only=True
    )

    def random(self, seed: int | np.random.Generator | None = None, scale: float = 1.0) -> Array:
        """A seeded random smooth vorticity matrix with root-mean-square vorticity ``scale``."""
        return random_vorticity(self.n, self.degree, seed, rms=scale, dtype=self.precision)

    def project(self, X: ArrayLike) -> Array:
        """:meth:`lieflow.SU.project`, its skew-Hermitian part in one compiled pass where
        numba is installed (:func:`~lieflow_zeitlin.projection.su_project`: the same bits)."""
        return su_project(X, super().project)


def _rotation(value: float) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if not math.isfinite(out):
        raise lieflow.InputError(f"rotation (Ω) must be a finite number, got {value!r}")
    return out


def _lamb(value: float) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if not (math.isfinite(out) and out >= 0):
        raise lieflow.InputError(
            f"lamb (the Lamb parameter F) must be finite and >= 0, got {value!r}"
        )
    return out


def _every(value: int | None) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise lieflow.InputError(
            f"diagnostics_every must be a non-negative integer (0: none), got {value!r}"
        )
    return int(value)


def _flag(value: bool) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise lieflow.InputError(f"diagnostics_levels must be true or false, got {value!r}")
    return bool(value)


#: From this N on, :class:`EulerZeitlin` turns its underflow guard on by default.
GUARD_FROM_N = 512


def _guard_default(self: Any) -> float:
    return TAU if self.N >= GUARD_FROM_N else 0.0


def _guard(value: float) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if not 0.0 <= out <= 2.0**-100:
        raise lieflow.InputError(
            f"underflow_guard must be 0 (off) or a threshold in (0, 2^-100] far below "
            f"roundoff (default {TAU:.3g} from N = {GUARD_FROM_N}), "
            f"got {value!r}"
        )
    return out


def _time_default(self: Any) -> str:
    return "fluid" if self.hbar_scaled is None or self.hbar_scaled else "matrix"


@attrs.frozen(eq=False)
class EulerZeitlin(lieflow.IsospectralSystem):
    r"""Euler's equations on the sphere, Zeitlin's su(N) model, optionally on a rotating
    sphere (``rotation = Ω``) and in the quasi-geostrophic form (``lamb = F``); module docs
    for the equations and conventions.

    Parameters
    ----------
    N : int
        Matrix size (``>= 2``; default 8, a test size: real runs use 64–512). The
        quantization resolves spherical-harmonic degrees ``l < N``.
    dtype : {"complex128", "complex64"}
        Precision of the states this system makes (random initial conditions). ``B`` works
        in the precision of its argument (complex64 in single, anything else in double).
    hbar_scaled : bool, optional
        Deprecated spelling of ``time``: ``True`` is ``"fluid"``, ``False`` ``"matrix"``.
    time : {"fluid", "matrix"}
        The time unit (module docs): ``"fluid"`` (default) integrates in the fluid's time,
        ``dW/dt = (1/ħ)[P, W]``; ``"matrix"`` is ``dW/dt = [P, W]`` (time scaled by ``1/ħ``).
    random_degree : int
        Band limit of :meth:`algebra`'s random elements (smooth random initial vorticity).
    rotation : float
        Rotation rate ``Ω`` of the sphere (fluid time units); planetary vorticity
        ``f = 2Ω cos θ``. The state is then the *absolute* vorticity ``W = Q(ω + f)``.
    lamb : float
        Lamb parameter ``F >= 0`` of the quasi-geostrophic model (``(a/L_d)²``); the state is
        the potential vorticity ``W = Q(Δψ - Fψ + f)``.
    diagnostics_every : int, optional
        Steps between the samples of :meth:`extra_diagnostics` that ``lieflow run`` writes
        under ``/diagnostics/extra`` (default: every saved state; ``0``: none).
    diagnostics_levels : bool
        Whether those samples include the vorticity levels and the Casimirs (default
        ``True``). They cost one Hermitian eigenvalue problem of size N, about 0.15–0.28
        midpoint steps per sample at N = 64–512, against 0.04–0.09 for the spectra;
        ``False`` keeps the spectra, energy and enstrophy only (``lieflow plot`` then takes
        the levels of the saved states, :func:`~lieflow_zeitlin.vorticity_levels` computes
        them for any).
    underflow_guard : float
        Relative threshold of the underflow guard (:mod:`lieflow.underflow`): before each
        product of the schemes' maps, entries below it times their matrix's largest are set
        to zero (``2^-280`` of roundoff), so that no product goes subnormal — on Intel
        cores each subnormal operation costs a microcode assist (the smooth field of
        ``benchmarks.device`` at N = 1024 holds entries down to ``1e-280``: its products
        ran 6× slower). Default :data:`lieflow.underflow.TAU` from N = 512 (the field's
        smallest entries reach the subnormal range of a product from there: ``2e-209`` at
        N = 512, ``1e-116`` at N = 256), ``0`` (off: every number as it is) below; off, the
        bits are those without the guard.

    Notes
    -----
    ``B(W) = σ (Δ_N - F)^{-1}(W - F_f)`` costs one O(N²) partitioned tridiagonal sweep over
    all diagonals of all matrices of a batch (:meth:`HoppeYauLaplacian.solve`). ``B`` is
    linear (``linear_B``) only without rotation; :meth:`B_derivative` is the linear part. For
    ``W`` outside su(N) (Newton directions) the solve is the pseudo-inverse: the trace is
    projected out.
    """

    N: int = attrs.field(default=8, converter=matrix_size)
    dtype: np.dtype = attrs.field(default=np.dtype(np.complex128), converter=_complex_dtype)
    hbar_scaled: bool | None = attrs.field(
        default=None,
        validator=attrs.validators.optional(attrs.validators.instance_of(bool)),
    )
    random_degree: int = attrs.field(default=8, converter=_degree)
    time: Literal["fluid", "matrix"] = attrs.field(
        default=attrs.Factory(_time_default, takes_self=True), kw_only=True
    )
    rotation: float = attrs.field(default=0.0, converter=_rotation, kw_only=True)
    lamb: float = attrs.field(default=0.0, converter=_lamb, kw_only=True)
    diagnostics_every: int | None = attrs.field(default=None, converter=_every, kw_only=True)
    diagnostics_levels: bool = attrs.field(default=True, converter=_flag, kw_only=True)
    underflow_guard: float = attrs.field(
        default=attrs.Factory(_guard_default, takes_self=True), converter=_guard, kw_only=True
    )
    laplacian: HoppeYauLaplacian = attrs.field(init=False, repr=False)
    planetary: Array = attrs.field(init=False, repr=False)
    # built once: every projection of a stage value goes through it
    _algebra: VorticityAlgebra = attrs.field(init=False, repr=False)

    casimir_powers = (2, 3, 4)

    @time.validator
    def _check_time(self, _attr: attrs.Attribute, value: str) -> None:
        if value not in ("fluid", "matrix"):
            raise lieflow.InputError(f'time must be "fluid" or "matrix", got {value!r}')
        if self.hbar_scaled is not None and (value == "fluid") != self.hbar_scaled:
            raise lieflow.InputError(
                f"hbar_scaled={self.hbar_scaled} contradicts time={value!r} (hbar_scaled is "
                'the old spelling: True is time="fluid", False is time="matrix"); give only time'
            )

    @laplacian.default
    def _laplacian(self) -> HoppeYauLaplacian:
        return HoppeYauLaplacian(self.N, scale=self.bracket_scale, shift=self.lamb)

    @_algebra.default
    def _algebra_default(self) -> VorticityAlgebra:
        return VorticityAlgebra(self.N, degree=self.random_degree, precision=self.dtype)

    @planetary.default
    def _planetary(self) -> Array:
        # Q(2Ω cos θ) = 2Ω · iħ S_3, S_3 = diag(i - s): exact (degree 1)
        s = (self.N - 1) / 2
        F = np.diag(2j * self.rotation * hbar(self.N) * (np.arange(self.N) - s))
        F.setflags(write=False)
        return F

    @property
    def bracket_scale(self) -> float:
        """``σ``: ``1/ħ`` in fluid time, ``1`` in matrix time."""
        return 1.0 / hbar(self.N) if self.time == "fluid" else 1.0

    @property
    def fluid_time_unit(self) -> float:
        """Fluid time per unit of this system's time: ``1`` (fluid) or ``ħ`` (matrix)."""
        return 1.0 if self.time == "fluid" else hbar(self.N)

    @property
    def linear_B(self) -> bool:  # type: ignore[override]
        """``B`` is linear exactly when the sphere does not rotate (``Ω = 0``)."""
        return self.rotation == 0.0

    @property
    def algebra(self) -> VorticityAlgebra:
        """su(N) (random elements are smooth vorticity fields)."""
        return self._algebra

    def _anomaly(self, W: Array) -> Array:
        if not is_numpy(W):  # an array of another library (lieflow.backends)
            if self.rotation == 0.0:
                return W
            xp = namespace(W)
            return W - from_host(self.planetary, W, xp.result_type(W.dtype, xp.complex64))
        W = np.asarray(W)
        if self.rotation == 0.0:
            return W
        return W - self.planetary.astype(np.result_type(W.dtype, np.complex64), copy=False)

    def random_state(self, seed: int | np.random.Generator | None = None) -> Array:
        """A seeded random state whose *relative* vorticity has unit Frobenius norm (smooth,
        degrees ``1..random_degree``): ``from_relative(R)``; without rotation and Lamb
        parameter, ``R`` itself (lieflow's contract: unit norm).

        ``[initial] random = true`` with ``scale`` multiplies the whole state, so on a
        rotating sphere keep ``scale = 1`` (or start from a file).
        """
        R = super().random_state(seed)
        if self.rotation == 0.0 and self.lamb == 0.0:
            return R
        return self.from_relative(R)

    @functools.cached_property
    def diagonal_tables(self) -> _rec.DiagonalTables | None:
        """The recurrence tables of the spectra by degree
        (:func:`~lieflow_zeitlin.diagnostics.matrix_squares_by_degree`), built on first use
        (O(N³/3) flops, ``5N²/2`` numbers) and kept; ``None`` without numba or for
        ``N > 1400``."""
        if not _rec.have_numba() or self.N > _rec.MAX_N:
            return None
        return _rec.DiagonalTables.of(self.N)

    def B(self, W: Array) -> Array:
        r"""``σ (Δ_N - F)^{-1}(W - F_f)`` (``σ`` times the stream matrix), broadcasting."""
        return self.laplacian.solve(self._anomaly(W))

    def stage_B(self, W: Array) -> Array:
        """``B(project_stage(W))``, bit for bit: without rotation the su(N) projection is
        formed in the Laplacian solve's own buffer (:meth:`HoppeYauLaplacian.solve`'s
        ``skew_part``: one ``N × N`` array and two passes over it less per update)."""
        if self.rotation == 0.0 and type(W) is np.ndarray:
            return self.laplacian.solve(W, skew_part=True)
        return self.B(self.project_stage(W))

    def compiled_B(self, shift: float = 0.0) -> tuple[Any, Array] | None:
        r"""``B`` for lieflow's compiled engine (complex128 data): the su(N) projection of a
        stage value, the same Laplacian sweeps as :meth:`B`, compiled, minus ``shift``
        times the projection (:mod:`lieflow_zeitlin._compiled`; see
        :meth:`lieflow.IsospectralSystem.compiled_B`)."""
        from . import _compiled

        lap = self.laplacian
        factors = lap._double.compact  # the double-precision factors of the sweeps
        return _compiled.zeitlin_B, _compiled.params(shift, self.planetary, factors)

    def B_derivative(self, W: Array, dW: Array) -> Array:
        """``B'(W)[dW] = σ (Δ_N - F)^{-1} dW`` (``B`` is affine)."""
        return self.laplacian.solve(dW)

    def stream(self, W: ArrayLike) -> Array:
        r"""The stream matrix ``P = Q(ψ) = (Δ_N - F)^{-1}(W - F_f)`` (no ``σ``)."""
        return self.B(np.asarray(W)) / self.bracket_scale

    def from_relative(self, W_rel: ArrayLike) -> Array:
        r"""The state ``Q(q)`` of the relative vorticity matrix ``Q(ζ)``, ``ζ = Δψ``:
        ``W = W_rel - F Δ_N^{-1} W_rel + F_f`` (``W_rel + F_f`` without the Lamb term)."""
        W_rel = np.asarray(W_rel)
        W = W_rel + self.planetary.astype(np.result_type(W_rel.dtype, np.complex64))
        if self.lamb:
            W = W - self.lamb * HoppeYauLaplacian(self.N).solve(W_rel).astype(W.dtype)
        return W

    def relative(self, W: ArrayLike) -> Array:
        r"""The relative vorticity matrix ``Q(ζ) = Δ_N P`` of the state ``W = Q(q)``:
        ``W - F_f + F P`` (``W - F_f`` without the Lamb term); inverse of
        :meth:`from_relative`."""
        W = np.asarray(W)
        Z = self._anomaly(W)
        if self.lamb:
            Z = Z + self.lamb * self.stream(W).astype(Z.dtype)
        return Z

    def hamiltonian(self, W: Array) -> Array:
        r"""Energy ``-½ Re tr((W - F_f)^† B(W)) >= 0``, shape ``W.shape[:-2]``."""
        A = self._anomaly(W)
        P = self.laplacian.solve(A)
        if not is_numpy(A):  # an array of another library (lieflow.backends), or traced
            xp = namespace(A)
            return -0.5 * xp.real(xp.sum(xp.conj(A) * P, axis=(-2, -1)))
        if A.dtype == P.dtype and A.dtype in _COMPLEX:
            # Re Σ conj(a) p = Σ (Re a Re p + Im a Im p): one dot product of the real views
            # per matrix (einsum's loop, no temporaries; single-threaded, so its sums do
            # not depend on the number of threads)
            real = P.real.dtype
            a = np.ascontiguousarray(A).reshape(*A.shape[:-2], -1).view(real)
            p = P.reshape(*P.shape[:-2], -1).view(real)
            return -0.5 * np.einsum("...i,...i->...", a, p)
        return -0.5 * np.real(np.sum(np.conj(A) * P, axis=(-2, -1)))

    def casimirs(self, W: Array) -> Array:
        r"""``tr((iW)^k)`` for ``k`` in :attr:`casimir_powers` (real), last axis indexes k.

        Uses ``tr(A^k) = Σ_ij (A^a)_ij (A^b)_ji`` with ``a = ⌊k/2⌋``, ``b = ⌈k/2⌉``, so
        ``k <= 4`` costs a single matrix product. The default powers 2, 3, 4 of
        ``complex128`` NumPy states from ``N = 64`` on (:data:`~lieflow_zeitlin.traces.MIN_N`)
        with numba installed: the product (half of one by ``zherk`` for a state, which is
        skew-Hermitian bit for bit) and one compiled pass
        (:func:`~lieflow_zeitlin.traces.casimirs_234`; the same sums, added in another
        order).
        """
        powers = [k for k in self.casimir_powers if k <= self.N]
        if is_foreign_array(W):  # an array of another library (lieflow.backends), or traced
            return self._casimirs_arrays(W, powers)
        W = np.asarray(W)
        if (
            tuple(powers) == traces.POWERS
            and W.dtype == np.complex128
            and self.N >= traces.MIN_N
            and _rec.have_numba()
        ):
            return traces.casimirs_234(W)
        A = 1j * W
        if not powers:
            return np.zeros((*A.shape[:-2], 0))
        top = (max(powers) + 1) // 2
        stack = [np.broadcast_to(np.eye(self.N), A.shape), A]
        for _ in range(2, top + 1):
            stack.append(stack[-1] @ A)
        # the transposed factors copied once each (contiguous: the products then read two
        # arrays along their rows, not one down its columns; the same products, the same
        # C-ordered temporaries and sums, the same bits; N = 256: 0.96 -> 0.79 ms)
        transposed = {
            b: np.ascontiguousarray(np.swapaxes(stack[b], -1, -2))
            for b in {k - k // 2 for k in powers}
        }
        out = [
            np.real(np.sum(stack[k // 2] * transposed[k - k // 2], axis=(-2, -1))) for k in powers
        ]
        return np.stack(out, axis=-1)

    def _casimirs_arrays(self, W: Any, powers: list[int]) -> Any:
        """:meth:`casimirs` in array-API operations (the same products)."""
        xp = namespace(W)
        A = 1j * W
        if not powers:
            return xp.zeros((*A.shape[:-2], 0), dtype=xp.float64)
        stack = [A]  # A^1, A^2, ...
        for _ in range(2, (max(powers) + 1) // 2 + 1):
            stack.append(stack[-1] @ A)
        out = []
        for k in powers:
            a, b = k // 2, k - k // 2
            if a == 0:  # tr(A)
                out.append(xp.real(xp.sum(xp.linalg.diagonal(A), axis=-1)))
            else:
                Xa, Xb = stack[a - 1], stack[b - 1]
                out.append(xp.real(xp.sum(Xa * xp.matrix_transpose(Xb), axis=(-2, -1))))
        return xp.stack(out, axis=-1)

    def extra_diagnostics(self, W: ArrayLike) -> dict[str, Array]:
        """The turbulence diagnostics of one state that ``lieflow run`` stores under
        ``/diagnostics/extra`` (:func:`lieflow_zeitlin.diagnostics.snapshot`): energy and
        enstrophy spectra of the relative vorticity, their sums and, with
        ``diagnostics_levels`` (the default), the vorticity levels (eigenvalues of ``-iW``)
        and the Casimirs ``tr((iW)^k)``, k = 2, 3, 4, 5, 6, 8.

        ``W`` is a state of a run of this system (the stepping loop's), so only its shape is
        checked; :func:`~lieflow_zeitlin.diagnostics.snapshot` also checks that a state from
        elsewhere is in su(N). Cost per sample, in midpoint steps (h = 1/N, rtol 1e-14;
        ``benchmarks/suites/euler_zeitlin.py``): the spectra 0.04–0.09 (one compiled pass of
        the harmonic recurrences), the levels and Casimirs 0.15–0.28 (one Hermitian
        eigenvalue problem, 2.5–6 complex N×N products) at N = 64–512.
        """
        from .diagnostics import _snapshot

        W = np.asarray(W)
        if W.ndim < 2 or W.shape[-2:] != (self.N, self.N):
            raise lieflow.InputError(
                f"W has shape {W.shape}, but su({self.N}) needs (..., {self.N}, {self.N})"
            )
        return _snapshot(self, W, levels=self.diagnostics_levels)

    def enstrophy(self, W: ArrayLike) -> Array:
        """``||W||_F² = tr((iW)²)`` (the ``k = 2`` Casimir)."""
        W = np.asarray(W)
        return np.sum(np.abs(W) ** 2, axis=(-2, -1))
