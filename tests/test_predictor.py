"""Warm starts by polynomial extrapolation of the previous steps' solutions (issue 18):
the weights, the predictor's error against the cold and linear guesses, the choice of the
number of points, fewer updates on both engines, and bit-for-bit resumes."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import lieflow as lf
from lieflow import stepping
from lieflow.app.reproduce import Case
from lieflow.warm_start import (
    DEFAULT_DEPTH,
    WarmStart,
    extrapolation_matrix,
    extrapolation_weights,
)


def _grb(n: int = 10) -> tuple[lf.IsospectralSystem, np.ndarray]:
    return Case("generalized_rigid_body", "", n, 0.01, 1, 1e-14).build(0)


@pytest.mark.parametrize("points", range(1, 8))
def test_weights_extrapolate_polynomials_exactly(points: int) -> None:
    """From ``m`` equidistant values the weights give p(k + 1) for every polynomial of
    degree < m, and not for degree m."""
    w = np.array(extrapolation_weights(points), dtype=float)
    k = np.arange(points)[::-1].astype(float)  # the history, most recent first: k = m-1..0
    for degree in range(points):
        assert w @ k**degree == pytest.approx(points**degree, abs=1e-9 * points**degree)
    assert abs(w @ k**points - points**points) > 0.5
    np.testing.assert_array_equal(extrapolation_matrix(points)[points - 1], w)
    assert np.all(np.triu(extrapolation_matrix(points), 1) == 0)


def _solved_offsets(scheme: str, h: float, steps: int) -> list[np.ndarray]:
    """The solved offsets of ``steps`` steps of the numpy engine, in order."""
    system, W0 = _grb()
    out = []
    for step in lf.iterate(system, lf.schemes.get(scheme), W0, h, lf.solvers.FixedPoint()):
        out.append(step.warm.last)
        if len(out) == steps:
            return out
    raise AssertionError("unreachable")


def test_predictor_error_falls_with_the_points_and_with_h() -> None:
    """On a smooth problem the extrapolation from m points errs by O(h^m): five points
    beat linear extrapolation, which beats the cold guess, and halving h gains about 2^m
    (a factor above 2^(m-1) is asked)."""
    errors = {}
    for h in (0.2, 0.1):
        offsets = _solved_offsets("gauss2", h, 8)
        history, solved = offsets[-2::-1][:5], offsets[-1]
        errors[h] = {0: float(np.linalg.norm(solved))}
        for m in (1, 2, 3, 5):
            guess = sum(w * x for w, x in zip(extrapolation_weights(m), history[:m], strict=True))
            errors[h][m] = float(np.linalg.norm(solved - guess))
        assert errors[h][0] > errors[h][1] > errors[h][2] > errors[h][3] > errors[h][5]
        assert errors[h][5] < 1e-3 * errors[h][2]
    for m in (2, 3, 5):
        assert errors[0.2][m] / errors[0.1][m] > 2 ** (m - 1), (m, errors)


def test_trusted_grows_to_the_depth_on_a_smooth_problem() -> None:
    system, W0 = _grb()
    flow = lf.SchemeFlow(system, lf.schemes.get("gauss3"))
    state = flow.init(W0)
    assert state is not None and state.depth == DEFAULT_DEPTH and state.history() == []
    seen = []
    W = W0
    for k in range(8):
        W, state, _ = flow.step(W, 0.1 * k, 0.1, state)
        seen.append(state.trusted)
    assert seen[:5] == [1, 2, 3, 4, 5] and all(t == DEFAULT_DEPTH for t in seen[4:])
    assert len(state.history()) == DEFAULT_DEPTH


def test_a_bad_history_falls_back_to_the_cold_guess() -> None:
    """A prediction worse than the cold guess is never trusted (and the arrays of the
    history are never written)."""
    rng = np.random.default_rng(1)
    solved = rng.normal(size=(2, 3, 3))
    noise = [rng.normal(size=(2, 3, 3)) for _ in range(3)]
    kept = [x.copy() for x in noise]
    state = WarmStart(noise[0], (noise[1], noise[2], None), 3)
    new = state.advance(solved)
    assert new.trusted == 0 and new.prediction() is None and new.guess() is None
    assert new.last is solved and new.previous[0] is noise[0] and new.previous[1] is noise[1]
    for a, b in zip(noise, kept, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_two_point_form_of_earlier_checkpoints_still_reads() -> None:
    """``previous`` as a bare array (files written before higher-order extrapolation)
    keeps two solutions and extrapolates linearly."""
    a, b = np.full((2, 2), 3.0), np.full((2, 2), 1.0)
    state = WarmStart(a, b, 2)
    assert state.depth == 2
    np.testing.assert_array_equal(state.prediction(), np.full((2, 2), 5.0))
    np.testing.assert_array_equal(WarmStart(a, b, True).prediction(), a)  # True reads as 1
    new = state.advance(np.full((2, 2), 5.0))
    assert new.previous is a and new.trusted == 2
    assert WarmStart(a, None, False).prediction() is None


def test_warm_start_is_validated() -> None:
    system, _ = _grb()
    with pytest.raises(lf.InputError, match="warm_start"):
        lf.SchemeFlow(system, lf.schemes.get("midpoint"), warm_start=-1)
    assert lf.SchemeFlow(system, lf.schemes.get("midpoint"), warm_start=False).init(None) is None
    state = lf.SchemeFlow(system, lf.schemes.get("midpoint"), warm_start=3).init(None)
    assert state is not None and state.previous == (None, None)


def _updates(scheme: str, h: float, steps: int, warm: bool | int, engine: str) -> Any:
    system, W0 = _grb()
    return lf.integrate(system, lf.schemes.get(scheme), W0, h, steps=steps, warm_start=warm,
                        engine=engine, diagnostics=False)  # fmt: skip


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_extrapolation_cuts_updates(engine: str) -> None:
    """Updates per step on so(10), cold / two points / five (measured): gauss4 at h = 0.5,
    24 steps: 19.7 / 17.1 / 13.8; midpoint at h = 0.1, 60 steps: 8.0 / 6.1 / 3.9. The
    solutions agree to the solver's tolerance."""
    if engine == "compiled":
        pytest.importorskip("numba")
    for scheme, h, steps, factor in (("gauss4", 0.5, 24, 0.85), ("midpoint", 0.1, 60, 0.7)):
        runs = {w: _updates(scheme, h, steps, w, engine) for w in (False, 2, True)}
        total = {w: int(sol.iterations.sum()) for w, sol in runs.items()}
        assert total[True] < factor * total[2] < total[False], (scheme, total)
        for sol in runs.values():
            np.testing.assert_allclose(sol.W, runs[False].W, rtol=0, atol=1e-12)


