"""The ``lieflow`` command line: list, run (errors, interrupt and --resume), plot."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

GOOD = {
    "system": 'name = "rigid_body"\nparams = { inertia = [1.0, 2.0, 3.0] }',
    "initial": "random = true\nseed = 0",
    "scheme": 'name = "gauss2"',
    "solver": 'name = "fixed_point"\nparams = { rtol = 1e-15 }',
    "run": 'h = 0.1\nsteps = 30\nsave_every = 10\noutput = "../out/traj.h5"',
}


def toml(**sections: str | None) -> str:
    """The good configuration with some sections replaced (``None`` drops a section)."""
    merged = {**GOOD, **sections}
    return "\n".join(f"[{name}]\n{body}\n" for name, body in merged.items() if body is not None)


@pytest.fixture
def dirs(tmp_path: Path) -> tuple[Path, Path]:
    """A directory for configurations and an (empty) output directory next to it."""
    cfg, out = tmp_path / "cfg", tmp_path / "out"
    cfg.mkdir()
    out.mkdir()
    return cfg, out


def write(cfg_dir: Path, text: str, name: str = "run.toml") -> Path:
    path = cfg_dir / name
    path.write_text(text, encoding="utf-8")
    return path


def test_list_shows_every_registered_name(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    registry = lf.default_registry()
    for kind in ("system", "scheme", "solver"):
        assert f"{kind}s:" in out
        for name, entry in registry.table(kind).items():
            line = next(line for line in out.splitlines() if line.split()[:1] == [name])
            assert entry.description.split()[0] in line
    assert "free rigid body" in out and "gauss3" in out


def test_list_one_kind(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["list", "--kind", "solver", "-v"]) == 0
    out = capsys.readouterr().out
    assert "fixed_point" in out and "rigid_body" not in out and "lieflow" in out


def test_version_and_usage(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert lf.__version__ in capsys.readouterr().out
    assert main([]) == 2
    assert main(["run"]) == 2


def test_run_writes_the_file(dirs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    cfg, out = dirs
    config = write(cfg, toml())
    assert main(["run", str(config), "--no-progress"]) == 0
    assert "complete: 30/30 steps" in capsys.readouterr().out
    traj = io.read_trajectory(out / "traj.h5")
    assert traj.completed_steps == 30 and list(traj.step) == [0, 10, 20, 30]

    # an existing output is never replaced silently
    assert main(["run", str(config), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "[run] output" in err and "--resume" in err and "--force" in err
    assert main(["run", str(config), "--no-progress", "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["traj.h5"]


def test_run_out_overrides_the_config(dirs: tuple[Path, Path]) -> None:
    cfg, out = dirs
    config = write(cfg, toml())
    assert main(["run", str(config), "--no-progress", "--out", str(out / "sub" / "x.h5")]) == 0
    assert (out / "sub" / "x.h5").is_file() and not (out / "traj.h5").exists()


def test_ctrl_c_then_resume_from_the_command_line(
    dirs: tuple[Path, Path],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    one_step_chunks: None,
) -> None:
    cfg, out = dirs
    config = write(cfg, toml(run='h = 0.1\nsteps = 50\nsave_every = 10\noutput = "../out/a.h5"'))
    assert main(["run", str(config), "--no-progress", "--out", str(out / "ref.h5")]) == 0

    real_advance = lf.stepping.advance

    def interrupted(*args: Any, **kwargs: Any) -> Iterator[lf.chunks.Chunk]:
        for chunk in real_advance(*args, **kwargs):
            yield chunk
            if chunk.stop == 23:
                raise KeyboardInterrupt  # as Ctrl-C would, between two steps

    monkeypatch.setattr(lf.stepping, "advance", interrupted)
    assert main(["run", str(config), "--no-progress"]) == 130
    assert "--resume" in capsys.readouterr().err
    assert io.read_checkpoint(out / "a.h5").step == 23
    monkeypatch.setattr(lf.stepping, "advance", real_advance)

    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    a, ref = io.read_trajectory(out / "a.h5"), io.read_trajectory(out / "ref.h5")
    assert np.array_equal(a.checkpoint.W, ref.checkpoint.W)  # bit for bit
    assert np.array_equal(a.W, ref.W)
    assert np.array_equal(a.energy_error, ref.energy_error)
    assert np.array_equal(a.iterations, ref.iterations)
    assert a.meta["resumes"] == 1


BAD_CONFIGS = {
    "unknown system": (toml(system='name = "rigid_bod"'), "[system] name", "Known systems"),
    "unknown scheme": (toml(scheme='name = "gauss9"'), "[scheme] name", "Known schemes"),
    "unknown solver": (toml(solver='name = "newtn"'), "[solver] name", "Known solvers"),
    "bad system params": (
        toml(system='name = "rigid_body"\nparams = { inertia = [1.0, -2.0, 3.0] }'),
        "[system] params",
        "inertia",
    ),
    "unknown parameter": (
        toml(scheme='name = "gauss2"\nparams = { stages = 3 }'),
        "[scheme] params",
        "stages",
    ),
    "missing key": (toml(run='steps = 30\noutput = "../out/t.h5"'), "[run] h", "missing"),
    "missing section": (toml(scheme=None), "[scheme]", "missing section"),
    "ill-typed key": (
        toml(run='h = 0.1\nsteps = "thirty"\noutput = "../out/t.h5"'),
        "[run] steps",
        "integer",
    ),
    "negative step": (
        toml(run='h = -0.1\nsteps = 30\noutput = "../out/t.h5"'),
        "[run] h",
        "positive",
    ),
    "misspelt key": (
        toml(run='h = 0.1\nstpes = 30\nsteps = 3\noutput = "../out/t.h5"'),
        "[run] stpes",
        "unknown key",
    ),
    "unknown section": (toml() + "\n[plot]\nx = 1\n", "[plot]", "unknown section"),
    "no initial condition": (toml(initial="scale = 2.0"), "[initial]", "exactly one"),
    "random without seed": (toml(initial="random = true"), "[initial] seed", "missing"),
    "W0 of the wrong shape": (
        toml(initial="matrix = [[0.0, 1.0], [-1.0, 0.0]]"),
        "[initial] matrix",
        "shape",
    ),
    "W0 not in the algebra": (
        toml(initial="matrix = [[1.0, 0, 0], [0, 0, 0], [0, 0, 0]]"),
        "[initial] matrix",
        "so(3)",
    ),
    "ragged matrix": (
        toml(initial="matrix = [[0.0, 1.0], [-1.0]]"),
        "[initial] matrix",
        "different lengths",
    ),
    "missing W0 file": (toml(initial='file = "nope.npy"'), "[initial] file", "does not exist"),
    "invalid TOML": (toml() + "\n[run\n", "not valid TOML", "correct the syntax"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_bad_config_names_the_key_and_writes_nothing(
    case: str, dirs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    cfg, out = dirs
    text, key, hint = BAD_CONFIGS[case]
    assert main(["run", str(write(cfg, text)), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lieflow: error: ")
    assert key in err and hint in err, err
    assert "Traceback" not in err and "To fix" in err
    assert err.count("\n") == 1  # one paragraph
    assert list(out.iterdir()) == []
    assert sorted(p.name for p in cfg.iterdir()) == ["run.toml"]


def test_unwritable_output_path(
    dirs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    cfg, out = dirs
    (out / "a_file").write_text("x")
    for target, hint in (
        (out / "a_file" / "traj.h5", "not a writable directory"),
        (out, "is a directory"),
    ):
        config = write(cfg, toml(run=f'h = 0.1\nsteps = 3\noutput = "{target}"'))
        assert main(["run", str(config), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert "[run] output" in err and hint in err
        assert main(["run", str(config), "--no-progress", "--out", str(target)]) == 2
        assert "--out" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["a_file"]


def test_missing_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(tmp_path / "nope.toml")]) == 2
    assert "cannot read the configuration" in capsys.readouterr().err


def test_initial_condition_from_a_file(dirs: tuple[Path, Path]) -> None:
    cfg, out = dirs
    np.save(cfg / "w0.npy", lf.systems.PAPER_W0)
    config = write(
        cfg,
        toml(
            system='name = "periodic_toda"',
            initial='file = "w0.npy"',
            scheme='name = "midpoint"',
            solver=None,
        ),
    )
    assert main(["run", str(config), "--no-progress"]) == 0
    traj = io.read_trajectory(out / "traj.h5")
    assert np.array_equal(traj.W[0], lf.systems.PAPER_W0)
    assert traj.meta["solver"] == "fixed_point"  # the default solver


@pytest.mark.parametrize("example", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.stem)
def test_examples_are_valid(example: Path, tmp_path: Path) -> None:
    from lieflow.app.config import build, load_config

    setup = build(load_config(example), output=tmp_path / "x.h5")
    assert setup.config.run.steps >= 1000
    assert not (tmp_path / "x.h5").exists()


def test_plot(dirs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    from matplotlib.image import imread

    cfg, out = dirs
    assert main(["run", str(write(cfg, toml())), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["plot", str(out / "traj.h5"), "--out", str(out / "plots")]) == 0
    written = [Path(line) for line in capsys.readouterr().out.split()]
    assert [p.name for p in written] == [
        "traj_energy.png",
        "traj_casimirs.png",
        "traj_iterations.png",
    ]
    for path in written:
        assert path.read_bytes()[:8] == PNG_SIGNATURE
        assert imread(path).ndim == 3


def test_plot_of_a_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plot", str(tmp_path / "missing.h5")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_heavy_dependencies_are_imported_lazily() -> None:
    import subprocess
    import sys

    code = (
        "import sys, lieflow, lieflow.app.cli, lieflow.app.config, lieflow.app.io, "
        "lieflow.app.plotting, lieflow.app.reproduce; "
        "print([m for m in ('h5py', 'matplotlib', 'rich') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
