"""lieflow's own systems, schemes and solvers, registered through the ``lieflow`` entry
point exactly as a third-party plugin registers its own."""

from __future__ import annotations

from typing import Literal

from . import tableaus
from .plugins import RegistryBuilder, hookimpl
from .schemes import BlockGauss, ModinViviani, SyDIRK
from .solvers import Auto, FixedPoint, FrozenB, Newton
from .systems import GeneralizedRigidBody, PeriodicToda, RigidBody


def gauss_scheme(
    stages: int = 2, form: Literal["reduced", "block"] = "reduced", update: str = "commutator"
) -> BlockGauss:
    """Gauss–Legendre ISOSyRK of order 2s via the block algorithm (any number of stages)."""
    return BlockGauss(tableaus.gauss(stages), form=form, update=update)


def modin_viviani_scheme(stages: int = 2, update: str = "commutator") -> ModinViviani:
    """Classic Modin–Viviani 3s+s^2 form with the s-stage Gauss tableau (reference)."""
    return ModinViviani(tableaus.gauss(stages), update=update)


@hookimpl
def lieflow_register(registry: RegistryBuilder) -> None:
    """Register the built-ins."""
    registry.add_system("rigid_body", RigidBody, "free rigid body on so(3), principal inertia")
    registry.add_system(
        "generalized_rigid_body", GeneralizedRigidBody, "Manakov generalized rigid body on so(n)"
    )
    registry.add_system("periodic_toda", PeriodicToda, "periodic Toda lattice on gl(n)")

    registry.add_scheme("midpoint", SyDIRK, "implicit midpoint rule (1s-SyDIRK), order 2")
    registry.add_scheme(
        "sydirk7",
        lambda update="commutator": SyDIRK(tableaus.yoshida6(), update=update),
        "7-stage SyDIRK (Yoshida), order 6",
    )
    registry.add_scheme(
        "triple_jump",
        lambda update="commutator": SyDIRK(tableaus.triple_jump(), update=update),
        "triple-jump SyDIRK, order 4",
    )
    registry.add_scheme(
        "suzuki5",
        lambda update="commutator": SyDIRK(tableaus.suzuki5(), update=update),
        "Suzuki 5-stage SyDIRK, order 4",
    )
    registry.add_scheme("gauss", gauss_scheme, "Gauss–Legendre with `stages` stages, order 2s")
    for s in (2, 3, 4):
        registry.add_scheme(
            f"gauss{s}",
            lambda s=s, form="reduced", update="commutator": gauss_scheme(s, form, update),
            f"{s}-stage Gauss–Legendre (block algorithm), order {2 * s}",
        )
    registry.add_scheme("block", BlockGauss, "block algorithm for any symplectic `tableau`")
    registry.add_scheme("modin_viviani", modin_viviani_scheme, modin_viviani_scheme.__doc__ or "")

    registry.add_solver("fixed_point", FixedPoint, "fixed-point iteration (optionally Anderson)")
    registry.add_solver("newton", Newton, "Newton with exact derivative (dense or GMRES)")
    registry.add_solver("frozen_b", FrozenB, "frozen-B quasi-Newton (Cayley-type) iteration")
    registry.add_solver("auto", Auto, "fixed point, falling back to Newton on failure")
