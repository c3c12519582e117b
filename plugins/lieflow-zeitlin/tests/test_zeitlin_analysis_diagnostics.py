"""Turbulence diagnostics of lieflow-zeitlin (issue 17.2) and their storage while a run goes
(``/diagnostics/extra``, the generic ``system.extra_diagnostics`` hook of lieflow.app.io).

Exact facts: Parseval (``Σ Z(l)`` is ``½∫ζ²`` by quadrature of a field given in closed form),
a single-degree field's spectrum in closed form (``sin³θ cos 3φ``: ``Z(3) = 16π/35``), the
energy of a degree-1 field, Casimirs from eigenvalues equal to traces of matrix powers, the
vorticity levels of a diagonal matrix; the writer's rows at the chosen interval, a resumed
run's rows identical, and the samples equal to the diagnostics of the saved states.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

lz = pytest.importorskip("lieflow_zeitlin")
pytest.importorskip("h5py")

from lieflow_zeitlin import diagnostics as dg  # noqa: E402

import lieflow as lf  # noqa: E402
from lieflow.app import io  # noqa: E402
from lieflow.app.cli import main  # noqa: E402


def _field_coeffs(f, N: int) -> np.ndarray:  # type: ignore[no-untyped-def]
    grid = lz.SphereGrid.for_size(N)
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    return lz.grid_to_sh(f(theta, phi), grid, N)


def test_single_degree_field_spectrum_in_closed_form() -> None:
    N = 12
    c = _field_coeffs(lambda t, p: np.sin(t) ** 3 * np.cos(3 * p), N)
    Z = dg.enstrophy_spectrum(c)
    E = dg.energy_spectrum(c)
    expected = 16 * math.pi / 35  # ½ ∫ sin^6θ cos² 3φ dΩ = ½ π ∫ sin^7θ dθ
    assert abs(Z[3] - expected) < 1e-13
    assert np.abs(np.delete(Z, 3)).max() < 1e-26
    assert abs(E[3] - expected / 12) < 1e-14 and np.abs(np.delete(E, 3)).max() < 1e-27
    # QG energy: (l(l+1) + F)|ψ|²: factor (12 + F)/12 more
    assert abs(dg.energy_spectrum(c, lamb=6.0)[3] - expected / 12 * 18 / 12) < 1e-14


def test_parseval_and_energy_against_quadrature() -> None:
    """``Σ Z(l) = ½∫ζ²`` and ``Σ E(l) = ½∫|∇ψ|²`` for ``ζ = cos θ + sin²θ cos 2φ cos θ``:
    ``ψ`` in closed form (degree 1 and 3 parts), integrals by a fine Gauss grid."""
    N = 10
    zeta = lambda t, p: np.cos(t) + np.sin(t) ** 2 * np.cos(t) * np.cos(2 * p)  # noqa: E731
    c = _field_coeffs(zeta, N)
    fine = lz.SphereGrid.for_size(40)
    theta, phi = np.meshgrid(fine.theta, fine.phi, indexing="ij")
    Z_quad = 0.5 * float(fine.integrate(zeta(theta, phi) ** 2))
    assert abs(dg.enstrophy_spectrum(c).sum() - Z_quad) < 1e-13
    # ψ = -cos θ / 2 - sin²θ cos θ cos 2φ / 12; |∇ψ|² = ψ_θ² + ψ_φ² / sin²θ
    psi_t = 0.5 * np.sin(theta) - (
        (2 * np.sin(theta) * np.cos(theta) ** 2 - np.sin(theta) ** 3) * np.cos(2 * phi) / 12
    )
    psi_p_over_sin = np.sin(theta) * np.cos(theta) * 2 * np.sin(2 * phi) / 12
    E_quad = 0.5 * float(fine.integrate(psi_t**2 + psi_p_over_sin**2))
    assert abs(dg.energy_spectrum(c).sum() - E_quad) < 1e-13


@pytest.mark.parametrize("rotation, lamb", [(0.0, 0.0), (1.5, 0.0), (0.7, 3.0)])
def test_spectra_of_a_state_and_the_hamiltonian(rotation: float, lamb: float) -> None:
    """The spectra of the system's state are of the *relative* vorticity, and
    ``Σ E(l) = η · 4π/(σN)`` (the Hamiltonian's closed form)."""
    N = 16
    system = lz.EulerZeitlin(N, rotation=rotation, lamb=lamb)
    c = lz.random_sh(N, 6, seed=2)
    W = system.from_relative(lz.sh_to_matrix(c))
    s = dg.spectra(system, W)
    assert np.abs(s["enstrophy_spectrum"] - dg.enstrophy_spectrum(c)).max() < 1e-13
    E = s["energy_spectrum"].sum()
    assert abs(E - system.hamiltonian(W) * 4 * math.pi / (system.bracket_scale * N)) < 1e-12


def test_spectra_refuse_a_state_of_another_n_or_outside_su_n() -> None:
    """Issue 29.4: these returned numbers (the spectra of some other field)."""
    system = lz.EulerZeitlin(8)
    W = system.algebra.random(seed=1)
    with pytest.raises(lf.InputError, match=r"su\(8\) needs \(\.\.\., 8, 8\)"):
        dg.spectra(system, lz.EulerZeitlin(10).algebra.random(seed=1))
    for off in (W + 1e-6j * np.eye(8), W + 0.1 * np.abs(W), np.ones((8, 8))):
        with pytest.raises(lf.AlgebraError, match=r"not in su\(8\)"):
            dg.spectra(system, off)
    with pytest.raises(lf.AlgebraError):  # one bad state of a stack
        dg.spectra(system, np.stack([W, np.ones((8, 8))]))
    with pytest.raises(lf.InputError, match="needs an EulerZeitlin system"):
        dg.spectra(lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0)), W)
    # a state projected to roundoff (a stored run's) and a stack are fine
    s = dg.spectra(system, np.stack([W, system.algebra.project(W * (1 + 1e-15))]))
    assert s["energy_spectrum"].shape == (2, 8)
    np.testing.assert_allclose(s["energy_spectrum"][0], s["energy_spectrum"][1], rtol=1e-13)


