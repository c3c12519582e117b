"""The result of :func:`lieflow.integrate`."""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Any

import attrs
import numpy as np

from .algebras import Array
from .errors import ConvergenceError, InputError
from .systems.base import IsospectralSystem


class Status(str, enum.Enum):
    """How a run ended."""

    SUCCESS = "success"
    FAILED = "failed"


@attrs.frozen(eq=False)
class Solution:
    """A trajectory with its diagnostics (SPEC §6).

    Attributes
    ----------
    t, W : ndarray
        Saved times ``(n_saved,)`` and states ``(n_saved, *batch, n, n)``; the initial state
        and the last computed state are always saved.
    saved_steps : ndarray
        Step index of each saved state (0 is the initial condition).
    iterations : ndarray
        Solver updates per completed step, ``(n_steps,)``.
    solvers : tuple of str
        The solver that finished each step (differs from the requested one under ``"auto"``).
    energy_error : ndarray or None
        ``|eta(W_k) - eta(W_0)| / |eta(W_0)|`` for ``k = 0..n_steps``, shape
        ``(n_steps + 1, *batch)``; ``None`` if diagnostics were off.
    casimir_drift : ndarray or None
        ``|C_j(W_k) - C_j(W_0)| / ||W_0||^{k_j}`` per step and Casimir, shape
        ``(n_steps + 1, *batch, n_casimirs)``.
    status : Status
        ``SUCCESS``, or ``FAILED`` with :attr:`failure` set (``on_failure="truncate"``).
    failure : ConvergenceError or None
        What went wrong, at which step.
    wall_time : float
        Seconds spent stepping.
    extra : dict of str to ndarray
        The system's own diagnostics (``system.extra_diagnostics``, e.g. Euler–Zeitlin's
        spectra), sampled every ``system.diagnostics_every`` steps (default: every saved
        state): ``"step"``, ``"t"`` and one array per name, one row per sample; empty if the
        system has none or diagnostics were off.
    """

    system: IsospectralSystem
    scheme: str
    h: float
    t: Array
    W: Array = attrs.field(repr=False)
    saved_steps: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    solvers: tuple[str, ...] = attrs.field(repr=False)
    energy_error: Array | None = attrs.field(repr=False)
    casimir_drift: Array | None = attrs.field(repr=False)
    status: Status
    failure: ConvergenceError | None
    wall_time: float
    extra: Mapping[str, Array] = attrs.field(factory=dict, repr=False)

    @property
    def n_steps(self) -> int:
        """Completed steps."""
        return int(self.iterations.shape[0])

    @property
    def W_final(self) -> Array:
        """The last computed state."""
        return self.W[-1]

    @property
    def t_final(self) -> float:
        """Time of the last computed state."""
        return float(self.t[-1])

    @property
    def success(self) -> bool:
        """Whether every requested step was computed."""
        return self.status is Status.SUCCESS

    def to_xarray(self) -> Any:
        """This solution as an :class:`xarray.Dataset` (in memory), with the dimensions and
        names of :func:`lieflow.open_run`: ``W (time, [ensemble,] row, col)``, ``W_final``,
        ``iterations (step)``, ``energy_error (step, [ensemble])`` and ``casimir_drift
        (step, [ensemble,] casimir)`` (left out when diagnostics were off), coordinates
        ``time``, ``saved_step``, ``step``, ``step_time``, ``casimir``, ``ensemble``. Needs
        the ``sweep`` extra (``pip install 'lieflow[sweep]'``).

        Raises
        ------
        InputError
            ``xarray`` is not installed, or ``W`` has more than one batch dimension.
        """
        try:
            import xarray as xr
        except ImportError as exc:
            raise InputError(
                "Solution.to_xarray needs xarray: pip install 'lieflow[sweep]'"
            ) from exc
        W = np.asarray(self.W)
        batch = W.shape[1:-2]
        if len(batch) > 1:
            raise InputError(f"one batch dimension at most, got W of shape {W.shape}")
        ens = ("ensemble",) if batch else ()
        k = np.arange(self.n_steps + 1)
        iterations = np.concatenate([[0], np.asarray(self.iterations, dtype=np.int64)])
        variables: dict[str, Any] = {
            "W": (("time", *ens, "row", "col"), W),
            "W_final": ((*ens, "row", "col"), W[-1]),
            "iterations": (("step",), iterations),
        }
        if self.energy_error is not None:
            variables["energy_error"] = (("step", *ens), np.asarray(self.energy_error))
        if self.casimir_drift is not None:
            variables["casimir_drift"] = (("step", *ens, "casimir"),
                                          np.asarray(self.casimir_drift))  # fmt: skip
        system = self.system
        powers = [p for p in system.casimir_powers if p <= system.algebra.n]
        coords: dict[str, Any] = {
            "time": ("time", np.asarray(self.t)),
            "saved_step": ("time", np.asarray(self.saved_steps)),
            "step": ("step", k),
            "step_time": ("step", k * self.h),
        }
        if self.casimir_drift is not None:
            coords["casimir"] = ("casimir", np.asarray(powers[: self.casimir_drift.shape[-1]]))
        if batch:
            coords["ensemble"] = ("ensemble", np.arange(batch[0]))
        attrs_ = {
            "system": system.name,
            "scheme": str(self.scheme),
            "h": float(self.h),
            "status": self.status.value,
            "completed_steps": self.n_steps,
            "wall_time": float(self.wall_time),
            "failure": "" if self.failure is None else str(self.failure),
        }
        return xr.Dataset(variables, coords=coords, attrs=attrs_)

    def spectrum_drift(self) -> Array:
        """``max_i |lambda_i(W_k) - lambda_i(W_0)| / max_i |lambda_i(W_0)|`` per saved state.

        Eigenvalues of ``W_k`` are matched to those of ``W_0`` by a minimum-cost assignment,
        so clusters and roundoff-level real parts cannot mis-pair them.
        """
        from scipy.optimize import linear_sum_assignment  # 0.1-0.3 s to import: on first use

        lam = np.linalg.eigvals(self.W)
        flat = lam.reshape(lam.shape[0], -1, lam.shape[-1])
        out = np.empty(flat.shape[:2])
        for b in range(flat.shape[1]):
            ref = flat[0, b]
            scale = max(float(np.max(np.abs(ref))), np.finfo(float).tiny)
            for k in range(flat.shape[0]):
                cost = np.abs(flat[k, b][:, None] - ref[None, :])
                rows, cols = linear_sum_assignment(cost)
                out[k, b] = np.max(cost[rows, cols]) / scale
        return out.reshape(lam.shape[:-1])

    def phase_space_distance(self) -> Array:
        """Relative distance ``||W - P(W)||_F / ||W||_F`` of each saved state from the
        system's phase space (:meth:`IsospectralSystem.project`): symmetric matrices for the
        periodic Toda lattice, traceless skew-Hermitian ones for su(N), the spheres
        ``|m_i| = |Γ_i|`` for point vortices, the algebra otherwise.

        Shape ``(n_saved, *batch)``.
        """
        return self.system.phase_space_distance(self.W)

    def algebra_distance(self) -> Array:
        """Alias of :meth:`phase_space_distance` (kept for old code).

        Before lieflow 0.2 this measured the distance from the algebra only, which is
        identically 0 for gl(n) (the Toda lattice): the phase space is the stronger test.
        Use ``system.algebra.distance(sol.W)`` for the old meaning.
        """
        return self.phase_space_distance()
