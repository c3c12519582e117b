r"""Orientation of the Euler–Zeitlin plugin: the matrix flow is Euler's equation *forward* in
time, on a rotating sphere and in the quasi-geostrophic model.

Every check here is against a physical fact computed without lieflow's integrators:

* the Poisson bracket of the sphere, ``{f, g} = n̂ · (∇f × ∇g)`` (outward normal), evaluated by
  fourth-order finite differences on a latitude–longitude grid, against
  ``-(1/ħ)[Q(f), Q(g)]``;
* Rossby–Haurwitz waves: ``ζ = a cos θ + ε sin^l θ cos(lφ)`` (solid-body rotation plus a
  sectoral degree-``l`` wave) is an exact solution of the quasi-geostrophic equation
  ``q_t = -{ψ, q}``, ``q = Δψ - Fψ + 2Ω cos θ``, and of its Zeitlin quantization; the wave
  moves *east* at the angular speed

  .. math:: c = \frac{(a/2)(l(l+1) - 2) - 2\Omega}{l(l+1) + F}

  (Euler: ``Ω = F = 0``, ``c = (a/2)(1 - 2/(l(l+1)))``; derivation in docs/euler-zeitlin.md);
* quflow's matrices for the same fields (numbers measured with quflow b42eede).

A sign flip anywhere (quantization, bracket, ``B``, time unit) moves the wave west or at the
wrong speed and fails these tests.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import lieflow as lf

lz = pytest.importorskip("lieflow_zeitlin")

from lieflow_zeitlin.laplacian import spin_matrices  # noqa: E402


# --------------------------------------------------------------------------- the bracket
def _fields(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two smooth real fields of degree <= 3, as polynomials in ``x, y, z``."""
    x, y, z = np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)
    f = x * y + 0.7 * z**3 - 0.4 * x + 0.2 * y * z
    g = 0.5 * z + x * z - 0.8 * y**2 * x + 0.3 * y
    return f, g


def _finite_difference_bracket(n: int) -> tuple[lz.SphereGrid, np.ndarray, ...]:
    r"""``{f, g} = (f_θ g_φ - f_φ g_θ)/sin θ`` by fourth-order central differences on the
    equiangular ``n × 2n`` grid (two ghost rows beyond each pole: the fields are analytic in
    ``θ``, and ``(−θ, φ)`` is the point ``(θ, φ + π)``)."""
    grid = lz.SphereGrid(n, 2 * n, "equiangular")
    dth, dph = math.pi / n, math.pi / n
    theta = np.concatenate([-grid.theta[1::-1], grid.theta, 2 * math.pi - grid.theta[:-3:-1]])
    TH, PH = np.meshgrid(theta, grid.phi, indexing="ij")
    f, g = _fields(TH, PH)

    def d_theta(u: np.ndarray) -> np.ndarray:
        return (-u[4:] + 8 * u[3:-1] - 8 * u[1:-3] + u[:-4]) / (12 * dth)

    def d_phi(u: np.ndarray) -> np.ndarray:
        u = u[2:-2]
        r = np.roll
        return (-r(u, -2, 1) + 8 * r(u, -1, 1) - 8 * r(u, 1, 1) + r(u, 2, 1)) / (12 * dph)

    bracket = (d_theta(f) * d_phi(g) - d_phi(f) * d_theta(g)) / np.sin(grid.theta)[:, None]
    return grid, f[2:-2], g[2:-2], bracket


def test_bracket_quantizes_to_minus_the_commutator_over_hbar() -> None:
    r"""``(1/ħ)[Q(f), Q(g)] = -Q({f, g}) + O(N⁻²)`` with the outward-normal bracket computed
    by finite differences (FD error ~1e-7). Measured relative errors 5.1e-2, 1.2e-2, 2.9e-3
    at N = 8, 16, 32 (ratio 4 per doubling); the opposite sign is off by 2."""
    grid, f, g, bracket = _finite_difference_bracket(192)
    errors = []
    for N in (8, 16, 32):
        Qf, Qg, Qb = (lz.grid_to_matrix(u, grid, N) for u in (f, g, bracket))
        C = (Qf @ Qg - Qg @ Qf) / lz.hbar(N)
        scale = np.linalg.norm(Qb)
        errors.append(np.linalg.norm(C + Qb) / scale)
        assert np.linalg.norm(C - Qb) / scale > 1.9  # the other orientation is wrong by 2
    assert errors[0] < 0.06 and errors[-1] < 3.5e-3, errors
    assert errors[0] / errors[1] > 3.5 and errors[1] / errors[2] > 3.5, errors


