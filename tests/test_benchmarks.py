"""The benchmark suite: its as-published baseline is honest, and the quick run produces every
table and cell."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf
from benchmarks import cli
from benchmarks.config import BenchContext, quick
from benchmarks.contenders import AsPublished, LieflowRun, PlainReduced
from benchmarks.paper_baseline import PaperScheme, dense_block_step, plain_reduced_step
from benchmarks.report import Table, TargetCheck, ratio
from benchmarks.suites import rigid_body_scaling
from benchmarks.suites.iteration_cost import plain_midpoint
from benchmarks.suites.scipy_work_precision import Point, levels, time_to_reach
from benchmarks.timing import Timing
from lieflow.app.reproduce import Case
from lieflow.schemes import BlockGauss
from lieflow.tableaus import gauss


def _grb(n: int) -> tuple[lf.IsospectralSystem, np.ndarray]:
    return Case("generalized_rigid_body", f"n = {n}", n, 0.01, 1, 1e-14).build(0)


@pytest.mark.parametrize("stages", [1, 2, 3])
@pytest.mark.parametrize("form", ["reduced", "block"])
def test_dense_baseline_matches_block_gauss(stages: int, form: Literal["reduced", "block"]) -> None:
    """The as-published dense algorithm takes the same step as lieflow's BlockGauss."""
    system, W0 = _grb(7)
    tableau = gauss(stages)
    ours = BlockGauss(tableau, form=form).step(W0, 0.05, system, lf.solvers.FixedPoint())
    theirs = dense_block_step(system, W0, 0.05, tableau.A, tableau.b)
    np.testing.assert_allclose(theirs.W, ours.W, rtol=0, atol=1e-12)
    assert theirs.iterations >= 2


@pytest.mark.parametrize("stages", [1, 2, 3])
def test_plain_reduced_baseline_matches_block_gauss(stages: int) -> None:
    """The plain-numpy reduced stage form takes the same step as lieflow."""
    system, W0 = _grb(7)
    tableau = gauss(stages)
    ours = BlockGauss(tableau).step(W0, 0.05, system, lf.solvers.FixedPoint())
    theirs = plain_reduced_step(system, W0, 0.05, tableau.A, tableau.b)
    np.testing.assert_allclose(theirs.W, ours.W, rtol=0, atol=1e-12)
    for name in ("midpoint", "sydirk7"):
        sol = lf.integrate(system, lf.schemes.get(name), W0, 0.05, steps=2, diagnostics=False)
        np.testing.assert_allclose(PlainReduced(name).run(system, W0, 0.05, 2).W, sol.W[-1],
                                   rtol=0, atol=1e-12)  # fmt: skip


def test_timings_report_the_median_round() -> None:
    assert Timing((3.0, 1.0, 2.0), None).median == 2.0
    assert Timing((), None, "x").median == float("inf")


def _pt(side: str, t: float, e: float) -> Point:
    return Point(side, side, "", t, e, 1e-16, "")


def test_scipy_comparison_frontier_and_levels() -> None:
    ours = [_pt("lieflow", 1.0, 1e-7), _pt("lieflow", 2.0, 1e-11), _pt("lieflow", 5.0, 1e-10)]
    theirs = [_pt("scipy", 4.0, 1e-9)]
    hit = time_to_reach(ours, 1e-9)  # between (1 s, 1e-7) and (2 s, 1e-11) in log–log
    assert hit is not None and hit[0] == pytest.approx(2**0.5)
    assert time_to_reach(theirs, 1e-10) is None
    res = {r.error: r.ratio for r in levels(ours + theirs)}
    assert res[1e-9] == pytest.approx(4.0 / 2**0.5)
    assert res[1e-10] == float("inf")  # scipy does not reach it
    assert 1e-12 not in res  # nobody reaches it
    # equal invariants: a faster scipy run whose Casimirs drift drops out of the comparison
    loose = Point("scipy", "scipy", "", 1.0, 1e-9, 1e-8, "")
    assert {r.error: r.ratio for r in levels([*ours, *theirs, loose])}[1e-9] < 1.0
    held = {r.error: r.ratio for r in levels([*ours, *theirs, loose], casimir=1e-12)}
    assert held[1e-9] == pytest.approx(4.0 / 2**0.5)


