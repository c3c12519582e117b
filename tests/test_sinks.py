"""The one consumer loop (:func:`lieflow.stepping.run`) and the sinks it feeds."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lieflow as lf
from lieflow.stepping import Cadence

RB = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
W0 = RB.random_state(seed=0)
MID = lf.schemes.get("midpoint")


class Recorder:
    """A Sink that writes down every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.kept: list[int] = []

    def record(self, chunk: Any, keep: Any, diagnostics: Any) -> None:
        self.calls.append(("record", chunk.stop))
        self.kept += chunk.index[keep].tolist()
        self.diagnostics = diagnostics

    def checkpoint(self, *, keep_last: bool = False) -> None:
        self.calls.append(("checkpoint", keep_last))

    def close(self, status: str, failure: Any, wall_time: float) -> None:
        self.calls.append(("close", status))

    def result(self) -> str:
        return "recorded"


class Extra(lf.IsospectralSystem):
    """The rigid body with an extra diagnostic (``|W|_F`` and the step's state)."""

    algebra = lf.SO(3)
    linear_B = True
    diagnostics_every = 2

    def B(self, W: np.ndarray) -> np.ndarray:
        return RB.B(W)

    def hamiltonian(self, W: np.ndarray) -> np.ndarray:
        return RB.hamiltonian(W)

    def extra_diagnostics(self, W: np.ndarray) -> dict[str, np.ndarray]:
        return {"norm": np.asarray(np.linalg.norm(W)), "W": np.array(W)}


def test_integrate_into_a_sink_object_returns_its_result() -> None:
    sink = Recorder()
    out = lf.integrate(RB, MID, W0, 0.1, steps=7, save_every=3, out=sink, engine="numpy")
    assert out == "recorded" and sink.kept == [3, 6, 7]
    # one second between checkpoints (a short run: only the final one), then close
    assert [c for c in sink.calls if c[0] != "record"] == [("checkpoint", False),
                                                            ("close", "complete")]  # fmt: skip
    sink = Recorder()
    lf.integrate(RB, MID, W0, 0.1, steps=7, save_every=3, out=sink, engine="numpy",
                 checkpoint_seconds=0)  # fmt: skip
    taken = [sink.calls[i - 1] for i, c in enumerate(sink.calls) if c[0] == "checkpoint"]
    assert taken[:-1] == [("record", k) for k in range(1, 8)]  # after every (one-step) chunk


class Closing(Recorder):
    """A Sink that notes the SIGINT handler in force when it is closed."""

    def close(self, status: str, failure: Any, wall_time: float) -> None:
        self.handler = signal.getsignal(signal.SIGINT)
        super().close(status, failure, wall_time)


class InMemory(Closing):
    """The same, keeping nothing outside the process."""

    durable = False


def test_interrupts_are_held_while_durable_sinks_close() -> None:
    default = signal.getsignal(signal.SIGINT)
    flow = lf.engines.scheme_flow(RB, MID, lf.solvers.FixedPoint(), W0, 3, engine="numpy")
    for sinks, held in (((Closing(),), True), ((InMemory(),), False),
                        ((InMemory(), Closing()), True)):  # fmt: skip
        lf.stepping.run(flow, W0, 0.1, 3, sinks=sinks)
        assert all((s.handler is not default) is held for s in sinks)
        assert all(s.calls[-2:] == [("checkpoint", False), ("close", "complete")] for s in sinks)
    assert signal.getsignal(signal.SIGINT) is default
    assert lf.sinks.MemorySink.durable is False


@pytest.mark.parametrize(
    ("cadence", "after"), [(Cadence(steps=4), [4, 8]), (Cadence(seconds=0), list(range(1, 11)))]
)
def test_checkpoint_cadence_is_not_the_save_cadence(cadence: Cadence, after: list[int]) -> None:
    sink = Recorder()
    flow = lf.SchemeFlow(RB, MID, lf.solvers.FixedPoint())
    outcome = lf.stepping.run(flow, W0, 0.1, 10, sinks=[sink], save_every=5, checkpoint=cadence)
    assert outcome.status == "complete" and outcome.done == 10
    calls = sink.calls
    taken = [calls[i - 1][1] for i, c in enumerate(calls) if c[0] == "checkpoint"]
    assert taken[:-1] == after and sink.kept == [5, 10]


