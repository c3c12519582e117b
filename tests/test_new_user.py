"""What a new user and an adversary hit, second round (issue 37 items 8 and 9): ``[run]
checkpoint`` found where a user looks for it, and every API message clear."""

from __future__ import annotations

import re
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
    # chunks of 64 steps: the save at step 100 lies in the second, the last step in the third
    taken = lf.integrate(RB, MID, W0, 0.1, steps=140, save_every=100, out=Recorder(),
                         checkpoint_seconds=None, engine="numpy")  # fmt: skip
    assert taken == [128, 140, 140]  # and once more as the run ends
    doc = lf.integrate.__doc__ or ""
    assert "``None``: after every chunk that holds a saved state" in doc
    with pytest.raises(lf.InputError, match="None to checkpoint at every saved state"):
        lf.integrate(RB, MID, W0, 0.1, steps=5, out=Recorder(), checkpoint_seconds="saves")
