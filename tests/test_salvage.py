"""Damaged trajectory files (issue 29 item 5): told apart from busy ones, verified before a
resume reports ``complete``, and salvaged back to their last verified checkpoint."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import damage_last_chunk, rigid_body_config

import lieflow as lf
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.io import _reader
from lieflow.app.salvage import salvage


def config_text(steps: int, name: str) -> str:
    return rigid_body_config(
        h=0.1, steps=steps, save_every=100, checkpoint="saves", output=f"{name}.h5",
        engine="numpy",
    )  # fmt: skip


#: three chunks of per-step rows (1024 rows each): 0..1023, 1024..2047, 2048..2100
STEPS = 2100


def _run(tmp_path: Path, name: str, steps: int = STEPS, *extra: str) -> tuple[Path, Path]:
    config = tmp_path / f"{name}.toml"
    config.write_text(config_text(steps=steps, name=name), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", *extra]) == 0
    return config, tmp_path / f"{name}.h5"


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> io.Trajectory:
    """The uninterrupted run of 2200 steps."""
    _, out = _run(tmp_path_factory.mktemp("reference"), "run", STEPS + 100)
    return io.read_trajectory(out)


def _damage_chunk(path: Path, name: str, chunk: int) -> None:
    """Flip a bit in chunk ``chunk`` of dataset ``name`` (its Fletcher-32 then fails)."""
    with h5py.File(path, "r") as f:
        offset = int(f[name].id.get_chunk_info(chunk).byte_offset)
    data = bytearray(path.read_bytes())
    data[offset + 5] ^= 4
    path.write_bytes(bytes(data))


def _same(a: io.Trajectory, b: io.Trajectory) -> None:
    for name in ("step", "W", "energy", "casimirs", "iterations", "residual"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_a_truncated_file_is_damaged_not_busy(tmp_path: Path) -> None:
    """HDF5's message for a truncated file names ``sblock``, which used to match "lock":
    ``OutputBusyError: another process has it open for writing`` with no other process."""
    _, out = _run(tmp_path, "run")
    os.truncate(out, out.stat().st_size // 2)
    with pytest.raises(io.DamagedOutputError, match="truncated") as info:
        io.read_trajectory(out)
    assert not isinstance(info.value, io.OutputBusyError)
    assert "lieflow salvage" in str(info.value) and "another process" not in str(info.value)


def test_resume_verifies_every_kept_row_before_it_reports_complete(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A flipped byte in the saved states (which --resume did not read) used to give
    "complete", exit 0, and a file no reader could open."""
    config, out = _run(tmp_path, "run")
    _damage_chunk(out, "W", 0)
    before = out.read_bytes()
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "is damaged" in err and "'W' fails its checksum from row 0" in err
    assert "lieflow salvage" in err and "Traceback" not in err
    assert out.read_bytes() == before