@pytest.mark.parametrize("N", [2, 3, 6])
def test_degree_one_bracket_is_exact(N: int) -> None:
    r"""``{x_a, x_b} = ε_abc x_c`` and ``Q(x_a) = iħ S_a``: ``(1/ħ)[Q(x_a), Q(x_b)] =
    -Q({x_a, x_b})`` exactly, and ``(1/ħ)[Q(z), Q(g)] = Q(∂_φ g)`` (``{z, g} = -∂_φ g``)."""
    hb = lz.hbar(N)
    S = spin_matrices(N)
    np.testing.assert_allclose(np.diag(S[2]).real, np.arange(N) - (N - 1) / 2)  # ascending
    Q = [1j * hb * s for s in S]
    for a, b, c in [(0, 1, 2), (1, 2, 0), (2, 0, 1)]:
        np.testing.assert_allclose((Q[a] @ Q[b] - Q[b] @ Q[a]) / hb, -Q[c], atol=1e-14)
    g = lz.random_sh(N, degree=N - 1, seed=3)
    _, m = lz.degrees_and_orders(N)
    Qz, Qg = lz.sh_to_matrix(_z_coefficients(N)), lz.sh_to_matrix(g)
    np.testing.assert_allclose(Qz, Q[2], atol=1e-14)
    np.testing.assert_allclose((Qz @ Qg - Qg @ Qz) / hb, lz.sh_to_matrix(1j * m * g), atol=1e-13)


def test_matrices_equal_quflows() -> None:
    """Same field, same matrix as quflow (``quflow.shc2mat`` of the coefficients ``ω/√(4π)``),
    N = 3: numbers measured with quflow (commit b42eede), whose Euler step is
    ``W <- W + (h/ħ)[P, W] + ...``: the conventions of this plugin in fluid time."""
    N, r = 3, math.sqrt(4 * math.pi)
    expected = {
        (1, 1): -1j * math.sqrt(1.5) * (np.eye(3, k=-1)),
        (2, 1): 1j * math.sqrt(1.5) * np.diag([1.0, -1.0], k=-1),
        (2, -2): 1j * math.sqrt(3.0) * np.eye(3, k=2),
    }
    for (l, m), W in expected.items():
        c = np.zeros(N * N, dtype=complex)
        c[lz.lm_index(l, m)] = r
        np.testing.assert_allclose(lz.sh_to_matrix(c), W, atol=1e-15)


# --------------------------------------------------------------------------- Rossby–Haurwitz
def _z_coefficients(N: int) -> np.ndarray:
    c = np.zeros(N * N, dtype=complex)
    c[lz.lm_index(1, 0)] = math.sqrt(4 * math.pi / 3)  # cos θ
    return c


def rh_speed(a: float, l: int, rotation: float = 0.0, lamb: float = 0.0) -> float:
    """Eastward angular phase speed of the Rossby–Haurwitz wave (module docs)."""
    L = l * (l + 1)
    return ((a / 2) * (L - 2) - 2 * rotation) / (L + lamb)


def measured_rh_speed(
    system: lz.EulerZeitlin,
    scheme: str,
    l: int,
    *,
    a: float = 1.0,
    eps: float = 0.1,
    steps: int = 20,
    engine: str = "auto",
    casimir_shift: float | str = 0.0,
) -> tuple[float, float]:
    """Integrate the Rossby–Haurwitz wave over fluid time ``T`` (phase ``lcT = 1`` rad); return
    the measured eastward speed ``-arg(c_ll(T)/c_ll(0))/(lT)`` and the relative change of
    ``|c_ll|``. The initial relative vorticity is sampled on a grid (no lieflow formula)."""
    N = system.N
    grid = lz.SphereGrid.for_size(N)
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    zeta = a * np.cos(theta) + eps * np.sin(theta) ** l * np.cos(l * phi)
    W_rel = lz.grid_to_matrix(zeta, grid, N)
    W0 = system.from_relative(W_rel)
    c = rh_speed(a, l, system.rotation, system.lamb)
    T = 1.0 / (l * abs(c))
    h = T / steps / system.fluid_time_unit
    solver = lf.solvers.FixedPoint(rtol=1e-14)
    sol = lf.integrate(
        system,
        lf.schemes.get(scheme),
        W0,
        h,
        steps=steps,
        solver=solver,
        save_every=steps,
        engine=engine,  # type: ignore[arg-type]
        casimir_shift=casimir_shift,  # type: ignore[arg-type]
    )
    before = lz.matrix_to_sh(W_rel)[lz.lm_index(l, l)]
    after = lz.matrix_to_sh(system.relative(sol.W_final))[lz.lm_index(l, l)]
    return -float(np.angle(after / before)) / (l * T), abs(abs(after) / abs(before) - 1)


