"""``lieflow reproduce``: rerun the paper's numerical experiments and compare with its tables.

The paper ("Efficient Implementation of high-order isospectral symplectic Runge–Kutta
schemes", section *Numerical experiments*) runs four integrators — 1s-SyDIRK (``midpoint``),
7s-SyDIRK (``sydirk7``), 2s-Gauss (``gauss2``) and 3s-Gauss (``gauss3``) — on

* the rigid body on so(3): N = 2000 steps, h = 0.1 and 0.01, random ``W0``, tolerance 1e-15;
* the periodic Toda lattice, n = 4, the paper's ``W0``: N = 1000, h = 0.1 and 0.01,
  tolerance 1e-14;
* the generalized rigid body on so(n), n = 10, 20, 50: N = 2000, h = 0.01, tolerance 1e-14;

28 runs. The paper states neither the rigid body's inertia nor the generalized rigid body's
``J`` nor its random ``W0``; lieflow's choices, all derived from one recorded seed ``s``:

* rigid body: principal moments (1, 2, 3), ``W0 = SO(3).random(seed=s)``;
* generalized rigid body on so(n): ``J_i`` uniform in [1, 2)
  (``GeneralizedRigidBody.random_inertia(n, seed=s)``), ``W0 = SO(n).random(seed=s + 1)``
  (i.i.d. standard normal entries, skew-symmetrised).

Every run uses ``FixedPoint(rtol=tol)`` — a relative test, SPEC §5 — with lieflow's default
warm starts; ``gauss2``/``gauss3`` use lieflow's default reduced stage form of the block
algorithm (SPEC §4.5: the same fixed point, fewer products). lieflow counts iterations as
updates performed, one more than the paper counts (SPEC §5); the report shows both.

Those defaults are not the paper's algorithm, so the Toda iteration table (Table 4) also
reruns the paper's algorithm itself (:func:`run_paper_algorithm`): the block form of SPEC
§4.3 for the Gauss schemes, cold starts (the ``h = 0`` guess every step) and the paper's
absolute stopping test ``||X_{k+1} - X_k||_F <= tol``; its counts are compared with the
published ones, and lieflow's defaults are shown in a separate, labelled column.

The package's modules: ``_cases`` (the paper's cases and tables, one run measured),
``_report`` (figures, CSV, report) and ``_run`` (:func:`reproduce`, :func:`reproduce_study`).
"""

from __future__ import annotations

from ..reports import machine_description
from ._cases import (
    ITERATION_SCHEMES,
    SCHEMES,
    Case,
    CaseResult,
    Published,
    paper_cases,
    published,
    run_case,
    run_paper_algorithm,
    warm_up,
)
from ._report import _like_with_like_table as _like_with_like_table
from ._run import STUDIES, ReproduceResult, reproduce, reproduce_study

__all__ = [
    "ITERATION_SCHEMES",
    "SCHEMES",
    "STUDIES",
    "Case",
    "CaseResult",
    "Published",
    "ReproduceResult",
    "machine_description",
    "paper_cases",
    "published",
    "reproduce",
    "reproduce_study",
    "run_case",
    "run_paper_algorithm",
    "warm_up",
]