def test_salvage_falls_back_to_the_previous_checkpoint_and_resumes_bit_for_bit(
    tmp_path: Path, reference: io.Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """The current checkpoint's W damaged: the other slot (step 2000) is verified, and the
    resume from it is the uninterrupted run, bit for bit."""
    config, out = _run(tmp_path, "run")
    with h5py.File(out, "r") as f:
        slot = f[f"checkpoint/slot{int(f['checkpoint'].attrs['current'])}/W"]
        offset = int(slot.id.get_chunk_info(0).byte_offset)
    data = bytearray(out.read_bytes())
    data[offset + 2] ^= 1
    out.write_bytes(bytes(data))
    damaged = out.read_bytes()
    assert main(["salvage", str(out)]) == 0
    said = capsys.readouterr().out
    assert "kept steps 0..2000 of 2100" in said and "bit for bit" in said
    assert (tmp_path / "run.h5.damaged").read_bytes() == damaged  # the original, kept
    salvaged = io.read_trajectory(out)
    assert salvaged.status == "interrupted" and salvaged.completed_steps == 2000
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def test_salvage_after_a_killed_write_keeps_the_verified_prefix(
    tmp_path: Path, reference: io.Trajectory
) -> None:
    """A process killed while it rewrote a chunk of per-step rows: both checkpoints lie
    after the damage, so the restart point is the last saved state before it (cold start),
    and everything before it is kept exactly."""
    config, out = _run(tmp_path, "run")
    _damage_chunk(out, "energy", 1)  # rows 1024..2047
    with pytest.raises(io.DamagedOutputError):
        io.run(io_setup(config), resume=True)
    report = salvage(out)
    assert (report.kept_steps, report.recorded_steps, report.bit_for_bit) == (1000, 2100, False)
    kept = io.read_trajectory(out)
    assert kept.completed_steps == 1000
    np.testing.assert_array_equal(kept.energy, reference.energy[:1001])
    np.testing.assert_array_equal(kept.W, reference.W[:11])
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    done = io.read_trajectory(out)
    assert done.status == "complete" and done.completed_steps == STEPS + 100
    np.testing.assert_array_equal(done.energy[:1001], reference.energy[:1001])
    # a cold solver start: the same trajectory to the solver's tolerance, not bit for bit
    np.testing.assert_allclose(done.W, reference.W, rtol=0, atol=1e-11)


def test_salvage_of_a_damaged_last_chunk_keeps_the_checkpoint_before_it(
    tmp_path: Path, reference: io.Trajectory
) -> None:
    config, out = _run(tmp_path, "run")
    damage_last_chunk(out, "iterations")  # rows 2048..2100: the checkpoint at 2000 is intact
    report = salvage(out)
    assert (report.kept_steps, report.bit_for_bit) == (2000, True)
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def test_salvage_of_an_intact_file_changes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, out = _run(tmp_path, "run", 60)
    before = out.read_bytes()
    capsys.readouterr()
    assert main(["salvage", str(out)]) == 0
    said = capsys.readouterr().out
    assert "verifies" in said and "nothing to salvage, the file is unchanged" in said
    assert out.read_bytes() == before
    assert io.read_trajectory(out).status == "complete"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5", "run.toml"]


def test_salvage_refuses_what_it_cannot_verify_and_leaves_it(tmp_path: Path) -> None:
    _, out = _run(tmp_path, "run", 60)
    damage_last_chunk(out, "energy")  # the only chunk: not even step 0 is verified
    before = out.read_bytes()
    with pytest.raises(io.DamagedOutputError, match="cannot be salvaged"):
        salvage(out)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5", "run.toml"]
    (tmp_path / "foreign.h5").write_bytes(b"not HDF5 at all")
    with pytest.raises(lf.LieflowError, match="not an HDF5 file"):
        salvage(tmp_path / "foreign.h5")


def test_salvage_of_a_truncated_file_pads_it_and_keeps_the_intact_beginning(
    tmp_path: Path,
) -> None:
    """Truncated past its data (the metadata HDF5 wrote last lost): refused with a clear
    error, never a traceback; the file itself untouched."""
    _, out = _run(tmp_path, "run", 60)
    os.truncate(out, out.stat().st_size // 2)
    before = out.read_bytes()
    with pytest.raises(io.DamagedOutputError, match="cannot be salvaged"):
        salvage(out)
    assert out.read_bytes() == before


def io_setup(config: Path) -> object:
    from lieflow.app.config import build, load_config

    return build(load_config(config))


# -- the checkpoint's SHA-256: every item it covers -------------------------------------------


def _items(path: Path) -> list[str]:
    with h5py.File(path, "r") as f:
        slot = f[f"checkpoint/slot{int(f['checkpoint'].attrs['current'])}"]
        return sorted(_reader._slot_items(slot))


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _run(tmp_path_factory.mktemp("finished"), "run", 60)[1]


def test_the_checkpoint_digest_covers_state_and_warm_start(finished: Path) -> None:
    """What the parametrised test below changes one by one."""
    items = _items(finished)
    assert "W" in items and "warm/last" in items and "warm/trusted" in items
    assert any(key.startswith("warm/previous/") for key in items)


@pytest.mark.parametrize(
    "item",
    ["W", "warm/last", "warm/previous/0", "warm/previous/3", "warm/trusted", "step", "t"],
)
def test_a_change_in_any_checkpoint_item_fails_the_sha256(
    finished: Path, tmp_path: Path, item: str
) -> None:
    """Changed through HDF5 itself, so its chunk checksums stay right: only the digest can
    tell (one bit of an array, the warm start's counter, the step index, the time)."""
    victim = tmp_path / "victim.h5"
    shutil.copyfile(finished, victim)
    with h5py.File(victim, "r+") as f:
        slot = f[f"checkpoint/slot{int(f['checkpoint'].attrs['current'])}"]
        if item in ("step", "t"):
            slot.attrs[item] = slot.attrs[item] + 1
        elif item == "warm/trusted":
            scalars = json.loads(slot.attrs["scalars"])
            scalars[item] += 1
            slot.attrs["scalars"] = json.dumps(scalars, sort_keys=True)
        else:
            value = slot[item][()]
            value.view(np.uint64).reshape(-1)[-1] ^= 1
            slot[item][...] = value
    with pytest.raises(lf.LieflowError, match="SHA-256"):
        io.read_checkpoint(victim)
    with pytest.raises(lf.LieflowError, match="SHA-256"):
        io.read_trajectory(victim)


def test_damaged_data_in_the_spare_slot_is_overwritten_by_the_next_checkpoint(
    tmp_path: Path, reference: io.Trajectory
) -> None:
    """Readers never read the spare slot, and the next checkpoint overwrites its arrays
    whole: damaged data there costs nothing (the resume is the uninterrupted run)."""
    config, out = _run(tmp_path, "run")
    with h5py.File(out, "r") as f:
        spare = f"checkpoint/slot{1 - int(f['checkpoint'].attrs['current'])}/W"
        offset = int(f[spare].id.get_chunk_info(0).byte_offset)
    data = bytearray(out.read_bytes())
    data[offset + 1] ^= 2
    out.write_bytes(bytes(data))
    io.read_trajectory(out)
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def test_a_slot_whose_structure_is_damaged_is_refused_not_a_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A flipped byte in the object header of the current slot's warm start: salvage falls
    back to the other slot, but HDF5 cannot remove the damaged one (it reads its members
    as it frees them), where the next checkpoint would go. It used to be "salvaged" and
    then fail at the resume's first checkpoint with h5py's "Can't visit links (dataspace dim
    2 size of 1048579 is greater than maxdim size of 3)"; now it is refused, file unchanged."""
    config, out = _run(tmp_path, "run")
    with h5py.File(out, "r") as f:
        slot = f[f"checkpoint/slot{int(f['checkpoint'].attrs['current'])}"]
        header = int(h5py.h5o.get_info(slot["warm/previous/3"].id).addr)
    data = bytearray(out.read_bytes())
    data[header + 50] ^= 1 << 4  # in its dataspace message
    out.write_bytes(bytes(data))
    before = out.read_bytes()
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    assert main(["salvage", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot remove it" in err and "Traceback" not in err
    assert out.read_bytes() == before