#: Largest relative phase-speed error of 40 steps per radian of phase (measured: midpoint
#: 1.19e-3, gauss2 1.33e-7, triple_jump 1.9e-5 at most, over the cases below).
TOLERANCE = {"midpoint": 2e-3, "gauss2": 3e-7, "triple_jump": 5e-5}


@pytest.mark.parametrize("time", ["fluid", "matrix"])
@pytest.mark.parametrize("scheme", sorted(TOLERANCE))
@pytest.mark.parametrize(("N", "l"), [(8, 2), (8, 5), (16, 3)])
def test_rossby_haurwitz_wave_moves_east_at_the_exact_speed(
    N: int, l: int, scheme: str, time: str
) -> None:
    system = lz.EulerZeitlin(N, time=time)
    c = rh_speed(1.0, l)
    speed, amplitude = measured_rh_speed(system, scheme, l, steps=40)
    assert speed > 0  # east
    assert abs(speed - c) <= TOLERANCE[scheme] * c, (speed, c)
    assert amplitude <= 1e-5


SCHEMES = sorted(lf.default_registry().schemes)


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize(("l", "m"), [(3, 3), (4, 2), (4, 1)])
def test_every_scheme_moves_every_degree_l_wave_east(scheme: str, l: int, m: int) -> None:
    r"""Any degree-``l`` wave on solid-body rotation moves rigidly east at ``c`` (the
    derivation uses only ``Δψ' = -l(l+1)ψ'``), so ``c_lm(t) = e^{-imct} c_lm(0)`` for sectoral
    (``m = l``) and tesseral waves alike. N = 10, 40 steps per radian of the ``m = l``
    phase; measured worst relative errors: midpoint 4.6e-4, triple_jump 2.9e-6, suzuki5
    4.1e-8, gauss2 (and block, modin_viviani, gauss) 2.0e-8, sydirk7 7.9e-10, gauss3 3.5e-13,
    gauss4 1e-15."""
    N, a, eps = 10, 1.0, 0.1
    system = lz.EulerZeitlin(N)
    c = rh_speed(a, l)
    coefficients = a * _z_coefficients(N)
    coefficients[lz.lm_index(l, m)] = eps * (0.6 + 0.8j)
    coefficients[lz.lm_index(l, -m)] = (-1) ** m * np.conj(coefficients[lz.lm_index(l, m)])
    W0 = lz.sh_to_matrix(coefficients)
    T, steps = 1.0 / (l * c), 40
    sol = lf.integrate(
        system,
        lf.schemes.get(scheme),
        W0,
        T / steps,
        steps=steps,
        solver=lf.solvers.FixedPoint(rtol=1e-14),
        save_every=steps,
    )
    ratio = lz.matrix_to_sh(sol.W_final)[lz.lm_index(l, m)] / coefficients[lz.lm_index(l, m)]
    speed = -float(np.angle(ratio)) / (m * T)
    assert speed > 0
    assert abs(speed - c) <= (1e-3 if scheme == "midpoint" else 1e-5) * c, (speed, c)


def test_rossby_haurwitz_error_is_the_schemes_alone() -> None:
    """The model is exact: the phase error of gauss2 falls as h⁴ (measured ratio 16.0)."""
    system = lz.EulerZeitlin(8)
    c = rh_speed(1.0, 2)
    e1, e2 = (abs(measured_rh_speed(system, "gauss2", 2, steps=n)[0] - c) for n in (10, 20))
    assert math.log2(e1 / e2) == pytest.approx(4.0, abs=0.1)


