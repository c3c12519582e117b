"""``lieflow reproduce --quick`` end to end, and the paper's setup and numbers."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from lieflow.app.cli import main
from lieflow.app.reproduce import SCHEMES, paper_cases, published

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
FIGURES = ("rigid_body_energy.png", "toda_energy.png", "generalized_rigid_body_energy.png")


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reproduce") / "out"
    assert main(["reproduce", "--quick", "--out", str(out), "--seed", "7", "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def rows(quick: Path) -> list[dict[str, str]]:
    with (quick / "results.csv").open(encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_figures_are_valid_pngs(quick: Path) -> None:
    from matplotlib.image import imread

    for name in FIGURES:
        path = quick / name
        assert path.read_bytes()[:8] == PNG_SIGNATURE
        image = imread(path)
        assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 300


def test_report_has_every_table_filled(quick: Path) -> None:
    report = (quick / "report.md").read_text(encoding="utf-8")
    for k in range(1, 7):
        assert f"**Table {k}.**" in report
    tables = [line for line in report.splitlines() if line.startswith("|")]
    assert len(tables) > 20
    for line in tables:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        assert all(cells), line
        assert "n/a" not in cells, line
    assert "Seed: **7**" in report
    for key in ("cpu_count", "numpy", "scipy", "blas", "platform"):
        assert f"- {key}: " in report
    for name in FIGURES:
        assert f"]({name})" in report


def test_results_csv_has_every_run(rows: list[dict[str, str]]) -> None:
    assert len(rows) == 5 * len(SCHEMES)  # quick: GRB at n = 10 only
    for row in rows:
        assert row["seed"] == "7"
        assert float(row["wall_time_s"]) > 0
        assert int(row["max_iterations"]) >= 1
        assert int(row["max_iterations_paper_count"]) == int(row["max_iterations"]) - 1
        assert float(row["max_energy_error"]) < 1e-3
        assert float(row["spectrum_drift"]) < 1e-12  # isospectral to roundoff
        assert float(row["paper_wall_time_s"]) > 0


def test_energy_error_decreases_with_order(rows: list[dict[str, str]]) -> None:
    """Rigid body, h = 0.01: order 6 < order 4 < order 2 (the paper's first figure)."""
    err = {
        r["scheme"]: float(r["max_energy_error"])
        for r in rows
        if r["system"] == "rigid_body" and r["case"] == "h = 0.01"
    }
    assert err["gauss3"] < err["gauss2"] < err["midpoint"]


def test_full_setup_is_the_papers() -> None:
    cases = paper_cases()
    assert len(cases) * len(SCHEMES) == 28
    setup = {(c.system, c.label): (c.n, c.h, c.steps, c.tol) for c in cases}
    assert setup == {
        ("rigid_body", "h = 0.1"): (3, 0.1, 2000, 1e-15),
        ("rigid_body", "h = 0.01"): (3, 0.01, 2000, 1e-15),
        ("toda", "h = 0.1"): (4, 0.1, 1000, 1e-14),
        ("toda", "h = 0.01"): (4, 0.01, 1000, 1e-14),
        ("generalized_rigid_body", "n = 10"): (10, 0.01, 2000, 1e-14),
        ("generalized_rigid_body", "n = 20"): (20, 0.01, 2000, 1e-14),
        ("generalized_rigid_body", "n = 50"): (50, 0.01, 2000, 1e-14),
    }
    assert all(published(system, label) is not None for system, label in setup)


def test_published_numbers() -> None:
    toda = published("toda", "h = 0.1")
    assert toda is not None and toda.max_iterations == (23, 17, 16)
    grb = published("generalized_rigid_body", "n = 50")
    assert grb is not None and grb.wall_time[3] == 112.5086
    assert published("toda", "h = 0.5") is None


def test_seeded_data_is_reproducible() -> None:
    import numpy as np

    grb = paper_cases(quick=True)[-1]
    (s1, w1), (s2, w2) = grb.build(3), grb.build(3)
    assert np.array_equal(w1, w2) and np.array_equal(s1.J, s2.J)  # type: ignore[attr-defined]
    assert not np.array_equal(w1, grb.build(4)[1])
