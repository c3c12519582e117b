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
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ...errors import InputError, LieflowError

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


@attrs.frozen
class Trend:
    """Spearman's rank correlation between ``γ`` and the outcome, with its uncertainty.

    Attributes
    ----------
    rho : float
        Spearman's ``ρ`` over the runs (negative: fewer structures at larger ``γ``).
    low, high : float
        The 95 % bootstrap interval (percentiles of ``ρ`` over ``resamples`` resamplings of
        the runs with replacement).
    p_value : float
        Two-sided p-value of ``ρ = 0`` (scipy's t approximation).
    runs : int
    resamples : int
    """

    rho: float
    low: float
    high: float
    p_value: float
    runs: int
    resamples: int

    def describe(self) -> str:
        """``ρ = -0.93 [-0.95, -0.86] (95 % bootstrap, n = 32, p = 4e-14)``."""
        return (
            f"ρ = {self.rho:+.2f} [{self.low:+.2f}, {self.high:+.2f}] (95 % bootstrap, "
            f"n = {self.runs}, p = {self.p_value:.1g})"
        )


def _spearman_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Spearman's ``ρ`` of each row pair of ``x`` and ``y`` (shape ``(m, n)``): the Pearson
    correlation of their ranks (ties averaged); NaN for a row without variation."""
    from scipy.stats import rankdata

    rx, ry = rankdata(x, axis=-1), rankdata(y, axis=-1)
    rx -= rx.mean(axis=-1, keepdims=True)
    ry -= ry.mean(axis=-1, keepdims=True)
    norm = np.sqrt((rx * rx).sum(axis=-1) * (ry * ry).sum(axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray((rx * ry).sum(axis=-1) / norm)


def rank_trend(
    gammas: Sequence[float], outcomes: Sequence[float], seed: int = 0, resamples: int = 2000
) -> Trend:
    """Spearman's ``ρ`` between ``gammas`` and ``outcomes`` and its bootstrap interval
    (the runs resampled with replacement ``resamples`` times; resamples without variation
    in either variable are left out).

    Raises
    ------
    InputError
        Fewer than 3 runs, or no variation in either.
    """
    from scipy.stats import spearmanr

    g = np.asarray(gammas, dtype=float)
    o = np.asarray(outcomes, dtype=float)
    keep = np.isfinite(g) & np.isfinite(o)
    g, o = g[keep], o[keep]
    if g.size < 3 or np.ptp(g) == 0 or np.ptp(o) == 0:
        raise InputError(
            f"the rank correlation needs at least 3 runs with varying gamma and outcome, got "
            f"{g.size} runs (outcomes {sorted(set(o.tolist()))})"
        )
    rho, p = spearmanr(g, o)
    draws = np.random.default_rng(seed).integers(0, g.size, size=(resamples, g.size))
    values = _spearman_rows(g[draws], o[draws])
    low, high = np.percentile(values[np.isfinite(values)], [2.5, 97.5])
    return Trend(float(rho), float(low), float(high), float(p), int(g.size), resamples)


@attrs.frozen(eq=False)
class RunResult:
    """What the analysis found in one run.

    Attributes
    ----------
    state : InitialState
    status : str
        The sweep's status of the run (``"complete"``, ``"failed"``, ...).
    error : str
    counts, positive, negative : ndarray
        Coherent vortices (all, positive, negative) at every saved state.
    outcome : int
        Most frequent count over the last ``settle`` fraction of the run (-1 if the run did
        not complete).
    share : float
        Fraction of that window with the outcome's count.
    alternatives : tuple of int
        The outcome with the detector settings of :data:`ALTERNATIVES`.
    final : VortexCensus or None
        The vortices of the last state.
    W_final : ndarray or None
        The last state.
    staircase : ndarray
        The coarse-grained vorticity (low-pass ``staircase_smoothing``) at the detector's
        points, sorted (each point stands for the area ``4π/n``), first and last state
        ``(2, n)``.
    levels : ndarray
        The fine-grained vorticity levels (eigenvalues of ``-iW``, a Casimir of the run)
        of the last state.
    gamma_drift, momentum_drift : float
        Largest ``|γ(t) - γ(0)|`` and ``‖L(t) - L(0)‖/√C₂`` over the saved states.
    energy_error, casimir_drift : float
        Largest relative energy error and Casimir drift (``|ΔC_k|/‖W_0‖^k``, k = 2, 3, 4)
        over every step.
    iterations : float
        Mean fixed-point updates per step.
    wall_time : float
        Seconds the run took (its worker's wall clock).
    """

    state: InitialState
    status: str
    error: str
    counts: np.ndarray = attrs.field(repr=False)
    positive: np.ndarray = attrs.field(repr=False)
    negative: np.ndarray = attrs.field(repr=False)
    outcome: int
    share: float
    alternatives: tuple[int, ...]
    final: Any = attrs.field(repr=False)
    W_final: Any = attrs.field(repr=False)
    staircase: np.ndarray = attrs.field(repr=False)
    levels: np.ndarray = attrs.field(repr=False)
    gamma_drift: float
    momentum_drift: float
    energy_error: float
    casimir_drift: float
    iterations: float
    wall_time: float

    @property
    def complete(self) -> bool:
        """Whether the run completed (and has an outcome)."""
        return self.status == "complete"


@attrs.frozen(eq=False)
class Analysis:
    """Every run's result, the trend, and the data the figure needs.

    Attributes
    ----------
    runs : tuple of RunResult
    time : ndarray
        Times of the saved states.
    trend : Trend or None
        ``None`` when too few runs completed (or all ended alike).
    alternative_trends : tuple of (Trend or None)
        The trend with each setting of :data:`ALTERNATIVES`.
    drift : dict
        ``step_time``, ``energy_error`` (runs × steps) and ``casimir_drift`` (runs × steps,
        the largest over k) for the figure.
    """

    runs: tuple[RunResult, ...]
    time: np.ndarray = attrs.field(repr=False)
    trend: Trend | None
    alternative_trends: tuple[Trend | None, ...]
    drift: dict[str, np.ndarray] = attrs.field(repr=False)


def _mode(values: np.ndarray) -> tuple[int, float]:
    """Most frequent value (the smaller on a tie) and its share."""
    if values.size == 0:
        return -1, math.nan
    uniq, count = np.unique(values, return_counts=True)
    k = int(np.argmax(count))
    return int(uniq[k]), float(count[k] / values.size)


def _trend_or_none(gammas: list[float], outcomes: list[int], seed: int) -> Trend | None:
    try:
        return rank_trend(gammas, outcomes, seed=seed)
    except InputError:
        return None


def analyse(
    plan: Plan,
    states: Sequence[InitialState],
    sweep_dir: Path,
    seed: int = 0,
    log: Log | None = None,
) -> Analysis:
    """Apply the detector along every run of the study's sweep and measure the trend."""
    from ..datasets import open_sweep

    lz = _plugin()
    ds = open_sweep(sweep_dir)
    axis = "file"
    files = [str(f) for f in ds[axis].values]
    detector = lz.VortexDetector(plan.N, smoothing=plan.smoothing, threshold=plan.threshold)
    others = [lz.VortexDetector(plan.N, smoothing=s, threshold=t) for s, t in ALTERNATIVES]
    coarse = lz.VortexDetector(plan.N, smoothing=plan.staircase_smoothing)
    time_values = np.asarray(ds["time"].values if "time" in ds.coords else [], dtype=float)
    window = time_values >= (1 - plan.settle) * plan.t_final - 1e-9 * plan.t_final
    energy = np.asarray(ds["energy_error"].values, dtype=float)
    casimir = np.nanmax(np.asarray(ds["casimir_drift"].values, dtype=float), axis=-1)
    iterations = np.asarray(ds["iterations"].values, dtype=float)[:, 1:]
    status, error, wall = (ds[k].values for k in ("status", "error", "wall_time"))
    results = []
    for state in states:
        i = files.index(state.file)
        W = ds["W"].isel({axis: i}).values if status[i] == "complete" else None
        if W is None or not np.all(np.isfinite(W)):
            results.append(_missing(state, str(status[i]), str(error[i]), coarse.points))
            continue
        values = detector.filtered(W)
        censuses = [detector.census_of_field(v) for v in values]
        counts = np.array([c.count for c in censuses])
        outcome, share = _mode(counts[window])
        alternatives = tuple(
            _mode(np.array([d.census_of_field(v).count for v in d.filtered(W[window])]))[0]
            for d in others
        )
        L = lz.angular_momentum(W)
        root_c2 = math.sqrt(state.casimirs[0] * 4 * math.pi / plan.N)
        gammas = lz.gamma(W)
        results.append(
            RunResult(
                state=state,
                status=str(status[i]),
                error="",
                counts=counts,
                positive=np.array([c.positive for c in censuses]),
                negative=np.array([c.negative for c in censuses]),
                outcome=outcome,
                share=share,
                alternatives=alternatives,
                final=censuses[-1],
                W_final=W[-1],
                staircase=np.sort(coarse.filtered(W[[0, -1]]), axis=-1),
                levels=lz.vorticity_levels(W[-1]),
                gamma_drift=float(np.max(np.abs(gammas - gammas[0]))),
                momentum_drift=float(np.max(np.linalg.norm(L - L[0], axis=-1)) / root_c2),
                energy_error=float(np.nanmax(energy[i])),
                casimir_drift=float(np.nanmax(casimir[i])),
                iterations=float(np.nanmean(iterations[i])),
                wall_time=float(wall[i]),
            )
        )
        if log is not None:
            log(
                f"  gamma = {state.gamma:.3f}, seed {state.seed}: {outcome} vortices "
                f"({100 * share:.0f} % of the last {100 * plan.settle:.0f} %), counts "
                + "".join(str(min(c, 9)) for c in counts[:: max(1, len(counts) // 40)])
            )
    done = [r for r in results if r.complete]
    g = [r.state.gamma for r in done]
    trend = _trend_or_none(g, [r.outcome for r in done], seed)
    alternative_trends = tuple(
        _trend_or_none(g, [r.alternatives[k] for r in done], seed) for k in range(len(others))
    )
    drift = {
        "step_time": np.asarray(ds["step"].values, dtype=float) * plan.h,
        "energy_error": energy,
        "casimir_drift": casimir,
        "files": np.asarray(files, dtype=object),
    }
    return Analysis(tuple(results), time_values, trend, alternative_trends, drift)


def _missing(state: InitialState, status: str, error: str, points: int) -> RunResult:
    nan = math.nan
    none = np.zeros(0, dtype=int)
    stairs = np.full((2, points), nan)
    return RunResult(state, status, error, none, none, none, -1, nan, (), None, None, stairs,
                     np.zeros(0), nan, nan, nan, nan, nan, nan)  # fmt: skip


@attrs.frozen(eq=False)
class StudyResult:
    """What :func:`reproduce_modin_viviani` did.

    Attributes
    ----------
    directory : Path
    plan : Plan
    analysis : Analysis
    files : tuple of Path
        The figure, report, CSV and dataset.
    wall_time : float
    """

    directory: Path
    plan: Plan
    analysis: Analysis
    files: tuple[Path, ...]
    wall_time: float


def reproduce_modin_viviani(
    out_dir: Path | str = "lieflow-out",
    *,
    plan: Plan | str = "full",
    seed: int = 0,
    executor: str = "local",
    workers: int | None = None,
    scheduler: str | None = None,
    device: str = "cpu",
    log: Log | None = None,
) -> StudyResult:
    """Run (or resume) the study and write its figure, report and results.

    Parameters
    ----------
    out_dir : path
        Parent directory; the study writes ``OUT/modin-viviani-2020[-quick|-smoke]/``.
    plan : Plan or {"full", "quick", "smoke"}
    seed : int
        First seed of the random fields (and of the bootstrap).
    executor, workers, scheduler
        Where the runs go (:func:`lieflow.sweep`): ``"local"`` process pool of ``workers``
        processes, or ``"dask"`` (a new LocalCluster, or the cluster at ``scheduler``).
    device : str
        ``[run] device`` of every run (``"cpu"``, ``"cupy"``, ``"torch:cuda:0"``, ...).
    log : callable, optional
        Receives progress lines.

    Raises
    ------
    InputError
        Bad arguments, a missing plugin or extra, an output directory that cannot be
        written or holds another version's initial data.
    KeyboardInterrupt
        The sweep was interrupted (its runs resume on the next call).
    """
    from ..reproduce import _output_dir
    from ..sweeps import SweepProgress, load_sweep, sweep

    if isinstance(plan, str):
        if plan not in PLANS:
            raise InputError(f"plan must be one of {', '.join(PLANS)}, got {plan!r}")
        plan = PLANS[plan]
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"reproduce {STUDY}: seed must be an integer >= 0, got {seed!r}")
    _plugin()
    start = time.perf_counter()
    suffix = "" if plan.name == "full" else f"-{plan.name}"
    out = _output_dir(Path(out_dir) / f"{STUDY}{suffix}")
    states = initial_states(plan, int(seed), out)
    grid_path = out / "grid.toml"
    grid_path.write_text(grid_text(plan, states, device), encoding="utf-8")
    if log is not None:
        log(f"{STUDY} ({plan.name}): {plan.runs} runs of {plan.steps} steps, N = {plan.N}: {out}")
    grid = load_sweep(grid_path)
    swept = sweep(grid, executor, workers=workers, scheduler=scheduler,
                  monitor=SweepProgress() if log is not None else None)  # fmt: skip
    if swept.interrupted:
        raise KeyboardInterrupt
    cpu = time.process_time()
    analysis = analyse(plan, states, grid.directory, seed=int(seed), log=log)
    if not any(r.complete for r in analysis.runs):
        raise LieflowError(
            f"reproduce {STUDY}: no run completed (see {grid.manifest}). To fix: read the "
            "runs' errors there, then run the command again (complete runs are kept)"
        )
    from .modin_viviani_2020_figure import study_figure
    from .modin_viviani_2020_report import write_csv, write_dataset, write_report

    figure = study_figure(plan, analysis, out / "modin_viviani_2020.png")
    analysis_cpu = time.process_time() - cpu
    timing = {
        "wall": time.perf_counter() - start,
        "runs": float(sum(r.get("wall_time", 0.0) or 0.0 for r in swept.runs)),
        "analysis": analysis_cpu,
    }
    files = (
        figure,
        write_report(
            plan,
            analysis,
            out / "report.md",
            seed=int(seed),
            device=device,
            executor=executor,
            timing=timing,
            figure=figure,
        ),
        write_csv(analysis, out / "results.csv"),
        write_dataset(plan, analysis, out / "results.nc", int(seed)),
    )
    if log is not None and analysis.trend is not None:
        log(f"{STUDY}: {analysis.trend.describe()}")
    return StudyResult(out, plan, analysis, files, time.perf_counter() - start)
