"""The paper's block algorithm *as published*: the baseline every speed ratio is taken against.

This is benchmark code, not library code. It follows the paper's section "Block Algorithm for
ISOSyRKs" literally:

* the unknown is the dense ``sn×sn`` matrix ``M``; ``𝔸 = A ⊗ I_n`` and the block-diagonal
  ``𝔹 = blockdiag(B(M_11), …, B(M_ss))`` are dense ``sn×sn`` matrices, and ``𝔹`` together
  with the products ``𝔸𝔹`` and ``𝔹𝔸^T`` is rebuilt at every iteration;
* the fixed-point map is ``C(M) = M - G(h, M)`` with
  ``G(h, M) = (I - h𝔸𝔹) M (I + h𝔹𝔸^T) - 𝕎_0``: four dense ``sn×sn`` products per iteration;
* every step starts cold from ``M = 𝕎_0`` (every block ``W0``);
* the update is ``W1 = W0 + h Σ_i b_i [B(M_ii), M_ii]``.

The stopping rule is lieflow's (SPEC §5), so iteration counts are comparable: stop when the
relative increment ``||M_{k+1} - M_k||_F <= rtol ||M_{k+1}||_F``, or accept a stagnation at
roundoff (no new minimum for ``patience`` updates while the best increment is below
``256 eps``). Iterations count updates performed.

The 1-stage case (``A = [1/2]``) is the minimal-variable midpoint rule; the 7-stage SyDIRK
is, as in the paper, a composition of such midpoint steps (:class:`PaperScheme` with
``composition=True``).
"""

from __future__ import annotations

import time

import attrs
import numpy as np
import scipy.linalg

from lieflow import IsospectralSystem
from lieflow.tableaus import ButcherTableau

_ROUNDOFF = 256 * float(np.finfo(float).eps)


class BaselineDivergedError(RuntimeError):
    """The as-published iteration did not converge within its iteration cap."""


@attrs.frozen
class PaperStep:
    """One step of the as-published algorithm: the new state and the updates it took."""

    W: np.ndarray = attrs.field(repr=False)
    iterations: int


@attrs.frozen
class PaperRun:
    """A run of :func:`paper_integrate`: final state, updates per step and wall time."""

    W: np.ndarray = attrs.field(repr=False)
    iterations: np.ndarray = attrs.field(repr=False)
    wall_time: float

    @property
    def steps(self) -> int:
        """Number of steps taken."""
        return int(self.iterations.size)


@attrs.frozen
class PaperScheme:
    """A scheme of the paper, implemented as published.

    Parameters
    ----------
    tableau : ButcherTableau
        The Runge–Kutta tableau. With ``composition=False`` the whole tableau is one dense
        block equation; with ``composition=True`` the tableau must be a composition of
        midpoint steps (a SyDIRK) and each sub-step of size ``b_i h`` is a 1-stage block
        equation, as the paper implements its 7s-SyDIRK.
    composition : bool
        Whether to step through the tableau's midpoint sub-steps one at a time.
    rtol : float
        Relative increment tolerance.
    max_iter : int
        Iteration cap per solve; exceeding it raises :class:`BaselineDivergedError`.
    patience : int
        Updates without a new smallest increment before stagnation is declared.
    """

    tableau: ButcherTableau
    composition: bool = False
    rtol: float = 1e-14
    max_iter: int = 100
    patience: int = 6

    @property
    def name(self) -> str:
        """``paper_<tableau name>``."""
        return f"paper_{self.tableau.name}"

    def step(self, W0: np.ndarray, h: float, system: IsospectralSystem) -> PaperStep:
        """Advance ``W0`` (one ``n×n`` matrix) by one step of size ``h``."""
        if not self.composition:
            return dense_block_step(
                system,
                W0,
                h,
                self.tableau.A,
                self.tableau.b,
                self.rtol,
                self.max_iter,
                self.patience,
            )
        W, total = W0, 0
        half = np.array([[0.5]])
        one = np.array([1.0])
        for bi in self.tableau.b:
            sub = dense_block_step(
                system, W, bi * h, half, one, self.rtol, self.max_iter, self.patience
            )
            W, total = sub.W, total + sub.iterations
        return PaperStep(W, total)


def dense_block_step(
    system: IsospectralSystem,
    W0: np.ndarray,
    h: float,
    A: np.ndarray,
    b: np.ndarray,
    rtol: float = 1e-14,
    max_iter: int = 100,
    patience: int = 6,
) -> PaperStep:
    """One step of the block algorithm with dense ``sn×sn`` matrices (see the module notes).

    Parameters
    ----------
    system : IsospectralSystem
        Provides ``B``.
    W0 : ndarray, shape (n, n)
        Current state.
    h : float
        Step size.
    A, b : ndarray
        Runge–Kutta coefficients, shapes ``(s, s)`` and ``(s,)``.
    rtol, max_iter, patience
        Stopping rule (module notes).

    Returns
    -------
    PaperStep
    """
    s, n = A.shape[0], W0.shape[-1]
    eye = np.eye(s * n, dtype=W0.dtype)
    bold_A = np.kron(A, np.eye(n))
    W0_bold = np.tile(W0, (s, s))
    M = W0_bold.copy()
    best, since_best = np.inf, 0
    for k in range(1, max_iter + 1):
        bold_B = scipy.linalg.block_diag(*_stage_B(system, M, s, n))
        left = eye - h * (bold_A @ bold_B)
        right = eye + h * (bold_B @ bold_A.T)
        G = left @ M @ right - W0_bold
        new = M - G
        rel = float(np.linalg.norm(new - M) / max(np.linalg.norm(new), np.finfo(float).tiny))
        M = new
        if not np.isfinite(rel):
            break
        if rel <= rtol:
            return PaperStep(_update(system, W0, M, h, b, s, n), k)
        if rel < best:
            best, since_best = rel, 0
        else:
            since_best += 1
        if since_best >= patience:
            if best <= _ROUNDOFF:
                return PaperStep(_update(system, W0, M, h, b, s, n), k)
            break
    raise BaselineDivergedError(f"dense block iteration failed to converge (h = {h}, s = {s})")


