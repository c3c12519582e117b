r"""``lieflow reproduce modin-viviani-2020``: the long-time fate of 2D Euler on the sphere
against the first integral ``γ = ‖L‖/√C₂`` (Modin & Viviani, "A Casimir preserving scheme for
long-time simulation of spherical ideal hydrodynamics", J. Fluid Mech. 884:A22, 2020).

The paper runs the isospectral midpoint rule on Zeitlin's su(N) model from random smooth
vorticity, without hyperviscosity, for long times, and finds that the flow settles into 2, 3
or 4 coherent vortex structures, the outcome correlating with ``γ``: small ``γ`` mostly 4,
intermediate 3, large 2. This module reruns that experiment as one command:

1. **Initial data** (:func:`initial_states`): for every ``γ`` of the plan and every seed,
   :func:`lieflow_zeitlin.random_vorticity_gamma` — random coefficients in a band of
   intermediate degrees plus the solid-body rotation that gives ``‖L‖ = γ√C₂`` (axis ``z``),
   rms vorticity 1 — written as ``initial/g<γ>-s<seed>.npy``, with its measured ``γ``,
   energy and Casimirs.
2. **Runs** (:func:`grid_text`, :func:`lieflow.app.sweeps.sweep`): one sweep over those
   files (local process pool or Dask; resumable; ``[run] device`` passed through), each run
   the isospectral midpoint rule with the isospectral (Cayley) update, no dissipation.
   Runs with ``γ > 0`` are stepped in the frame that turns with their solid-body part:
   ``EulerZeitlin(rotation=Ω)``, ``Ω = 3L_z/8π``, with the state the (absolute) vorticity —
   the same flow, exactly, seen from a rotating frame (``L`` is conserved), without the
   fast rotation that otherwise limits the step of the fixed-point iteration (the states
   differ from the inertial frame's by a rotation about ``z``, which the detector does not
   see).
3. **Analysis** (:func:`analyse`): the coherent-vortex detector
   (:class:`lieflow_zeitlin.VortexDetector`) on every saved state of every run; the outcome
   of a run is the most frequent count over the last ``settle`` fraction of the run. The
   trend is Spearman's rank correlation between ``γ`` and the outcome, with a bootstrap
   confidence interval over runs (:func:`rank_trend`), repeated for other detector settings.
4. **Outputs**: ``modin_viviani_2020.png`` (outcome against ``γ``, the count along every run,
   final vorticity of typical 2-, 3- and 4-vortex runs with the detected centres, energy and
   Casimir drift of every run, the coarse-grained vorticity distribution — the "staircase"
   — of the 4-vortex runs), ``report.md``, ``results.csv`` (one row per run) and
   ``results.nc`` (the same and the count time series as an :mod:`xarray` dataset); the
   trajectories stay in ``sweep/`` (:func:`lieflow.open_sweep`).

The package's modules: ``plan`` (variants, initial data, the grid), ``analysis`` (detector
outcomes, the trend), ``figure``, ``report`` (CSV, dataset, Markdown) and ``study``
(:func:`reproduce_modin_viviani`).
"""

from __future__ import annotations

from .analysis import Analysis, RunResult, Trend, analyse, rank_trend
from .plan import PLANS, STUDY, InitialState, Plan, grid_text, initial_states
from .study import StudyResult, reproduce_modin_viviani

__all__ = [
    "PLANS",
    "STUDY",
    "Analysis",
    "InitialState",
    "Plan",
    "RunResult",
    "StudyResult",
    "Trend",
    "analyse",
    "grid_text",
    "initial_states",
    "rank_trend",
    "reproduce_modin_viviani",
]
