"""The Euler–Zeitlin example configurations under ``lieflow run``: the Rossby–Haurwitz wave
of the QG model on a rotating sphere moves west at the exact speed, and a forced-dissipative
run on the rotating sphere (``[splitting]`` with this plugin's flows) resumes bit for bit."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

lz = pytest.importorskip("lieflow_zeitlin")
pytest.importorskip("h5py")

from lieflow.app import io  # noqa: E402
from lieflow.app.cli import main  # noqa: E402
from lieflow.app.config import build, load_config  # noqa: E402

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _copy(tmp_path: Path, name: str, replacements: list[tuple[str, str]]) -> Path:
    text = (EXAMPLES / name).read_text(encoding="utf-8")
    for old, new in replacements:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_rossby_haurwitz_example_moves_west_at_the_exact_speed(tmp_path: Path) -> None:
    """The shipped initial state is the documented field; 100 steps (fluid time 5) of the
    example move the degree-4 wave west at c = ((1/2)·18 - 12)/(20 + 10) = -0.1 (measured
    -0.100051 over the full 400 steps: gauss2's error at h = 0.05)."""
    from importlib.util import module_from_spec, spec_from_file_location

    spec = spec_from_file_location("make_w0", EXAMPLES / "make_rossby_haurwitz_w0.py")
    assert spec is not None and spec.loader is not None
    module = module_from_spec(spec)
    spec.loader.exec_module(module)
    shipped = np.load(EXAMPLES / "rossby_haurwitz_n32.npy")
    np.testing.assert_allclose(shipped, module.initial_state(), atol=1e-14)

    shutil.copy(EXAMPLES / "rossby_haurwitz_n32.npy", tmp_path)
    config = _copy(tmp_path, "rossby_haurwitz_n32.toml", [("steps = 400", "steps = 100")])
    assert main(["run", str(config), "--no-progress"]) == 0
    traj = io.read_trajectory(tmp_path / "rossby_haurwitz_n32.h5")
    assert traj.status == "complete" and traj.t[-1] == pytest.approx(5.0)
    system = build(load_config(config)).system
    assert (system.N, system.rotation, system.lamb, system.time) == (32, 6.0, 10.0, "fluid")
    c = lz.matrix_to_sh(system.relative(traj.W))[:, lz.lm_index(4, 4)]
    phase = np.unwrap(np.angle(c / c[0]))
    assert -phase[-1] / (4 * traj.t[-1]) == pytest.approx(-0.1, rel=1e-3)
    assert np.all(np.diff(phase) > 0)  # west all along: the phase of c_44 grows
    assert np.abs(np.abs(c) / np.abs(c[0]) - 1).max() <= 1e-6
    assert np.max(traj.energy_error) <= 1e-10
    # lieflow plot draws the relative vorticity of rotating/QG runs
    from lieflow_zeitlin.plotting import _relative

    np.testing.assert_array_equal(_relative(traj).W, system.relative(traj.W))
    assert _relative(traj).t is traj.t


def test_forced_example_runs_and_resumes_bit_for_bit(tmp_path: Path) -> None:
    """A small copy (N = 16, degrees 4..6): 20 steps at once, and 10 steps then resumed to
    20, give the same states bit for bit (the forcing noise is a function of the seed and
    the sub-step index, the flows keep no other state)."""
    small = [
        ("N = 64", "N = 16"),
        ("l1 = 20, l2 = 24", "l1 = 4, l2 = 6"),
        ("nu = 6.1e-8", "nu = 2e-5"),
        ("steps = 5000", "steps = 20"),
        ("save_every = 50", "save_every = 10"),
    ]
    once = tmp_path / "once"
    twice = tmp_path / "twice"
    once.mkdir()
    twice.mkdir()
    config = _copy(once, "forced_rotating_n64.toml", small)
    setup = build(load_config(config))
    assert [type(f).__name__ for f in setup.flows] == [
        "Hyperviscosity",
        "LinearDrag",
        "StochasticForcing",
    ]
    assert main(["run", str(config), "--no-progress"]) == 0
    half = _copy(
        twice, "forced_rotating_n64.toml", [*small[:3], ("steps = 5000", "steps = 10"), small[4]]
    )
    assert main(["run", str(half), "--no-progress"]) == 0
    full = _copy(twice, "forced_rotating_n64.toml", small)
    assert main(["run", str(full), "--resume", "--no-progress"]) == 0
    a = io.read_trajectory(once / "forced_rotating_n64.h5")
    b = io.read_trajectory(twice / "forced_rotating_n64.h5")
    assert a.status == b.status == "complete" and b.completed_steps == 20
    np.testing.assert_array_equal(a.W, b.W)
    assert lz.VorticityAlgebra(16).contains(a.W[-1], tol=1e-13)
