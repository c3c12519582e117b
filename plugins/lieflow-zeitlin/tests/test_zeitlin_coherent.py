"""The coherent-vortex detector (:mod:`lieflow_zeitlin.coherent`) on fields whose vortices are
known: Gaussian blobs placed on the sphere (2, 3 and 4, of both signs and unequal strengths),
rotated copies of them, the same with white noise of the field's own size, a weak bump on a
vortex's flank, and a solid-body rotation, whose two vortices (the hemispheres) have a
closed-form circulation. Every test compares the exact count, and the signs and positions.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lieflow as lf

lz = pytest.importorskip("lieflow_zeitlin")

N = 32


@pytest.fixture(scope="module")
def detector() -> lz.VortexDetector:
    return lz.VortexDetector(N)


def unit(lat: float, lon: float) -> np.ndarray:
    la, lo = math.radians(lat), math.radians(lon)
    return np.array([math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)])


def blobs(centres: np.ndarray, strengths: list[float], width: float = 0.35) -> np.ndarray:
    """``Q(Σ s_i exp(-(1 - x·c_i)/width²))`` minus its mean: Gaussian vortices of angular
    width ``width`` (radians) centred at ``c_i``, projected onto degrees ``< N``."""
    grid = lz.SphereGrid.for_size(N, oversample=2)
    th, ph = grid.theta[:, None], grid.phi[None, :]
    X = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th) + 0 * ph], -1)
    f = sum(s * np.exp(-(1 - X @ c) / width**2) for c, s in zip(centres, strengths, strict=True))
    W = lz.grid_to_matrix(f, grid, N)
    np.einsum("ii->i", W)[:] -= np.trace(W) / N
    return W


def noise(W: np.ndarray, size: float, seed: int) -> np.ndarray:
    """White noise over every degree with Frobenius norm ``size · ||W||``."""
    R = lz.random_vorticity(N, degree=N - 1, seed=seed)
    return W + size * np.linalg.norm(W) * R / np.linalg.norm(R)


#: name -> (centres as (lat, lon), signed strengths)
CASES = {
    "dipole": ([(30, 10), (-30, 190)], [1.0, -1.0]),
    "tripole": ([(60, 0), (-30, 0), (-30, 180)], [1.0, -0.6, -0.6]),
    "quadrupole": ([(35, 0), (35, 180), (-35, 90), (-35, 270)], [1.0, 1.0, -1.0, -1.0]),
    "tetrahedron": ([(90, 0), (-19.47, 0), (-19.47, 120), (-19.47, 240)], [1, -1, 1, -1]),
    "unequal four": ([(20, 0), (-10, 95), (40, 200), (-50, 260)], [1.0, -0.5, 0.6, -0.8]),
}


def angle(a: np.ndarray, b: np.ndarray) -> float:
    """Great-circle distance in degrees."""
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b)))))


def check(
    census: lz.VortexCensus, centres: list[np.ndarray], strengths: list[float], tol: float = 5.0
) -> None:
    """Exactly one detected vortex of the right sign within ``tol`` degrees of each centre."""
    assert census.count == len(centres), [(v.lat, v.lon, v.sign) for v in census.vortices]
    assert census.positive == sum(s > 0 for s in strengths)
    assert census.negative == sum(s < 0 for s in strengths)
    found = [np.asarray(v.position) for v in census.vortices]
    for c, s in zip(centres, strengths, strict=True):
        near = [i for i, p in enumerate(found) if angle(p, c) < tol]
        assert len(near) == 1, (c, [(v.lat, v.lon) for v in census.vortices])
        v = census.vortices[near[0]]
        assert v.sign == np.sign(s)
        assert np.sign(v.circulation) == np.sign(s)
        assert v.persistence >= 0.2 * census.amplitude


@pytest.mark.parametrize("name", CASES)
def test_blobs_at_known_places(detector: lz.VortexDetector, name: str) -> None:
    where, strengths = CASES[name]
    centres = [unit(*p) for p in where]
    check(detector.census(blobs(np.array(centres), strengths)), centres, strengths)


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("seed", [1, 2])
def test_rotated_copies(detector: lz.VortexDetector, name: str, seed: int) -> None:
    where, strengths = CASES[name]
    R = Rotation.random(random_state=seed).as_matrix()
    centres = [R @ unit(*p) for p in where]
    check(detector.census(blobs(np.array(centres), strengths)), centres, strengths)


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("size", [0.5, 1.0])
def test_with_noise(detector: lz.VortexDetector, name: str, size: float) -> None:
    """White noise of half and of the full norm of the field: the low-pass removes it (the
    weakest vortex moves by up to 6°)."""
    where, strengths = CASES[name]
    centres = [unit(*p) for p in where]
    W = noise(blobs(np.array(centres), strengths), size, seed=len(name))
    check(detector.census(W), centres, strengths, tol=8.0)


def test_circulations_partition_the_field(detector: lz.VortexDetector) -> None:
    """The basins of a tripole are the whole sphere: the circulations add up to
    ``∫ω̄ dΩ = 0``, the two mirror-image negative vortices carry equal shares, and the
    basins' areas add up to 4π."""
    where = [(90, 0), (-30, 0), (-30, 180)]
    census = detector.census(blobs(np.array([unit(*p) for p in where]), [1.0, -0.6, -0.6]))
    positive = [v.circulation for v in census.vortices if v.sign > 0]
    negative = [v.circulation for v in census.vortices if v.sign < 0]
    assert positive[0] > 0.5
    assert negative[0] == pytest.approx(negative[1], rel=0.02)
    assert sum(negative) == pytest.approx(-positive[0], rel=0.01)
    assert sum(v.area for v in census.vortices) == pytest.approx(4 * math.pi, rel=1e-12)


