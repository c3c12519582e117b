"""The ``lieflow`` entry point of this distribution: registers the system ``"euler_zeitlin"``,
its ``lieflow plot`` figures, and the dissipative and forcing sub-flows for ``[splitting]``
(``zeitlin_viscosity``, ``zeitlin_hyperviscosity``, ``zeitlin_drag``, ``zeitlin_forcing``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lieflow

from .dissipation import Hyperviscosity, LinearDrag, StochasticForcing, Viscosity
from .system import EulerZeitlin


def plot_run(trajectory: Any, out_dir: Path, stem: str) -> list[Path]:
    """Vorticity snapshots, drift, spectra, vorticity distribution and statistics of an
    ``euler_zeitlin`` run (imports matplotlib lazily: :func:`lieflow_zeitlin.plotting.plot_run`)."""
    from .plotting import plot_run as plot

    return plot(trajectory, out_dir, stem)


def movie(trajectory: Any, path: Path, progress: Any = None) -> Path:
    """The vorticity of every saved state as a movie (``.mp4`` or ``.gif``):
    :func:`lieflow_zeitlin.movie.save_movie`, for ``lieflow plot FILE --movie OUT``."""
    from .movie import save_movie

    return save_movie(trajectory, path, progress=progress)


#: ``lieflow plot --movie`` looks for a ``movie(trajectory, path, progress)`` attribute on a
#: system's plotter function.
plot_run.movie = movie  # type: ignore[attr-defined]


def viscosity(system: EulerZeitlin, nu: float, method: str = "exact") -> Viscosity:
    """Viscosity ``ν Δ`` (exact per-degree decay, or ``method = "crank_nicolson"``)."""
    return Viscosity(system, nu=nu, method=method)  # type: ignore[arg-type]


def hyperviscosity(system: EulerZeitlin, nu: float, order: int = 2) -> Hyperviscosity:
    """Hyperviscosity ``(-1)^{p+1} ν Δ^p`` (exact per-degree decay), ``order = p``."""
    return Hyperviscosity(system, nu=nu, order=order)


def drag(system: EulerZeitlin, mu: float) -> LinearDrag:
    """Linear drag ``-μ ζ`` (exact)."""
    return LinearDrag(system, mu=mu)


def forcing(
    system: EulerZeitlin, amplitude: float, l1: int, l2: int, seed: int = 0
) -> StochasticForcing:
    """White-in-time stochastic forcing in the degrees ``l1..l2`` (seeded, resumable)."""
    return StochasticForcing(system, amplitude=amplitude, l1=l1, l2=l2, seed=seed)


@lieflow.hookimpl
def lieflow_register(registry: lieflow.RegistryBuilder) -> None:
    """Register :class:`~lieflow_zeitlin.EulerZeitlin` as the system ``"euler_zeitlin"``,
    its ``lieflow plot`` figures, and the flows of :mod:`lieflow_zeitlin.dissipation`."""
    registry.add_system(
        "euler_zeitlin",
        EulerZeitlin,
        "Euler equations on the (rotating) sphere and the QG model, Zeitlin's su(N) model",
    )
    registry.add_plotter(
        "euler_zeitlin", plot_run, "vorticity snapshots on the sphere, energy/enstrophy drift"
    )
    if hasattr(registry, "add_flow"):  # lieflow with [splitting] support
        registry.add_flow(
            "zeitlin_viscosity",
            viscosity,
            "euler_zeitlin: viscosity nu*Laplacian (params nu, method = exact|crank_nicolson)",
        )
        registry.add_flow(
            "zeitlin_hyperviscosity",
            hyperviscosity,
            "euler_zeitlin: hyperviscosity (-1)^(p+1) nu Laplacian^p (params nu, order = p)",
        )
        registry.add_flow("zeitlin_drag", drag, "euler_zeitlin: linear drag -mu*vorticity (mu)")
        registry.add_flow(
            "zeitlin_forcing",
            forcing,
            "euler_zeitlin: white-in-time noise in degrees l1..l2 (amplitude, l1, l2, seed)",
        )