def test_bad_cadence_is_refused() -> None:
    with pytest.raises(lf.InputError, match="checkpoint steps"):
        Cadence(steps=0)
    with pytest.raises(lf.InputError, match="checkpoint seconds"):
        Cadence(seconds=float("nan"))


def test_a_failed_step_keeps_the_last_state_and_closes_failed() -> None:
    sink = Recorder()
    solver = lf.solvers.FixedPoint(max_iter=2)
    scheme = lf.schemes.get("gauss2")
    flow = lf.SchemeFlow(RB, scheme, solver)
    outcome = lf.stepping.run(flow, 50 * W0, 0.5, 5, sinks=[sink], save_every=5)
    assert outcome.status == "failed" and isinstance(outcome.failure, lf.ConvergenceError)
    assert sink.calls[-2:] == [("checkpoint", True), ("close", "failed")]
    sol = lf.integrate(RB, scheme, 50 * W0, 0.5, steps=5, solver=solver, on_failure="truncate")
    assert not sol.success and sol.saved_steps[-1] == sol.n_steps == outcome.done


def test_extra_diagnostics_reach_memory_and_file_alike(tmp_path: Path) -> None:
    """``system.extra_diagnostics`` used to be recorded by the HDF5 writer only."""
    system = Extra()
    mem = lf.integrate(system, MID, W0, 0.1, steps=5, engine="numpy")
    assert mem.extra["step"].tolist() == [0, 2, 4]
    np.testing.assert_array_equal(mem.extra["t"], [0.0, 0.2, 0.4])
    saved = mem.extra["W"]
    sol = lf.integrate(system, MID, W0, 0.1, steps=5, engine="numpy", save_every=1)
    np.testing.assert_array_equal(saved, sol.W[[0, 2, 4]])  # the states themselves
    np.testing.assert_allclose(mem.extra["norm"], np.linalg.norm(W0), rtol=1e-14)
    disk = lf.integrate(system, MID, W0, 0.1, steps=5, engine="numpy", out=tmp_path / "x.h5")
    assert sorted(disk.extra) == sorted(mem.extra)
    for name, value in mem.extra.items():
        np.testing.assert_array_equal(disk.extra[name], value)


def test_memory_sink_and_file_sink_see_the_same_diagnostics(tmp_path: Path) -> None:
    mem = lf.integrate(RB, MID, W0, 0.1, steps=9, save_every=4, engine="numpy")
    disk = lf.integrate(RB, MID, W0, 0.1, steps=9, save_every=4, engine="numpy",
                        out=tmp_path / "r.h5")  # fmt: skip
    assert mem.energy_error is not None and disk.energy_error is not None
    np.testing.assert_array_equal(mem.energy_error, disk.energy_error)
    np.testing.assert_array_equal(mem.iterations, disk.iterations)
    np.testing.assert_array_equal(mem.W[-1], disk.W[-1])
    # recomputed independently at the saved states; the Casimir tr W^2 is exact (isospectral)
    H = np.array([RB.hamiltonian(W) for W in mem.W])
    H0 = RB.hamiltonian(W0)
    np.testing.assert_allclose(mem.energy_error[mem.saved_steps], np.abs(H - H0) / abs(H0),
                               rtol=1e-12, atol=0)  # fmt: skip
    assert mem.casimir_drift is not None and mem.casimir_drift.max() < 1e-13


