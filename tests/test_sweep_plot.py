"""``lieflow plot SWEEP_DIR``: convergence and work–precision figures of a sweep, with the
observed orders checked against the schemes' theoretical orders."""

from __future__ import annotations

import concurrent.futures as cf
from pathlib import Path

import pytest

import lieflow as lf
from lieflow.app.cli import main
from lieflow.app.plotting import plot_sweep, sweep_groups

pytest.importorskip("xarray")

GRID = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }
[initial]
random = true
seed = 0
[scheme]
name = "gauss2"
[solver]
name = "fixed_point"
params = { rtol = 1e-15 }
[run]
t_final = 2.0
h = 0.1
engine = "numpy"
[sweep]
directory = "study"
"scheme.name" = ["midpoint", "gauss2"]
"run.h" = [0.1, 0.05, 0.025]
"""


def test_sweep_figures_and_orders(tmp_path: Path) -> None:
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID)
    with cf.ThreadPoolExecutor(2) as pool:
        result = lf.sweep(grid, executor=pool)
    assert all(r["status"] == "complete" for r in result.runs)
    groups = {g.label: g for g in sweep_groups(tmp_path / "study")}
    assert sorted(groups) == ["scheme = gauss2", "scheme = midpoint"]
    # energy errors of symplectic schemes of order p scale as h^p
    assert groups["scheme = midpoint"].order() == pytest.approx(2.0, abs=0.1)
    assert groups["scheme = gauss2"].order() == pytest.approx(4.0, abs=0.1)
    paths = plot_sweep(tmp_path / "study", tmp_path / "figures")
    assert [p.name for p in paths] == ["convergence.png", "work_precision.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
    assert main(["plot", str(tmp_path / "study" / "manifest.json")]) == 0
    assert (tmp_path / "study" / "convergence.png").exists()


def test_plot_of_a_directory_that_is_no_sweep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["plot", str(tmp_path)]) == 2
    assert "manifest" in capsys.readouterr().err
