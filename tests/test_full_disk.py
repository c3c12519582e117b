"""A full disk (issue 29 item 6): one clear lieflow error, nothing lost, and the same command
continues the run once space is freed — on a real tiny filesystem (a tmpfs of a few MB,
mounted where this process may mount; skipped elsewhere)."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.io import _disk

CONFIG = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }

[initial]
random = true
seeds = [{seeds}]

[scheme]
name = "midpoint"

[solver]
name = "fixed_point"
params = { rtol = 1e-15 }

[run]
h = 0.05
steps = 800
save_every = 5
checkpoint = "saves"
output = "traj.h5"
engine = "numpy"
""".replace("{seeds}", ", ".join(map(str, range(64))))


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    """A 1.5 MB tmpfs; ``mount -o remount,size=...`` frees space."""
    where = tmp_path / "disk"
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1500k", "tmpfs", str(where)],
        capture_output=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        (where / "run.toml").write_text(CONFIG, encoding="utf-8")
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def _grow(disk: Path) -> None:
    subprocess.run(["mount", "-o", "remount,size=8m", str(disk)], check=True)


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> io.Trajectory:
    """The same run on a disk with room."""
    tmp_path = tmp_path_factory.mktemp("reference")
    config = tmp_path / "reference.toml"
    config.write_text(CONFIG.replace('"traj.h5"', '"reference.h5"'), encoding="utf-8")
    assert main(["run", str(config), "--no-progress"]) == 0
    return io.read_trajectory(tmp_path / "reference.h5")


def _one_clear_error(err: str) -> None:
    assert err.startswith("lieflow: error: no space left on device writing "), err
    assert "free space on that disk and run the same command again" in err
    assert err.count("\n") == 1 and "Traceback" not in err and "HDF5" not in err


@pytest.mark.parametrize("margin", [_disk._SPACE_MARGIN, 0], ids=["stops-before", "hdf5-enospc"])
def test_a_full_disk_is_one_error_and_the_same_command_continues(
    disk: Path,
    reference: io.Trajectory,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    margin: int,
) -> None:
    """``hdf5-enospc``: no reserve, so HDF5's own writes fail (errno 28 inside multi-line
    HDF5 dumps, then ``RuntimeError: Can't destroy cache`` at close) — still one line."""
    capsys.readouterr()
    monkeypatch.setattr(_disk, "_SPACE_MARGIN", margin)
    config, out = disk / "run.toml", disk / "traj.h5"
    assert main(["run", str(config), "--no-progress"]) == 2
    _one_clear_error(capsys.readouterr().err)
    kept = io.read_checkpoint(out).step
    assert 0 < kept < 800
    if margin:  # stopped before writing, with room left for its status (it used to say "running")
        stopped = io.read_trajectory(out)
        assert stopped.status == "interrupted" and stopped.completed_steps == kept
    monkeypatch.setattr(_disk, "_SPACE_MARGIN", 1 << 20)
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2  # still full
    _one_clear_error(capsys.readouterr().err)
    # refused before writing, or stopped at its first checkpoint: nothing lost either way
    still = io.read_trajectory(out)
    assert still.completed_steps == kept and still.status in ("interrupted", "running")
    _grow(disk)
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    done = io.read_trajectory(out)
    assert done.status == "complete"
    for name in ("step", "W", "energy", "casimirs", "iterations", "residual"):
        np.testing.assert_array_equal(getattr(done, name), getattr(reference, name), name)
    assert sorted(p.name for p in disk.iterdir()) == ["run.toml", "traj.h5"]