def test_dense_baseline_rigid_body_and_composition() -> None:
    """so(3) rigid body, and the 7-stage SyDIRK as a composition of dense midpoint steps."""
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W0 = lf.SO(3).random(seed=3)
    for name in ("gauss3", "sydirk7"):
        sol = lf.integrate(system, lf.schemes.get(name), W0, 0.1, steps=3, diagnostics=False)
        run = AsPublished(name).run(system, W0, 0.1, 3)
        np.testing.assert_allclose(run.W, sol.W[-1], rtol=0, atol=1e-12)


def test_paper_scheme_names_and_contender_labels() -> None:
    assert PaperScheme(gauss(2)).name == "paper_gauss2"
    assert AsPublished("gauss3").paper_scheme().composition is False
    assert AsPublished("sydirk7").paper_scheme().composition is True
    assert LieflowRun("gauss3", form="block", warm_start=False).label == (
        "gauss3, block form, warm starts off"
    )


def test_report_helpers() -> None:
    assert ratio(2.0, 1.0) == "2.00×"
    assert ratio(1.0, float("inf")) == "n/a"
    assert "**not met**" in TargetCheck("t", "m", False, "2× short", "why").markdown()
    with pytest.raises(ValueError, match="cells"):
        Table(("a", "b"), (("1",),))


def test_scaling_row_for_one_case() -> None:
    """One (n, scheme) cell of the scaling benchmark, every lever measured."""
    ctx = BenchContext(quick())
    row = rigid_body_scaling.measure(ctx, 5, "gauss2")
    assert row.paper is not None and row.block is not None
    assert row.default > 0 and row.mean_iterations >= 1 and row.memory > 0


def _table_rows(page: str) -> list[list[str]]:
    rows = []
    for line in page.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows


@pytest.mark.parametrize(
    ("name", "n", "h"), [("rigid_body", 3, 0.1), ("generalized_rigid_body", 10, 0.05)]
)
def test_plain_midpoint_loop_is_the_numpy_engines_algorithm(name: str, n: int, h: float) -> None:
    """The baseline of the small-n benchmark (issue 27) runs lieflow's algorithm: the same
    updates per step as the numpy engine with ``warm_start=1`` and the same states to
    roundoff (it skips the stage and state projections, which change only roundoff)."""
    system, W0 = Case(name, "", n, h, 60, 1e-14).build(0)
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    sol = lf.integrate(system, lf.schemes.get("midpoint"), W0, h, steps=60, solver=solver,
                       engine="numpy", diagnostics=False, warm_start=1)  # fmt: skip
    W, updates = plain_midpoint(np.asarray(system.hadamard_factor), W0, h, 60)
    assert updates == int(sol.iterations.sum()) > 2 * 60
    assert np.max(np.abs(W - sol.W[-1])) <= 1e-13 * np.max(np.abs(W0))


