"""The underflow guard (lieflow.underflow): the numbers it keeps and drops, the bound that
no product of kept entries is subnormal, trajectories within roundoff of unguarded ones with
the spectrum kept, and the guard off: nothing called, the same bits."""

from __future__ import annotations

import importlib.util
from typing import Any

import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf
from lieflow import underflow
from lieflow.underflow import TAU, flush_tiny

#: Products at least this large (and zero) keep every partial sum a multiple of 2^-1022
#: (lieflow.underflow's module docs).
PRODUCT_FLOOR = 2.0**-916
SMALLEST_NORMAL = 2.0**-1022


def _wide(seed: int, shape: tuple[int, ...] = (3, 40, 40)) -> np.ndarray:
    """Complex matrices whose real numbers span 300 decades (log-uniform), a few zeros."""
    rng = np.random.default_rng(seed)
    X = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    X *= 10.0 ** rng.uniform(-300, 0, shape)
    X.real[..., ::7, :] = 0.0
    return X


def _numbers(X: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(X).view(X.real.dtype).reshape(*X.shape[:-2], -1)


@pytest.fixture(params=["compiled", "numpy"])
def implementation(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The numba loops, or NumPy operations without numba: the same numbers."""
    underflow._kernels.cache_clear()
    if request.param == "numpy":
        monkeypatch.setattr(underflow, "_kernels", lambda: None)
    elif importlib.util.find_spec("numba") is None:
        pytest.skip("numba is not installed")
    return str(request.param)


@pytest.mark.usefixtures("implementation")
def test_drops_exactly_the_numbers_below_tau_times_the_largest() -> None:
    X = _wide(0)
    out = flush_tiny(X, TAU)
    before, after = _numbers(X), _numbers(out)
    limit = TAU * np.abs(before).max(axis=-1, keepdims=True)
    below = np.abs(before) < limit
    assert below.sum() > 1000  # the data do reach the range
    assert np.all(after[below] == 0)
    np.testing.assert_array_equal(after[~below], before[~below])  # kept bit for bit
    # in place: the same numbers in the same memory
    Y = X.copy()
    assert np.shares_memory(flush_tiny(Y, TAU, in_place=True), Y)
    np.testing.assert_array_equal(_numbers(Y), after)
    # nothing below: the array itself
    Z = np.ones((4, 4))
    assert flush_tiny(Z, TAU) is Z


@pytest.mark.usefixtures("implementation")
def test_leaves_a_matrix_with_a_non_finite_entry_alone() -> None:
    X = _wide(1)
    X[1, 2, 3] = np.inf
    X[2, 0, 0] = np.nan
    out = flush_tiny(X, TAU)
    np.testing.assert_array_equal(_numbers(out)[1], _numbers(X)[1])
    assert np.isnan(out[2, 0, 0])  # a NaN stays for the stopping test to see
    np.testing.assert_array_equal(_numbers(out)[0], _numbers(flush_tiny(X[:1], TAU))[0])


def test_array_api_gives_the_same_numbers() -> None:
    xps = pytest.importorskip("array_api_strict")
    X = _wide(2)
    strict = lf.backends.to_numpy(flush_tiny(xps.asarray(X), TAU))
    np.testing.assert_array_equal(_numbers(strict), _numbers(flush_tiny(X, TAU)))


def test_no_product_of_kept_numbers_is_subnormal() -> None:
    A, B = _wide(3, (60, 60)), _wide(4, (60, 60))

    def smallest_product(X: np.ndarray, Y: np.ndarray) -> float:
        x, y = np.abs(_numbers(X)), np.abs(_numbers(Y))
        return float(x[x > 0].min() * y[y > 0].min())

    def subnormal_products(X: np.ndarray, Y: np.ndarray) -> int:
        """Pairs (a, b) of nonzero real numbers of X and Y with a subnormal product."""
        x, y = np.abs(_numbers(X)), np.abs(_numbers(Y))
        x, y = np.sort(x[x > 0]), np.sort(y[y > 0])
        # for each a: the b with a * b < 2^-1022 are those below 2^-1022 / a
        return int(np.searchsorted(y, SMALLEST_NORMAL / x).sum())

    assert subnormal_products(A, B) > 10_000  # unguarded: many
    Ag, Bg = flush_tiny(A, TAU), flush_tiny(B, TAU)
    assert subnormal_products(Ag, Bg) == 0
    assert smallest_product(Ag, Bg) >= PRODUCT_FLOOR  # the bound of the module docs

    # and the product changes (in extended precision: exactly enough) by at most
    # 2 n tau max|A| max|B|: 2^-280 of its normwise rounding bound n eps max|A| max|B|
    def exact(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        return np.asarray(X.astype(np.clongdouble) @ Y.astype(np.clongdouble))

    scale = float(np.abs(_numbers(A)).max() * np.abs(_numbers(B)).max())
    change = float(np.max(np.abs(exact(Ag, Bg) - exact(A, B))))
    assert 0 < change <= 2 * 60 * 2 * TAU * scale  # 2: a complex entry has two parts
    assert change <= 2.0**-270 * 60 * np.finfo(float).eps * scale


# Euler–Zeitlin with a state of a very wide dynamic range (the diagonals of a smooth field
# scaled down by 1e-6 per diagonal: entries down to 1e-300 at N = 48)


def _decayed(N: int) -> np.ndarray:
    lz = import_plugin("lieflow_zeitlin")
    W = lz.random_vorticity(N, degree=N - 1, seed=5)
    i, j = np.indices((N, N))
    return np.asarray(W * 10.0 ** (-6.4 * np.abs(i - j)))


def _system(guard: float) -> Any:
    return lf.systems.get("euler_zeitlin", N=48, underflow_guard=guard, diagnostics_every=0)


def test_guarded_steps_are_within_roundoff_and_isospectral() -> None:
    W0 = _decayed(48)
    assert np.abs(W0).min() < 1e-290  # products of such entries are subnormal
    for name in ("midpoint", "gauss2"):
        scheme = lf.schemes.get(name)
        runs = [
            lf.integrate(_system(g), scheme, W0, 0.05, steps=20, engine="numpy") for g in (0.0, TAU)
        ]
        off, on = runs
        scale = np.max(np.abs(off.W_final))
        # by about tau (2^-332) relative: far below roundoff, as the bound says
        assert np.max(np.abs(on.W_final - off.W_final)) <= 2.0**-300 * scale
        levels = [np.linalg.eigvalsh(1j * W) for W in (W0, on.W_final)]
        assert np.max(np.abs(levels[1] - levels[0])) <= 1e-13 * np.max(np.abs(levels[0]))
        assert np.array_equal(on.iterations, off.iterations)


def test_the_guard_removes_the_subnormal_products_of_a_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # every matrix a guarded midpoint step multiplies: before the guard, pairs of its real
    # numbers whose products are subnormal; after it, none
    seen: list[tuple[np.ndarray, np.ndarray]] = []

    def spy(X: Any, tau: float, in_place: bool = False) -> Any:
        before = np.array(X, copy=True)
        out = flush_tiny(X, tau, in_place)
        seen.append((before, np.asarray(out)))
        return out

    monkeypatch.setattr("lieflow.schemes.base.flush_tiny", spy)
    W0 = _decayed(48)
    lf.schemes.get("midpoint").step(W0, 0.05, _system(TAU), lf.solvers.FixedPoint())
    assert len(seen) > 10
    prone_before = prone_after = 0
    for before, after in seen:
        x, y = np.abs(_numbers(before)), np.abs(_numbers(after))
        assert y.max() == x.max() >= 2.0**-126  # scales at which the bound holds
        # numbers whose product with a number like them is below 2^-916 (subnormal range)
        prone_before += int((x[x > 0] < 2.0**-458 * x.max()).sum())
        prone_after += int((y[y > 0] < 2.0**-458 * y.max()).sum())
        assert (y[y > 0] >= TAU * y.max()).all()  # so kept products >= TAU^2 max max
    assert prone_before > 1000 and prone_after == 0


def test_guard_off_calls_nothing_and_changes_no_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    # a guard that drops nothing gives the same bits as the guard off, and off it is never
    # called (the code path of a run without it)
    lz = import_plugin("lieflow_zeitlin")
    W0 = lz.random_vorticity(32, degree=8, seed=1)
    runs = {}
    for guard in (0.0, 2.0**-1070):
        system = lf.systems.get("euler_zeitlin", N=32, underflow_guard=min(guard, 2**-100))
        runs[guard] = [
            lf.integrate(system, lf.schemes.get(s), W0, 0.05, steps=10, engine="numpy").W
            for s in ("midpoint", "gauss2")
        ]

    def refuse(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the guard is off")

    monkeypatch.setattr("lieflow.schemes.base.flush_tiny", refuse)
    system = lf.systems.get("euler_zeitlin", N=32)
    assert system.underflow_guard == 0.0  # the default below N = 512
    again = [
        lf.integrate(system, lf.schemes.get(s), W0, 0.05, steps=10, engine="numpy").W
        for s in ("midpoint", "gauss2")
    ]
    for a, b, c in zip(again, runs[0.0], runs[2.0**-1070], strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_euler_zeitlin_guard_defaults_and_validation() -> None:
    lz = import_plugin("lieflow_zeitlin")
    assert lz.EulerZeitlin(64).underflow_guard == 0.0
    assert lz.EulerZeitlin(512).underflow_guard == TAU
    assert lz.EulerZeitlin(64, underflow_guard=TAU).underflow_guard == TAU
    with pytest.raises(lf.InputError, match="underflow_guard"):
        lz.EulerZeitlin(64, underflow_guard=1e-20)
    with pytest.raises(lf.InputError, match="underflow_guard"):
        lz.EulerZeitlin(64, underflow_guard=-1.0)
    # the compiled engine does not run it: refused, and auto takes numpy
    from lieflow.engines import compiled

    system = lz.EulerZeitlin(16, underflow_guard=TAU)
    reason = compiled.plan(system, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(),
                           system.random_state(0))  # fmt: skip
    assert isinstance(reason, str) and "underflow guard" in reason


def test_split_guard_passes_have_the_serial_bits() -> None:
    """The guard's compiled passes split into groups of chunks (numba's threads for large
    states: lieflow.numba_cache.SplitKernel) give the serial passes' limits and numbers."""
    pytest.importorskip("numba")
    from lieflow import _underflow_kernel as kernel

    rng = np.random.default_rng(2)
    real = rng.standard_normal((2, 3 * kernel.CHUNK + 17)) * 10.0 ** rng.integers(
        -320, 0, (2, 3 * kernel.CHUNK + 17)
    )
    results = []
    for groups in (1, 2, 3, 50):
        limits = kernel.limits(groups, real, 2.0**-332)
        out = np.full_like(real, np.nan)
        kernel.flush(groups, real, limits, out, False)
        inplace = real.copy()
        kernel.flush(groups, inplace, limits, inplace, True)
        results.append((limits, out, inplace))
    np.testing.assert_array_equal(results[0][0], 2.0**-332 * np.abs(real).max(axis=1))
    assert np.array_equal(results[0][1], results[0][2])
    for got in results[1:]:
        for a, e in zip(got, results[0], strict=True):
            assert np.array_equal(a, e)
