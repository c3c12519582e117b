"""Figures of the docs page ``docs/euler-zeitlin.md`` (run from the repository root).

    python plugins/lieflow-zeitlin/docs/make_figures.py        # -> docs/img/zeitlin_*.png

1. ``zeitlin_rossby_haurwitz.png``: a Rossby–Haurwitz wave (degree 4) on a non-rotating
   sphere, on rotating ones (eastward and westward) and in the quasi-geostrophic model:
   the measured eastward phase against the exact ``c t``, and the wave along the equator
   at ``t = 0`` and ``t = T``.
2. ``zeitlin_forced.png``: forcing in degrees 8..10 with drag and hyperviscosity, N = 32:
   enstrophy against time with the closed-form steady level of forcing + drag alone, and
   the final relative vorticity.

Needs matplotlib; about a minute on one core.
"""

from __future__ import annotations

import math
from pathlib import Path

import lieflow_zeitlin as lz
import numpy as np
from matplotlib.figure import Figure

import lieflow as lf
from lieflow.flows import SchemeFlow, Splitting

OUT = Path(__file__).resolve().parents[3] / "docs" / "img"


def rossby_haurwitz() -> Path:
    N, l, a, eps, h, steps = 24, 4, 1.0, 0.1, 0.05, 200
    cases = [
        ("Euler", 0.0, 0.0),
        ("Ω = 0.5", 0.5, 0.0),
        ("Ω = 6 (west)", 6.0, 0.0),
        ("QG, Ω = 6, F = 10", 6.0, 10.0),
    ]
    grid = lz.SphereGrid.for_size(N)
    theta, phi = np.meshgrid(grid.theta, grid.phi, indexing="ij")
    zeta = a * np.cos(theta) + eps * np.sin(theta) ** l * np.cos(l * phi)
    W_rel = lz.grid_to_matrix(zeta, grid, N)
    fig = Figure(figsize=(10, 3.6), layout="constrained")
    ax_phase, ax_wave = fig.subplots(1, 2)
    t = h * np.arange(steps + 1)
    lon = np.linspace(0, 2 * math.pi, 361)
    for k, (label, rotation, lamb) in enumerate(cases):
        system = lz.EulerZeitlin(N, rotation=rotation, lamb=lamb)
        sol = lf.integrate(
            system, lf.schemes.get("gauss2"), system.from_relative(W_rel), h, steps=steps
        )
        coeff = lz.matrix_to_sh(system.relative(sol.W))[:, lz.lm_index(l, l)]
        shift = -np.unwrap(np.angle(coeff / coeff[0])) / l
        L = l * (l + 1)
        c = ((a / 2) * (L - 2) - 2 * rotation) / (L + lamb)
        color = f"C{k}"
        ax_phase.plot(
            t, np.degrees(shift), color=color, lw=2.5, alpha=0.5, label=f"{label}: lieflow"
        )
        ax_phase.plot(t, np.degrees(c * t), "k:", lw=1)
        # the wave along the equator from the m = ±l coefficients: 2 Re(c_ll Y_ll(π/2, φ))
        y_ll = _y_ll_equator(l)
        wave = 2 * (coeff[-1] * y_ll * np.exp(1j * l * lon)).real
        if k == 0:
            ax_wave.plot(
                np.degrees(lon),
                2 * (coeff[0] * y_ll * np.exp(1j * l * lon)).real,
                "k",
                lw=1,
                label="t = 0",
            )
        ax_wave.plot(
            np.degrees(lon), wave, color=color, lw=2.5, alpha=0.6, label=f"{label}, t = {t[-1]:g}"
        )
        exact = 2 * (coeff[0] * y_ll * np.exp(1j * l * (lon - c * t[-1]))).real
        ax_wave.plot(np.degrees(lon), exact, "k:", lw=1)
    ax_phase.set(
        xlabel="fluid time t",
        ylabel="eastward displacement (degrees)",
        title=f"Rossby–Haurwitz wave, l = {l}, N = {N}, gauss2, h = {h}",
    )
    ax_phase.legend(fontsize=8, title="dotted: exact c t", title_fontsize=8)
    ax_wave.set(
        xlabel="longitude (degrees)",
        ylabel="wave part of ζ on the equator",
        xlim=(0, 180),
        title="dotted: exact, shifted by c t",
    )
    ax_wave.legend(fontsize=8)
    path = OUT / "zeitlin_rossby_haurwitz.png"
    fig.savefig(path, dpi=110)
    return path


def _y_ll_equator(l: int) -> complex:
    from scipy.special import sph_harm_y

    return complex(sph_harm_y(l, l, math.pi / 2, 0.0))


def forced() -> Path:
    N, h, steps = 32, 0.05, 3000
    mu, nu4, sigma = 0.05, 2e-7, 0.08
    system = lz.EulerZeitlin(N)
    forcing = lz.StochasticForcing(system, amplitude=sigma, l1=8, l2=10, seed=1)
    cons = SchemeFlow(system, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(rtol=1e-12))
    damping = Splitting.lie(
        lz.LinearDrag(system, mu=mu), lz.Hyperviscosity(system, nu=nu4, order=2)
    )
    split = Splitting.strang(damping, cons)
    split = Splitting.lie(split, forcing)
    W = np.zeros((N, N), dtype=complex)
    state = split.init(W)
    Z = np.empty(steps + 1)
    Z[0] = 0.0
    for k in range(steps):
        W, state, _ = split.step(W, k * h, h, state)
        Z[k + 1] = system.enstrophy(W)
    steady = (N / (4 * math.pi)) * sigma**2 * forcing.modes / (2 * mu)
    fig = Figure(figsize=(10, 3.6), layout="constrained")
    ax_z, ax_map = fig.subplots(1, 2, width_ratios=[1, 1.3])
    t = h * np.arange(steps + 1)
    ax_z.plot(t, Z, lw=1, label="lieflow: Strang(drag + hyperviscosity, midpoint) + forcing")
    ax_z.axhline(steady, color="k", ls=":", label="forcing + drag alone: (N/4π)σ²n/(2μ)")
    ax_z.set(
        xlabel="fluid time t",
        ylabel="enstrophy ||W||²_F",
        title=f"forced-dissipative run, N = {N}, degrees 8–10, μ = {mu}",
    )
    ax_z.legend(fontsize=8, loc="lower right")
    grid = lz.SphereGrid(90, 180, "equiangular")
    field = lz.matrix_to_grid(W, grid)
    vmax = float(np.max(np.abs(field)))
    im = ax_map.imshow(
        field, extent=(0, 360, -90, 90), cmap="RdBu_r", vmin=-vmax, vmax=vmax, aspect="auto"
    )
    ax_map.set(xlabel="longitude", ylabel="latitude", title=f"relative vorticity at t = {t[-1]:g}")
    fig.colorbar(im, ax=ax_map)
    path = OUT / "zeitlin_forced.png"
    fig.savefig(path, dpi=110)
    return path


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    for make in (rossby_haurwitz, forced):
        print(make())
