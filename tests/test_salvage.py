"""Damaged trajectory files (issue 29 item 5, issue 37 items 2, 3 and 10): told apart from busy
ones, verified before a resume reports ``complete``, and salvaged: every row that reads back
kept, what has a copy repaired, the rest said."""

from __future__ import annotations

import json
import os
import re
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


#: 17 chunks of per-step rows (CHUNK_ROWS = 128 each): 0..127, ..., 2048..2100
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
    assert "is damaged" in err and "'W' does not read back from row 0" in err
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


def _same_but(a: io.Trajectory, b: io.Trajectory, holes: dict[str, slice]) -> None:
    """``a`` is (the beginning of) ``b`` bit for bit, but for the rows ``holes`` of the named
    diagnostics, which hold NaN (-1 for solver updates) in ``a``."""
    for name in ("step", "W", "energy", "casimirs", "iterations", "residual"):
        got = getattr(a, name)
        want = getattr(b, name)[: len(got)]
        if name in holes:
            hole = got[holes[name]]
            assert (hole == -1).all() if name == "iterations" else np.isnan(hole).all(), name
            got, want = got.copy(), want.copy()
            got[holes[name]] = want[holes[name]]
        np.testing.assert_array_equal(got, want, err_msg=name)


def test_a_damaged_chunk_of_per_step_rows_costs_its_rows_only(
    tmp_path: Path, reference: io.Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """A process killed while it rewrote a chunk of energies: the salvage used to cut the
    file back to the saved state before that chunk (a cold restart, every later step lost);
    now the chunk's 128 rows are holes, every other row and the checkpoint are kept, and the
    resume continues bit for bit."""
    config, out = _run(tmp_path, "run")
    _damage_chunk(out, "energy", 1)  # rows 128..255
    with pytest.raises(io.DamagedOutputError):
        io.run(io_setup(config), resume=True)
    capsys.readouterr()
    assert main(["salvage", str(out)]) == 0
    said = capsys.readouterr().out
    assert "kept steps 0..2100 of 2100" in said and "bit for bit" in said
    assert "lost: energy of steps 128..255" in said and ".salvage" not in said
    _same_but(io.read_trajectory(out), reference, {"energy": slice(128, 256)})
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    done = io.read_trajectory(out)
    assert done.status == "complete" and done.completed_steps == STEPS + 100
    _same_but(done, reference, {"energy": slice(128, 256)})


def test_salvage_of_a_damaged_last_chunk_keeps_every_other_row(
    tmp_path: Path, reference: io.Trajectory
) -> None:
    config, out = _run(tmp_path, "run")
    damage_last_chunk(out, "iterations")  # steps 2048..2100
    report = salvage(out)
    assert (report.kept_steps, report.bit_for_bit) == (2100, True)
    assert report.lost == ("iterations of steps 2048..2100 (NaN or -1 in the file)",)
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same_but(io.read_trajectory(out), reference, {"iterations": slice(2048 - 1, 2100)})


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


@pytest.mark.parametrize("kept", [0.3, 0.5, 0.7, 0.9, 0.99, 0.9999])
def test_a_truncated_file_is_salvaged_and_resumes_to_the_uninterrupted_run(
    tmp_path: Path, reference: io.Trajectory, capsys: pytest.CaptureFixture[str], kept: float
) -> None:
    """Issue 37 item 2: none of 7 truncations (10 % to 99.99 % kept) of a complete file was
    recovered, and the deep cuts' error named the hidden temporary ``.f.h5.<pid>.salvage``.
    Now the file is read as padded (bytes that fail every checksum), its verified rows are
    kept, and the resume ends where an uninterrupted run ends."""
    config, out = _run(tmp_path, "run")
    data = out.read_bytes()
    out.write_bytes(data[: int(len(data) * kept)])
    capsys.readouterr()
    assert main(["salvage", str(out)]) == 0
    said = capsys.readouterr().out
    assert ".salvage" not in said and "Traceback" not in said
    report_exact = "bit for bit" in said.splitlines()[0]
    assert (tmp_path / "run.h5.damaged").read_bytes() == data[: int(len(data) * kept)]
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    done = io.read_trajectory(out)
    assert done.status == "complete" and done.completed_steps == STEPS + 100
    if report_exact:
        np.testing.assert_array_equal(done.checkpoint.W, reference.checkpoint.W)
    else:  # a cold restart from a saved state
        np.testing.assert_allclose(done.checkpoint.W, reference.checkpoint.W, rtol=0, atol=1e-11)
    m = ~np.isnan(done.energy)
    np.testing.assert_allclose(done.energy[m], reference.energy[m], rtol=1e-13, atol=0)


def test_a_file_cut_before_its_structure_is_refused_and_left(tmp_path: Path) -> None:
    """Cut to its first 10 %: its HDF5 structure (the root group's index and attributes, and
    every copy of them) lies after the cut. Refused with a clear error naming the file only
    (not a hidden temporary), the file untouched, nothing left beside it."""
    _, out = _run(tmp_path, "run", 60)
    os.truncate(out, out.stat().st_size // 10)
    before = out.read_bytes()
    with pytest.raises(io.DamagedOutputError, match="cannot be salvaged") as info:
        salvage(out)
    assert ".salvage" not in str(info.value)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5", "run.toml"]


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


def test_a_slot_whose_structure_is_damaged_is_salvaged_from_the_other(
    tmp_path: Path, reference: io.Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """A flipped byte in the object header of the current slot's warm start. It used to be
    "salvaged" in place and then fail at the resume's first checkpoint (h5py: "Can't visit
    links"), later refused because HDF5 cannot remove the damaged slot; the salvage now
    writes a new file, so the damaged slot is simply not copied: the other slot's checkpoint
    (step 2000) is kept, and the resume is the uninterrupted run, bit for bit."""
    config, out = _run(tmp_path, "run")
    with h5py.File(out, "r") as f:
        slot = f[f"checkpoint/slot{int(f['checkpoint'].attrs['current'])}"]
        header = int(h5py.h5o.get_info(slot["warm/previous/3"].id).addr)
    data = bytearray(out.read_bytes())
    data[header + 50] ^= 1 << 4  # in its object header
    out.write_bytes(bytes(data))
    before = out.read_bytes()
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    assert out.read_bytes() == before  # refused without writing
    capsys.readouterr()
    assert main(["salvage", str(out)]) == 0
    assert "kept steps 0..2000 of 2100" in capsys.readouterr().out
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def test_a_damaged_initial_condition_is_repaired_from_its_copy(
    tmp_path: Path, reference: io.Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 37 item 2: one flip in ``initial/W0`` alone made the file unrecoverable; the
    saved state of step 0 is its copy."""
    config, out = _run(tmp_path, "run")
    _damage_chunk(out, "initial/W0", 0)
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    capsys.readouterr()
    assert main(["salvage", str(out)]) == 0
    said = capsys.readouterr().out
    assert "kept steps 0..2100 of 2100" in said and "bit for bit" in said
    assert "repaired: initial/W0 (from the saved state of step 0)" in said
    assert "every row of those steps read back intact" in said
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["initial/W0"][()], reference.W[0])
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def _attribute_unreadable(path: Path, name: str) -> None:
    """Flip one bit where HDF5 keeps the root attribute ``name`` so that it no longer reads
    back while the file opens and the copy in ``initial/W0`` reads: the first such bit near
    an occurrence of the attribute's name (in HDF 1.10's format the root attributes share
    one checksummed heap, so the others are then unreadable too)."""
    data = path.read_bytes()
    for found in re.finditer(re.escape(name.encode()), data):
        for offset in range(found.start(), found.start() + 64):
            trial = bytearray(data)
            trial[offset] ^= 1
            path.write_bytes(bytes(trial))
            try:
                with h5py.File(path, "r") as f:
                    f["initial/W0"].attrs["header"]
                    try:
                        f.attrs[name]
                    except (OSError, KeyError, RuntimeError):
                        return
            except (OSError, KeyError, RuntimeError):
                pass
    raise AssertionError(f"no bit makes {name} unreadable")  # pragma: no cover


def test_an_unreadable_attribute_is_refused_before_writing_and_salvaged(
    tmp_path: Path, reference: io.Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 37 item 3: one flipped byte in the root attribute ``config_source``; --resume
    appended 100 steps, marked the file complete, then failed "check the disk", while
    salvage said "nothing to salvage" and readers "damaged, run salvage". Now the resume
    is refused before it writes anything, and the salvage restores the attribute from its
    copy written with the file."""
    config, out = _run(tmp_path, "run")
    _attribute_unreadable(out, "config_source")
    before = out.read_bytes()
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    capsys.readouterr()
    assert main(["run", str(config), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "header attributes" in err and "lieflow salvage" in err and "Traceback" not in err
    assert out.read_bytes() == before
    assert main(["salvage", str(out)]) == 0
    said = capsys.readouterr().out
    assert "repaired: attribute config_source" in said and "kept steps 0..2100" in said
    assert io.read_trajectory(out).meta["config_source"].endswith("run.toml")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def test_a_silently_changed_attribute_is_caught_by_its_copy(
    tmp_path: Path, reference: io.Trajectory
) -> None:
    """An attribute's value changed on disk reads back as another valid value (HDF5 does
    not checksum it): ``h`` is compared with its copy in ``initial/W0``, so the file is
    refused, and salvage restores it."""
    config, out = _run(tmp_path, "run")
    with h5py.File(out, "r+") as f:
        f.attrs["h"] = 0.2
    with pytest.raises(io.DamagedOutputError, match="h differ from their copy"):
        io.run(io_setup(config), resume=True)
    report = salvage(out)
    assert any(line.startswith("attribute h (changed") for line in report.repaired)
    assert io.read_trajectory(out).meta["h"] == 0.1
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same(io.read_trajectory(out), reference)


def test_a_restart_on_a_chunk_boundary_keeps_exactly_the_rows_before_the_damage(
    tmp_path: Path,
) -> None:
    """Issue 37 item 10: a salvage that kept one row too many passed the whole suite: no
    test restarted next to a chunk boundary. Every step is saved, both checkpoints are
    damaged, and so is the last chunk of energies (300 steps: three chunks of at most 128
    rows, a checkpoint at every step): the restart point must be the last row of
    the chunk before it (the state there and its energy read back), not one row later (its
    energy is lost: the resume would refuse the file) nor one earlier."""
    config = tmp_path / "run.toml"
    config.write_text(
        rigid_body_config(h=0.1, steps=300, save_every=1, checkpoint="saves",
                          output="run.h5", engine="numpy"),
        encoding="utf-8",
    )  # fmt: skip
    assert main(["run", str(config), "--no-progress"]) == 0
    out = tmp_path / "run.h5"
    with h5py.File(out, "r") as f:
        rows = f["energy"].chunks[0]
        last = (f["energy"].shape[0] - 1) // rows  # the chunk of the last steps
    for slot in (0, 1):
        _damage_chunk(out, f"checkpoint/slot{slot}/W", 0)
    _damage_chunk(out, "energy", last)
    report = salvage(out)
    boundary = last * rows  # the first step of the damaged chunk
    assert (report.kept_steps, report.bit_for_bit) == (boundary - 1, False)
    kept = io.read_trajectory(out)
    assert kept.completed_steps == boundary - 1 and not np.isnan(kept.energy).any()
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    assert io.read_trajectory(out).status == "complete"


def _lose_a_chunk_from_the_index(path: Path, name: str) -> int:
    """Flip one bit of the key of a chunk in HDF5's (version 1, unchecksummed) B-tree
    chunk index of ``name``, so that a plain read of that chunk's rows returns zeros with no
    error; returns the first row of that chunk."""
    data = path.read_bytes()
    with h5py.File(path, "r") as f:
        want = f[name][()]
        rows = f[name].chunks[0]
    for found in re.finditer(b"TREE", data):
        for entry in range(1, 64):  # the key of entry j: size 4, mask 4, offsets 8 each
            trial = bytearray(data)
            trial[found.start() + 24 + 32 * entry + 11] ^= 2
            path.write_bytes(bytes(trial))
            try:
                with h5py.File(path, "r") as f:
                    got = f[name][()]
            except (OSError, KeyError, RuntimeError, ValueError):
                continue
            zeroed = np.flatnonzero((got == 0) & (want != 0))
            if zeroed.size:
                return int(zeroed[0]) // rows * rows
    raise AssertionError("no key flip loses a chunk")  # pragma: no cover


def test_a_chunk_lost_from_the_index_is_not_read_as_zeros(
    tmp_path: Path, reference: io.Trajectory
) -> None:
    """A flipped bit in a key of the (unchecksummed) B-tree chunk index makes HDF5 read a
    chunk's rows as zeros without an error: --resume used to continue such a file, its
    energies silently zero; now the resume is refused and the salvage keeps those rows as
    holes."""
    config, out = _run(tmp_path, "run")
    first = _lose_a_chunk_from_the_index(out, "energy")
    with pytest.raises(io.DamagedOutputError, match="'energy' does not read back"):
        io.run(io_setup(config), resume=True)
    report = salvage(out)
    rows = slice(first, first + 128)
    assert report.lost == (f"energy of steps {first}..{first + 127} (NaN or -1 in the file)",)
    config.write_text(config_text(steps=STEPS + 100, name="run"), encoding="utf-8")
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    _same_but(io.read_trajectory(out), reference, {"energy": rows})


def test_salvage_in_a_read_only_directory_says_what_it_writes(tmp_path: Path) -> None:
    """Issue 37 item 9: salvage in a read-only folder spoke of "/proc" (the output's fix).
    On a real read-only filesystem (a tmpfs remounted read-only; skipped where this process
    may not mount)."""
    import subprocess

    where = tmp_path / "ro"
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(where)],
                          capture_output=True, check=False)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        _, out = _run(where, "run", 60)
        damage_last_chunk(out, "iterations")
        subprocess.run(["mount", "-o", "remount,ro", str(where)], check=True)
        with pytest.raises(lf.LieflowError, match="salvage writes in the file's directory") as e:
            salvage(out)
        assert "/proc" not in str(e.value) and "Read-only file system" in str(e.value)
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)