def test_a_weak_bump_on_a_flank_is_not_a_vortex(detector: lz.VortexDetector) -> None:
    bump = np.array([unit(0, 0), unit(0, 45), unit(0, 180)])
    census = detector.census(blobs(bump, [1.0, 0.15, -1.0]))
    assert census.count == 2 and census.positive == 1 and census.negative == 1
    # a strong second vortex further away counts
    apart = np.array([unit(0, 0), unit(0, 90), unit(0, 225)])
    assert detector.census(blobs(apart, [1.0, 0.8, -1.0])).count == 3


def test_threshold_decides_weak_vortices(detector: lz.VortexDetector) -> None:
    """A separate vortex of 0.3 the strongest one's strength: below the default threshold
    (persistence 0.2 · max|ω̄|), counted with a lower one."""
    W = blobs(np.array([unit(0, 0), unit(0, 120), unit(0, 240)]), [1.0, 0.3, -1.0])
    assert detector.census(W).count == 2
    low = lz.VortexDetector(N, threshold=0.1, points=detector.points)
    census = low.census(W)
    assert census.count == 3 and census.positive == 2
    weak = min(census.vortices, key=lambda v: abs(v.circulation))
    assert angle(np.asarray(weak.position), unit(0, 120)) < 5.0


def test_solid_body_rotation_is_two_hemispheres(detector: lz.VortexDetector) -> None:
    """``ω = b·x``: a positive vortex at ``b̂`` and a negative one at ``-b̂``, each the
    hemisphere, with circulation ``±π|b|`` times the filter's ``exp(-σ²)`` on degree 1."""
    b = np.array([0.3, -1.1, 0.6])
    W = 1j * lz.hbar(N) * sum(ba * Sa for ba, Sa in zip(b, lz.spin_matrices(N), strict=True))
    census = detector.census(W)
    assert census.count == 2
    expected = math.pi * np.linalg.norm(b) * math.exp(-(detector.smoothing**2))
    for v in census.vortices:
        assert angle(np.asarray(v.position), v.sign * b / np.linalg.norm(b)) < 1.0
        assert v.circulation == pytest.approx(v.sign * expected, rel=0.01)
        assert v.area == pytest.approx(2 * math.pi, rel=0.01)


def test_low_pass_is_the_field_the_detector_samples(detector: lz.VortexDetector) -> None:
    """``low_pass(W, σ)`` multiplies degree ``l`` by ``exp(-σ² l(l+1)/2)``, and the detector's
    samples of ``W`` are the values of that field (its harmonics summed at the points)."""
    from scipy.special import sph_harm_y

    W = lz.random_vorticity(N, degree=20, seed=9)
    coeffs = lz.matrix_to_sh(lz.low_pass(W, detector.smoothing))
    l, m = lz.degrees_and_orders(N)
    factor = np.exp(-0.5 * detector.smoothing**2 * l * (l + 1))
    np.testing.assert_allclose(coeffs, lz.matrix_to_sh(W) * factor, atol=1e-13)
    p = detector.xyz[::97]
    theta, phi = np.arccos(p[:, 2]), np.arctan2(p[:, 1], p[:, 0])
    values = sum(c * sph_harm_y(lk, mk, theta, phi) for c, lk, mk in zip(coeffs, l, m, strict=True))
    np.testing.assert_allclose(detector.filtered(W)[::97], values.real, atol=1e-10)


def test_fields_without_vortices(detector: lz.VortexDetector) -> None:
    assert detector.census(np.zeros((N, N), complex)).count == 0
    assert detector.filtered(np.zeros((3, N, N), complex)).shape == (3, detector.points)


def test_bad_input(detector: lz.VortexDetector) -> None:
    with pytest.raises(lf.InputError, match="this detector is for"):
        detector.filtered(np.zeros((8, 8), complex))
    with pytest.raises(lf.InputError, match="one state"):
        detector.census(np.zeros((2, N, N), complex))
    with pytest.raises(lf.InputError, match="threshold"):
        lz.VortexDetector(N, threshold=1.5)
    for smoothing in (-1.0, 0.0, math.nan):
        with pytest.raises(lf.InputError, match="smoothing"):
            lz.VortexDetector(N, smoothing=smoothing)
    with pytest.raises(lf.InputError, match="integer >= 12"):
        lz.fibonacci_points(5)


def test_fibonacci_points_are_uniform() -> None:
    p = lz.fibonacci_points(2000)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=1e-3)
    # each octant holds an eighth of the points
    octant = (p[:, 0] > 0) * 4 + (p[:, 1] > 0) * 2 + (p[:, 2] > 0)
    np.testing.assert_allclose(np.bincount(octant) / 2000, 1 / 8, atol=0.01)