def test_casimirs_from_levels_are_traces_of_powers() -> None:
    N = 9
    W = lz.random_vorticity(N, degree=5, seed=4)
    levels = dg.vorticity_levels(W)
    assert np.all(np.diff(levels) >= 0)
    A = 1j * W
    for k, C in zip(dg.CASIMIR_POWERS, dg.casimirs_from_levels(levels), strict=True):
        trace = np.trace(np.linalg.matrix_power(A, k)).real
        assert abs(C - trace) < 1e-12 * max(1.0, abs(trace))
    # a diagonal W = i diag(d): -iW = diag(d), levels are sorted d
    d = np.array([0.5, -1.0, 0.25, 0.25])
    assert np.array_equal(dg.vorticity_levels(1j * np.diag(d)), np.sort(d))
    with pytest.raises(lf.InputError):
        dg.casimirs_from_levels(levels, [0])


@pytest.mark.parametrize("N", [2, 3, 8, 17, 40])
def test_squares_by_degree_straight_from_the_matrix(N: int) -> None:
    """The compiled pass (recurrence fused with the products, lower diagonals only) against
    the coefficients of the eigensolver's harmonics (``matrix_to_sh(method="reference")``),
    for a stack; a matrix off su(N) gives its skew-Hermitian part's squares."""
    c = np.stack([lz.random_sh(N, min(N - 1, 6), seed=s) for s in (1, 2)])
    W = lz.sh_to_matrix(c).reshape(2, 1, N, N)
    reference = dg._squares_by_degree(lz.matrix_to_sh(W, method="reference"))
    S = dg.matrix_squares_by_degree(W)
    assert S.shape == (2, 1, N)
    np.testing.assert_allclose(S, reference, rtol=1e-13, atol=1e-15 * reference.max())
    H = np.random.default_rng(3).standard_normal((N, N))
    H = H + H.T  # Hermitian: no skew-Hermitian part
    off = dg.matrix_squares_by_degree(W[0, 0] + H)
    np.testing.assert_allclose(off, S[0, 0], rtol=1e-12, atol=1e-14 * S.max())
    tables = lz.EulerZeitlin(N).diagonal_tables
    np.testing.assert_array_equal(dg.matrix_squares_by_degree(W, tables), S)
    with pytest.raises(lf.InputError, match="tables for N = 9"):
        dg.matrix_squares_by_degree(W, lz.EulerZeitlin(9).diagonal_tables)


