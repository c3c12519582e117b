from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lieflow as lf

ALGEBRAS = [lf.SO(4), lf.U(3), lf.SU(5), lf.GL(3)]


@pytest.mark.parametrize("g", ALGEBRAS, ids=str)
def test_random_element_is_in_algebra_with_right_dtype(g: lf.LieAlgebra) -> None:
    X = g.random(seed=1)
    assert X.shape == g.shape and X.dtype == g.dtype
    assert g.contains(X, tol=1e-15)
    np.testing.assert_array_equal(g.random(seed=1), X)  # seeded


@pytest.mark.parametrize("g", ALGEBRAS, ids=str)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_projection_is_idempotent_and_bracket_closes(g: lf.LieAlgebra, seed: int) -> None:
    rng = np.random.default_rng(seed)
    X = rng.standard_normal(g.shape) + (
        1j * rng.standard_normal(g.shape) if g.dtype.kind == "c" else 0
    )
    P = g.project(X)
    np.testing.assert_allclose(g.project(P), P, atol=1e-15)
    Y = g.random(seed + 1)
    assert g.contains(g.bracket(P, Y), tol=1e-13)
    # the projection is orthogonal: <X - P(X), Y> = 0 for Y in g
    assert abs(g.inner(X - P, Y)) <= 1e-12 * (np.linalg.norm(X) * np.linalg.norm(Y))


def test_dimensions() -> None:
    assert [g.dimension for g in ALGEBRAS] == [6, 9, 24, 9]


def test_inner_product_is_real_frobenius() -> None:
    g = lf.U(3)
    X, Y = g.random(0), g.random(1)
    assert g.inner(X, Y) == pytest.approx(np.real(np.trace(X.conj().T @ Y)), rel=1e-14)


def test_validate_refuses_bad_input() -> None:
    g = lf.SO(3)
    with pytest.raises(lf.InputError, match="shape"):
        g.validate(np.zeros((3, 4)))
    with pytest.raises(lf.InputError, match="NaN or Inf"):
        g.validate(np.full((3, 3), np.nan))
    with pytest.raises(lf.AlgebraError, match=r"not in so\(3\).*W\^T = -W"):
        g.validate(np.eye(3))
    with pytest.raises(lf.InputError, match="complex"):
        g.validate(1j * g.random(0))
    with pytest.raises(lf.AlgebraError, match="tr W = 0"):
        lf.SU(2).validate(1j * np.eye(2))
    with pytest.raises(lf.InputError, match="numeric"):
        g.validate(np.array([["a"] * 3] * 3))
    with pytest.raises(lf.InputError):
        lf.SO(0)


@pytest.mark.parametrize("g", ALGEBRAS, ids=str)
def test_validate_decides_as_contains(g: lf.LieAlgebra) -> None:
    """validate accepts what contains accepts and refuses the rest: exact members (which it
    accepts without computing the distance), members perturbed within the tolerance, and
    data perturbed beyond it, whose error names the distance."""
    X = g.random(seed=3)
    rng = np.random.default_rng(0)
    for size, inside in ((0.0, True), (1e-14, True), (1e-6, False)):
        Y = X + size * np.linalg.norm(X) * rng.standard_normal(X.shape)
        if size and type(g) is lf.GL:
            inside = True  # every real matrix is in gl(n)
        assert g.contains(Y) is inside
        if inside:
            out = g.validate(Y)
            assert out is not Y and np.array_equal(out, Y)
        else:
            with pytest.raises(lf.AlgebraError, match=r"relative distance \d\.\d\de-0[67]"):
                g.validate(Y)


def test_validate_keeps_single_precision() -> None:
    X = lf.U(3).random(0).astype(np.complex64)
    assert lf.U(3).validate(X, tol=1e-6).dtype == np.complex64


@pytest.mark.parametrize("g", ALGEBRAS, ids=str)
def test_projection_keeps_single_precision(g: lf.LieAlgebra) -> None:
    """su(N)'s trace removal used a float64 identity and returned complex128."""
    dt = np.complex64 if g.dtype.kind == "c" else np.float32
    X = g.random(seed=2).astype(dt)
    assert g.project(X).dtype == dt
    assert g.project(X[None].repeat(2, axis=0)).shape == (2, *g.shape)


def test_su_projection_removes_the_trace_that_u_keeps() -> None:
    """A trace is invisible to u(n) but not to su(n) (the bracket of two su(n) elements is
    traceless only to roundoff, so nothing keeps it at zero but the projection)."""
    X = lf.SU(4).random(seed=0) + 1e-6j * np.eye(4)
    assert float(lf.U(4).distance(X)) == 0.0
    assert float(lf.SU(4).distance(X)) == pytest.approx(2e-6 / np.linalg.norm(X), rel=1e-6)
    assert abs(np.trace(lf.SU(4).project(X))) <= 4e-16


