"""integrate(): saving, diagnostics, and a clear typed error for every bad input."""

from __future__ import annotations

import numpy as np
import pytest

import lieflow as lf

RB = lf.systems.get("rigid_body")
W0 = RB.random_state(seed=0)
MID = lf.schemes.get("midpoint")


def test_saving_and_bookkeeping() -> None:
    sol = lf.integrate(RB, MID, W0, 0.1, steps=25, save_every=10)
    assert sol.success and sol.n_steps == 25 and sol.scheme == "midpoint"
    np.testing.assert_array_equal(sol.saved_steps, [0, 10, 20, 25])
    np.testing.assert_allclose(sol.t, [0.0, 1.0, 2.0, 2.5], rtol=0, atol=1e-15)
    assert sol.W.shape == (4, 3, 3) and sol.t_final == pytest.approx(2.5)
    assert sol.iterations.shape == (25,) and np.all(sol.iterations >= 1)
    assert sol.energy_error is not None and sol.energy_error.shape == (26,)
    assert sol.energy_error[0] == 0.0 and 0 < sol.energy_error.max() < 1e-3
    assert sol.casimir_drift is not None and sol.casimir_drift.shape == (26, 1)
    assert sol.wall_time > 0 and len(sol.solvers) == 25
    np.testing.assert_array_equal(sol.W[0], W0)


def test_t_final_and_no_diagnostics() -> None:
    sol = lf.integrate(RB, MID, W0, 0.25, t_final=2.0, diagnostics=False)
    assert sol.n_steps == 8 and sol.energy_error is None and sol.casimir_drift is None


def test_energy_error_decreases_with_order() -> None:
    errs = [
        lf.integrate(RB, lf.schemes.get(name), W0, 0.1, steps=200).energy_error.max()  # type: ignore[union-attr]
        for name in ("midpoint", "gauss2", "gauss3")
    ]
    assert errs[0] > 100 * errs[1] > 100 * 100 * errs[2]


def test_input_is_not_modified() -> None:
    W = W0.copy()
    lf.integrate(RB, MID, W, 0.1, steps=3)
    np.testing.assert_array_equal(W, W0)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"h": 0.0}, lf.InputError, "positive"),
        ({"h": -0.1}, lf.InputError, "positive"),
        ({"h": float("nan")}, lf.InputError, "finite"),
        ({"h": "big"}, lf.InputError, "real number"),
        ({"steps": 0}, lf.InputError, "positive integer"),
        ({"steps": 2.5}, lf.InputError, "positive integer"),
        ({"steps": None, "t_final": 1.05}, lf.InputError, "whole number of steps"),
        ({"steps": 5, "t_final": 1.0}, lf.InputError, "exactly one"),
        ({"save_every": 0}, lf.InputError, "save_every"),
        ({"on_failure": "ignore"}, lf.InputError, "on_failure"),
        ({"W0": np.zeros((4, 4))}, lf.InputError, r"shape \(4, 4\)"),
        ({"W0": np.eye(3)}, lf.AlgebraError, r"not in so\(3\)"),
        ({"W0": np.full((3, 3), np.inf)}, lf.InputError, "NaN or Inf"),
        ({"system": "rigid_body"}, lf.InputError, "IsospectralSystem"),
        ({"scheme": "gauss2"}, lf.InputError, "Scheme"),
        ({"solver": object()}, lf.InputError, "Solver protocol"),
        ({"solver": lf.solvers.FixedPoint}, lf.InputError, r"pass an instance: FixedPoint\(\)"),
        ({"scheme": lf.schemes.SyDIRK}, lf.InputError, r"pass an instance: SyDIRK\(\)"),
    ],
)
def test_bad_input_raises_a_clear_error(kwargs: dict, error: type, match: str) -> None:
    args = {"system": RB, "scheme": MID, "W0": W0, "h": 0.1, "steps": 3} | kwargs
    with pytest.raises(error, match=match):
        lf.integrate(args.pop("system"), args.pop("scheme"), args.pop("W0"), args.pop("h"), **args)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"h": "0.1"}, lf.InputError, "real number"),
        ({"h": -0.1}, lf.InputError, "positive"),
        ({"h": 0.0}, lf.InputError, "positive"),
        ({"W0": np.eye(3)}, lf.AlgebraError, r"not in so\(3\)"),
        ({"W0": np.zeros((4, 4))}, lf.InputError, r"shape \(4, 4\)"),
        ({"system": "rigid_body"}, lf.InputError, "IsospectralSystem"),
        ({"scheme": "midpoint"}, lf.InputError, "Scheme"),
        ({"solver": lf.solvers.FixedPoint}, lf.InputError, r"pass an instance: FixedPoint\(\)"),
        ({"solver": object()}, lf.InputError, "Solver protocol"),
        ({"start": -1}, lf.InputError, "start"),
    ],
)
def test_iterate_checks_its_arguments_when_called(kwargs: dict, error: type, match: str) -> None:
    """``iterate`` refuses what ``integrate`` refuses, at the call (not at the first step)."""
    args = {"system": RB, "scheme": MID, "W0": W0, "h": 0.1, "solver": lf.solvers.FixedPoint()}
    args |= kwargs
    with pytest.raises(error, match=match):
        lf.iterate(args.pop("system"), args.pop("scheme"), args.pop("W0"), args.pop("h"),
                   args.pop("solver"), **args)  # fmt: skip


