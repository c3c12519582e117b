r"""The underflow guard: entries far below a matrix's largest set to zero before it enters a
product, so that no product of kept entries (nor any partial sum of one) is a subnormal
number.

Why
---
Smooth states of large Euler–Zeitlin systems hold entries spanning hundreds of decades (the
field of ``benchmarks.device`` at N = 1024 after a few steps: entries down to ``1e-280``
times the largest, 9.6 % of them below ``1e-150``). In a matrix product their products and
partial sums fall below ``2^-1022``, into the subnormal range, and Intel cores pay a
microcode assist for each such operation: ``B(W) @ W`` took 73 ms against 11.9 ms for
random matrices of the size on a 16-core Xeon (issue 38; AMD cores pay nothing).

The rule (:func:`flush_tiny`)
-----------------------------
For a matrix ``X`` (each matrix of a stack on its own) let ``t = τ · max |x|`` over all real
numbers ``x`` of ``X`` (real and imaginary parts apart). Every real number ``|x| < t`` is
set to zero; the others are kept bit for bit. ``τ`` is the system's
:attr:`~lieflow.IsospectralSystem.underflow_guard` (0: off, nothing is touched); the default
for systems that use it is :data:`TAU` ``= 2^-332 ≈ 1.1e-100`` (the ``1e-100`` measured in
issue 38, as a power of two).

**No product changes by more than roundoff.** Zeroing entries of ``A`` below ``τ max|A|``
changes ``A`` by ``ΔA`` with ``|Δa_ij| < τ max|A|``, so each entry of ``AB`` (``n`` terms)
changes by less than ``n τ max|A| max|B| ≤ n τ ‖A‖_F ‖B‖_F`` (twice that for complex
entries), while the rounding error of the product itself is bounded by
``γ_n ‖A‖_F ‖B‖_F ≈ n ε ‖A‖_F ‖B‖_F`` (Higham, *Accuracy and Stability of Numerical
Algorithms*, §3.5). The change is ``τ / ε = 2^-332 / 2^-52 = 2^-280`` of that bound: about
``5e-85`` of roundoff. The same holds for the map's result and for the step, whose
difference from the unguarded one stays ``≤ 2^-280`` of the unguarded rounding errors per
guarded product (measured: ``tests/test_underflow.py``).

**Products of kept entries cannot go subnormal.** Every real number ``|x| ≥ 2^e`` is a
multiple of ``2^(e-52)``, so the exact product of kept real numbers ``|a| ≥ 2^e_a``,
``|b| ≥ 2^e_b`` is a multiple of ``2^(e_a+e_b-104)``; if ``e_a + e_b ≥ -918`` it is a
multiple of ``2^-1022``. Sums of multiples of ``2^-1022`` are multiples of ``2^-1022``, and
rounding one to double precision gives a multiple of ``2^-1022`` again (below ``2^-970``
such a number has at most 52 significant bits and is exact; above, the spacing of doubles
is at least ``2^-1022``). By induction every partial sum of the product — in any order,
with or without fused multiply-adds — is zero or at least ``2^-1022`` in magnitude: never
subnormal. Kept entries satisfy ``|a| ≥ τ max|A|``, ``|b| ≥ τ max|B|``, so the condition
``|a b| ≥ 2^-916`` (which gives ``e_a + e_b ≥ -918``) holds whenever

.. math:: \max|A| \cdot \max|B| \ \ge\ 2^{-916} / τ^2 = 2^{-252} \approx 1.4 \times 10^{-76},

i.e. for a state of any physical scale (it takes ``max|W| max|B(W)| < 1e-76`` to break it:
a vorticity of ``1e-38`` in fluid time units). Zeros stay zeros
(``0 · b = 0`` is exact).

**Isospectrality** is a property of the scheme's update, which the guard does not touch:
the fixed point is that of a map perturbed by ``2^-280`` of its roundoff, and the step's
Casimirs and spectrum move by roundoff as before (tested).

Where
-----
:class:`~lieflow.schemes.base.StageProblem` applies it to the operands of every product
the stage maps form through it (its ``B`` and its commutator update) and the midpoint map to
its iterate, ``B`` and ``BM``: every engine that runs these maps (NumPy, the array-API
path, a traced program) inherits it.

Cost: a pass for the largest entry and one writing the result per guarded matrix; with
numba installed one compiled, multi-threaded pass pair on NumPy arrays (the same numbers:
a maximum and a comparison do not depend on the order of evaluation).
"""