@pytest.mark.parametrize("scale", ["1", float("nan"), float("inf"), True, None])
def test_random_refuses_a_scale_that_is_not_a_finite_number(scale: object) -> None:
    with pytest.raises(lf.InputError, match="scale must be a finite real number"):
        lf.SO(3).random(seed=0, scale=scale)  # type: ignore[arg-type]


@pytest.mark.parametrize("n", [3, 64, 65, 130, 200])
@pytest.mark.parametrize("kind", ["real", "complex"])
def test_minus_dagger_is_x_minus_its_conjugate_transpose_bit_for_bit(n: int, kind: str) -> None:
    from lieflow.algebras import minus_dagger

    rng = np.random.default_rng(n)
    X = rng.standard_normal((2, n, n))
    if kind == "complex":
        X = X + 1j * rng.standard_normal((2, n, n))
    expected = X - np.conj(np.swapaxes(X, -1, -2))
    got = minus_dagger(X)
    assert got.shape == X.shape and got.dtype == X.dtype
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("shape", [(3, 3), (64, 64), (2, 65, 65), (130, 130)])
@pytest.mark.parametrize("kind", ["real", "complex"])
@pytest.mark.parametrize("with_y", [False, True])
def test_skew_combination_is_the_five_numpy_passes_bit_for_bit(
    shape: tuple[int, ...], kind: str, with_y: bool
) -> None:
    """The midpoint map's tail ((X - X^†) s + A) + Y t: the fused pass (numba, n > 64)
    returns exactly what minus_dagger and NumPy's in-place operations return."""
    from lieflow.algebras import minus_dagger, skew_combination

    rng = np.random.default_rng(len(shape) + shape[-1])

    def draw() -> np.ndarray:
        Z = rng.standard_normal(shape)
        return Z + 1j * rng.standard_normal(shape) if kind == "complex" else Z

    X, A, Y = draw(), draw(), draw()
    X[..., 1, 2] = 0.0  # zeros and tiny numbers round as NumPy's
    A[..., 0, 1] = 1e-310
    s, t = np.array(0.015625), np.array(1.5e-3)
    expected = minus_dagger(X)
    expected *= s
    expected += A
    if with_y:
        expected += Y * t
    got = skew_combination(X, s, A, Y if with_y else None, t if with_y else None)
    assert got.shape == X.shape and got.dtype == X.dtype
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("n", [8, 100])
@pytest.mark.parametrize("kind", ["real", "complex"])
def test_skew_combination_norms_are_the_numpy_norms(n: int, kind: str) -> None:
    """skew_combination_norms: the combination's bits, and (where the compiled pass runs:
    numba, n > 64) ||out||² and ||out - old||² summed in that pass — NumPy's sums up to
    their order, the same on every call; elsewhere no norms."""
    from lieflow.algebras import skew_combination, skew_combination_norms

    rng = np.random.default_rng(n)

    def draw() -> np.ndarray:
        Z = rng.standard_normal((n, n))
        return Z + 1j * rng.standard_normal((n, n)) if kind == "complex" else Z

    X, A, Y, old = draw(), draw(), draw(), draw()
    s, t = np.array(0.015625), np.array(1.5e-3)
    out, norms = skew_combination_norms(X, s, A, Y, t, old)
    np.testing.assert_array_equal(out, skew_combination(X, s, A, Y, t))
    if n <= 64 or importlib.util.find_spec("numba") is None:
        assert norms is None
        return
    assert norms is not None
    size2 = float(np.sum(np.abs(out) ** 2))
    step2 = float(np.sum(np.abs(out - old) ** 2))
    assert norms[0] == pytest.approx(size2, rel=1e-13)
    assert norms[1] == pytest.approx(step2, rel=1e-13)
    assert skew_combination_norms(X, s, A, Y, t, old)[1] == norms


