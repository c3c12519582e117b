r"""Compiled ``B`` of :class:`~lieflow_zeitlin.EulerZeitlin` for lieflow's compiled engine
(imported only by :meth:`EulerZeitlin.compiled_B`, so numba stays optional).

It follows lieflow's compiled-map convention ``f(W, params, out)`` (see
:meth:`lieflow.IsospectralSystem.compiled_B`) for ``complex128`` data: ``W`` and ``out`` are
C-contiguous ``(N, N)``, and :func:`zeitlin_B` writes

.. math:: B(V) - c V,\qquad B(V) = \sigma (\Delta_N - F)^{+}(V - F_f),\qquad
          V = \tfrac12 (W - W^\dagger) - \tfrac{\operatorname{tr}}{N} I

(``V``: the su(N) projection of the stage value; ``c``: a Casimir shift). The solve is
:meth:`HoppeYauLaplacian.solve <lieflow_zeitlin.HoppeYauLaplacian.solve>` written out: the
trace removed, the ``N²`` entries copied into the packed ``(N, N+1)`` layout, the same
partitioned Thomas sweeps (:func:`lieflow_zeitlin.laplacian._sweep_loops`, compiled) with the
same factors (``σ`` is in them), the trace removed again.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lieflow.engines.compiled import linked_function, skew_hermitian_part
from lieflow.numba_cache import cached_njit

from . import laplacian

#: The partitioned sweeps of :meth:`HoppeYauLaplacian.solve`, compiled (the numpy path's
#: compilation, :func:`lieflow_zeitlin.laplacian.sweep_kernel`), which ``zeitlin_B`` calls
#: by their symbol (:func:`lieflow.engines.compiled.linked_function`): linked into it by
#: name, their code would be optimized and generated a second time (issue 37 item 11).
_sweep_compiled = laplacian.sweep_kernel("d")
_sweeps = linked_function(
    "lieflow_zeitlin_sweeps_f8", _sweep_compiled, _sweep_compiled.nopython_signatures[0]
)

#: ``params = [c, nb, b, 1, Im diag F_f (N entries), factors]`` (the ``(4, nb, b, 2(N+1))``
#: stack of the sweeps' factors, flattened; :func:`params`); the ``1`` is the parameter
#: of ``lieflow.engines.compiled.skew_hermitian_part`` that removes the trace.
HEADER = 4


def params(shift: float, planetary: Any, factors: Any) -> Any:
    """The ``params`` vector of :func:`zeitlin_B`: the shift ``c``, the block layout of the
    factors, the imaginary diagonal of the planetary vorticity matrix ``F_f`` and the
    double-precision compact factors of the partitioned sweeps
    (``_BlockedFactor.compact``, ``(4, nb, b, 2(N+1))``)."""
    nb, b = factors.shape[1:3]
    parts = [np.array([shift, nb, b, 1.0], dtype=float), np.imag(np.diagonal(planetary))]
    return np.concatenate([*parts, np.ravel(factors)]).astype(np.float64)


@cached_njit
def zeitlin_B(W: Any, params: Any, out: Any) -> None:
    """``out = B(V) - c V`` for the su(N) projection ``V`` of ``W`` (module docs)."""
    N = W.shape[0]
    C = N + 1
    shift = params[0]
    nb, b = int(params[1]), int(params[2])
    skew_hermitian_part(W, params[3:4], out)  # V, the su(N) projection, into out
    # the right-hand side V - F_f in the packed layout (zero past its N² entries), trace
    # removed (solve); np.empty and a loop, not np.zeros: one compiled numpy function less
    # (a first run's compile time, issue 37 item 11)
    buf = np.empty(nb * b * C, dtype=np.complex128)
    for i in range(N):
        for j in range(N):
            buf[i * N + j] = out[i, j]
    for k in range(N * N, buf.size):
        buf[k] = 0.0
    mean = 0.0j
    for i in range(N):
        buf[i * C] -= 1j * params[HEADER + i]
        mean += buf[i * C]
    mean = mean / N
    for i in range(N):
        buf[i * C] -= mean
    # the sweeps' factors (4, nb, b, 2(N+1)) of params
    size = nb * b * 2 * C
    factors = params[HEADER + N : HEADER + N + 4 * size].reshape(4, nb, b, 2 * C)
    rows = buf.view(np.float64).reshape(1, nb, b, 2 * C)
    _sweeps(rows)(1, rows, factors)
    mean = 0.0j
    for i in range(N):
        mean += buf[i * C]
    mean = mean / N
    for i in range(N):
        buf[i * C] -= mean
    for i in range(N):
        for j in range(N):
            out[i, j] = buf[i * N + j] - shift * out[i, j]
