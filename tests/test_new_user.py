"""What a new user and an adversary hit, second round (issue 37 items 8 and 9): ``[run]
checkpoint`` found where a user looks for it, and every API message clear."""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

import pytest
from helpers import rigid_body_config

import lieflow as lf
from lieflow.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
RB = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
W0 = RB.random_state(seed=0)
MID = lf.schemes.get("midpoint")


def _documented_run_keys() -> set[str]:
    """The keys of docs/config.md's ``[run]`` table."""
    text = (ROOT / "docs" / "config.md").read_text("utf-8")
    table = text.split("### `[run]`", 1)[1].split("\n\n", 2)[1]
    return set(re.findall(r"^\| `(\w+)` \|", table, flags=re.M))


def test_a_misspelt_run_key_lists_every_key_and_the_docs_have_them_all(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A misspelt key used to list "device, engine, h, output, save_every, steps": not
    ``t_final``, ``casimir_shift`` or ``checkpoint``, which docs/config.md did not list
    either."""
    config = tmp_path / "run.toml"
    config.write_text(rigid_body_config(h=0.1, steps=5, chekpoint=1.0), encoding="utf-8")
    assert main(["run", str(config), "--no-progress"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    listed = re.search(r"\[run\] accepts ([\w, ]+)", err)
    assert listed is not None, err
    accepted = set(listed.group(1).split(", "))
    assert {"checkpoint", "t_final", "casimir_shift", "device"} <= accepted
    assert accepted == _documented_run_keys()


class Recorder:
    """A Sink that writes down where its checkpoints fall."""

    def __init__(self) -> None:
        self.stop = 0
        self.checkpoints: list[int] = []

    def record(self, chunk: Any, keep: Any, diagnostics: Any) -> None:
        self.stop = chunk.stop

    def checkpoint(self, *, keep_last: bool = False) -> None:
        self.checkpoints.append(self.stop)

    def close(self, status: str, failure: Any, wall_time: float) -> None:
        pass

    def result(self) -> list[int]:
        return self.checkpoints


def test_checkpoint_seconds_none_checkpoints_at_every_save_and_saves_is_named() -> None:
    """``checkpoint_seconds=None`` is the configuration's ``"saves"`` (documented now);
    ``"saves"`` itself is refused with a message naming ``None``."""
    # a numpy flow's chunks (up to 64 steps) end at the saved states: at step 100, then 140
    taken = lf.integrate(RB, MID, W0, 0.1, steps=140, save_every=100, out=Recorder(),
                         checkpoint_seconds=None, engine="numpy")  # fmt: skip
    assert taken == [100, 140, 140]  # and once more as the run ends
    doc = lf.integrate.__doc__ or ""
    assert "``None``: after every chunk that holds a saved state" in doc
    with pytest.raises(lf.InputError, match="None to checkpoint at every saved state"):
        lf.integrate(RB, MID, W0, 0.1, steps=5, out=Recorder(), checkpoint_seconds="saves")


EXAMPLES = sorted(
    [*ROOT.glob("examples/**/*.toml"), *ROOT.glob("plugins/*/examples/*.toml")],
    key=lambda p: str(p),
)


def _header_commands(path: Path) -> list[list[str]]:
    """The ``lieflow`` commands in a configuration's comment header (continued lines
    joined; trailing comments dropped)."""
    import shlex

    lines = [ln[1:].strip() for ln in path.read_text("utf-8").splitlines() if ln.startswith("#")]
    text = "\n".join(lines).replace("\\\n", " ")
    return [shlex.split(ln, comments=True) for ln in text.splitlines() if ln.startswith("lieflow ")]


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: str(p.relative_to(ROOT)))
def test_an_examples_header_commands_work_from_the_repository_root(example: Path) -> None:
    """Issue 37 item 9: ``turbulence_n24.toml``'s header ran the example, then plotted
    ``turbulence_n24.h5`` — a file the run had written beside the configuration, not in the
    current directory. Every command of every example's header names files that exist, or
    that an earlier command of the header writes, from the repository root."""
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover - Python 3.10
        import tomli as tomllib

    written: set[Path] = set()
    for command in _header_commands(example):
        kind, target = command[1], ROOT / command[2]
        options = dict(zip(command[3::2], command[4::2], strict=False))
        if kind in ("run", "sweep"):
            assert target.is_file(), f"{example.name}: {' '.join(command)}"
            table = tomllib.loads(target.read_text("utf-8"))
            if "--out" in options:
                written.add((ROOT / options["--out"]).resolve())
            elif kind == "run":
                name = table["run"].get("output", f"{target.stem}.h5")
                written.add((target.parent / name).resolve())
            else:
                name = table.get("sweep", {}).get("directory", target.stem)
                written.add((target.parent / name).resolve())
        elif kind == "plot":
            assert target.resolve() in written or target.exists(), (
                f"{example.name}: `{' '.join(command)}` plots a file its header does not write "
                f"(it writes {sorted(map(str, written))})"
            )


# -- item 9: each API message ----------------------------------------------------------------


def test_a_sink_class_for_out_is_refused_with_the_instance_to_pass() -> None:
    """``out=lf.MemorySink`` used to end in ``TypeError: MemorySink.close() missing 1
    required positional argument``."""
    with pytest.raises(lf.InputError, match=r"got the class MemorySink.*MemorySink\(\.\.\.\)"):
        lf.integrate(RB, MID, W0, 0.1, steps=5, out=lf.MemorySink)  # type: ignore[arg-type]


def test_out_that_is_a_directory_or_exists_speaks_of_the_api(tmp_path: Path) -> None:
    """``out="/tmp"`` used to say "already exists ... pass --resume / --force", the command
    line's flags."""
    with pytest.raises(lf.LieflowError, match="is a directory") as info:
        lf.integrate(RB, MID, W0, 0.1, steps=5, out=tmp_path)
    assert "--" not in str(info.value)
    out = tmp_path / "run.h5"
    lf.integrate(RB, MID, W0, 0.1, steps=5, out=out)
    with pytest.raises(lf.LieflowError, match="already exists") as info:
        lf.integrate(RB, MID, W0, 0.1, steps=5, out=out)
    assert "resume=True" in str(info.value) and "replace=True" in str(info.value)
    assert "--resume" not in str(info.value) and "--force" not in str(info.value)