def test_engines_agree_with_extrapolation() -> None:
    pytest.importorskip("numba")
    system, W0 = _grb(6)
    W0 = np.stack([W0, 0.9 * W0])  # an ensemble: trust is decided for the whole stack
    for scheme in ("gauss3", "triple_jump"):
        ref = lf.integrate(system, lf.schemes.get(scheme), W0, 0.2, steps=40, engine="numpy")
        fast = lf.integrate(system, lf.schemes.get(scheme), W0, 0.2, steps=40, engine="compiled")
        np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=1e-13)
        assert np.max(np.abs(fast.iterations - ref.iterations)) <= 1


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_resumed_runs_equal_uninterrupted_ones_bit_for_bit(engine: str) -> None:
    """The state (the kept solutions and ``trusted``) is all a resume needs, whether the
    run stops at a chunk end (compiled: a call of the loops) or anywhere (numpy)."""
    if engine == "compiled":
        pytest.importorskip("numba")
    from lieflow.engines import scheme_flow

    system, W0 = _grb()
    scheme, solver = lf.schemes.get("gauss2"), lf.solvers.FixedPoint()
    flow = scheme_flow(system, scheme, solver, W0, 30, engine=engine, warm_start=True)
    whole = list(stepping.advance(flow, W0, 0.1, 30))
    cut = 7
    first = [c for c in stepping.advance(flow, W0, 0.1, cut)]
    last = first[-1]
    state = last.state
    # the state survives a round trip through its leaves (what a checkpoint stores)
    from lieflow import state_trees

    state = state_trees.rebuild(flow.init(W0), {p: np.copy(v) if isinstance(v, np.ndarray) else v
                                         for p, v in state_trees.paths(state)})  # fmt: skip
    rest = list(stepping.advance(flow, last.W[-1], 0.1, 30, start=cut, state=state))
    a = np.concatenate([c.W for c in whole])
    b = np.concatenate([c.W for c in first + rest])
    assert np.array_equal(a, b)
    assert np.array_equal(np.concatenate([c.iterations for c in whole]),
                          np.concatenate([c.iterations for c in first + rest]))  # fmt: skip


def _leaf_sum(weights: tuple[int, ...], history: list[np.ndarray]) -> np.ndarray:
    """The plain NumPy extrapolation, as the leaf-by-leaf form writes it."""
    acc = weights[0] * history[0]
    for w, x in zip(weights[1:], history[1:], strict=False):
        acc += w * x
    return acc


