"""lieflow-vortices: K point vortices on the unit sphere as an isospectral so(3)^K system.

A lieflow plugin built on lieflow's public API only; installing the distribution registers
the system ``"point_vortices"`` through the ``lieflow`` entry-point group::

    import lieflow as lf
    system = lf.systems.get("point_vortices", strengths=(1.0, 1.0, 1.0, -1.0))
    W0 = system.random_initial_condition(seed=0)
    sol = lf.integrate(system, lf.schemes.get("gauss3"), W0, h=0.05, steps=200)
"""

from __future__ import annotations

from .algebra import BlockSO3, block_hat, block_vee, diagonal_blocks
from .system import COLLISION_GAP, PointVortices, random_positions

__all__ = [
    "COLLISION_GAP",
    "BlockSO3",
    "PointVortices",
    "block_hat",
    "block_vee",
    "diagonal_blocks",
    "random_positions",
]
