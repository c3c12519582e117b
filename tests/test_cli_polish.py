"""The command line's small promises (issue 29 item 8): a closed pipe, an energy that is not
conserved by design, a run with nothing to plot, a huge quoted value, a W0 file that is not
.npy, a missing output directory, ``--resume`` of a missing file."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf
from lieflow.app.cli import main

RIGID = """
[system]
name = "rigid_body"
params = {{ inertia = {inertia} }}
[initial]
{initial}
[scheme]
name = "midpoint"
[solver]
name = "fixed_point"
params = {{ {solver} }}
[run]
h = 0.1
steps = 20
save_every = 5
output = "traj.h5"
engine = "numpy"
"""


SEEDED = "random = true\nseed = 0"


def _config(tmp_path: Path, inertia: str = "[1.0, 2.0, 3.0]", initial: str = SEEDED,
            solver: str = "rtol = 1e-12") -> Path:  # fmt: skip
    path = tmp_path / "run.toml"
    text = RIGID.format(inertia=inertia, initial=initial, solver=solver)
    path.write_text(text, encoding="utf-8")
    return path


def test_a_closed_pipe_ends_quietly_as_unix_tools_do() -> None:
    """``lieflow list -v | head`` used to print "[Errno 32] Broken pipe. To fix: check the
    disk". The reader is gone before the first write (no timing)."""
    read, write = os.pipe()
    os.close(read)
    done = subprocess.run(
        [sys.executable, "-m", "lieflow", "list", "-v"],
        stdout=write,
        stderr=subprocess.PIPE,
        text=True,
        timeout=120,
    )
    os.close(write)
    assert done.returncode == 141, done.stderr  # 128 + SIGPIPE, as `yes | head` reports
    assert done.stderr == ""


def test_a_forced_dissipative_run_reports_an_energy_change(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With [splitting] flows the energy changes by design: "max energy error 2.4e+03" read
    as a failure of the scheme."""
    import_plugin("lieflow_zeitlin")
    config = tmp_path / "forced.toml"
    config.write_text(
        """
[system]
name = "euler_zeitlin"
params = { N = 6 }
[initial]
random = true
seed = 0
scale = 0.1
[scheme]
name = "midpoint"
[solver]
name = "fixed_point"
params = { rtol = 1e-12 }
[splitting]
method = "strang"
flows = [{ name = "zeitlin_drag", params = { mu = 0.5 } }]
[run]
h = 0.1
steps = 4
save_every = 2
output = "forced.h5"
engine = "numpy"
""",
        encoding="utf-8",
    )
    assert main(["run", str(config), "--no-progress"]) == 0
    said = capsys.readouterr().out
    assert "max energy change (not conserved: [splitting])" in said
    assert "energy error" not in said
    plain = _config(tmp_path)
    assert main(["run", str(plain), "--no-progress"]) == 0
    assert "max energy error" in capsys.readouterr().out


def test_a_run_that_failed_at_its_first_step_has_nothing_to_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It used to write empty figures."""
    config = _config(tmp_path, solver="rtol = 1e-15, max_iter = 1")
    assert main(["run", str(config), "--no-progress"]) == 2
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "traj.h5"), "--out", str(tmp_path / "figs")]) == 2
    err = capsys.readouterr().err
    assert "holds no step after the initial state (status 'failed'" in err
    assert "nothing to plot" in err and err.count("\n") == 1
    assert not (tmp_path / "figs").exists()


def test_an_error_quotes_a_long_value_short(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 50 000-entry parameter list made a 250 KB message (607 KB in the report)."""
    inertia = "[" + ", ".join(["1.5"] * 50_000) + "]"
    assert main(["run", str(_config(tmp_path, inertia=inertia)), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert len(err) < 1000, len(err)
    assert "rejected its parameters {'inertia': [1.5, 1.5" in err and "...]" in err
    assert "To fix: correct [system] params." in err
    assert lf.errors.shorten("x" * 5000, 100).count("characters left out") == 1


def test_a_w0_file_that_is_not_npy_is_named_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It used to say the file "does not exist" or "contains pickled (object) data"."""
    (tmp_path / "w0.txt").write_text("0 1 2\n")
    np.savez(tmp_path / "w0.npz", W0=np.zeros((3, 3)))
    for name in ("w0.txt", "w0.npz"):
        config = _config(tmp_path, initial=f'file = "{name}"')
        assert main(["run", str(config), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert f"'{tmp_path / name}' exists but is not a .npy file" in err
        assert "numpy.save" in err and "does not exist" not in err


def test_integrate_refuses_a_missing_output_directory(tmp_path: Path) -> None:
    """``integrate(out="/nonexistent/a.h5")`` used to create /nonexistent."""
    system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    W0 = system.algebra.project(np.arange(9.0).reshape(3, 3))
    out = tmp_path / "missing" / "deeper" / "a.h5"
    with pytest.raises(lf.LieflowError, match=r"its directory .* does not exist") as info:
        lf.integrate(system, lf.schemes.get("midpoint"), W0, h=0.1, steps=2, out=out)
    assert "mkdir -p" in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    sol = lf.integrate(system, lf.schemes.get("midpoint"), W0, h=0.1, steps=2,
                       out=tmp_path / "a.h5")  # fmt: skip
    assert sol.status == lf.Status.SUCCESS


def test_resume_of_a_missing_file_says_it_starts_a_new_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = _config(tmp_path)
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    err = capsys.readouterr().err
    assert f"--resume: '{tmp_path / 'traj.h5'}' does not exist yet; starting a new run" in err
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0  # now it exists
    assert "does not exist" not in capsys.readouterr().err