def test_iterate_steps_match_integrate() -> None:
    """The stream's default solver is integrate's, and its states are integrate's."""
    import itertools

    steps = list(itertools.islice(lf.iterate(RB, MID, W0, 0.1), 4))
    assert [s.index for s in steps] == [1, 2, 3, 4]
    assert [s.t for s in steps] == [0.1 * k for k in (1, 2, 3, 4)]
    sol = lf.integrate(RB, MID, W0, 0.1, steps=4, engine="numpy")
    np.testing.assert_array_equal(np.stack([s.W for s in steps]), sol.W[1:])


def test_system_parameters_are_validated() -> None:
    with pytest.raises(lf.InputError, match="positive"):
        lf.systems.get("rigid_body", inertia=(1.0, -2.0, 3.0))
    with pytest.raises(lf.InputError, match="3 principal moments"):
        lf.systems.get("rigid_body", inertia=(1.0, 2.0))
    with pytest.raises(lf.InputError, match="n >= 3"):
        lf.systems.get("periodic_toda", n=2)


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")  # the point of the test
def test_non_finite_step_is_an_error() -> None:
    class Blowup(lf.IsospectralSystem):
        algebra = lf.SO(3)
        linear_B = True

        def B(self, W: np.ndarray) -> np.ndarray:
            return W * 1e300

        def hamiltonian(self, W: np.ndarray) -> np.ndarray:
            return np.sum(W * W, axis=(-2, -1))

    with pytest.raises(lf.ConvergenceError) as info:
        lf.integrate(Blowup(), MID, W0, 0.1, steps=2)
    assert info.value.reason in ("non_finite", "diverged")


def test_progress_bar_runs() -> None:
    sol = lf.integrate(RB, MID, W0, 0.1, steps=20, progress=True)
    assert sol.success


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"W0": np.zeros((0, 3, 3))}, "empty stack"),
        ({"steps": 2**60}, "too many"),
        ({"progress": "yes"}, "Monitor"),
        ({"h": "0.1"}, "real number"),
    ],
)
def test_bad_run_arguments_are_refused(kwargs: dict, match: str) -> None:
    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    args = {"W0": body.random_state(0), "h": 0.1, "steps": 3, **kwargs}
    with pytest.raises(lf.InputError, match=match):
        lf.integrate(body, lf.schemes.get("midpoint"), **args)


def test_a_monitor_object_hears_of_every_step_chunk_by_chunk() -> None:
    """A numpy flow's steps come in chunks of at most ``BATCH_STEPS`` (issue 36: batched
    whoever watches); the monitor hears of each, and of every step once."""
    seen: list[tuple[str, int]] = []

    class Log:
        def start(self, done: int, total: int) -> None:
            seen.append(("start", total))

        def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
            seen.append(("advance", steps))

        def stop(self) -> None:
            seen.append(("stop", 0))

    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    lf.integrate(body, lf.schemes.get("midpoint"), body.random_state(0), 0.1, steps=150,
                 progress=Log(), engine="numpy")  # fmt: skip
    sizes = [k for what, k in seen if what == "advance"]
    assert seen[0] == ("start", 150) and seen[-1] == ("stop", 0) and len(seen) == len(sizes) + 2
    assert sum(sizes) == 150 and sizes == [64, 64, 22]  # lf.stepping.BATCH_STEPS = 64