# --------------------------------------------------------------------------- rotating sphere
def test_solid_body_rotation_is_steady_in_the_rotating_frame() -> None:
    """``ζ = a cos θ`` relative to a sphere rotating at ``Ω``: a steady state."""
    N, a = 12, 0.7
    system = lz.EulerZeitlin(N, rotation=3.0)
    W_rel = a * lz.sh_to_matrix(_z_coefficients(N))
    W0 = system.from_relative(W_rel)
    np.testing.assert_allclose(W0, (a + 6.0) * lz.sh_to_matrix(_z_coefficients(N)), atol=1e-14)
    sol = lf.integrate(system, lf.schemes.get("gauss2"), W0, 0.1, steps=10)
    np.testing.assert_allclose(system.relative(sol.W_final), W_rel, atol=1e-13)


@pytest.mark.parametrize("time", ["fluid", "matrix"])
def test_tilted_solid_body_rotation_precesses_west_at_omega(time: str) -> None:
    r"""Relative vorticity ``2k·x`` (solid-body rotation about a tilted axis ``k``) on a
    sphere rotating at ``Ω``: the absolute flow is a steady solid-body rotation in the
    inertial frame, so in the rotating frame ``k`` precesses about ``z`` at ``-Ω``:
    the ``m = 1`` coefficient turns by ``e^{iΩT}``, the ``m = 0`` one stays (exact:
    degree 1; ``c = -2Ω/2`` in the Rossby–Haurwitz formula with ``l = 1, a = 0``)."""
    N, Omega, T, steps = 10, 1.3, 2.0, 40
    system = lz.EulerZeitlin(N, rotation=Omega, time=time)
    c = np.zeros(N * N, dtype=complex)
    c[lz.lm_index(1, 0)] = 0.5
    c[lz.lm_index(1, 1)], c[lz.lm_index(1, -1)] = 0.3 - 0.2j, -(0.3 + 0.2j)
    W0 = system.from_relative(lz.sh_to_matrix(c))
    h = T / steps / system.fluid_time_unit
    sol = lf.integrate(system, lf.schemes.get("gauss2"), W0, h, steps=steps, save_every=steps)
    after = lz.matrix_to_sh(system.relative(sol.W_final))
    assert after[lz.lm_index(1, 0)] == pytest.approx(0.5, abs=1e-12)
    turn = after[lz.lm_index(1, 1)] / c[lz.lm_index(1, 1)]
    assert abs(turn) == pytest.approx(1.0, abs=1e-12)
    assert np.angle(turn) == pytest.approx(Omega * T, abs=1e-6)  # westward: phase +ΩT


@pytest.mark.parametrize(
    ("rotation", "lamb", "l"), [(0.5, 0.0, 3), (-0.4, 0.0, 2), (0.5, 4.0, 3), (1.0, 25.0, 4)]
)
@pytest.mark.parametrize("time", ["fluid", "matrix"])
def test_rossby_haurwitz_speed_with_rotation_and_lamb_parameter(
    rotation: float, lamb: float, l: int, time: str
) -> None:
    """``c = ((a/2)(l(l+1) - 2) - 2Ω)/(l(l+1) + F)``: Euler on the rotating sphere (F = 0)
    and the quasi-geostrophic model. gauss2, 40 steps per radian of phase; measured relative
    errors 2.4e-7, 3.6e-8, 5.3e-7, 8.2e-7 (time discretisation only: the model is exact)."""
    system = lz.EulerZeitlin(12, time=time, rotation=rotation, lamb=lamb)
    c = rh_speed(1.0, l, rotation, lamb)
    speed, amplitude = measured_rh_speed(system, "gauss2", l, steps=40)
    assert abs(speed - c) <= 5e-6 * abs(c), (speed, c)
    assert amplitude <= 1e-6


