"""lieflow-zeitlin: Euler's equations on the sphere as the isospectral Euler–Zeitlin system.

A lieflow plugin built on lieflow's public API only; installing the distribution registers
the system ``"euler_zeitlin"`` through the ``lieflow`` entry-point group::

    import lieflow as lf
    import lieflow_zeitlin as lz

    system = lf.systems.get("euler_zeitlin", N=64)
    W0 = lz.random_vorticity(64, degree=8, seed=0)          # smooth, rms vorticity 1
    sol = lf.integrate(system, lf.schemes.get("gauss2"), W0, h=0.01, steps=200)  # fluid time 2
    omega = lz.matrix_to_grid(sol.W_final, lz.SphereGrid.for_size(64))   # back to a field

Modules: :mod:`~lieflow_zeitlin.laplacian` (Hoppe–Yau Laplacian, O(N²) solve, quantized
harmonics), :mod:`~lieflow_zeitlin.quantization` (fields ↔ matrices),
:mod:`~lieflow_zeitlin.system` (the :class:`EulerZeitlin` system: Euler, rotating sphere,
quasi-geostrophic), :mod:`~lieflow_zeitlin.dissipation` (viscosity, hyperviscosity, drag and
stochastic forcing as lieflow flows, for ``lieflow.flows.Splitting``) and
:mod:`~lieflow_zeitlin.diagnostics` (spectra by degree, Casimirs, vorticity distribution, time
averages; stored by ``lieflow run`` under ``/diagnostics/extra``) and
:mod:`~lieflow_zeitlin.plotting` (PNG figures; needs matplotlib, imported on demand),
:mod:`~lieflow_zeitlin.momentum` (total angular momentum, Modin & Viviani's first integral
``γ = ‖L‖/√C₂`` and random initial vorticity with a prescribed ``γ``) and
:mod:`~lieflow_zeitlin.coherent` (the coherent vortex structures of a state: count, signs,
positions, strengths).
"""

from __future__ import annotations

from . import diagnostics
from .coherent import Vortex, VortexCensus, VortexDetector, fibonacci_points, low_pass
from .diagnostics import (
    energy_spectrum,
    enstrophy_spectrum,
    running_mean,
    spectra,
    time_mean,
    vorticity_levels,
)
from .dissipation import (
    Hyperviscosity,
    LinearDrag,
    StochasticForcing,
    Viscosity,
    degree_multiplier,
)
from .laplacian import HoppeYauLaplacian, harmonics, spin_matrices, tridiagonal
from .momentum import (
    GAMMA_MAX,
    angular_momentum,
    enstrophy_integral,
    gamma,
    random_vorticity_gamma,
    solid_body_rotation,
)
from .quantization import (
    SphereGrid,
    degrees_and_orders,
    grid_to_matrix,
    grid_to_sh,
    hbar,
    kappa,
    lm_index,
    matrix_to_grid,
    matrix_to_sh,
    random_sh,
    random_vorticity,
    sh_to_grid,
    sh_to_matrix,
)
from .quflow import import_quflow, read_quflow
from .system import EulerZeitlin, VorticityAlgebra

__all__ = [
    "GAMMA_MAX",
    "EulerZeitlin",
    "HoppeYauLaplacian",
    "Hyperviscosity",
    "LinearDrag",
    "SphereGrid",
    "StochasticForcing",
    "Viscosity",
    "Vortex",
    "VortexCensus",
    "VortexDetector",
    "VorticityAlgebra",
    "angular_momentum",
    "degree_multiplier",
    "degrees_and_orders",
    "diagnostics",
    "energy_spectrum",
    "enstrophy_integral",
    "enstrophy_spectrum",
    "fibonacci_points",
    "gamma",
    "grid_to_matrix",
    "grid_to_sh",
    "harmonics",
    "hbar",
    "import_quflow",
    "kappa",
    "lm_index",
    "low_pass",
    "matrix_to_grid",
    "matrix_to_sh",
    "random_sh",
    "random_vorticity",
    "random_vorticity_gamma",
    "read_quflow",
    "running_mean",
    "sh_to_grid",
    "sh_to_matrix",
    "solid_body_rotation",
    "spectra",
    "spin_matrices",
    "time_mean",
    "tridiagonal",
    "vorticity_levels",
]