@pytest.mark.slow  # nine benchmark suites, a study of minutes under load (issue 37)
def test_quick_run_writes_every_table(tmp_path: Path) -> None:
    """``python -m benchmarks --quick`` writes the page with every section and cell (the
    sweeps suite, which starts process pools and a Dask cluster, has its own test below)."""
    out = tmp_path / "benchmarks.md"
    others = "reproduce,scaling,work_precision,scipy,so3,iteration_cost,zeitlin,memory,file_output"
    assert cli.main(["--quick", "--only", others, "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")
    for title in (
        "The reproduction suite",
        "Generalized rigid body: scaling in n",
        "Work–precision",
        "so(3) rigid body",
        "Large n: cost of one iteration",
        "Euler–Zeitlin",
        "Work–precision against scipy",
        "Bounded memory",
        "Writing a run to a trajectory file",
        "Targets at a glance",
    ):
        assert title in page
    assert (tmp_path / "img" / "work_precision.png").stat().st_size > 1000
    assert (tmp_path / "img" / "scipy_wp_rigid_body.png").stat().st_size > 1000
    assert "× vs plain numpy reduced" in page and "median" in page
    rows = _table_rows(page)
    assert len(rows) > 30
    headers = [r for r in rows if r[0] in ("system", "n", "scheme", "run", "N")]
    assert headers, "no table headers found"
    for row in rows:
        if row[0] == "**total**":
            continue
        assert all(cell for cell in row), f"empty cell in {row}"
    # every target has a verdict
    verdicts = re.findall(r"^- \*\*(met|not met|not measured)\*\* — ", page, re.MULTILINE)
    assert len(verdicts) >= 2 * 7  # the summary and the sections


def test_unknown_benchmark_name_is_refused_before_any_engine_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A misspelt ``--only`` is refused at once: no engine is probed (the probe compiles
    the compiled engine's loops, seconds to minutes on a first run)."""

    def probed() -> tuple[str, ...]:
        raise AssertionError("an engine was probed before the names were checked")

    monkeypatch.setattr(cli, "available_engines", probed)
    assert cli.main(["--quick", "--only", "so3,nope", "--out", str(tmp_path / "x.md")]) == 2
    assert "unknown benchmark(s): nope" in capsys.readouterr().err
    assert not (tmp_path / "x.md").exists()


@pytest.mark.slow  # process pools and a Dask cluster timed (issue 37)
def test_sweeps_suite_quick_reports_every_field() -> None:
    """The sweeps benchmark in quick mode: every row and target present (not the timings)."""
    import importlib.util

    pytest.importorskip("xarray")
    from benchmarks.suites import sweeps

    section = sweeps.run(BenchContext(quick()))
    assert section.title.startswith("Sweeps")
    (table,) = section.tables
    assert table.header == ("case", "how", "median", "per run", "speed-up")
    hows = [row[1] for row in table.rows]
    assert hows[0].startswith("one after another") and hows[1].startswith("local pool")
    assert any(h.startswith("open_sweep +") for h in hows)
    assert any('store = "zarr"' in h for h in hows)
    assert len(section.targets) == 3
    pool, dask, opening = section.targets
    assert pool.met is not None and opening.met is not None
    assert "cores' worth" in pool.limit and "×" in pool.measured
    assert "ms per run" in dask.measured or dask.met is None
    if importlib.util.find_spec("distributed") is not None:
        assert dask.met is not None and any("Dask LocalCluster" in h for h in hows)
    assert any("load average" in note for note in section.notes)


def test_stiffness_of_the_rigid_body_matches_its_linearisation() -> None:
    """ρ(J) of the so(3) rigid body against the eigenvalues of Euler's equations linearised
    at W0, derived independently in R³: ẇ = w × I⁻¹w (lieflow's hat map W = ŵ, B = (I⁻¹w)^)."""
    from benchmarks.config import BenchContext, quick
    from benchmarks.suites.scipy_work_precision import problems, stiffness

    problem = next(p for p in problems(BenchContext(quick())) if p.key == "rigid_body")
    W0 = problem.W0
    w = np.array([W0[2, 1], W0[0, 2], W0[1, 0]])
    B = problem.system.B(W0)
    Iinv = np.array([B[2, 1], B[0, 2], B[1, 0]]) / w  # B = S ⊙ W: the inverse inertias

    def cross(a: np.ndarray) -> np.ndarray:
        return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])

    # d/dw (w × Iinv w) = [w]× diag(Iinv) - [Iinv w]×  (up to lieflow's sign of the bracket)
    jac = cross(w) @ np.diag(Iinv) - cross(Iinv * w)
    rho = float(np.max(np.abs(np.linalg.eigvals(jac))))
    st = stiffness(problem)
    assert st.frequency == pytest.approx(rho, rel=1e-10)
    assert 0 < st.norm_shifted <= st.norm_B