def _stage_B(system: IsospectralSystem, M: np.ndarray, s: int, n: int) -> list[np.ndarray]:
    return [system.B(M[i * n : (i + 1) * n, i * n : (i + 1) * n]) for i in range(s)]


def _update(
    system: IsospectralSystem,
    W0: np.ndarray,
    M: np.ndarray,
    h: float,
    b: np.ndarray,
    s: int,
    n: int,
) -> np.ndarray:
    W1 = W0.copy()
    for i, Bi in enumerate(_stage_B(system, M, s, n)):
        Mi = M[i * n : (i + 1) * n, i * n : (i + 1) * n]
        W1 += h * b[i] * (Bi @ Mi - Mi @ Bi)
    return W1


def paper_integrate(
    system: IsospectralSystem,
    scheme: PaperScheme | PlainScheme,
    W0: np.ndarray,
    h: float,
    steps: int,
) -> PaperRun:
    """Take ``steps`` steps of ``scheme`` from ``W0`` (no diagnostics, no saving).

    Raises
    ------
    BaselineDivergedError
        If a step does not converge.
    """
    W = np.array(W0)
    iterations = np.zeros(steps, dtype=np.int64)
    start = time.perf_counter()
    for k in range(steps):
        res = scheme.step(W, h, system)
        W, iterations[k] = res.W, res.iterations
    return PaperRun(W, iterations, time.perf_counter() - start)


# -- the plain-numpy reduced stage form -----------------------------------------------------


def plain_reduced_step(
    system: IsospectralSystem,
    W0: np.ndarray,
    h: float,
    A: np.ndarray,
    b: np.ndarray,
    rtol: float = 1e-14,
    max_iter: int = 100,
    patience: int = 6,
) -> PaperStep:
    """One step of the *reduced stage form* written as a plain numpy prototype.

    The same algorithm as lieflow's default evaluation (SPEC §4.5: ``3s`` products of
    ``n×n`` matrices per iteration) with none of lieflow's machinery: stages
    ``G_i = I + h Σ_j a_ij G_j B_j^†``, ``P_i = W0 − h Σ_j a_ij P_j B_j`` with
    ``B_j = B(G_j^† P_j)``, iterated from the cold start ``(I, W0)`` under the module's
    stopping rule; ``W1 = W0 + h Σ_i b_i [B_i, W_i]`` with ``W_i = G_i^† P_i``. Beside the
    dense as-published algorithm it separates what the algorithm change is worth from what
    lieflow's implementation adds.
    """
    s, n = A.shape[0], W0.shape[-1]
    eye = np.eye(n, dtype=W0.dtype)
    hA = h * np.asarray(A, dtype=float)
    G = np.broadcast_to(eye, (s, n, n)).copy()
    P = np.broadcast_to(W0, (s, n, n)).copy()
    best, since_best = np.inf, 0
    for k in range(1, max_iter + 1):
        B = system.B(np.conj(np.swapaxes(G, -1, -2)) @ P)
        GB = G @ np.conj(np.swapaxes(B, -1, -2))
        PB = P @ B
        G_new = eye + np.einsum("ij,jab->iab", hA, GB)
        P_new = W0 - np.einsum("ij,jab->iab", hA, PB)
        num = np.sqrt(np.linalg.norm(G_new - G) ** 2 + np.linalg.norm(P_new - P) ** 2)
        den = np.sqrt(np.linalg.norm(G_new) ** 2 + np.linalg.norm(P_new) ** 2)
        rel = float(num / max(den, np.finfo(float).tiny))
        G, P = G_new, P_new
        if not np.isfinite(rel):
            break
        done = rel <= rtol
        if not done:
            if rel < best:
                best, since_best = rel, 0
            else:
                since_best += 1
            done = since_best >= patience and best <= _ROUNDOFF
            if since_best >= patience and not done:
                break
        if done:
            Ws = np.conj(np.swapaxes(G, -1, -2)) @ P
            Bs = system.B(Ws)
            W1 = W0 + h * np.einsum("i,iab->ab", np.asarray(b, dtype=float), Bs @ Ws - Ws @ Bs)
            return PaperStep(W1, k)
    raise BaselineDivergedError(f"plain reduced iteration failed to converge (h = {h}, s = {s})")


@attrs.frozen
class PlainScheme:
    """A scheme of the paper as a plain numpy prototype of the reduced stage form (Gauss
    tableaus as one system of ``s`` stages; SyDIRKs as compositions of midpoint steps)."""

    tableau: ButcherTableau
    composition: bool = False
    rtol: float = 1e-14
    max_iter: int = 100
    patience: int = 6

    def step(self, W0: np.ndarray, h: float, system: IsospectralSystem) -> PaperStep:
        """Advance ``W0`` by one step of size ``h``."""
        if not self.composition:
            return plain_reduced_step(system, W0, h, self.tableau.A, self.tableau.b,
                                      self.rtol, self.max_iter, self.patience)  # fmt: skip
        W, total = W0, 0
        half, one = np.array([[0.5]]), np.array([1.0])
        for bi in self.tableau.b:
            sub = plain_reduced_step(system, W, bi * h, half, one, self.rtol, self.max_iter,
                                     self.patience)  # fmt: skip
            W, total = sub.W, total + sub.iterations
        return PaperStep(W, total)
