r"""Dissipation and forcing for Euler–Zeitlin (``lieflow_zeitlin.dissipation``), composed with
the isospectral step by ``lieflow.flows.Splitting``.

Checked against exact facts, not against lieflow itself:

* a single degree-``l`` mode is a steady state of Euler, so under viscosity it decays as
  ``exp(-ν l(l+1) t)`` exactly (hyperviscosity ``exp(-ν (l(l+1))^p t)``, drag ``exp(-μt)``);
* the observed orders of Lie (1) and Strang (2) splittings, and of the triple-jump
  composition (4), against a tight-tolerance DOP853 solution (scipy) of the matrix ODE
  ``dW/dt = (1/ħ)[P(W), W] + ν Δ_N (W - Q(f))`` on a rotating sphere;
* forcing + drag: Euler conserves ``||W||_F`` and the forcing injects a known amount, so the
  stationary mean enstrophy is known in closed form whatever the nonlinear transfer does.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

import lieflow as lf

lz = pytest.importorskip("lieflow_zeitlin")
flows = pytest.importorskip("lieflow.flows")

from lieflow_zeitlin.dissipation import (  # noqa: E402
    Hyperviscosity,
    LinearDrag,
    StochasticForcing,
    Viscosity,
    degree_multiplier,
)

Splitting = flows.Splitting
SchemeFlow = flows.SchemeFlow


def _run(flow: Any, W0: np.ndarray, h: float, steps: int, start: int = 0) -> np.ndarray:
    """Advance ``flow`` by hand (``flow.init``, then ``flow.step`` at ``t = k h``)."""
    state = flow.init(W0)
    W = W0
    for k in range(start, start + steps):
        W, state, _ = flow.step(W, k * h, h, state)
    return W


def _conservative(system: lz.EulerZeitlin, scheme: str = "gauss2", **kw: Any) -> Any:
    return SchemeFlow(system, lf.schemes.get(scheme), lf.solvers.FixedPoint(rtol=1e-15), **kw)


def _mode(N: int, l: int, m: int) -> np.ndarray:
    """``Q(Y_lm + (-1)^m Y_l,-m)``-type real single-degree field (``m >= 0``)."""
    c = np.zeros(N * N, dtype=complex)
    c[lz.lm_index(l, m)] = 0.4 + 0.3j if m else 0.5
    if m:
        c[lz.lm_index(l, -m)] = (-1) ** m * np.conj(c[lz.lm_index(l, m)])
    return lz.sh_to_matrix(c)


# --------------------------------------------------------------------------- the multiplier
def test_degree_multiplier_is_diagonal_in_the_harmonics() -> None:
    N = 7
    W = lz.random_vorticity(N, 6, seed=1)
    g = np.linspace(0.3, 1.7, N)
    l, _ = lz.degrees_and_orders(N)
    expected = lz.sh_to_matrix(lz.matrix_to_sh(W) * g[l])
    np.testing.assert_allclose(degree_multiplier(W, g), expected, atol=1e-14)
    batch = np.stack([W, 2j * W])
    np.testing.assert_allclose(degree_multiplier(batch, g)[1], 2j * expected, atol=1e-14)
    with pytest.raises(lf.InputError, match="one multiplier per degree"):
        degree_multiplier(W, g[:-1])


# --------------------------------------------------------------------------- exact decay
@pytest.mark.parametrize("time", ["fluid", "matrix"])
@pytest.mark.parametrize(("l", "m"), [(1, 0), (3, 2), (5, 5)])
def test_viscous_decay_of_a_single_mode_is_exact(l: int, m: int, time: str) -> None:
    """Strang(viscosity, gauss2), fluid time 2: ``W(T) = e^{-ν l(l+1) T} W0`` to roundoff
    (measured 1e-15 relative); the same for hyperviscosity (p = 2) and drag."""
    N, nu, T, steps = 8, 0.03, 2.0, 10
    system = lz.EulerZeitlin(N, time=time)
    h = T / steps / system.fluid_time_unit
    W0 = _mode(N, l, m)
    L = l * (l + 1)
    cases = [
        (Viscosity(system, nu=nu), math.exp(-nu * L * T)),
        (Hyperviscosity(system, nu=nu / 10, order=2), math.exp(-nu / 10 * L**2 * T)),
        (LinearDrag(system, mu=0.7), math.exp(-0.7 * T)),
    ]
    for dissipation, decay in cases:
        W = _run(Splitting.strang(dissipation, _conservative(system)), W0, h, steps)
        assert np.linalg.norm(W - decay * W0) <= 1e-13 * np.linalg.norm(W0), dissipation.name


def test_crank_nicolson_viscosity_factor() -> None:
    """CN multiplies degree ``l`` by ``(1 - νλτ/2)/(1 + νλτ/2)``, ``λ = l(l+1)``, with the
    O(N²) shifted solve: exact to roundoff against that rational function; it agrees with
    the exact factor to O(τ³) per step."""
    N, nu, h = 9, 0.02, 0.3
    system = lz.EulerZeitlin(N, rotation=0.4)  # acts on W - Q(f)
    W_rel = lz.random_vorticity(N, 8, seed=2)
    W = system.from_relative(W_rel)
    cn = Viscosity(system, nu=nu, method="crank_nicolson")
    out, state, stats = cn.step(W, 0.0, h, None)
    assert state is None and stats.iterations == 0
    l, _ = lz.degrees_and_orders(N)
    a = 0.5 * nu * h * l * (l + 1.0)
    expected = lz.sh_to_matrix(lz.matrix_to_sh(W_rel) * (1 - a) / (1 + a))
    np.testing.assert_allclose(system.relative(out), expected, atol=1e-14)
    exact, _, _ = Viscosity(system, nu=nu).step(W, 0.0, h, None)
    np.testing.assert_allclose(
        system.relative(exact),
        lz.sh_to_matrix(lz.matrix_to_sh(W_rel) * np.exp(-2 * a)),
        atol=1e-14,
    )
    assert lf.SU(N).contains(out, tol=1e-14)


# --------------------------------------------------------------------------- splitting orders
N_ORDER, NU, OMEGA, T_ORDER = 6, 0.05, 0.5, 1.0


@pytest.fixture(scope="module")
def dissipative_reference() -> tuple[lz.EulerZeitlin, np.ndarray, np.ndarray]:
    """DOP853 (rtol = atol = 1e-13) of ``dW/dt = (1/ħ)[P, W] + ν Δ_N (W - Q(f))``."""
    from scipy.integrate import solve_ivp

    system = lz.EulerZeitlin(N_ORDER, rotation=OMEGA)
    W0 = system.from_relative(lz.random_vorticity(N_ORDER, 4, seed=2))
    lap = lz.HoppeYauLaplacian(N_ORDER)

    def rhs(_t: float, y: np.ndarray) -> np.ndarray:
        W = y.reshape(N_ORDER, N_ORDER)
        B = system.B(W)
        return (B @ W - W @ B + NU * lap.apply(W - system.planetary)).ravel()

    sol = solve_ivp(rhs, (0, T_ORDER), W0.ravel(), method="DOP853", rtol=1e-13, atol=1e-13)
    assert sol.success
    return system, W0, sol.y[:, -1].reshape(N_ORDER, N_ORDER)


def _orders(split: Any, reference: Any, ns: list[int]) -> tuple[list[float], list[float]]:
    system, W0, ref = reference
    h_unit = system.fluid_time_unit
    errors = [
        float(np.linalg.norm(_run(split, W0, T_ORDER / n / h_unit, n) - ref))
        / float(np.linalg.norm(ref))
        for n in ns
    ]
    return errors, [math.log2(errors[i] / errors[i + 1]) for i in range(len(errors) - 1)]


@pytest.mark.parametrize(
    ("kind", "method", "order", "bound"),
    [
        ("lie", "exact", 1, 1.1e-3),
        ("strang", "exact", 2, 2e-6),
        ("strang", "crank_nicolson", 2, 7.5e-6),
        ("triple_jump", "exact", 4, 3e-9),
    ],
)
def test_observed_splitting_order_against_dop853(
    dissipative_reference: Any, kind: str, method: str, order: int, bound: float
) -> None:
    """Relative errors at fluid time 1, N = 6, Ω = 0.5, ν = 0.05 (measured: Lie 1.04e-3,
    Strang 1.92e-6, Strang with CN 6.97e-6 at h = 1/32; triple jump 2.45e-9 at h = 1/16);
    the conservative step is gauss2 (gauss3 under the triple jump), whose own error is far
    below the splitting error."""
    system = dissipative_reference[0]
    viscosity = Viscosity(system, nu=NU, method=method)
    if kind == "lie":
        split, ns = Splitting.lie(_conservative(system), viscosity), [8, 16, 32]
    elif kind == "strang":
        split, ns = Splitting.strang(viscosity, _conservative(system)), [8, 16, 32]
    else:
        cons = _conservative(system, "gauss3")
        split, ns = Splitting.composition(viscosity, cons, method="triple_jump"), [4, 8, 16]
    errors, orders = _orders(split, dissipative_reference, ns)
    assert orders[-1] == pytest.approx(order, abs=0.1), (errors, orders)
    assert errors[-1] <= bound, errors


def test_matrix_time_splitting_is_the_same_run(dissipative_reference: Any) -> None:
    """In matrix time (``h`` in units of ħ) the splitting reproduces the fluid-time run."""
    system, W0, _ = dissipative_reference
    matrix = lz.EulerZeitlin(N_ORDER, rotation=OMEGA, time="matrix")
    hb = lz.hbar(N_ORDER)
    fluid_run = _run(Splitting.strang(Viscosity(system, nu=NU), _conservative(system)), W0, 0.1, 5)
    split = Splitting.strang(Viscosity(matrix, nu=NU), _conservative(matrix))
    np.testing.assert_allclose(_run(split, W0, 0.1 / hb, 5), fluid_run, atol=1e-13)


# --------------------------------------------------------------------------- forcing
def test_forcing_noise_is_band_limited_white_and_a_function_of_seed_and_step() -> None:
    N = 10
    system = lz.EulerZeitlin(N)
    forcing = StochasticForcing(system, amplitude=1.0, l1=2, l2=5, seed=3)
    assert forcing.modes == 36 - 4 and forcing.enstrophy_rate == 0.5 * 32
    Q = forcing.noise(0.3, 0.1)
    assert lf.SU(N).contains(Q, tol=1e-14)
    c = lz.matrix_to_sh(Q)
    l, _ = lz.degrees_and_orders(N)
    assert np.max(np.abs(c[(l < 2) | (l > 5)])) <= 1e-14
    np.testing.assert_array_equal(Q, forcing.noise(0.3 + 1e-12, 0.1))  # k = round(t/h) = 3
    assert not np.allclose(Q, forcing.noise(0.4, 0.1))
    other = StochasticForcing(system, amplitude=1.0, l1=2, l2=5, seed=4)
    assert not np.allclose(Q, other.noise(0.3, 0.1))
    # i.i.d. standard normal real coefficients: E ∫η² = n (400 draws: within 3 %)
    mean = np.mean(
        [np.sum(np.abs(lz.matrix_to_sh(forcing.noise(k, 1.0))) ** 2) for k in range(400)]
    )
    assert mean == pytest.approx(forcing.modes, rel=0.03)
    # one step adds amplitude * sqrt(fluid time) * Q(η)
    W = lz.random_vorticity(N, 3, seed=5)
    out, _, _ = StochasticForcing(system, amplitude=0.3, l1=2, l2=5, seed=3).step(W, 0.3, 0.1, None)
    np.testing.assert_allclose(out, W + 0.3 * math.sqrt(0.1) * Q, atol=1e-15)
    matrix = lz.EulerZeitlin(N, time="matrix")
    out_m, _, _ = StochasticForcing(matrix, amplitude=0.3, l1=2, l2=5, seed=3).step(
        W, 3.0, 1.0, None
    )
    Qm = forcing.noise(3.0, 1.0)
    np.testing.assert_allclose(out_m, W + 0.3 * math.sqrt(lz.hbar(N)) * Qm, atol=1e-15)


def test_forcing_and_drag_reach_the_exact_statistically_steady_enstrophy() -> None:
    r"""Lie splitting Euler → drag → forcing from rest, N = 12, μ = 1, σ = 0.5, degrees
    3..6 (n = 40 modes), h = 0.05, 2000 steps. Per step ``E||W||²`` maps to
    ``e^{-2μτ} E||W||² + (N/4π)σ²nτ`` (Euler conserves ``||W||_F``, the noise is
    independent), so the stationary mean is ``(N/4π)σ²nτ/(1 - e^{-2μτ}) = 5.017``.
    Measured time mean after t = 10: 5.105 (+1.7 %; the statistical error of the mean is
    about 2 %); six consecutive windows of 15 time units: -9 %..+6 %."""
    N, mu, sigma, h, steps = 12, 1.0, 0.5, 0.05, 2000
    system = lz.EulerZeitlin(N)
    forcing = StochasticForcing(system, amplitude=sigma, l1=3, l2=6, seed=7)
    split = Splitting.lie(_conservative(system, "midpoint"), LinearDrag(system, mu=mu), forcing)
    W = np.zeros((N, N), dtype=complex)
    state = split.init(W)
    Z = np.empty(steps)
    for k in range(steps):
        W, state, _ = split.step(W, k * h, h, state)
        Z[k] = system.enstrophy(W)
    predicted = (N / (4 * math.pi)) * sigma**2 * forcing.modes * h / (1 - math.exp(-2 * mu * h))
    assert predicted == pytest.approx(5.0174, rel=1e-4)
    steady = Z[200:]
    assert steady.mean() == pytest.approx(predicted, rel=0.06)
    windows = [w.mean() / predicted for w in np.array_split(steady, 6)]
    assert min(windows) > 0.8 and max(windows) < 1.2, windows
    # spun up from rest: E||W_k||² = predicted (1 - e^{-2μτk}), mean 0.41 predicted over k < 10
    assert Z[:10].mean() < 0.6 * predicted
    assert lf.SU(N).contains(W, tol=1e-12)


def test_forced_runs_are_reproducible_and_resumable() -> None:
    """Same seed, same run, bit for bit; a run resumed at step 30 (fresh flow state, the
    clock at 30 h) continues exactly as the uninterrupted one; another seed differs."""
    N, h = 8, 0.05
    system = lz.EulerZeitlin(N)

    def split(seed: int) -> Any:
        forcing = StochasticForcing(system, amplitude=0.4, l1=1, l2=4, seed=seed)
        drag = LinearDrag(system, mu=0.2)
        cons = _conservative(system, "midpoint", warm_start=False)
        return Splitting.strang(forcing, Splitting.strang(drag, cons))

    W0 = lz.random_vorticity(N, 3, seed=1)
    full = _run(split(11), W0, h, 50)
    np.testing.assert_array_equal(full, _run(split(11), W0, h, 50))
    half = _run(split(11), W0, h, 30)
    np.testing.assert_array_equal(full, _run(split(11), half, h, 20, start=30))
    assert not np.allclose(full, _run(split(12), W0, h, 50))


# --------------------------------------------------------------------------- bad input
def test_bad_dissipation_and_forcing_parameters_are_clear_errors() -> None:
    system = lz.EulerZeitlin(6)
    with pytest.raises(lf.InputError, match="viscosity nu must be finite and >= 0"):
        Viscosity(system, nu=-1.0)
    with pytest.raises(lf.InputError, match="method"):
        Viscosity(system, nu=1.0, method="euler")
    with pytest.raises(lf.InputError, match="order p"):
        Hyperviscosity(system, nu=1.0, order=0)
    with pytest.raises(lf.InputError, match="drag mu"):
        LinearDrag(system, mu=float("inf"))
    with pytest.raises(lf.InputError, match="EulerZeitlin"):
        LinearDrag("euler", mu=1.0)
    with pytest.raises(lf.InputError, match="l1 <= l2"):
        StochasticForcing(system, amplitude=1.0, l1=3, l2=2, seed=0)
    with pytest.raises(lf.InputError, match="1 <= l1"):
        StochasticForcing(system, amplitude=1.0, l1=0, l2=2, seed=0)
    with pytest.raises(lf.InputError, match="N-1 = 5"):
        StochasticForcing(system, amplitude=1.0, l1=1, l2=6, seed=0)
    with pytest.raises(lf.InputError, match="seed"):
        StochasticForcing(system, amplitude=1.0, l1=1, l2=2, seed=-1)
    with pytest.raises(lf.InputError, match="amplitude"):
        StochasticForcing(system, amplitude=-0.1, l1=1, l2=2, seed=0)
    with pytest.raises(lf.InputError, match='needs method="exact"'):
        Viscosity(system, nu=1.0, method="crank_nicolson").step(np.zeros((6, 6)), 0.0, -0.1, None)
    forcing = StochasticForcing(system, amplitude=1.0, l1=1, l2=2, seed=0)
    with pytest.raises(lf.InputError, match="h > 0"):
        forcing.step(np.zeros((6, 6), complex), 0.0, 0.0, None)
    with pytest.raises(lf.InputError, match="t >= 0"):
        forcing.step(np.zeros((6, 6), complex), -1.0, 0.1, None)