@pytest.mark.parametrize("shape", [(130, 130), (2, 192, 192), (257, 257), (520, 520)])
@pytest.mark.parametrize("kind", ["real", "complex"])
def test_skew_matmul_is_the_product_of_skew_factors(shape: tuple[int, ...], kind: str) -> None:
    """skew_matmul((B M), B) for skew-Hermitian B, M (the midpoint map's BMB): the product to
    roundoff, skew-Hermitian outside its diagonal panels bit for bit (those entries are
    mirrored: -conj of the computed ones); below n = 192 the BLAS product itself."""
    from lieflow.algebras import skew_matmul

    rng = np.random.default_rng(shape[-1])

    def skew() -> np.ndarray:
        Z = rng.standard_normal(shape)
        if kind == "complex":
            Z = Z + 1j * rng.standard_normal(shape)
        return Z - np.conj(np.swapaxes(Z, -1, -2))

    B, M = skew(), skew()
    BM = B @ M
    out = np.empty_like(BM)
    assert skew_matmul(BM, B, out) is out
    expected = BM @ B
    n = shape[-1]
    if n < 192:
        np.testing.assert_array_equal(out, expected)
        return
    scale = np.max(np.abs(BM)) * np.max(np.abs(B)) * n
    assert np.max(np.abs(out - expected)) < 1e-15 * scale
    panels = min(n // 64, 8)
    edges = [i * n // panels for i in range(panels + 1)]
    block = np.repeat(np.arange(panels), np.diff(edges))
    off = block[:, None] != block[None, :]  # entries outside the diagonal panels
    mirrored = -np.conj(np.swapaxes(out, -1, -2))
    np.testing.assert_array_equal(out[..., off], mirrored[..., off])


def test_split_combination_has_the_serial_bits() -> None:
    """The combination's compiled pass split into groups of bands (numba's threads, for
    large matrices: lieflow.numba_cache.SplitKernel) gives the serial pass's numbers and
    row sums, bit for bit, for any number of groups; small passes are not split."""
    pytest.importorskip("numba")
    from lieflow import _skew_kernel as kernel
    from lieflow.numba_cache import SPLIT_SIZE, work_groups

    rng = np.random.default_rng(5)
    X, A, Y, old = (rng.standard_normal((2, 70, 140)) for _ in range(4))
    results = []
    for groups in (1, 2, 3, 7, 300):
        out = np.empty_like(X)
        sums = np.empty((2, 70, 2))
        kernel.combine(groups, X, 0.25, A, Y, 1e-3, True, 2, out, old, True, sums)
        results.append((out, sums))
    for out, sums in results[1:]:
        assert np.array_equal(out, results[0][0]) and np.array_equal(sums, results[0][1])
    assert work_groups(SPLIT_SIZE - 1) == 1


def test_midpoint_map_with_norms_is_the_map() -> None:
    """The midpoint map with its stopping-test norms returns the map's bits."""
    pytest.importorskip("lieflow_zeitlin")
    from lieflow.schemes.sydirk import MidpointProblem

    system = lf.systems.get("euler_zeitlin", N=96)
    W0 = system.random_state(seed=0)
    problem = MidpointProblem(system, W0, 0.01)
    M = problem.map(problem.x0)
    g, norms = problem.map_with_norms(M)
    np.testing.assert_array_equal(g, problem.map(M))
    if norms is not None:
        assert norms[0] == pytest.approx(float(np.sum(np.abs(g) ** 2)), rel=1e-13)
        assert norms[1] == pytest.approx(float(np.sum(np.abs(g - M) ** 2)), rel=1e-13)


def test_midpoint_map_of_a_large_skew_system_is_its_formula() -> None:
    """The midpoint map M -> W0 + q (BM - MB) + q² BMB, q = h/2, of a skew algebra from
    n = 192 on (BMB from its upper triangle: skew_matmul) against the formula's plain
    products, to roundoff (so(200), generalized rigid body)."""
    from lieflow.schemes.sydirk import MidpointProblem

    n, h = 200, 0.05
    system = lf.systems.get("generalized_rigid_body", J=tuple(1.0 + 0.01 * np.arange(n)))
    W0 = system.random_state(0)
    problem = MidpointProblem(system, W0, h)
    M = problem.x0 + 0.1 * system.random_state(1)
    B = system.B(M)
    q = h / 2
    expected = W0 + q * (B @ M - M @ B) + q * q * (B @ M @ B)
    got = problem.map(M)
    assert np.max(np.abs(got - expected)) < 1e-14 * np.max(np.abs(expected))


def test_validate_returns_native_float64_for_any_byte_order() -> None:
    """validate's fast path for float64 data (issue 27 item 5) takes native data only: a
    big-endian W0 comes back as a native float64 copy, as before, equal to it."""
    W = lf.SO(4).random(0)
    for X in (W, W.astype(">f8"), W.astype("<f8")):
        V = lf.SO(4).validate(X)
        assert V.dtype == np.float64 and V.dtype.isnative
        assert V is not X
        np.testing.assert_array_equal(V, W)