@pytest.mark.parametrize("out", [None, "run.h5"])
def test_a_huge_save_every_is_refused_before_anything_is_written(
    tmp_path: Path, out: str | None
) -> None:
    """``save_every=10**30`` used to end in ``OverflowError`` (in memory) or an h5py dtype
    error, leaving a file behind."""
    where = None if out is None else tmp_path / out
    for save_every in (10**30, 2**63):
        with pytest.raises(lf.InputError, match="save_every"):
            lf.integrate(RB, MID, W0, 0.1, steps=5, save_every=save_every, out=where)
    assert list(tmp_path.iterdir()) == []
    sol = lf.integrate(RB, MID, W0, 0.1, steps=5, save_every=2**53)  # the largest allowed
    assert sol.saved_steps.tolist() == [0, 5]


def test_resume_and_replace_together_are_refused(tmp_path: Path) -> None:
    with pytest.raises(lf.InputError, match="pass one of them"):
        lf.integrate(RB, MID, W0, 0.1, steps=5, out=tmp_path / "r.h5", resume=True, replace=True)
    assert list(tmp_path.iterdir()) == []


def test_a_wrapped_error_says_what_to_do_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A non-symmetric Toda W0 in a configuration used to read "... To fix: pass a symmetric
    matrix ... or use gl_gradient=True .... To fix: give an initial condition for
    PeriodicToda on gl(3)." — two fixes, the second contradicting the first."""
    config = tmp_path / "toda.toml"
    config.write_text(
        '[system]\nname = "periodic_toda"\nparams = { n = 3 }\n[initial]\n'
        "matrix = [[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n"
        '[scheme]\nname = "midpoint"\n[run]\nh = 0.1\nsteps = 10\n',
        encoding="utf-8",
    )
    assert main(["run", str(config), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("To fix") == 1 and "symmetric" in err and "on gl(3)" not in err, err
    assert "gl_gradient = true" in err  # how a configuration says it


def test_steps_beyond_what_can_be_counted_are_refused_by_a_configuration(
    tmp_path: Path,
) -> None:
    """``steps = 100000000000000000`` was accepted (the API refuses it), and the run sat at
    step 0; now refused up front (the configuration is read, nothing written), as
    ``integrate`` refuses it."""
    from lieflow.app.config import ConfigError, load_config

    config = tmp_path / "run.toml"
    for run in ({"steps": 10**17}, {"t_final": 1e16}):
        config.write_text(rigid_body_config(h=0.1, **run), encoding="utf-8")
        with pytest.raises(ConfigError, match="too many"):
            load_config(config)
    with pytest.raises(lf.InputError, match="too many to count"):
        lf.integrate(RB, MID, W0, 0.1, steps=10**17)
