"""``lieflow reproduce modin-viviani-2020``: the study's pieces (plans, grid, initial data, the
rank correlation) and the whole command at toy size (``--smoke``, seconds); the laptop
variant (``--quick``, minutes) is a slow test that checks the paper's trend."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import needs_zeitlin
from scipy.stats import spearmanr

import lieflow as lf
from lieflow.app.cli import main

pytest.importorskip("xarray")

from lieflow.app.studies import modin_viviani_2020 as mv
from lieflow.app.sweeps import parse_sweep

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@needs_zeitlin
def test_plans_fit_the_issue() -> None:
    import lieflow_zeitlin as lz

    quick = mv.PLANS["quick"]
    assert quick.runs >= 24 and len(set(quick.gammas)) >= 6 and 0.0 in quick.gammas
    for plan in mv.PLANS.values():
        assert max(plan.gammas) <= lz.GAMMA_MAX
        assert 2 <= plan.degrees[0] <= plan.degrees[1] < plan.N
        assert plan.steps * plan.h == pytest.approx(plan.t_final)
        assert plan.steps % plan.save_every == 0


@needs_zeitlin
def test_grid_is_a_sweep_over_the_initial_files(tmp_path: Path) -> None:
    import lieflow_zeitlin as lz

    plan = mv.PLANS["smoke"]
    states = mv.initial_states(plan, 3, tmp_path)
    assert [(s.gamma, s.seed) for s in states] == [(0.0, 3), (0.0, 4), (1.2, 3), (1.2, 4)]
    grid = parse_sweep(mv.grid_text(plan, states, device="array_api_strict"),
                       source=str(tmp_path / "grid.toml"), base_dir=tmp_path)  # fmt: skip
    assert grid.shape == (4,) and grid.axes[0].name == "file"
    for run, state in zip(grid.runs, states, strict=True):
        cfg = run.config
        assert cfg.initial.file == tmp_path / state.file
        assert cfg.system.name == "euler_zeitlin" and cfg.system.params["N"] == plan.N
        assert cfg.system.params["rotation"] == state.rotation
        assert cfg.scheme.name == "midpoint" and cfg.scheme.params["update"] == "conjugation"
        assert cfg.run.device == "array_api_strict" and cfg.run.steps == plan.steps
        W = np.load(cfg.initial.file)
        assert lz.gamma(W) == pytest.approx(state.gamma, abs=1e-13)
        assert state.measured_gamma == pytest.approx(state.gamma, abs=1e-13)
        # the frame turns with the solid-body part: Ω = 3 L_z / 8π, L along z
        assert state.rotation == pytest.approx(lz.solid_body_rotation(W)[2], abs=1e-13)
        assert np.allclose(lz.angular_momentum(W)[:2], 0, atol=1e-13)
        assert state.casimirs[0] == pytest.approx(plan.N, rel=1e-12)  # rms 1: ‖W‖² = N
    assert states[0].rotation == 0.0


@needs_zeitlin
def test_initial_data_of_another_version_is_refused(tmp_path: Path) -> None:
    plan = mv.PLANS["smoke"]
    states = mv.initial_states(plan, 0, tmp_path)
    assert mv.initial_states(plan, 0, tmp_path) == states  # the same data: kept
    path = tmp_path / states[1].file
    np.save(path, 2 * np.load(path))
    with pytest.raises(lf.InputError, match="another initial condition"):
        mv.initial_states(plan, 0, tmp_path)


def test_rank_trend_against_scipy() -> None:
    rng = np.random.default_rng(1)
    gammas = np.repeat([0.0, 0.3, 0.6, 0.9], 6)
    outcomes = np.clip(4 - np.round(2.2 * gammas + rng.normal(0, 0.5, gammas.size)), 2, 4)
    trend = mv.rank_trend(gammas, outcomes, seed=5)
    rho, p = spearmanr(gammas, outcomes)
    assert trend.rho == pytest.approx(rho, abs=1e-14) and trend.p_value == pytest.approx(p)
    assert trend.low <= trend.rho <= trend.high < 0
    assert trend.runs == 24 and "ρ = " in trend.describe()
    # no trend: the interval covers zero; the opposite trend: positive
    flat = mv.rank_trend(gammas, rng.permutation(outcomes), seed=5)
    assert flat.low < 0 < flat.high or abs(flat.rho) < 0.5
    assert mv.rank_trend(gammas, 6 - outcomes, seed=5).rho == pytest.approx(-rho)
    # a strictly monotone relation: every resample has rho = -1
    perfect = mv.rank_trend([0, 1, 2, 3, 4], [6, 5, 4, 3, 2])
    assert [perfect.rho, perfect.low, perfect.high] == pytest.approx([-1.0] * 3, abs=1e-12)
    with pytest.raises(lf.InputError, match="at least 3 runs"):
        mv.rank_trend([0, 1, 2], [4, 4, 4])


def test_unknown_study_and_options_the_paper_does_not_take(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["reproduce", "modin-viviani", "--smoke"]) == 2
    assert "unknown study 'modin-viviani'" in capsys.readouterr().err
    assert main(["reproduce", "--device", "cupy", "--quick"]) == 2
    assert "--device apply to the studies that run sweeps" in capsys.readouterr().err
    assert main(["reproduce", "modin-viviani-2020", "--quick", "--smoke"]) == 2


@pytest.fixture(scope="module")
def smoke(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("mv") / "out"
    argv = ["reproduce", "modin-viviani-2020", "--smoke", "--out", str(out), "--workers", "2"]
    assert main([*argv, "-q"]) == 0
    return out / "modin-viviani-2020-smoke"


@needs_zeitlin
def test_smoke_writes_every_output(smoke: Path) -> None:
    from matplotlib.image import imread

    figure = smoke / "modin_viviani_2020.png"
    assert figure.read_bytes()[:8] == PNG_SIGNATURE
    assert imread(figure).shape[0] > 600
    report = (smoke / "report.md").read_text(encoding="utf-8")
    for heading in ("## Outcome against γ", "## Conservation", "## Runs", "## Machine"):
        assert heading in report
    assert "4 of 4 runs complete" in report
    assert (smoke / "sweep" / "manifest.json").exists()


@needs_zeitlin
def test_smoke_results(smoke: Path) -> None:
    import xarray as xr

    with (smoke / "results.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 4
    for row in rows:
        assert row["status"] == "complete"
        assert abs(float(row["measured_gamma"]) - float(row["gamma"])) < 1e-13
        assert float(row["max_casimir_drift"]) < 1e-12  # the Cayley update: roundoff
        assert float(row["gamma_drift"]) < 1e-3
        assert int(row["outcome"]) >= 1
        assert float(row["C2"]) == pytest.approx(8.0, rel=1e-12)  # N = 8, rms vorticity 1
    with xr.open_dataset(smoke / "results.nc", engine="h5netcdf") as ds:
        assert dict(ds.sizes)["gamma"] == 2 and dict(ds.sizes)["seed"] == 2
        assert ds["count"].dims == ("gamma", "seed", "time")
        assert (ds["count"] >= 0).all()
        assert np.allclose(ds["measured_gamma"].values, [[0.0, 0.0], [1.2, 1.2]], atol=1e-13)
        assert ds.attrs["study"] == "modin-viviani-2020"
        outcome = ds["outcome"].values
        assert (outcome[1] == 2).all()  # gamma = 1.2: a dipole at once (the solid-body part)


@needs_zeitlin
@pytest.mark.slow
def test_smoke_on_a_device_equals_the_cpu(smoke: Path, tmp_path: Path) -> None:
    """``[run] device`` passed through: the eager engine on ``array_api_strict`` arrays (the
    array API on the CPU) gives every saved state of every run to roundoff."""
    result = mv.reproduce_modin_viviani(tmp_path, plan="smoke", device="array_api_strict")
    cpu, device = lf.open_sweep(smoke / "sweep"), lf.open_sweep(result.directory / "sweep")
    assert np.abs(cpu.W.values - device.W.values).max() < 1e-13
    with (smoke / "results.csv").open(encoding="utf-8") as fh:
        outcomes = [int(row["outcome"]) for row in csv.DictReader(fh)]
    assert [r.outcome for r in result.analysis.runs] == outcomes


@needs_zeitlin
@pytest.mark.slow
def test_quick_study_finds_the_trend(tmp_path: Path) -> None:
    """The laptop variant (about 3 minutes on 2 idle cores): fewer coherent vortices at
    larger γ, the rank correlation negative with its whole 95 % interval, and the Casimirs
    at roundoff."""
    result = mv.reproduce_modin_viviani(tmp_path, plan="quick", workers=2)
    trend = result.analysis.trend
    assert trend is not None and trend.high < -0.5
    done = [r for r in result.analysis.runs if r.complete]
    assert len(done) == result.plan.runs
    assert max(r.casimir_drift for r in done) < 1e-12
    small = [r.outcome for r in done if r.state.gamma == 0.0]
    large = [r.outcome for r in done if r.state.gamma == max(result.plan.gammas)]
    assert np.mean(small) > np.mean(large)
    assert math.isfinite(result.wall_time)
