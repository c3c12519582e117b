"""Ctrl-C at any moment (issue 15.3): ``lieflow run`` on a pseudo-terminal, with its
progress bar drawing, interrupted by SIGINT at random points, always leaves a file that is
marked interrupted (exit code 130) or complete (exit code 0), and whose resumed run equals
an uninterrupted one bit for bit."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from processes import Children, on_a_terminal

from lieflow.app import io

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX pseudo-terminals")

CONFIG = """
[system]
name = "generalized_rigid_body"
params = { J = [1.0, 1.3, 1.7, 2.2, 2.8, 3.1] }
[initial]
random = true
seed = 1
[scheme]
name = "gauss2"
[run]
h = 0.05
steps = 1200
save_every = 7
engine = "numpy"
"""


STEPS = 1200  # the run's steps in CONFIG
#: The progress bar's count of steps done, e.g. ``" 254/1200"`` (rich redraws it 10 times a
#: second whatever the load).
_COUNT = re.compile(rb"(\d+)/%d" % STEPS)


def _run_on_a_terminal(
    children: Children, args: list[str], interrupt_after: int | None = None
) -> tuple[int, str]:
    """Run ``lieflow`` on a pseudo-terminal (so the progress bar draws). With
    ``interrupt_after``: send SIGINT as soon as the bar shows at least that many steps done
    — an event the run itself reports, so the point of the interrupt is a step count, not a
    time that a busy machine stretches. Returns the exit code and the terminal's output."""
    reached = threading.Event()

    def watch(tail: bytes, proc: subprocess.Popen[bytes]) -> None:
        if interrupt_after is not None and not reached.is_set():
            if any(int(m) >= interrupt_after for m in _COUNT.findall(tail)):
                proc.send_signal(signal.SIGINT)
                reached.set()

    code, out = on_a_terminal(children, [sys.executable, "-m", "lieflow", *args], watch)
    if interrupt_after is not None:
        assert reached.is_set(), "the progress bar never showed the step to interrupt at"
    return code, out


def test_sigint_at_random_points_on_a_terminal(tmp_path: Path, children: Children) -> None:
    config = tmp_path / "run.toml"
    config.write_text(CONFIG)
    ref = tmp_path / "ref.h5"
    code, out = _run_on_a_terminal(children, ["run", str(config), "--out", str(ref)])
    assert code == 0, out
    reference = io.read_trajectory(ref)

    rng = np.random.default_rng(20261123)
    interrupted = 0
    # at random steps of the first half: the run cannot finish before the signal arrives
    for trial, step in enumerate(rng.integers(0, STEPS // 2, size=5)):
        path = tmp_path / f"t{trial}.h5"
        code, out = _run_on_a_terminal(
            children, ["run", str(config), "--out", str(path)], int(step)
        )
        assert code in (0, 130), out  # never the internal-error exit code
        assert "Traceback" not in out and "internal error" not in out, out
        first = io.read_trajectory(path)
        assert first.status == ("interrupted" if code == 130 else "complete")
        interrupted += code == 130
        code, out = _run_on_a_terminal(
            children, ["run", str(config), "--out", str(path), "--resume", "--no-progress"]
        )
        assert code == 0, out
        resumed = io.read_trajectory(path)
        assert resumed.status == "complete"
        assert np.array_equal(resumed.checkpoint.W, reference.checkpoint.W)
        assert np.array_equal(resumed.energy_error, reference.energy_error)
        assert np.array_equal(resumed.iterations, reference.iterations)
    assert interrupted >= 3  # the test did exercise interrupts


@pytest.mark.parametrize("at_call", [2, 5, 37])
def test_a_ctrl_c_between_a_step_and_its_record_keeps_state_and_flow_state_together(
    monkeypatch: pytest.MonkeyPatch, at_call: int
) -> None:
    """Ctrl-C after a step returns but before the chunk holds it (here: in the finiteness
    check that follows every step) must not yield the chunk's last state with the next
    step's flow state: a checkpoint would keep them, and the resumed run's warm start would
    be one step ahead (its updates per step differ from the uninterrupted run's; seen by
    ``test_sigint_at_random_points_on_a_terminal`` once in CI)."""
    import lieflow as lf
    from lieflow import chunks, stepping
    from lieflow.engines import scheme_flow

    system = lf.systems.GeneralizedRigidBody((1.0, 1.3, 1.7, 2.2, 2.8, 3.1))
    W0, h, steps = system.algebra.random(seed=1), 0.05, 120

    def flow() -> lf.SchemeFlow:
        scheme, solver = lf.schemes.get("gauss2"), lf.solvers.FixedPoint()
        return scheme_flow(system, scheme, solver, W0, steps, engine="numpy")

    whole = list(stepping.advance(flow(), W0, h, steps, batch=16))
    calls = 0
    finite = stepping.all_finite

    def interrupted(W: np.ndarray) -> bool:
        nonlocal calls
        calls += 1
        if calls == at_call:
            raise KeyboardInterrupt
        return finite(W)

    monkeypatch.setattr(stepping, "all_finite", interrupted)
    first: list[chunks.Chunk] = []
    with pytest.raises(KeyboardInterrupt):
        first.extend(stepping.advance(flow(), W0, h, steps, batch=16))
    monkeypatch.undo()
    last = first[-1]
    assert last.stop == at_call - 1  # the interrupted step is not in the chunk
    rest = stepping.advance(flow(), last.W[-1], h, steps, start=last.stop, state=last.state,
                            batch=16)  # fmt: skip
    resumed = [*first, *rest]
    for what in ("W", "iterations"):
        np.testing.assert_array_equal(
            np.concatenate([getattr(c, what) for c in resumed]),
            np.concatenate([getattr(c, what) for c in whole]),
        )