def test_splitting_suite_quick_reports_the_target(tmp_path: Path) -> None:
    """The forced-dissipative splitting suite (issue 26.3) runs and gives a verdict."""
    pytest.importorskip("numba")
    import_plugin("lieflow_zeitlin")
    out = tmp_path / "benchmarks.md"
    assert cli.main(["--quick", "--only", "splitting", "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")
    assert "forced, dissipative: drag + forcing (compiled)" in page
    assert re.search(r"^- \*\*(met|not met)\*\* — forced, dissipative", page, re.MULTILINE)


def _quflow_rows(page: str, label: str) -> dict[int, float]:
    """Steps -> error at T of one curve of the quflow suite's table."""
    rows = re.findall(rf"^\| {re.escape(label)} \| (\d+) \| ([0-9.e+-]+) \|", page, re.MULTILINE)
    return {int(n): float(e) for n, e in rows}


@pytest.mark.parametrize("with_quflow", [True, False])
def test_quflow_suite_quick(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, with_quflow: bool
) -> None:
    """The quflow comparison (issue 27.4) runs in quick mode: lieflow's midpoint curve is
    second order against the gauss4 reference, gauss4 is far more accurate, and without
    quflow the section says so and gives no verdict."""
    import_plugin("lieflow_zeitlin")
    from benchmarks.suites import quflow_accuracy

    if with_quflow:
        pytest.importorskip("quflow")
    else:
        monkeypatch.setattr(quflow_accuracy, "quflow_isomp", lambda: None)
    out = tmp_path / "benchmarks.md"
    assert cli.main(["--quick", "--only", "quflow", "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")
    mid = _quflow_rows(page, "lieflow midpoint commutator rtol 1e-14")
    assert sorted(mid) == [8, 16, 32]
    assert 3.5 < mid[8] / mid[16] < 4.5 and 3.5 < mid[16] / mid[32] < 4.5
    assert max(_quflow_rows(page, "lieflow gauss4 commutator rtol 1e-14").values()) < 1e-10
    conj = _quflow_rows(page, "lieflow midpoint conjugation rtol 1e-08")
    assert all(conj[n] == pytest.approx(mid[n], rel=1e-3) for n in mid)
    # the recommended configuration (gauss2, conjugation, Casimir shift): fourth order
    rec = _quflow_rows(page, quflow_accuracy.RECOMMENDED)
    assert sorted(rec) == [1, 2] and 10 < rec[1] / rec[2] < 25
    if with_quflow:
        assert re.search(r"^- \*\*(met|not met)\*\* — Euler–Zeitlin N = 16", page, re.MULTILINE)
        qf = _quflow_rows(page, "quflow isomp (tol auto)")
        assert all(qf[n] == pytest.approx(mid[n], rel=1e-3) for n in mid)
        found = re.search(r"at equal steps differ by ≤ ([0-9.e+-]+) relative", page)
        assert found is not None and float(found.group(1)) < 1e-8
        assert "| quflow / recommended |" in page
    else:
        assert "**quflow skipped**" in page
        assert "**not measured** — Euler–Zeitlin N = 16" in page
        assert "quflow isomp (tol auto)" not in page


@pytest.mark.slow  # fresh interpreters timed (issue 37)
def test_startup_suite_quick_reports_what_each_case_imported() -> None:
    from benchmarks.suites import startup

    import_plugin("lieflow_zeitlin")
    section = startup.run(BenchContext(quick()))
    rows = {row[0]: row for row in section.tables[0].rows}
    assert rows["lieflow run"][3] == "none"
    assert "lieflow_zeitlin" in rows["lieflow run, all plugins loaded first"][3]
    assert section.targets[0].met is True


def test_call_cost_suite_quick_reports_every_case() -> None:
    """The fixed-cost suite (issue 27): a row per system, engine and diagnostics setting,
    a verdict against 50 µs on the call overhead (T(1) − the bare first step, both
    definitions stated), and the first step's updates (a cold solve) listed."""
    from benchmarks.config import BenchContext, quick
    from benchmarks.suites import call_cost

    section = call_cost.run(BenchContext(quick(), ("compiled",), "numpy"))
    (table,) = section.tables
    assert len(table.rows) == 8
    assert {row[1] for row in table.rows} == {"numpy", "compiled"}
    off, on = section.targets
    assert "without diagnostics" in off.target and "default diagnostics" in on.target
    for target in (off, on):
        assert target.met is not None and "50 µs" in target.target
        assert target.measured.count("T(1) − step") == 4
    first = [row[table.header.index("updates: first step (mean)")] for row in table.rows]
    assert all(cell.split()[0] in ("7", "5") for cell in first)  # the cold first solves
    bare = table.header.index("bare first step")
    assert all(row[bare].endswith("s") for row in table.rows)  # a time