def test_an_unregistered_suffix_is_written_as_a_trajectory_file(tmp_path: Path) -> None:
    sol = lf.integrate(RB, MID, W0, 0.1, steps=3, out=tmp_path / "run.dat")
    assert sol.success and lf.open_run(tmp_path / "run.dat").W_final.shape == (3, 3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"out": 123}, "file path or a Sink"),
        ({"out": "x.h5", "checkpoint_seconds": "1"}, "checkpoint seconds"),
        ({"out": "x.h5", "checkpoint_seconds": -1.0}, "checkpoint seconds"),
    ],
)
def test_bad_outputs_are_refused_before_anything_is_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kwargs: dict, match: str
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(lf.InputError, match=match):
        lf.integrate(RB, MID, W0, 0.1, steps=3, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_rows_written_ahead_of_the_checkpoint_are_dropped_on_resume(tmp_path: Path) -> None:
    """A killed run whose states went to the file ahead of its checkpoint (the buffer
    filled: 64 KiB of so(3) states, about 900) resumes from the checkpoint, bit for bit."""
    import subprocess
    import sys
    import textwrap

    from lieflow.app import io

    out = tmp_path / "killed.h5"
    script = textwrap.dedent(
        f"""
        import os, sys
        import lieflow as lf
        from lieflow.app import io

        write_rows = io.TrajectoryWriter._write_rows

        def spy(self, **kwargs):
            sys.stderr.write(f"rows ahead: {{self._n_saved}}\\n")
            sys.stderr.flush()
            return write_rows(self, **kwargs)

        io.TrajectoryWriter._write_rows = spy

        class Kill:
            def start(self, done, total): self.done = done
            def advance(self, steps, iterations, err):
                self.done += steps
                if self.done >= 1500:  # the first chunk to end there
                    os._exit(9)
            def stop(self): pass

        body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
        lf.integrate(body, lf.schemes.get("midpoint"), body.random_state(0), 0.01,
                     steps=2000, engine="numpy", out={str(out)!r}, progress=Kill(),
                     checkpoint_seconds=1e9)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=300)
    assert proc.returncode == 9, proc.stderr.decode()
    assert io.read_checkpoint(out).step == 0  # no checkpoint but the first ...
    assert b"rows ahead: 1" in proc.stderr  # ... yet states went to the file ahead of it
    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    args = (body, MID, body.random_state(0), 0.01)
    resumed = lf.integrate(*args, steps=2000, engine="numpy", out=out, resume=True)
    lf.integrate(*args, steps=2000, engine="numpy", out=tmp_path / "whole.h5")
    a, b = io.read_trajectory(out), io.read_trajectory(tmp_path / "whole.h5")
    for name in ("step", "W", "energy_error", "casimir_drift", "iterations", "residual"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.completed_steps == 2000 and resumed.success
    memory = lf.integrate(*args, steps=2000, engine="numpy")  # no file involved
    np.testing.assert_array_equal(a.step, memory.saved_steps)
    np.testing.assert_array_equal(a.W, memory.W)
    np.testing.assert_array_equal(a.energy_error, memory.energy_error)


# The identities files were written with before lieflow.sinks.run_identity: a resume compares
# them as text, so they must not change (or files written before would no longer resume).
_CONFIG_IDENTITY = (
    '{"casimir_shift": 0.5, "h": 0.05, "save_every": 2, "scheme": {"name": "gauss2", "params":'
    ' {}}, "solver": {"name": "fixed_point", "params": {"rtol": 1e-12}}, "splitting": {"flows"'
    ': [{"name": "drag", "params": {"mu": 0.3}}], "method": "strang"}, "system": {"name": "rig'
    'id_body", "params": {"inertia": [1.0, 2.0, 3.0]}}}'
)
_INTEGRATE_IDENTITY = (
    '{"casimir_shift": 0.5, "h": 0.05, "save_every": 2, "scheme": {"form": "reduced", "tableau'
    '": {"A": "array <f8 (2, 2) sha256:1f65b96d0488038d", "b": "array <f8 (2,) sha256:606e5166'
    '986dd9f1", "c": "array <f8 (2,) sha256:24163de9e7c772cb", "name": "gauss2", "order": 4, "'
    'type": "ButcherTableau"}, "type": "BlockGauss", "update": "commutator"}, "solver": {"ande'
    'rson": 0, "atol": 0.0, "divergence_factor": 100.0, "max_iter": 100, "patience": 6, "round'
    'off_floor": 5.684341886080802e-14, "rtol": 1e-12, "type": "FixedPoint"}, "system": {"iner'
    'tia": "array <f8 (3,) sha256:a68de4b5e96a60c8", "type": "RigidBody"}, "warm_start": 2}'
)


def test_one_identity_for_lieflow_run_and_integrate_keeps_the_old_files(tmp_path: Path) -> None:
    import h5py

    from lieflow.app.config import parse_config
    from lieflow.sinks import run_identity

    text = """
[system]
name = "rigid_body"
params = { inertia = [1.0, 2.0, 3.0] }
[initial]
random = true
seed = 0
[scheme]
name = "gauss2"
[solver]
name = "fixed_point"
params = { rtol = 1e-12 }
[splitting]
method = "strang"
flows = [{ name = "drag", params = { mu = 0.3 } }]
[run]
h = 0.05
steps = 4
save_every = 2
casimir_shift = 0.5
"""
    assert parse_config(text).identity() == _CONFIG_IDENTITY
    no_shift = parse_config(text.replace("casimir_shift = 0.5\n", "")).identity()
    assert "casimir_shift" not in no_shift  # left out, not null: older files had no such key
    system = lf.systems.get("rigid_body", inertia=[1.0, 2.0, 3.0])
    scheme, W0 = lf.schemes.get("gauss2"), system.algebra.random(0)
    solver = lf.solvers.get("fixed_point", rtol=1e-12)
    out = tmp_path / "run.h5"
    lf.integrate(system, scheme, W0, 0.05, steps=3, save_every=2, solver=solver,
                 warm_start=2, casimir_shift=0.5, out=out)  # fmt: skip
    with h5py.File(out, "r") as f:
        assert f.attrs["identity"] == _INTEGRATE_IDENTITY
    # the one definition: both are run_identity of their parts
    described = run_identity(system=system, scheme=scheme, solver=solver, h=0.05, save_every=2,
                             warm_start=2, casimir_shift=0.5, splitting=None)  # fmt: skip
    assert described == _INTEGRATE_IDENTITY
    # and a file written with it resumes
    sol = lf.integrate(system, scheme, W0, 0.05, steps=6, save_every=2, solver=solver,
                       warm_start=2, casimir_shift=0.5, out=out, resume=True)  # fmt: skip
    assert sol.saved_steps.tolist() == [0, 6]


class FailsAt:
    """A flow stepping the rigid body that raises ``exc`` at step ``k``."""

    name = "fails"

    def __init__(self, k: int, exc: BaseException) -> None:
        self.flow, self.k, self.exc = lf.SchemeFlow(RB, MID), k, exc

    def init(self, W0: np.ndarray) -> Any:
        return self.flow.init(W0)

    def step(self, W: np.ndarray, t: float, h: float, state: Any) -> Any:
        if round(t / h) + 1 == self.k:
            raise self.exc
        return self.flow.step(W, t, h, state)


def test_chunks_of_many_steps_are_the_one_step_chunks_joined() -> None:
    flow = lf.SchemeFlow(RB, MID)
    one = list(lf.stepping.advance(flow, W0, 0.1, 150))
    many = list(lf.stepping.advance(flow, W0, 0.1, 150, batch=64))
    assert [c.size for c in one] == [1] * 150
    assert [c.stop for c in many] == [64, 128, 150]  # cut by step counts alone
    assert [c.start for c in many[1:]] == [c.stop for c in many[:-1]]
    for name in ("W", "iterations", "residuals"):
        a = np.concatenate([getattr(c, name) for c in one])
        b = np.concatenate([getattr(c, name) for c in many])
        assert np.array_equal(a, b)  # the same steps, bit for bit
    assert sum((c.solvers for c in many), ()) == sum((c.solvers for c in one), ())
    assert np.array_equal(many[-1].state.history()[0], one[-1].state.history()[0])


@pytest.mark.parametrize(
    "exc",
    [
        lf.ConvergenceError("diverged", solver="x", iterations=3, residuals=(1.0,)),
        KeyboardInterrupt(),
    ],
)
def test_a_chunk_cut_by_a_failure_or_ctrl_c_yields_its_steps_first(exc: BaseException) -> None:
    chunks: list[Any] = []
    with pytest.raises(type(exc)) as info:
        for chunk in lf.stepping.advance(FailsAt(40, exc), W0, 0.1, 100, batch=64):
            chunks.append(chunk)
    assert [c.stop for c in chunks] == [39] and chunks[0].W.shape == (39, 3, 3)
    failure = info.value
    if isinstance(failure, lf.ConvergenceError):
        assert failure.step == 40
    sink = Recorder()
    lf.integrate(RB, MID, W0, 0.1, steps=100, out=sink, engine="numpy")  # batched chunks
    assert sink.kept[-1] == 100
    assert [c[1] for c in sink.calls if c[0] == "record"] == [64, 100]


class Slow:
    """A flow stepping the rigid body whose every step also waits ``seconds``."""

    name = "slow"

    def __init__(self, seconds: float) -> None:
        self.flow, self.seconds = lf.SchemeFlow(RB, MID), seconds

    def init(self, W0: np.ndarray) -> Any:
        return self.flow.init(W0)

    def step(self, W: np.ndarray, t: float, h: float, state: Any) -> Any:
        time.sleep(self.seconds)
        return self.flow.step(W, t, h, state)


def test_chunks_do_not_depend_on_how_long_steps_take() -> None:
    """Chunks used to end after 5 ms of stepping as well, so what a sink saw (and where a
    checkpoint fell) depended on the machine's load: here every step takes 6 ms, as a busy
    machine makes a fast one take, and the chunks are still cut by step counts alone."""
    chunks = list(lf.stepping.advance(Slow(0.006), W0, 0.1, 10, batch=4))
    assert [c.stop for c in chunks] == [4, 8, 10]
    fast = list(lf.stepping.advance(lf.SchemeFlow(RB, MID), W0, 0.1, 10, batch=4))
    assert np.array_equal(chunks[-1].W, fast[-1].W)


def test_a_run_whose_first_step_fails_has_its_step_0_diagnostics() -> None:
    """A memory run computes W0's diagnostics with the first chunk's
    (``Diagnostics.deferred``): with no chunk, the solution still has step 0's, zero, in
    the shapes of the energies and Casimirs of the (here batched) state."""
    solver = lf.solvers.FixedPoint(max_iter=2)
    batch = np.stack([50 * W0, 40 * W0])
    sol = lf.integrate(RB, lf.schemes.get("gauss2"), batch, 0.5, steps=5, solver=solver,
                       on_failure="truncate")  # fmt: skip
    assert not sol.success and sol.n_steps == 0
    assert sol.energy_error is not None and sol.casimir_drift is not None
    np.testing.assert_array_equal(sol.energy_error, np.zeros((1, 2)))
    np.testing.assert_array_equal(sol.casimir_drift, np.zeros((1, 2, 1)))


def test_deferred_diagnostics_are_the_eager_ones() -> None:
    """W0's energy and Casimirs computed in one batch with the first chunk's states equal
    those computed alone (to roundoff), and so do the chunk's errors."""
    body = lf.systems.get("generalized_rigid_body", J=(1.0, 1.3, 1.7, 2.2, 2.8, 3.1))
    X0 = body.random_state(3)
    flow = lf.SchemeFlow(body, MID)
    chunk = next(lf.stepping.advance(flow, X0, 0.05, 3, batch=3))
    assert chunk.size == 3
    eager = lf.chunks.Diagnostics.of(body, X0)
    diag, first = lf.chunks.Diagnostics.deferred(body, X0).start(chunk)
    np.testing.assert_allclose(diag.H0, eager.H0, rtol=1e-15, atol=0)
    np.testing.assert_allclose(diag.C0, eager.C0, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(diag.scale, eager.scale)
    want = eager.of_chunk(chunk)
    np.testing.assert_allclose(first.energy, want.energy, rtol=1e-15, atol=0)
    np.testing.assert_allclose(first.energy_error, want.energy_error, rtol=0, atol=1e-15)
    np.testing.assert_allclose(first.casimir_drift, want.casimir_drift, rtol=0, atol=1e-15)
    # the chunk's errors are the definition's, recomputed state by state
    H = np.array([body.hamiltonian(W) for W in chunk.W])
    np.testing.assert_allclose(first.energy_error, np.abs(H - eager.H0) / abs(eager.H0),
                               rtol=1e-12, atol=0)  # fmt: skip