def test_squares_by_degree_without_numba(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without numba the squares come from the coefficients: the same numbers."""
    W = lz.random_vorticity(12, degree=5, seed=2)
    fast = dg.matrix_squares_by_degree(W)
    monkeypatch.setattr(dg._rec, "have_numba", lambda: False)
    np.testing.assert_allclose(dg.matrix_squares_by_degree(W), fast, rtol=1e-13, atol=1e-30)


def test_casimirs_of_exactly_isospectral_copies_agree_to_roundoff() -> None:
    """A permutation and phases ±1, ±i conjugate ``W`` exactly in floating point, so the
    Casimirs of the copies differ only by the diagnostics' own error: ``<= 4e-16`` of
    ``||W||_F^k`` (with ``C_2 = Σλ²`` from the levels it was 2e-15 at N = 64)."""
    N = 64
    system = lz.EulerZeitlin(N)
    W = lz.random_vorticity(N, degree=8, seed=1)
    scale = np.linalg.norm(W) ** np.array(dg.CASIMIR_POWERS)
    C = system.extra_diagnostics(W)["casimirs"]
    rng = np.random.default_rng(0)
    worst = np.zeros(len(dg.CASIMIR_POWERS))
    for _ in range(10):
        p = rng.permutation(N)
        phase = 1j ** rng.integers(0, 4, N)
        V = phase[:, None] * W[p][:, p] * np.conj(phase)[None, :]
        worst = np.maximum(worst, np.abs(system.extra_diagnostics(V)["casimirs"] - C) / scale)
    assert worst.max() <= 4e-16, worst
    # C_2 is ||W||_F², the others power sums of the levels (traces of powers, k = 3, 4)
    A = 1j * W
    assert C[0] == system.enstrophy(W)
    assert abs(C[1] - np.trace(A @ A @ A).real) <= 1e-15 * scale[1]
    assert abs(C[2] - np.linalg.norm(A @ A) ** 2) <= 1e-15 * scale[2]


def test_extra_diagnostics_check_the_shape_and_match_the_snapshot() -> None:
    system = lz.EulerZeitlin(10, rotation=0.5, lamb=2.0)
    W = system.random_state(seed=3)
    extra, snap = system.extra_diagnostics(W), dg.snapshot(system, W)
    assert extra.keys() == snap.keys()
    for name in extra:
        np.testing.assert_array_equal(extra[name], snap[name])
    with pytest.raises(lf.InputError, match=r"su\(10\) needs \(\.\.\., 10, 10\)"):
        system.extra_diagnostics(np.zeros((8, 8), complex))
    # without the levels: the spectra and their sums, the same numbers
    lean = lz.EulerZeitlin(10, rotation=0.5, lamb=2.0, diagnostics_levels=False)
    spectra_only = lean.extra_diagnostics(W)
    assert sorted(spectra_only) == ["energy", "energy_spectrum", "enstrophy", "enstrophy_spectrum"]
    for name in spectra_only:
        np.testing.assert_array_equal(spectra_only[name], snap[name])


def test_running_and_time_means() -> None:
    v = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 8.0]])
    assert np.array_equal(dg.running_mean(v), [[1, 2], [2, 2], [3, 4]])
    assert np.array_equal(dg.time_mean([0, 1, 2], v, t_start=1), [4, 5])
    with pytest.raises(lf.InputError, match="no samples"):
        dg.time_mean([0, 1], v[:2], t_start=5)


CONFIG = """
[system]
name = "euler_zeitlin"
params = {{ N = 10, diagnostics_every = {every} }}

[initial]
random = true
seed = 3

[scheme]
name = "midpoint"

[splitting]
method = "strang"
flows = [
  {{ name = "zeitlin_drag", params = {{ mu = 0.5 }} }},
  {{ name = "zeitlin_forcing", params = {{ amplitude = 0.3, l1 = 2, l2 = 4, seed = 1 }} }},
]

[run]
h = 0.05
steps = {steps}
save_every = 6
output = "run.h5"
"""


def _run(directory: Path, steps: int, every: int = 2, resume: bool = False) -> Path:
    directory.mkdir(exist_ok=True)
    cfg = directory / "run.toml"
    cfg.write_text(CONFIG.format(every=every, steps=steps))
    args = ["run", str(cfg), "--no-progress", *(["--resume"] if resume else [])]
    assert main(args) == 0
    return directory / "run.h5"


def test_run_writes_diagnostics_at_the_chosen_interval_and_resumes(tmp_path: Path) -> None:
    path = _run(tmp_path / "once", 13)
    extra = io.read_extra(path)
    assert list(extra["step"]) == [0, 2, 4, 6, 8, 10, 12]
    assert np.allclose(extra["t"], extra["step"] * 0.05)
    assert extra["energy_spectrum"].shape == (7, 10)
    assert extra["vorticity_levels"].shape == (7, 10)
    assert extra["casimirs"].shape == (7, len(dg.CASIMIR_POWERS))
    # the samples at saved steps are the diagnostics of the saved states
    traj = io.read_trajectory(path)
    system = lz.EulerZeitlin(10)
    assert list(traj.step) == [0, 6, 12, 13]  # the last state is saved, not sampled
    for step, W in zip(traj.step[:3], traj.W[:3], strict=True):
        row = list(extra["step"]).index(step)
        snap = dg.snapshot(system, W)
        for name in ("energy_spectrum", "enstrophy", "vorticity_levels", "casimirs"):
            assert np.allclose(extra[name][row], snap[name], rtol=1e-12, atol=1e-14)
    # Parseval on the stored rows; C_2 = tr((iW)²) = ||W||_F² = enstrophy · N/2π
    assert np.allclose(extra["enstrophy_spectrum"].sum(axis=1), extra["enstrophy"])
    assert np.allclose(extra["casimirs"][:, 0], extra["enstrophy"] * 10 / (2 * math.pi))
    # stopped at step 7 (checkpoint at 6: the sample at step 6 is kept), resumed to 13
    twice = tmp_path / "twice"
    _run(twice, 7)
    assert list(io.read_extra(twice / "run.h5")["step"]) == [0, 2, 4, 6]
    resumed = io.read_extra(_run(twice, 13, resume=True))
    assert resumed.keys() == extra.keys()
    for name in extra:
        np.testing.assert_array_equal(resumed[name], extra[name])


def test_diagnostics_every_zero_writes_none_and_is_validated(tmp_path: Path) -> None:
    path = _run(tmp_path, 4, every=0)
    assert io.read_extra(path) == {}
    with pytest.raises(lf.InputError, match="diagnostics_every"):
        lz.EulerZeitlin(8, diagnostics_every=-1)
    with pytest.raises(lf.InputError, match="diagnostics_levels must be true or false"):
        lz.EulerZeitlin(8, diagnostics_levels="no")


def test_docs_page_shows_the_example_configuration() -> None:
    """docs/turbulence.md quotes plugins/lieflow-zeitlin/examples/turbulence_n24.toml (its
    python blocks run the file): the quoted TOML is the file without its comments."""
    root = Path(__file__).resolve().parents[3]  # the lieflow repository
    page = (root / "docs" / "turbulence.md").read_text()
    quoted = page.split("```toml\n", 1)[1].split("```", 1)[0]
    example = (root / "plugins/lieflow-zeitlin/examples/turbulence_n24.toml").read_text()
    body = "\n".join(line for line in example.splitlines() if not line.startswith("#"))
    assert quoted.strip() == body.strip()