def _large_history(dtype: str, points: int) -> list[np.ndarray]:
    """``points`` arrays above the stacking size, with exact zeros of both signs and
    entries of all magnitudes (where a fused multiply-add would round differently)."""
    rng = np.random.default_rng(points)
    shape = (1, 160, 160)
    out = []
    for _ in range(points):
        x = rng.standard_normal(shape) * 10.0 ** rng.integers(-8, 8, shape)
        if dtype == "complex":
            x = x + 1j * rng.standard_normal(shape)
        flat = x.reshape(-1).view(np.float64)
        flat[rng.random(flat.size) < 0.05] = 0.0
        flat[rng.random(flat.size) < 0.05] = -0.0
        out.append(x)
    return out


@pytest.mark.parametrize("dtype", ["real", "complex"])
@pytest.mark.parametrize("points", [2, 3, 5, 7, 9])
def test_compiled_extrapolation_has_numpys_bits(dtype: str, points: int) -> None:
    """Large histories take one compiled pass (lieflow._warm_kernel): the guess is the
    plain NumPy sum's, bit for bit (signs of zeros too), and the prediction errors are its
    squared norms up to the order of their sums; ``trusted`` is what the NumPy sums give."""
    pytest.importorskip("numba")
    from lieflow import warm_start

    history = _large_history(dtype, points)
    assert warm_start._flat(history) is not None  # the compiled pass is what is tested
    weights = extrapolation_weights(points)
    guess = warm_start._combine(weights, history)
    expected = _leaf_sum(weights, history)
    assert np.array_equal(guess, expected)
    assert np.array_equal(np.signbit(guess.view(np.float64)), np.signbit(expected.view(np.float64)))
    solved = _leaf_sum(extrapolation_weights(2), history[:2]) + 1e-3 * history[-1]
    state = WarmStart.keeping(points + 1).replaced(history, points)
    advanced = state.advance(solved)
    predictions = [_leaf_sum(extrapolation_weights(m), history) for m in range(1, points + 1)]
    errors = [float(np.vdot(d, d).real) for d in [solved] + [solved - p for p in predictions]]
    sums = np.empty(points + 1)
    views = [x.reshape(-1).view(np.float64) for x in [solved, *history]]
    warm_start._kernel().errors(1, views[0], tuple(views[1:]), extrapolation_matrix(points), sums)
    np.testing.assert_allclose(sums, errors, rtol=1e-12)
    assert advanced.trusted == lf.warm_start.trusted_points(errors, points, points + 1)
    assert advanced.last is solved and len(advanced.history()) == points + 1


def test_one_compilation_of_each_warm_pass_serves_every_history_length() -> None:
    """A run's history grows 1, 2, ... points as it starts: the passes take it padded to a
    fixed length (lieflow._warm_kernel._padded), so each compiles once, not once per
    length (numba types a tuple's length); 9 points pad to 16."""
    numba = pytest.importorskip("numba")
    from lieflow import _warm_kernel as kernel

    views = [x.reshape(-1).view(np.float64) for x in _large_history("real", 10)]
    histories = [tuple(views[1 : points + 1]) for points in range(1, 10)]
    types = [numba.typeof(kernel._padded(xs)) for xs in histories]
    assert len(set(types[:8])) == 1 and types[8] != types[0]
    passes = (kernel._errors_pass.dispatcher(), kernel._extrapolate_pass.dispatcher())
    before = [set(d.signatures) for d in passes]  # other tests may have compiled them
    for points, xs in enumerate(histories[:8], start=1):
        kernel.errors(1, views[0], xs, extrapolation_matrix(points), np.empty(points + 1))
        w = np.array(extrapolation_weights(points), dtype=float)
        kernel.extrapolate(1, w, xs, 1, np.empty_like(views[0]))
    assert all(len(set(d.signatures) - b) <= 1 for d, b in zip(passes, before, strict=True))


def test_split_warm_passes_have_the_serial_bits() -> None:
    """The extrapolation and the prediction errors split into groups of chunks (numba's
    threads: lieflow.numba_cache.SplitKernel) give the serial passes' bits."""
    pytest.importorskip("numba")
    from lieflow import _warm_kernel as kernel

    views = [x.reshape(-1).view(np.float64) for x in _large_history("complex", 6)]
    w = np.array(extrapolation_weights(5), dtype=float)
    C = extrapolation_matrix(5)
    results = []
    for groups in (1, 2, 5, 100):
        out = np.empty_like(views[0])
        sums = np.empty(6)
        kernel.extrapolate(groups, w, tuple(views[1:]), 2, out)
        kernel.errors(groups, views[0], tuple(views[1:]), C, sums)
        results.append((out, sums))
    for out, sums in results[1:]:
        assert np.array_equal(out, results[0][0]) and np.array_equal(sums, results[0][1])
