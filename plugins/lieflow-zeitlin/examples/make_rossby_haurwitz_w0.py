"""Write ``rossby_haurwitz_n32.npy``, the initial state of ``rossby_haurwitz_n32.toml``.

    python plugins/lieflow-zeitlin/examples/make_rossby_haurwitz_w0.py

The relative vorticity ``ζ = a cos θ + ε sin⁴θ cos 4φ`` (a = 1, ε = 0.1: solid-body rotation
plus a sectoral degree-4 wave), sampled on a Gauss grid and quantized, then turned into the
state of the quasi-geostrophic model on the rotating sphere (potential vorticity
``q = ζ - Fψ + 2Ω cos θ``, ``Ω = 6``, ``F = 10``) by ``EulerZeitlin.from_relative``. The wave
is an exact solution; it moves *west* at ``c = ((a/2)(l(l+1) - 2) - 2Ω)/(l(l+1) + F) = -0.1``.
"""

from __future__ import annotations

from pathlib import Path

import lieflow_zeitlin as lz
import numpy as np

N, L, A, EPS, OMEGA, LAMB = 32, 4, 1.0, 0.1, 6.0, 10.0


def initial_state() -> np.ndarray:
    """The state ``Q(q)`` of the example."""
    grid = lz.SphereGrid.for_size(N)
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    zeta = A * np.cos(theta) + EPS * np.sin(theta) ** L * np.cos(L * phi)
    system = lz.EulerZeitlin(N, rotation=OMEGA, lamb=LAMB)
    W = system.from_relative(lz.grid_to_matrix(zeta, grid, N))
    return lz.VorticityAlgebra(N).project(W)  # exactly skew-Hermitian and traceless


if __name__ == "__main__":
    path = Path(__file__).with_name("rossby_haurwitz_n32.npy")
    np.save(path, initial_state())
    print(path)