from __future__ import annotations

import functools
import importlib.util
from types import ModuleType

import numpy as np

from .algebras import Array
from .backends import device_of, is_numpy, namespace

#: The default relative threshold of systems that use the guard: ``2^-332 ≈ 1.1e-100``
#: (module docs: ``2^-280`` of roundoff; no subnormal product above a scale of ``1e-76``).
TAU = 2.0**-332


def flush_tiny(X: Array, tau: float, in_place: bool = False) -> Array:
    """``X`` with every real number (real and imaginary parts apart) below ``tau`` times the
    largest of its matrix (the last two axes) set to zero (module docs). ``in_place``: ``X``
    (a contiguous NumPy array the caller owns) is overwritten and returned; else a new
    array, or ``X`` itself when nothing is below (NumPy). Matrices whose largest entry is
    not finite are left as they are."""
    if is_numpy(X):
        X = np.asarray(X)
        if X.dtype.kind not in "fc" or X.size == 0:
            return X
        real = _real_rows(X)
        kernels = _kernels()
        if kernels is None:
            top = np.maximum(real.max(axis=-1), -real.min(axis=-1))
            limit = np.where(np.isfinite(top), tau * top, 0.0)[:, None]
            small = np.abs(real) < limit
            small &= real != 0
            if not small.any():
                return X
            out = real if in_place else real.copy()
            np.copyto(out, 0.0, where=small)
        else:
            groups = kernels.work_groups(real.size)
            limits = kernels.limits(groups, real, float(tau))
            if in_place:
                out = real
            elif kernels.count_below(real, limits):
                out = np.empty_like(real)
            else:
                return X
            kernels.flush(groups, real, limits, out, in_place)
        return out.view(X.dtype).reshape(X.shape)
    return _flush_array_api(X, tau)


def _real_rows(X: np.ndarray) -> np.ndarray:
    """The real numbers of each matrix of ``X`` as the rows of a 2-D array (a view of a
    contiguous ``X``)."""
    X = np.ascontiguousarray(X)
    rows = int(np.prod(X.shape[:-2], dtype=np.int64))
    real = X.view(X.real.dtype) if X.dtype.kind == "c" else X
    return real.reshape(rows, -1)


def _flush_array_api(X: Array, tau: float) -> Array:
    """:func:`flush_tiny` through the array API (any library, traceable: no host values)."""
    xp = namespace(X)
    axes = (-2, -1)
    complex_data = xp.isdtype(X.dtype, "complex floating")
    parts = (xp.real(X), xp.imag(X)) if complex_data else (X,)
    top = parts[0]
    top = xp.max(xp.abs(parts[0]), axis=axes, keepdims=True)
    for p in parts[1:]:
        top = xp.maximum(top, xp.max(xp.abs(p), axis=axes, keepdims=True))
    limit = xp.where(xp.isfinite(top), tau * top, xp.zeros_like(top))
    small = [xp.abs(p) < limit for p in parts]
    kept = [xp.where(s, xp.zeros_like(p), p) for s, p in zip(small, parts, strict=True)]
    if not complex_data:
        return kept[0]
    unit = xp.asarray(1j, dtype=X.dtype, device=device_of(X))
    rebuilt = xp.astype(kept[0], X.dtype) + xp.astype(kept[1], X.dtype) * unit
    # entries with nothing flushed keep their exact bits (signed zeros, non-finite parts)
    return xp.where(small[0] | small[1], rebuilt, X)


@functools.cache
def _kernels() -> ModuleType | None:
    """The compiled loops (:mod:`lieflow._underflow_kernel`) where numba is installed, else
    ``None`` (NumPy operations: the same numbers, more passes)."""
    if importlib.util.find_spec("numba") is None:
        return None
    from . import _underflow_kernel

    return _underflow_kernel
