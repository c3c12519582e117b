"""The abstract isospectral Lie–Poisson system ``dW/dt = [B(W), W]`` (SPEC §1, §3)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from ..algebras import GL, SO, SU, Array, LieAlgebra, U, frobenius_norm
from ..backends import device_of, from_host, is_numpy, namespace
from ..errors import LieflowError


def _real_trace(P: Array) -> Array:
    """``Re tr P`` over the last two axes: numpy's own methods for a numpy array (the same
    numbers as ``np.real(np.trace(P, axis1=-2, axis2=-1))`` without the wrappers, 2 µs less
    per call: the Casimirs are evaluated once per chunk of a run), else those functions."""
    if isinstance(P, np.ndarray):
        t = P.trace(axis1=-2, axis2=-1)
        return t.real if P.dtype.kind == "c" else t
    if is_numpy(P):
        return np.real(np.trace(P, axis1=-2, axis2=-1))
    xp = namespace(P)  # another array library (lieflow.backends)
    t = xp.linalg.trace(P)
    return xp.real(t) if xp.isdtype(t.dtype, "complex floating") else t


def read_only(arr: np.ndarray) -> np.ndarray:
    """``arr`` made read-only (in place) and returned: a system's constant arrays, so that
    nothing can change a system after it was built (the compiled engine keeps values
    derived from it, :func:`lieflow.engines.compiled.plan`). Pass an array the system owns (a
    copy)."""
    arr.setflags(write=False)
    return arr


def table_like(table: np.ndarray, W: Array) -> Array:
    """A system's constant ``table`` (float64) in the real precision of ``W`` (a float32
    state stays float32), for products with ``W`` (the rigid bodies' weights, Toda's signs);
    ``table`` itself for a double-precision ``W`` (no dtype promotion per call); for ``W``
    of another array library (:mod:`lieflow.backends`) a copy on its device (small)."""
    if type(W) is np.ndarray and W.dtype.char == "d":  # the common case first (per update)
        return table
    if not is_numpy(W):
        xp = namespace(W)
        single = W.dtype in (xp.float32, xp.complex64)
        return from_host(table, W, xp.float32 if single else xp.float64)
    dtype = W.dtype if isinstance(W, np.ndarray) else np.asarray(W).dtype
    if dtype.char in "dD":
        return table
    return table.astype(np.result_type(np.asarray(W).real.dtype, np.float32), copy=False)


class IsospectralSystem(ABC):
    """An isospectral Lie–Poisson system ``dW/dt = [B(W), W]`` on a matrix Lie algebra.

    ``B(W) = (grad eta(W))^†`` for the Hamiltonian ``eta`` (SPEC §1). To add a system,
    subclass and provide :attr:`algebra` (a class attribute, property or attrs field),
    :meth:`B` and :meth:`hamiltonian`::

        class Euler3(IsospectralSystem):
            algebra = lieflow.algebras.SO(3)
            linear_B = True
            def B(self, W): return -W * weights
            def hamiltonian(self, W): return 0.5 * np.sum(W * W * weights, axis=(-2, -1))

    Every method must broadcast over leading axes: ``W`` has shape ``(..., n, n)``.

    Attributes
    ----------
    linear_B : bool
        Whether ``B`` is linear. Then its derivative is ``B`` itself and Newton needs
        nothing more; a nonlinear ``B`` should override :meth:`B_derivative`.
    casimir_powers : tuple of int
        The ``k`` in the default Casimirs ``tr W^k`` (capped at ``n``).
    underflow_guard : float
        The relative threshold ``τ`` of the underflow guard (:mod:`lieflow.underflow`): the
        schemes' stage maps set every real number below ``τ`` times its matrix's largest to
        zero before a product, so that no product goes subnormal (slow on Intel cores);
        ``0`` (the default) leaves every number as it is. States of large systems with
        smooth, rapidly decaying spectra need it (Euler–Zeitlin sets it from N = 512).
    """

    linear_B: ClassVar[bool] = False
    casimir_powers: ClassVar[tuple[int, ...]] = (2, 3, 4)
    underflow_guard: float = 0.0

    @property
    @abstractmethod
    def algebra(self) -> LieAlgebra:
        """The Lie algebra ``W`` lives in."""

    @abstractmethod
    def B(self, W: Array) -> Array:
        """The map ``B(W) = (grad eta(W))^†`` (one call per stage and iteration)."""

    @abstractmethod
    def hamiltonian(self, W: Array) -> Array:
        """The Hamiltonian ``eta(W)``, shape ``W.shape[:-2]``."""

    @property
    def name(self) -> str:
        """A short human-readable name."""
        return type(self).__name__

    @property
    def hadamard_factor(self) -> Array | None:
        r"""The constant matrix ``S`` with :math:`B(W) = S \odot W` (entrywise product), or
        ``None`` (the default) when ``B`` is not of that form.

        Rigid bodies (:math:`B = -\mathcal I^{-1}W`, SPEC §3) and the periodic Toda lattice
        are. From ``S`` the default :meth:`compiled_B` is derived, so such a system runs on
        :func:`lieflow.integrate`'s compiled engine. A subclass that overrides :meth:`B`
        must override this property too (or return ``None``).
        """
        return None

    def compiled_B(self, shift: float = 0.0) -> tuple[Any, Array] | None:
        """``B`` of a stage value for the compiled engine (:mod:`lieflow.engines.compiled`), or
        ``None`` (then the engine refuses the system and ``engine="auto"`` uses numpy).

        Returns ``(function, params)``: a numba-compiled ``function(W, params, out)`` that
        writes ``B(V) - shift V``, ``V = project_stage(W)`` — what
        :class:`~lieflow.schemes.base.StageProblem` evaluates — into ``out`` (``W``,
        ``out``: C-contiguous ``(n, n)`` of the data's dtype, ``float64`` or, on u(n) and
        su(N), ``complex128``; ``params``: a ``float64`` vector of the system's constants).
        ``shift`` is the Casimir shift ``c`` of
        :class:`~lieflow.systems.shifted.CasimirShifted` (``B - cW``, the same flow); a
        system whose map cannot fold one in returns ``None`` for ``shift != 0``, and so must
        one whose stage values leave the span of its phase space under ``B - cW`` (the
        loops' commutator update uses the stage value itself, the numpy path its
        projection): the Toda lattice, where ``B - cW`` is not skew. It reaches the loops
        as a typed first-class function, so numba's disk cache of the loops stays valid for
        every system; compile it with ``numba.njit(cache=True)`` at module level (or
        the decorator :func:`lieflow.engines.compiled.compiled_map`) so that it is cached too;
        lieflow's
        own maps (:data:`lieflow.engines.map_checks.MAPS`) are returned by name (``("hadamard_B",
        params)``: the system need not import the engine) or called. The engine checks it
        against :meth:`B` and :meth:`project_stage` on the initial state (to roundoff)
        before use, once per system and dtype while this method returns the same function
        and ``params`` (the engine keeps the check, :func:`lieflow.engines.compiled.plan`; a system
        whose ``B`` changes after it was built must show the change in ``params`` to be
        checked again). Importing numba inside this method keeps it optional.

        The default is derived from :attr:`hadamard_factor` ``S`` for the algebra's own
        stage projection on so(n) (``(S - shift) ⊙ (W - W^T)/2``) and gl(n)
        (``(S - shift) ⊙ W``); ``None`` otherwise. The point-vortex plugin
        (``lieflow_vortices``) shows a nonlinear one, the Euler–Zeitlin plugin
        (``lieflow_zeitlin``) a complex one (a Laplacian solve).
        """
        S = self.hadamard_factor
        if S is None or type(self).project_stage is not IsospectralSystem.project_stage:
            return None
        kind = type(self.algebra)
        if kind is not SO and kind is not GL:
            return None
        fn = "hadamard_B_skew" if kind is SO else "hadamard_B"  # lieflow's own, by name
        if shift == 0.0:  # S itself, copied (x - 0.0 is x: the same params, one pass less)
            return fn, np.array(S, dtype=np.float64, order="C").ravel()
        return fn, np.ascontiguousarray(np.asarray(S) - shift, dtype=np.float64).ravel()

    def compiled_project(self) -> tuple[Any, Array] | None:
        """:meth:`project` for the compiled engine, applied to each new state inside its
        loops as the numpy path does; ``(function, params)`` as for :meth:`compiled_B`
        (``function(W, params, out)`` writes ``project(W)`` into ``out``, which may be
        ``W``), or ``None``: the engine then projects each chunk's states with
        :meth:`project` once the chunk is done — exact when the loops keep states on the
        phase space anyway (so(n), gl(n), the default there). On u(n) and su(N) the default
        is the algebra's projection, compiled (skew-Hermitian part, trace removed on su(N)),
        when :meth:`project` is the algebra's."""
        if type(self).project is not IsospectralSystem.project or not isinstance(self.algebra, U):
            return None
        return "skew_hermitian_part", np.array([isinstance(self.algebra, SU)], float)

    def B_derivative(self, W: Array, dW: Array) -> Array:
        """Fréchet derivative ``B'(W)[dW]``; needed by Newton's method (SPEC §5).

        The default is ``B(dW)`` for a linear ``B``; a nonlinear ``B`` must override it.
        """
        if self.linear_B:
            return self.B(dW)
        raise LieflowError(
            f"{self.name} has a nonlinear B but does not implement B_derivative(W, dW); "
            "implement it to use Newton's method, or use FixedPoint or FrozenB"
        )

    def project(self, W: Array) -> Array:
        """The nearest point of the system's *phase space* to ``W`` (Frobenius norm), O(n²).

        The phase space is the set the exact flow keeps states in: the algebra itself
        (default, :meth:`LieAlgebra.project <lieflow.LieAlgebra.project>`), or a subset of it
        (symmetric matrices for the periodic Toda lattice, products of spheres for point
        vortices). Integrators apply it to each new state, so that no defect (roundoff, or
        the solver's tolerance) can accumulate along a transversally unstable direction.
        It must not change a state that is already on the phase space by more than
        roundoff, and it must keep the precision of ``W`` (float32 stays float32).
        Broadcasts over leading axes.
        """
        return self.algebra.project(W)

    def project_stage(self, W: Array) -> Array:
        """Orthogonal projection onto the *linear span* of the phase space, O(n²).

        Applied to stage values before ``B`` is evaluated: stage values of a Runge–Kutta
        step lie in the span of the phase space at the fixed point, but not on the phase
        space itself when that is curved (a stage value of a point-vortex step is not on
        the spheres ``|m_i| = |Γ_i|``). Being linear, it commutes with the scheme's linear
        combinations and leaves the fixed point unchanged. The default is
        :meth:`project` when that is linear, i.e. the algebra's projection; systems whose
        phase space is curved override both.
        """
        return self.algebra.project(W)

    def stage_B(self, W: Array) -> Array:
        """``B(project_stage(W))``: ``B`` at stage values, what the schemes' fixed-point maps
        evaluate on every update (:class:`~lieflow.schemes.base.StageProblem`).

        The default composes the two maps; a system may compute it in fewer passes over
        ``W`` (the rigid bodies: one product less), bit for bit the composition.
        """
        return self.B(self.project_stage(W))

    def phase_space_distance(self, W: Array) -> Array:
        """``||W - project(W)||_F / ||W||_F``: relative distance from the phase space.

        Shape ``W.shape[:-2]`` (batched over leading axes); 0 for the zero matrix.
        """
        W = np.asarray(W)
        tiny = np.finfo(W.real.dtype).tiny if W.dtype.kind in "fc" else np.finfo(float).tiny
        scale = np.maximum(frobenius_norm(W), tiny)
        dist: Array = frobenius_norm(W - self.project(W)) / scale
        return dist

    def casimirs(self, W: Array) -> Array:
        """Casimirs ``Re tr W^k`` for ``k`` in :attr:`casimir_powers`, last axis indexes k."""
        powers = [k for k in self.casimir_powers if k <= self.algebra.n]
        out = []
        P = W
        for k in range(2, max(powers, default=1) + 1):
            P = P @ W
            if k in powers:
                out.append(_real_trace(P))
        if 1 in powers:
            out.insert(0, _real_trace(W))
        if not is_numpy(W):  # another array library (lieflow.backends)
            xp = namespace(W)
            if not out:
                return xp.zeros((*W.shape[:-2], 0), dtype=W.dtype, device=device_of(W))
            return xp.stack(out, axis=-1)
        if not out:
            return np.zeros((*W.shape[:-2], 0))
        if isinstance(W, np.ndarray) and W.ndim == 2:  # one state: a vector of scalars
            return np.array(out)
        return np.stack(out, axis=-1)

    def random_state(self, seed: int | np.random.Generator | None = None) -> Array:
        """A seeded random initial condition of unit Frobenius norm (test and demo input).

        The default draws from the algebra; systems whose phase space is smaller (symmetric
        Toda matrices, vortices on spheres) override it.
        """
        W = self.algebra.random(seed)
        return W / frobenius_norm(W)

    def validate(self, W0: ArrayLike, tol: float = 1e-12) -> Array:
        """Check an initial condition and return it as a fresh array (raises InputError)."""
        return self.algebra.validate(W0, name="W0", tol=tol)

    def casimir_scale(self, W0: Array) -> Array:
        """``||W0||_F^k`` for each Casimir ``tr W^k``: divides Casimir drift to make it
        dimensionless (``tr W^3`` of an so(n) matrix is zero, so no relative error exists)."""
        powers = [k for k in self.casimir_powers if k <= self.algebra.n]
        if type(W0) is np.ndarray and W0.ndim == 2 and W0.dtype.char == "d":
            # one real state: the norm by one dot product and its powers in Python floats
            # (equal to the array formula below to roundoff; a few µs less per run)
            x = W0.ravel()
            f = math.sqrt(float(x @ x))
            return np.array([max(f**k, 1e-300) for k in powers], dtype=float)
        return np.maximum(frobenius_norm(W0)[..., None] ** np.array(powers), 1e-300)

    def __repr__(self) -> str:
        return f"{self.name}(algebra={self.algebra})"