@pytest.mark.parametrize(
    ("scheme", "rotation", "lamb", "shift"),
    [
        ("gauss2", 0.0, 0.0, 0.0),
        ("triple_jump", 0.0, 0.0, 0.0),
        ("gauss2", 0.5, 4.0, 0.0),
        ("gauss2", 0.5, 4.0, "auto"),
        ("triple_jump", -0.4, 0.0, "auto"),
    ],
)
def test_the_compiled_engine_moves_the_wave_at_the_exact_speed(
    scheme: str, rotation: float, lamb: float, shift: float | str
) -> None:
    """The compiled engine's complex loops (and the plugin's compiled B, with rotation,
    Lamb parameter and Casimir shift folded in) against the exact Rossby–Haurwitz speed,
    with the numpy path's tolerances: a transpose left unconjugated, or a sign of B, moves
    the wave at the wrong speed."""
    pytest.importorskip("numba")
    system = lz.EulerZeitlin(12, rotation=rotation, lamb=lamb)
    c = rh_speed(1.0, 3, rotation, lamb)
    speed, amplitude = measured_rh_speed(
        system, scheme, 3, steps=40, engine="compiled", casimir_shift=shift
    )
    assert speed * c > 0
    tolerance = 5e-6 if scheme == "gauss2" else TOLERANCE[scheme]
    assert abs(speed - c) <= tolerance * abs(c), (speed, c)
    assert amplitude <= 1e-5


def test_relative_vorticity_helpers_round_trip() -> None:
    """``from_relative``/``relative`` are inverse; the state is ``Q(ζ - Fψ + f)``."""
    N, Omega, F = 9, 0.8, 3.0
    system = lz.EulerZeitlin(N, rotation=Omega, lamb=F)
    W_rel = lz.random_vorticity(N, degree=5, seed=1)
    W = system.from_relative(W_rel)
    np.testing.assert_allclose(system.relative(W), W_rel, atol=1e-14)
    psi = lz.HoppeYauLaplacian(N).solve(W_rel)  # Q(ψ), Δψ = ζ
    f = 2 * Omega * lz.sh_to_matrix(_z_coefficients(N))
    np.testing.assert_allclose(W, W_rel - F * psi + f, atol=1e-14)
    np.testing.assert_allclose(system.stream(W), psi, atol=1e-14)
    assert lf.SU(N).contains(W, tol=1e-14)


def test_rotating_energy_gradient_and_newton() -> None:
    """``B = (grad η)^†`` for the affine ``B``; Newton (which uses ``B_derivative``) agrees
    with the fixed point; ``η = (σN/4π) ½∫(|∇ψ|² + Fψ²)``."""
    N, F = 8, 2.0
    system = lz.EulerZeitlin(N, rotation=0.7, lamb=F)
    assert not system.linear_B and lz.EulerZeitlin(N, lamb=F).linear_B
    W = system.from_relative(lz.random_vorticity(N, degree=4, seed=2))
    dW = lf.SU(N).project(np.random.default_rng(3).standard_normal((N, N)) * (1 + 1j))
    eps = 1e-6
    dH = (system.hamiltonian(W + eps * dW) - system.hamiltonian(W - eps * dW)) / (2 * eps)
    B = system.B(W)
    assert dH == pytest.approx(float(np.real(np.sum(np.conj(B.conj().T) * dW))), rel=1e-7)
    np.testing.assert_allclose(system.B_derivative(W, dW), system.B(W + dW) - B, atol=1e-12)
    psi = lz.matrix_to_sh(system.stream(W))
    l, _ = lz.degrees_and_orders(N)
    fluid = 0.5 * np.sum((l * (l + 1.0) + F) * np.abs(psi) ** 2)
    expected = system.bracket_scale * N / (4 * math.pi) * fluid
    assert system.hamiltonian(W) == pytest.approx(expected, rel=1e-12)
    ref = lf.integrate(system, lf.schemes.get("gauss2"), W, 0.05, steps=5)
    newton = lf.integrate(
        system, lf.schemes.get("gauss2"), W, 0.05, steps=5, solver=lf.solvers.Newton()
    )
    np.testing.assert_allclose(newton.W_final, ref.W_final, atol=1e-12)
    assert newton.spectrum_drift().max() <= 1e-12


def test_bad_rotation_and_lamb_are_clear_errors() -> None:
    with pytest.raises(lf.InputError, match="lamb"):
        lz.EulerZeitlin(4, lamb=-1.0)
    with pytest.raises(lf.InputError, match="rotation"):
        lz.EulerZeitlin(4, rotation=float("nan"))
    with pytest.raises(lf.InputError, match="time"):
        lz.EulerZeitlin(4, time="seconds")
    with pytest.raises(lf.InputError, match="contradicts"):
        lz.EulerZeitlin(4, hbar_scaled=False, time="fluid")
    with pytest.raises(lf.InputError, match="shift"):
        lz.HoppeYauLaplacian(4, shift=-1.0)
