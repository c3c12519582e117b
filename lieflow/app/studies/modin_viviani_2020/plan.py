"""The variants of the study (:data:`PLANS`), its initial conditions (:func:`initial_states`)
and the sweep that runs them (:func:`grid_text`)."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ....errors import InputError

STUDY = "modin-viviani-2020"

Log = Callable[[str], None]


def _plugin() -> Any:
    try:
        import lieflow_zeitlin
    except ImportError:
        raise InputError(
            f"reproduce {STUDY} needs the fluids plugin lieflow-zeitlin. To fix: pip install "
            "./plugins/lieflow-zeitlin (from lieflow's repository)"
        ) from None
    return lieflow_zeitlin


@attrs.frozen
class Plan:
    """The parameters of one variant of the study.

    Attributes
    ----------
    name : str
        ``"quick"``, ``"full"`` or ``"smoke"``.
    N : int
        Matrix size (spherical-harmonic degrees ``< N``).
    h : float
        Step size, in fluid time (rms initial vorticity 1).
    t_final : float
        Length of every run.
    save_every : int
        Steps between the saved states (the detector's samples).
    gammas : tuple of float
        The values of ``γ = ‖L‖/√C₂`` (``0 <= γ <= √(4π/3)``).
    seeds : int
        Random fields per ``γ`` (seeds ``seed, seed + 1, ...``; one seed gives the same
        field shape at every ``γ``).
    degrees : (int, int)
        Band of the random part of the initial vorticity.
    rtol : float
        Relative tolerance of the fixed-point iteration.
    settle : float
        Fraction of the run, at its end, over which the outcome is taken.
    smoothing, threshold : float
        The detector's low-pass width (radians) and persistence threshold.
    staircase_smoothing : float
        Low-pass width of the coarse-grained vorticity whose distribution is the staircase.
    """

    name: str
    N: int
    h: float
    t_final: float
    save_every: int
    gammas: tuple[float, ...]
    seeds: int
    degrees: tuple[int, int] = (2, 10)
    rtol: float = 1e-10
    settle: float = 0.5
    smoothing: float = 0.3
    threshold: float = 0.2
    staircase_smoothing: float = 0.15

    @property
    def steps(self) -> int:
        """Steps of every run."""
        return round(self.t_final / self.h)

    @property
    def runs(self) -> int:
        """Number of runs."""
        return len(self.gammas) * self.seeds


#: The variants: ``smoke`` checks the pipeline in seconds (its numbers mean nothing),
#: ``quick`` is the laptop study (2 cores, minutes), ``full`` the cluster / GPU one.
PLANS: dict[str, Plan] = {
    "smoke": Plan(
        "smoke",
        N=8,
        h=0.1,
        t_final=4.0,
        save_every=10,
        gammas=(0.0, 1.2),
        seeds=2,
        degrees=(2, 4),
        smoothing=0.5,
    ),
    "quick": Plan(
        "quick",
        N=32,
        h=0.05,
        t_final=1000.0,
        save_every=200,
        gammas=(0.0, 0.15, 0.3, 0.45, 0.6, 0.75, 0.9, 1.2),
        seeds=4,
    ),
    "full": Plan(
        "full",
        N=128,
        h=0.025,
        t_final=2000.0,
        save_every=800,
        gammas=tuple(round(0.15 * k, 2) for k in range(13)),
        seeds=8,
    ),
}

#: Other detector settings whose outcomes are reported next to the default's.
ALTERNATIVES: tuple[tuple[float, float], ...] = ((0.3, 0.1), (0.3, 0.3), (0.2, 0.2), (0.45, 0.2))


@attrs.frozen
class InitialState:
    """One initial condition of the study.

    Attributes
    ----------
    gamma : float
        The prescribed ``γ``.
    seed : int
    file : str
        Its ``.npy`` file, relative to the study directory.
    rotation : float
        ``Ω = 3 L_z / 8π`` of its solid-body part: the rotation of the frame it is run in.
    measured_gamma : float
        ``γ`` of the matrix written.
    energy : float
        Kinetic energy ``½∫|∇ψ|² dΩ``.
    casimirs : tuple of float
        ``tr((iW)^k)`` for ``k = 2, 3, 4`` (``C_2 = ||W||_F²``).
    """

    gamma: float
    seed: int
    file: str
    rotation: float
    measured_gamma: float
    energy: float
    casimirs: tuple[float, ...]


def _same_array(path: Path, W: np.ndarray) -> bool:
    try:
        old = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return False
    return old.shape == W.shape and old.dtype == W.dtype and np.array_equal(old, W)


def initial_states(plan: Plan, seed: int, directory: Path) -> list[InitialState]:
    """Write the initial vorticity of every run into ``directory/initial`` and describe them.

    A file that exists already must hold the same array (a resumed study continues the same
    runs); otherwise :class:`~lieflow.InputError` is raised before anything is run.
    """
    lz = _plugin()
    (directory / "initial").mkdir(parents=True, exist_ok=True)
    c2 = 4 * math.pi  # rms vorticity 1
    system = lz.EulerZeitlin(plan.N)  # the inertial frame's energy and Casimirs
    out = []
    for g in plan.gammas:
        for s in range(seed, seed + plan.seeds):
            W = lz.random_vorticity_gamma(plan.N, g, seed=s, degrees=plan.degrees, axis=(0, 0, 1))
            name = f"initial/g{g:.3f}-s{s}.npy"
            path = directory / name
            if path.exists():
                if not _same_array(path, W):
                    raise InputError(
                        f"reproduce {STUDY}: {str(path)!r} holds another initial condition than "
                        f"this version of the study makes (gamma = {g}, seed = {s}). To fix: "
                        "give another --out directory (the runs there belong to the old data)"
                    )
            else:
                tmp = path.with_suffix(f".tmp{os.getpid()}.npy")
                np.save(tmp, W)
                os.replace(tmp, path)
            rotation = (3 / (8 * math.pi)) * g * math.sqrt(c2)  # Ω = 3 L_z / 8π, L along z
            # ½∫|∇ψ|² dΩ = η · 4πħ/N (η: the system's Hamiltonian in fluid time)
            energy = float(system.hamiltonian(W)) * 4 * math.pi * lz.hbar(plan.N) / plan.N
            out.append(
                InitialState(
                    gamma=float(g),
                    seed=s,
                    file=name,
                    rotation=rotation,
                    measured_gamma=float(lz.gamma(W)),
                    energy=energy,
                    casimirs=tuple(float(c) for c in system.casimirs(W)),
                )
            )
    return out


def grid_text(plan: Plan, states: Sequence[InitialState], device: str = "cpu") -> str:
    """The sweep grid (a ``lieflow sweep`` file) of the study: the base run and one zipped
    axis over the initial files and their frames' rotations."""
    files = ", ".join(json.dumps(s.file) for s in states)
    rotations = ", ".join(repr(s.rotation) for s in states)
    return f"""\
# lieflow reproduce {STUDY} ({plan.name}): Euler's equations on the sphere (Zeitlin, N = {plan.N})
# from random vorticity with prescribed gamma = |L|/sqrt(C2); isospectral midpoint, no
# dissipation. Each run is stepped in the frame turning with its solid-body part
# (rotation = 3 L_z / 8 pi), which is the same flow seen from a rotating frame.

[system]
name = "euler_zeitlin"
params = {{ N = {plan.N}, time = "fluid", rotation = 0.0, diagnostics_every = 0 }}

[initial]
file = {json.dumps(states[0].file)}

[scheme]
name = "midpoint"
params = {{ update = "conjugation" }}

[solver]
name = "fixed_point"
params = {{ rtol = {plan.rtol!r} }}

[run]
h = {plan.h!r}
steps = {plan.steps}
save_every = {plan.save_every}
device = {json.dumps(device)}

[sweep]
directory = "sweep"

[[sweep.zip]]
"initial.file" = [{files}]
"system.params.rotation" = [{rotations}]
"""
