"""Long runs that decide whether the conjugation update (SPEC §4.7) with an inexact solve
may be the default (issue 27, item 3): converged (commutator update, ``rtol = 1e-14``)
against inexact (conjugation update, ``rtol = 1e-4 … 1e-8``) at equal step.

``python -m benchmarks.conjugation_long_runs [--quick]`` writes ``docs/img/conjugation_*.png``
and prints the markdown tables of ``docs/conjugation.md``:

* the relative energy error over the run, summarised by its maximum over each quarter of
  the run and by the exponent ``p`` of a fit ``max_{s <= t} |e(s)| ~ t^p`` over the second
  half (``p ≈ 0``: bounded; ``p ≈ 1``: secular, linear drift; ``0.5``: a random walk);
* the Casimir drift (max over ``tr W^k``, ``k = 2 … 5``);
* the Lie–Poisson defect of the step map ``Φ`` (cold start, ``k`` fixed-point updates,
  then the update): ``||J Π(W0) J^T − Π(W1)||_F / ||Π(W1)||_F`` with ``J`` the Jacobian of
  ``Φ`` at ``W0`` in an orthonormal basis ``e_a`` of the algebra (central differences) and
  ``Π(W)_ab = <W, [e_a, e_b]>`` the Lie–Poisson bivector. A Poisson map has defect 0; the
  differences' own error (~1e-10 here) is the floor.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

import lieflow as lf
from lieflow.app.reproduce import Case
from lieflow.chunks import Diagnostics
from lieflow.schemes import SyDIRK
from lieflow.schemes.sydirk import MidpointProblem

IMG = Path(__file__).resolve().parent.parent / "docs" / "img"
TODA_W0 = np.array([[-1.0, -1, 0, 1], [-1, 1, 1, 0], [0, 1, -1, -1], [1, 0, -1, 1]])
#: (label, update, rtol) of the compared runs.
VARIANTS = (
    ("converged", "commutator", 1e-14),
    ("conjugation rtol=1e-8", "conjugation", 1e-8),
    ("conjugation rtol=1e-6", "conjugation", 1e-6),
    ("conjugation rtol=1e-4", "conjugation", 1e-4),
)


def growth_exponent(t: np.ndarray, e: np.ndarray) -> float:
    """``p`` of ``max_{s <= t} |e(s)| ~ t^p``, fitted over the second half of the run."""
    env = np.maximum.accumulate(np.abs(e))
    half = slice(len(t) // 2, None)
    keep = env[half] > 0
    if keep.sum() < 2:
        return math.nan
    return float(np.polyfit(np.log(t[half][keep]), np.log(env[half][keep]), 1)[0])


def long_run(
    title: str,
    system: lf.IsospectralSystem,
    W0: np.ndarray,
    h: float,
    steps: int,
    saves: int,
) -> tuple[list[str], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The variants' runs: table rows and the energy-error curves."""
    rows = []
    curves = {}
    diag = Diagnostics.of(system, W0)
    for label, update, rtol in VARIANTS:
        scheme = SyDIRK(update=update)
        start = time.perf_counter()
        sol = lf.integrate(
            system, scheme, W0, h, steps=steps, solver=lf.solvers.FixedPoint(rtol=rtol),
            save_every=max(1, steps // saves), diagnostics=False,
        )  # fmt: skip
        seconds = time.perf_counter() - start
        e = np.asarray(diag.energy_error(np.asarray(system.hamiltonian(sol.W))))
        e_signed = np.asarray(system.hamiltonian(sol.W)) / float(system.hamiltonian(W0)) - 1
        cas = float(np.max(diag.casimir_drift(np.asarray(system.casimirs(sol.W)))))
        t = np.asarray(sol.t)
        quarters = [float(np.max(q)) for q in np.array_split(e[1:], 4)]
        p = growth_exponent(t[1:], e_signed[1:])
        curves[label] = (t, e)
        rows.append(
            f"| {title} | {label} | {float(np.mean(sol.iterations)):.2f} | "
            + " / ".join(f"{q:.1e}" for q in quarters)
            + f" | {p:.2f} | {cas:.1e} | {seconds:.1f} s |"
        )
        print(rows[-1], flush=True)
    return rows, curves


def _basis(algebra: lf.LieAlgebra) -> np.ndarray:
    """An orthonormal (Frobenius) basis of the algebra, ``(d, n, n)``."""
    n = algebra.n
    dtype = algebra.dtype
    out = []
    for i in range(n):
        for j in range(n):
            for unit in (1.0, 1j) if dtype.kind == "c" else (1.0,):
                E = np.zeros((n, n), dtype=dtype)
                E[i, j] = unit
                out.append(algebra.project(E).ravel())
    # orthonormalize the spanning set in the real inner product Re tr(A^† B)
    M = np.array(out)
    real = np.concatenate([M.real, M.imag], axis=1) if dtype.kind == "c" else M
    u, s, _vt = np.linalg.svd(real.T, full_matrices=False)
    u = u[:, s > 1e-10 * s[0]]
    if dtype.kind == "c":
        half = u.shape[0] // 2
        u = u[:half] + 1j * u[half:]
    return u.T.reshape(-1, n, n)


def _coords(basis: np.ndarray, W: np.ndarray) -> np.ndarray:
    return np.real(np.einsum("aij,ij->a", basis.conj(), W))


def _bivector(basis: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``Π(W)_ab = <W, [e_a, e_b]>``."""
    E = basis
    comm = np.einsum("aij,bjk->abik", E, E) - np.einsum("bij,ajk->abik", E, E)
    return np.real(np.einsum("ij,abij->ab", W.conj(), comm))


def step_map(
    system: lf.IsospectralSystem, h: float, updates: int | None, update: str
) -> Callable[[np.ndarray], np.ndarray]:
    """One midpoint step from the cold guess: ``updates`` fixed-point updates (``None``:
    solved to roundoff), then the ``update`` (``"commutator"`` or ``"conjugation"``)."""

    def phi(W0: np.ndarray) -> np.ndarray:
        problem = MidpointProblem(system, W0, h)
        x = problem.x0
        if updates is None:
            res = lf.solvers.FixedPoint(rtol=1e-15).solve(problem)
            x = res.x
        else:
            for _ in range(updates):
                x = problem.map(x)
        return problem.update(x) if update == "commutator" else problem.conjugation_update(x)

    return phi


def poisson_defect(
    system: lf.IsospectralSystem, W0: np.ndarray, phi: Callable[[np.ndarray], np.ndarray]
) -> float:
    basis = _basis(system.algebra)
    W1 = phi(W0)
    eps = 1e-5 * float(np.linalg.norm(W0))
    cols = []
    for e in basis:
        cols.append(
            (_coords(basis, phi(W0 + eps * e)) - _coords(basis, phi(W0 - eps * e))) / (2 * eps)
        )
    J = np.array(cols).T
    P0, P1 = _bivector(basis, W0), _bivector(basis, W1)
    return float(np.linalg.norm(J @ P0 @ J.T - P1) / np.linalg.norm(P1))


def defects(title: str, system: lf.IsospectralSystem, W0: np.ndarray, h: float) -> list[str]:
    rows = []
    for updates in (1, 2, 3, 5, None):
        vals = [poisson_defect(system, W0, step_map(system, h, updates, u)) for u in
                ("commutator", "conjugation")]  # fmt: skip
        k = "solved (rtol 1e-15)" if updates is None else str(updates)
        rows.append(f"| {title} | {k} | {vals[0]:.1e} | {vals[1]:.1e} |")
        print(rows[-1], flush=True)
    return rows


def plot(curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for label, (t, e) in curves.items():
        ax.loglog(t[1:], np.maximum(e[1:], 1e-17), label=label, lw=0.8)
    ax.set_xlabel("t")
    ax.set_ylabel("relative energy error")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short runs (a smoke test)")
    parser.add_argument("--only", choices=("so10", "toda", "zeitlin", "defect"), default=None)
    args = parser.parse_args(argv)
    q = args.quick
    IMG.mkdir(parents=True, exist_ok=True)
    header = (
        "| system | variant | updates/step | energy error by quarter | growth p | "
        "Casimir drift | wall time |\n|---|---|---|---|---|---|---|"
    )
    cases: list[tuple[str, str, Any, np.ndarray, float, int]] = []
    if args.only in (None, "so10"):
        grb, W = Case("generalized_rigid_body", "", 10, 0.01, 1, 1e-14).build(0)
        n = 2000 if q else 100_000
        cases.append(("so10", "so(10) body, midpoint h = 0.1", grb, W, 0.1, n))
        cases.append(("so10_h04", "so(10) body, midpoint h = 0.4", grb, W, 0.4, n))
    if args.only in (None, "toda"):
        toda = lf.systems.get("periodic_toda")
        cases.append(
            ("toda", "Toda n = 4, midpoint h = 0.1", toda, TODA_W0, 0.1, 2000 if q else 100_000)
        )
    if args.only in (None, "zeitlin"):
        import lieflow_zeitlin as lz

        N = 16 if q else 64
        ez = lf.systems.get("euler_zeitlin", N=N, time="fluid")
        W = lz.random_vorticity(N, degree=8, seed=0)
        cases.append(
            (
                "zeitlin",
                f"Euler–Zeitlin N = {N}, midpoint h = 1/32",
                ez,
                W,
                1 / 32,
                500 if q else 20_000,
            )
        )
    for key, title, system, W0, h, steps in cases:
        print(header, flush=True)
        _rows, curves = long_run(title, system, W0, h, steps, 2000)
        plot(curves, f"{title}, {steps} steps", IMG / f"conjugation_{key}.png")
    if args.only in (None, "defect"):
        print("| system | updates | defect, commutator update | defect, conjugation update |")
        print("|---|---|---|---|")
        grb, W = Case("generalized_rigid_body", "", 10, 0.01, 1, 1e-14).build(0)
        defects("so(10) body, h = 0.1", grb, W, 0.1)
        import lieflow_zeitlin as lz

        ez = lf.systems.get("euler_zeitlin", N=8, time="fluid")
        defects(
            "Euler–Zeitlin N = 8, h = 1/32", ez, lz.random_vorticity(8, degree=4, seed=0), 1 / 32
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
