"""Trajectory files are never lost, overwritten by a second writer or resumed from damaged
bytes (issue 15, items 4, 5 and 7): real `lieflow run` processes, bit flips, signals."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import damage_last_chunk, rigid_body_config
from processes import Children

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.config import ConfigError, build, load_config
from lieflow.app.io import _reader


def config_text(seed: int, steps: int) -> str:
    # engine numpy: what is tested here is the file, not the engine (no numba start-up)
    return rigid_body_config(
        seed=seed, h=0.1, steps=steps, save_every=10, output="traj.h5", engine="numpy"
    )


#: long enough that a run is still going when the test acts on it (it is always stopped)
FOREVER = 10**9


def write_config(tmp_path: Path, *, seed: int = 0, steps: int = 60, name: str = "run") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(config_text(seed=seed, steps=steps), encoding="utf-8")
    return path


def lieflow_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "lieflow", *args]


def start(children: Children, config: Path, *args: str) -> subprocess.Popen[str]:
    return children.popen(
        lieflow_cmd("run", str(config), "--no-progress", *args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_until_written(proc: subprocess.Popen[str], out: Path, timeout: float = 120.0) -> None:
    """Until ``proc`` holds the lock on ``out`` and has checkpointed past step 0."""
    lock = out.with_name(f".{out.name}.lock")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        if lock.exists() and out.exists():
            time.sleep(0.5)  # a few saves
            return
        time.sleep(0.05)
    pytest.fail(f"{out} did not appear within {timeout} s")


def finish(proc: subprocess.Popen[str], sig: int | None = None) -> tuple[int, str, str]:
    if sig is not None:
        proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    return proc.returncode, out, err


# -- one writer per file (item 4) ------------------------------------------------------------


def test_a_second_writer_is_refused_while_a_run_holds_the_file(
    tmp_path: Path, children: Children
) -> None:
    first = write_config(tmp_path, seed=1, steps=FOREVER, name="first")
    second = write_config(tmp_path, seed=2, steps=FOREVER, name="second")
    out = tmp_path / "traj.h5"
    a = start(children, first)
    try:
        wait_until_written(a, out)
        for extra in ((), ("--force",), ("--resume",)):
            proc = subprocess.run(
                lieflow_cmd("run", str(second), "--no-progress", *extra),
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert proc.returncode == 2, (extra, proc.stderr)
            assert "Traceback" not in proc.stderr
            if extra == ():  # refused before anything is computed: the file exists
                assert "already exists" in proc.stderr
            else:
                assert "being written by another lieflow run" in proc.stderr, proc.stderr
                assert f"pid {a.pid}" in proc.stderr
    finally:
        rc, _, err = finish(a, signal.SIGINT)
    assert rc == 130, err
    traj = io.read_trajectory(out)  # the first run's file, intact and resumable
    assert traj.status == "interrupted" and traj.completed_steps > 0
    assert "seed = 1" in traj.meta["config"]
    assert not out.with_name(f".{out.name}.lock").exists()


def test_two_runs_started_together_on_a_new_path_one_wins(
    tmp_path: Path, children: Children
) -> None:
    """Both used to exit 0 and print '-> race.h5'; the file held one of them."""
    configs = [write_config(tmp_path, seed=s, steps=300, name=f"c{s}") for s in (1, 2)]
    procs = [start(children, c) for c in configs]
    results = [finish(p) for p in procs]
    codes = sorted(rc for rc, _, _ in results)
    assert codes == [0, 2], results
    winner = next(i for i, (rc, _, _) in enumerate(results) if rc == 0)
    loser_err = results[1 - winner][2]
    assert "already exists" in loser_err or "being written by another" in loser_err
    traj = io.read_trajectory(tmp_path / "traj.h5")
    assert traj.status == "complete" and traj.completed_steps == 300
    assert f"seed = {winner + 1}" in traj.meta["config"]


def test_a_run_whose_file_was_deleted_does_not_report_success(
    tmp_path: Path, children: Children
) -> None:
    config = write_config(tmp_path, steps=FOREVER)
    out = tmp_path / "traj.h5"
    a = start(children, config)
    try:
        wait_until_written(a, out)
        out.unlink()  # what `rm` (or an old lieflow's --force) does to a running output
    finally:
        rc, stdout, err = finish(a, signal.SIGINT)
    assert rc == 2, (rc, err)
    assert "was deleted or replaced by another program" in err
    assert "Traceback" not in err and "->" not in stdout


def test_a_completed_run_whose_file_was_replaced_fails(tmp_path: Path) -> None:
    """In one process: the file is swapped for another while the run steps."""
    config = write_config(tmp_path, steps=40)
    setup = build(load_config(config))
    decoy = tmp_path / "decoy.h5"
    decoy.write_bytes(b"someone else's file")

    class Swap:
        done = False

        def start(self, done: int, total: int) -> None:
            pass

        def advance(self, *args: object) -> None:
            if not self.done:
                os.replace(decoy, setup.output)
                self.done = True

        def stop(self) -> None:
            pass

    with pytest.raises(lf.LieflowError, match="deleted or replaced"):
        io.run(setup, monitor=Swap())
    assert setup.output.read_bytes() == b"someone else's file"  # not touched either


def test_exclusive_create_refuses_an_existing_file(tmp_path: Path) -> None:
    """``replace=False`` (the command line without --force) never replaces a file, even one
    that appears after the command's own check."""
    config = write_config(tmp_path, steps=5)
    setup = build(load_config(config), replace=False)
    setup.output.write_bytes(b"appeared meanwhile")
    with pytest.raises(ConfigError, match="already exists"):
        io.run(setup)
    assert setup.output.read_bytes() == b"appeared meanwhile"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml", "traj.h5"]


def test_sigterm_marks_the_file_interrupted_and_it_resumes(
    tmp_path: Path, children: Children
) -> None:
    config = write_config(tmp_path, steps=FOREVER)
    out = tmp_path / "traj.h5"
    a = start(children, config)
    wait_until_written(a, out)
    rc, _, err = finish(a, signal.SIGTERM)
    assert rc == 143, err
    assert "terminated (SIGTERM)" in err and "--resume" in err
    traj = io.read_trajectory(out)
    assert traj.status == "interrupted"
    done = traj.completed_steps
    config.write_text(config_text(seed=0, steps=done + 20), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    assert io.read_trajectory(out).completed_steps == done + 20


def test_python_dash_m_lieflow() -> None:
    proc = subprocess.run(lieflow_cmd("--version"), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == f"lieflow {lf.__version__}"


# -- integrity (item 5) ----------------------------------------------------------------------


@pytest.fixture
def finished(tmp_path: Path) -> tuple[Path, Path]:
    """A complete 60-step run (config, file)."""
    config = write_config(tmp_path)
    assert main(["run", str(config), "--no-progress"]) == 0
    return config, tmp_path / "traj.h5"


def _checkpoint_offset(path: Path) -> int:
    """Byte offset of the current checkpoint's W in the file."""
    with h5py.File(path, "r") as f:
        ck = f["checkpoint"]
        ds = ck[f"slot{int(ck.attrs['current'])}"]["W"]
        info = ds.id.get_chunk_info(0) if ds.chunks else None
        return int(info.byte_offset) if info is not None else int(ds.id.get_offset())


def _flip(path: Path, offset: int, bit: int = 0) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 1 << bit
    path.write_bytes(bytes(data))


def test_a_bit_flipped_in_the_checkpoint_is_refused_without_writing(
    finished: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """It used to resume and finish "complete" with energy error 2e-11 instead of 6.6e-15."""
    config, out = finished
    config.write_text(config_text(seed=0, steps=80), encoding="utf-8")
    _flip(out, _checkpoint_offset(out) + 3)
    before = out.read_bytes()
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "is damaged" in err and "Traceback" not in err and err.count("\n") == 1
    assert out.read_bytes() == before
    assert main(["plot", str(out)]) == 2  # a one-line error, not an h5py traceback
    err = capsys.readouterr().err
    assert err.startswith("lieflow: error: ") and "is damaged" in err and err.count("\n") == 1


def test_a_chunk_a_killed_write_left_unreadable_is_refused_on_resume(
    finished: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """A process killed while it rewrote a chunk leaves the chunk's checksum wrong, and rows
    before the checkpoint can share that chunk. Resume used to find it only at the next
    write, as h5py's "filter returned failure during read" (seen when a Dask worker was
    SIGKILLed): now it is refused, before any step is computed, with the fix."""
    config, out = finished
    config.write_text(config_text(seed=0, steps=80), encoding="utf-8")
    damage_last_chunk(out, "iterations")  # not read by the checkpoint's checks
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "is damaged" in err and "killed while it wrote" in err and "Traceback" not in err
    with pytest.raises(io.DamagedOutputError):
        io.run(build(load_config(config)), resume=True)


def test_a_rewritten_checkpoint_fails_its_sha256(finished: tuple[Path, Path]) -> None:
    """Changed through HDF5 itself (so HDF5's own chunk checksums are recomputed)."""
    config, out = finished
    with h5py.File(out, "r+") as f:
        ck = f["checkpoint"]
        ds = ck[f"slot{int(ck.attrs['current'])}"]["W"]
        W = ds[()]
        W.view(np.uint64)[0, 1] ^= 1  # the last bit of one entry
        ds[...] = W
    before = out.read_bytes()
    with pytest.raises(lf.LieflowError, match="SHA-256"):
        io.run(build(load_config(config)), resume=True)
    with pytest.raises(lf.LieflowError, match="SHA-256"):
        io.read_trajectory(out)
    assert out.read_bytes() == before


def test_a_checkpoint_that_does_not_reproduce_its_invariants_is_refused(
    finished: tuple[Path, Path],
) -> None:
    """A state changed together with its digest (a forged or buggy writer)."""
    config, out = finished
    with h5py.File(out, "r+") as f:
        ck = f["checkpoint"]
        slot = ck[f"slot{int(ck.attrs['current'])}"]
        W = slot["W"][()] * 1.001
        slot["W"][...] = W
        items = _reader._slot_items(slot)
        slot.attrs["sha256"] = io.checkpoint_digest(
            int(slot.attrs["step"]), float(slot.attrs["t"]), items
        )
    io.read_trajectory(out)  # the digest matches: the reader cannot tell
    with pytest.raises(lf.LieflowError, match="does not reproduce the invariants"):
        io.run(build(load_config(config)), resume=True)


@pytest.mark.parametrize(
    ("content", "message"),
    [(b"", "is empty (0 bytes)"), (b"certainly not HDF5\n" * 10, "not an HDF5 file")],
)
def test_resume_of_an_empty_or_foreign_file_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes, message: str
) -> None:
    """A 0-byte file used to get an HDF5 skeleton written into it before being refused."""
    config = write_config(tmp_path)
    out = tmp_path / "traj.h5"
    out.write_bytes(content)
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err
    assert message in err and "--force" in err and "Traceback" not in err
    assert out.read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml", "traj.h5"]


def test_random_bit_flips_never_give_a_traceback(
    finished: tuple[Path, Path], tmp_path: Path
) -> None:
    """Flip one bit anywhere: reading gives the data or a LieflowError, nothing else; and a
    flip inside a dataset's data is always detected (HDF5 Fletcher-32 chunk checksums)."""
    _, out = finished
    good = out.read_bytes()
    with h5py.File(out, "r") as f:
        data_ranges = []
        spare = f"checkpoint/slot{1 - int(f['checkpoint'].attrs['current'])}"

        def visit(name: str, obj: object) -> None:  # what a reader reads: not the spare slot
            read = not name.startswith((spare, "initial"))  # W0 is read by --resume
            if isinstance(obj, h5py.Dataset) and obj.chunks and read:
                for i in range(obj.id.get_num_chunks()):
                    info = obj.id.get_chunk_info(i)
                    data_ranges.append((info.byte_offset, info.byte_offset + info.size))

        f.visititems(visit)
    rng = np.random.default_rng(0)
    victim = tmp_path / "victim.h5"
    outcomes = {"read": 0, "refused": 0}
    positions = list(rng.integers(0, len(good), 150)) + [
        int(rng.integers(a, b)) for a, b in data_ranges
    ]
    for pos in positions:
        data = bytearray(good)
        data[pos] ^= 1 << int(rng.integers(8))
        victim.write_bytes(bytes(data))
        in_data = any(a <= pos < b for a, b in data_ranges)
        try:
            io.read_trajectory(victim)
        except lf.LieflowError:
            outcomes["refused"] += 1
            continue
        assert not in_data, f"a flip at byte {pos} inside a dataset's data was not detected"
        outcomes["read"] += 1
    assert outcomes["refused"] >= len(data_ranges)


def test_the_lock_follows_symlinks(tmp_path: Path) -> None:
    """Two names for one file share one lock."""
    config = write_config(tmp_path, steps=5)
    setup = build(load_config(config))
    writer = io.TrajectoryWriter.create(setup)
    try:
        (tmp_path / "alias.h5").symlink_to(setup.output)
        alias = build(load_config(config), output=tmp_path / "alias.h5")
        with pytest.raises(io.OutputBusyError, match="being written by another lieflow run"):
            io.TrajectoryWriter.reopen(alias)
    finally:
        writer.close("interrupted", None, 0.0)
    assert not (tmp_path / ".traj.h5.lock").exists()
