r"""Anderson acceleration of a fixed-point iteration ``x <- F(x)``, as pure functions over
arrays of any array-API library, eager or traced (``jax.jit``, ``lax.while_loop``).

The algorithm (type II, mixing parameter 1; Walker & Ni, SIAM J. Numer. Anal. 49, 2011)
--------------------------------------------------------------------------------------
With residuals ``f_k = g_k - x_k`` of the map values ``g_k = F(x_k)`` and the differences
``Δf_j = f_{j+1} - f_j``, ``Δg_j = g_{j+1} - g_j`` of the last ``m`` updates (the columns of
``ΔF``, ``ΔG``), the next iterate is

.. math:: x_{k+1} = g_k - ΔG\,γ,\qquad γ = \arg\min_γ \lVert f_k - ΔF\,γ\rVert,

the plain update ``g_k`` corrected by the secant information of the last ``m`` steps. Per
update this costs ``O(m · size)``: the new columns are written into a ring buffer of ``m``
slots (:func:`lieflow.backends.put`); one product of the history with ``Δf`` gives the new
row and column of the Gram matrix ``ΔFᵀΔF`` (kept, ``m × m``); the right-hand side is
updated, ``ΔFᵀ f_k = ΔFᵀ f_{k-1} + ΔFᵀ Δf``, with one inner product for the new column; and
one product of ``γ`` with the history ``ΔG`` gives the correction. Inner products are real,
``Re⟨a, b⟩`` (complex unknowns are real vectors of twice the length).

**Keeping the small problem well conditioned.** The normal equations square the condition
number of ``ΔF``, which grows as the columns become dependent (the iteration converges, or
settles on a few slow modes). They carry a Tikhonov term :data:`REGULARIZATION` relative to
each column's squared norm — the system of the normalized columns plus
``REGULARIZATION · I``, solved without the scaling, to which Gaussian elimination is
indifferent: directions in which the normalized columns are dependent to below
``sqrt(REGULARIZATION)`` are damped instead of amplified, so noise in nearly dependent
columns cannot produce a large ``γ``. Old columns leave the ring as new ones arrive.

**Safeguards.** (a) *Restart*: a problem whose residual grew after a mixed update
(``‖f_k‖ > ‖f_{k-1}‖``, the extrapolation was bad) drops its whole history and takes the
plain update ``g_k``; after a plain one growth is the map's own, and the history stays (it
is what lets Anderson converge where the plain iteration does not). (b) *Roundoff*: no
mixing once the relative residual ``‖f_k‖ / ‖g_k‖`` is below :data:`QUIET` machine
epsilons: there the differences are dominated by the rounding errors of ``F`` and an
extrapolation amplifies them; the plain update is as good as any and the stopping rule
ends the iteration. (c) *Only where it pays*: a problem is accelerated (*engaged*) from the
first update whose relative residual shrank by less than :data:`ENGAGE`; a fast
contraction (Euler–Zeitlin at small ``N h``: a few updates per step) is left plain, since
Anderson gains nothing there. Once engaged, a problem stays engaged for the solve. Problems
of fewer than :data:`MIN_SIZE` numbers are never engaged (:func:`accelerates`).

Batches: a stack of problems (leading axes before the ``core_ndim`` axes of one unknown) is
accelerated *per problem*: each has its own Gram matrix, coefficients, restarts and
engagement (independent problems share nothing but the ring's slots).

Interface
---------
``state = start(x0, depth, core_ndim)``, then for each map value ``g = F(x)``:
``state, x = update(state, x, g)``. The state is an :class:`AndersonState` (a
``NamedTuple`` of arrays of fixed shapes, a JAX pytree); ``update`` uses no Python control
flow on array values, no host copies and static shapes, so it traces under ``jax.jit``
inside ``lax.while_loop``. For NumPy, CuPy and PyTorch the history is written in place:
``update`` consumes its state (use the one it returns).
"""

from __future__ import annotations

import functools
import importlib.util
import math
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from ..algebras import Array
from ..backends import device_of, is_numpy, namespace, put, vdot

#: Tikhonov term of the normalized Gram system (unit diagonal): directions in which the
#: normalized difference columns are dependent to below ``sqrt(REGULARIZATION) = 1e-5``
#: are damped. The normal equations are formed to about ``m eps`` absolute on the unit
#: diagonal, so everything kept is resolved to ``1e-6`` relative or better.
REGULARIZATION = 1e-10

#: A problem is accelerated from the first update whose relative residual ``‖f‖ / ‖g‖``
#: shrank by less than this factor: a contraction this slow needs more than about
#: ``log(1e-13) / log(ENGAGE) ≈ 19`` plain updates from scratch (measured: at 0.13 per
#: update, N = 256 and h = 1/64, Anderson took 11 → 8 updates, about what its overhead
#: costs; at 0.25–0.5, 19 → 11 and 33 → 12.5).
ENGAGE = 0.2

#: Problems of fewer real numbers than this (a complex number counts two: Euler–Zeitlin
#: from N = 128, a real n × n problem from n = 182) are never accelerated. Below it, an
#: update of the history costs too much against a map evaluation (the eager engines' fixed
#: cost per call, ~0.15 ms in NumPy, and its O(m · size) passes against the map's
#: products), so Anderson does not pay for itself even where it cuts updates (measured,
#: NumPy engine: Euler–Zeitlin N = 32 at h = 1/4, 35 → 23 updates and 1.2× slower; N = 64 at
#: h = 1/8, 34 → 22 updates, break-even; from N = 128 it pays: h = 1/32, 19 → 11 updates,
#: 0.84× the time per step; a 4 × 4 Toda lattice at h = 0.5: 5× slower). The compiled
#: (numba) engine, which ``engine="auto"`` picks only below this size, therefore runs
#: ``FixedPoint(anderson=m)`` as the plain iteration it is there.
MIN_SIZE = 32768

#: No mixing where the relative residual ``‖f‖ / ‖g‖`` is below this many machine
#: epsilons of the unknowns' precision (rounding errors of the map dominate the
#: differences there).
QUIET = 16.0


class AndersonState(NamedTuple):
    """The history of an Anderson-accelerated iteration (:func:`start`, :func:`update`).

    ``m`` is the depth, ``shape = batch + core`` the unknowns' shape; every field has a
    fixed shape and dtype for the whole solve.

    Attributes
    ----------
    dF, dG : (m, *shape) arrays
        Differences of residuals and of map values, a ring buffer of ``m`` slots.
    f, g : shape arrays
        The last residual ``g - x`` and map value ``g``.
    gram : (*batch, m, m) real array
        ``Re⟨dF_i, dF_j⟩`` per problem.
    rhs : (*batch, m) real array
        ``Re⟨dF_i, f⟩`` per problem.
    valid : (*batch, m) bool array
        Whether slot ``i`` holds a column of the problem's current history.
    norm2, gnorm2, rel2 : (*batch,) real arrays
        ``‖f‖²``, ``‖g‖²`` and ``‖f‖² / ‖g‖²`` of the last residual and map value, per
        problem (the stopping test of one NumPy problem reads the first two:
        :meth:`lieflow.solvers.FixedPoint.solve`).
    engaged, mixed : (*batch,) bool arrays
        Whether the problem is accelerated; whether its last iterate was an extrapolation.
    seen, head : 0-d integer arrays
        Map values recorded so far; the slot the next column goes to.
    spare : array
        NumPy: two arrays of the unknowns' shape that one problem's mixed iterates are
        written to in turn (never the one passed in as ``x``); elsewhere empty. (Fresh
        arrays for them, and apart from the history, came from the operating system as
        often as not: N = 256, ~175 page faults and 0.35 ms of system time per update.)
    """

    dF: Array
    dG: Array
    f: Array
    g: Array
    gram: Array
    rhs: Array
    valid: Array
    norm2: Array
    gnorm2: Array
    rel2: Array
    engaged: Array
    mixed: Array
    seen: Array
    head: Array
    spare: Array


def accelerates(x: Array, core_ndim: int | None = None) -> bool:
    """Whether :func:`update` ever mixes for unknowns of ``x``'s shape and dtype (a static
    question, answered from shapes): one problem (the trailing ``core_ndim`` axes, default
    all) holds at least :data:`MIN_SIZE` real numbers."""
    shape = x.shape
    size = math.prod(shape if core_ndim is None else shape[len(shape) - core_ndim :])
    if 2 * size < MIN_SIZE:  # too small even as complex numbers (a rigid body: 0.3 µs)
        return False
    return size >= MIN_SIZE or namespace(x).isdtype(x.dtype, "complex floating")


def start(x0: Array, depth: int, core_ndim: int | None = None) -> AndersonState:
    """The empty history of an iteration from ``x0`` with ``depth`` columns (``>= 1``);
    the trailing ``core_ndim`` axes of ``x0`` form one problem (default: all of them, the
    whole array one problem), leading axes index independent problems."""
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    xp = namespace(x0)
    core = x0.ndim if core_ndim is None else int(core_ndim)
    batch = tuple(x0.shape[: x0.ndim - core])
    real = xp.finfo(x0.dtype).dtype
    device = device_of(x0)
    flags = xp.zeros(batch, dtype=xp.bool, device=device)
    count = xp.asarray(0, dtype=xp.int64, device=device)
    if is_numpy(x0):
        # one allocation for the history, the residual and the spare iterates: NumPy asks
        # the kernel for huge pages from 4 MiB on (N = 256, m = 5: ~1400 page faults per
        # solve in five allocations, a few dozen in one)
        held = np.zeros((2 * depth + 3, *x0.shape), dtype=x0.dtype)
        dF, dG, zero, spare = held[:depth], held[depth : 2 * depth], held[-3], held[-2:]
    else:
        dF = xp.zeros((depth, *x0.shape), dtype=x0.dtype, device=device)
        dG = xp.zeros((depth, *x0.shape), dtype=x0.dtype, device=device)
        zero = xp.zeros_like(x0)
        spare = xp.zeros((0,), dtype=x0.dtype, device=device)
    return AndersonState(
        dF=dF,
        dG=dG,
        f=zero,
        g=zero,
        gram=xp.zeros((*batch, depth, depth), dtype=real, device=device),
        rhs=xp.zeros((*batch, depth), dtype=real, device=device),
        valid=xp.zeros((*batch, depth), dtype=xp.bool, device=device),
        norm2=xp.zeros(batch, dtype=real, device=device),
        gnorm2=xp.zeros(batch, dtype=real, device=device),
        rel2=xp.zeros(batch, dtype=real, device=device),
        engaged=flags,
        mixed=flags,
        seen=count,
        head=count,
        spare=spare,
    )


def update(
    state: AndersonState, x: Array, g: Array, skew: bool = False
) -> tuple[AndersonState, Array]:
    """Record the map value ``g = F(x)`` and return ``(state, x_next)``: the accelerated
    iterate (module docs), or ``g`` itself for every problem that is not mixed this
    update (not engaged, restarted, at roundoff, or without history yet).

    ``skew``: the caller's promise that the unknowns are skew-Hermitian matrices
    (skew-symmetric if real) up to roundoff, as the midpoint map's are for a skew algebra.
    One square NumPy matrix with numba installed then works on its upper triangle alone
    (half the memory traffic; inner products weigh the off-diagonal entries twice: the
    Frobenius product of skew-Hermitian matrices) and returns a mixed iterate whose lower
    triangle is the mirror image ``-conj`` of its upper one; everywhere else it is
    ignored (the full arrays are used).

    One NumPy problem with numba installed writes a mixed iterate into one of the state's
    two :attr:`~AndersonState.spare` arrays (never the ``x`` passed in): it is overwritten
    two mixed updates later, so copy an iterate to keep it."""
    nb = state.gram.ndim - 2  # batch axes
    if nb == 0 and type(g) is np.ndarray and type(x) is np.ndarray:
        kernel = _kernel()
        if kernel is not None and g.dtype == x.dtype == state.dF.dtype and g.dtype.kind in "fc":
            return _update_host(state, x, g, kernel, skew)
    xp = namespace(x, g)
    depth = state.dF.shape[0]
    core = tuple(range(nb, x.ndim))
    real = state.gram.dtype
    f = g - x
    have = state.seen > 0
    slot = state.head
    # the new columns (garbage on the first update: never marked valid)
    dF, df = put(state.dF, slot, f, state.f)
    dG, _ = put(state.dG, slot, g, state.g)
    row = _inner(dF, df, nb)  # Re<dF_j, df>, (*batch, m)
    norm2 = _dot(f, f, core)
    gnorm2 = _dot(g, g, core)
    finfo = xp.finfo(real)
    rel2 = norm2 / xp.maximum(gnorm2, xp.full_like(norm2, finfo.smallest_normal))
    # safeguards (module docs)
    grew = have & state.mixed & (norm2 > state.norm2)
    engaged = state.engaged
    if accelerates(x, x.ndim - nb):  # static: small problems never engage
        engaged = engaged | (have & (rel2 > ENGAGE * ENGAGE * state.rel2))
    quiet = rel2 <= (QUIET * float(finfo.eps)) ** 2
    # the ring: slot `slot` holds the new column where there was a previous value
    onehot = xp.arange(depth, device=device_of(x)) == slot
    valid = xp.where(onehot, have, state.valid) & ~grew[..., None]
    gram = xp.where(onehot[:, None], row[..., None, :], state.gram)
    gram = xp.where(onehot[None, :], row[..., :, None], gram)
    # Re<dF_j, f> = Re<dF_j, f_prev> + Re<dF_j, df> for the old columns (one product
    # of the history per update, not two), computed for the new one
    rhs = xp.where(onehot, _dot(df, f, core)[..., None], state.rhs + row)
    mix = engaged & ~grew & ~quiet
    gamma = _coefficients(gram, rhs, valid & mix[..., None], xp)
    if is_numpy(g) and not mix.any():
        x_next = g  # nothing mixed (eager NumPy): the combination, all zero, is skipped
    else:
        x_next = _correct(g, gamma, dG, nb)
    advance = xp.astype(have, state.head.dtype)
    new = AndersonState(
        dF=dF,
        dG=dG,
        f=f,
        g=g,
        gram=gram,
        rhs=rhs,
        valid=valid,
        norm2=norm2,
        gnorm2=gnorm2,
        rel2=rel2,
        engaged=engaged,
        mixed=mix & xp.any(valid, axis=-1),
        seen=state.seen + 1,
        head=(state.head + advance) % depth,
        spare=state.spare,
    )
    return new, x_next


def _update_host(
    state: AndersonState, x: np.ndarray, g: np.ndarray, kernel: ModuleType, skew: bool
) -> tuple[AndersonState, np.ndarray]:
    """:func:`update` of one NumPy problem (no batch axes) with numba installed: the same
    rule in two compiled passes over the numbers (:mod:`lieflow.solvers._anderson_kernel`:
    the residual, the new columns, the Gram row and the norms in one; the correction in
    the other) and the small problem in Python floats, in place of about a dozen NumPy
    passes and forty calls on ``m``-vectors; the history's columns that are not valid are
    neither read nor used (N = 256 Euler–Zeitlin, ``m = 5``, one thread, with the stopping
    test reading its norms: an accelerated update 1.24 -> 1.11 times a plain one).
    ``skew``: :func:`update`'s."""
    depth = state.dF.shape[0]
    have = int(state.seen) > 0
    slot = int(state.head)
    valid = state.valid.tolist()
    others = np.array([j for j in range(depth) if valid[j] and j != slot], dtype=np.intp)
    real = _real_view(g).dtype
    eps, smallest = _precision(real)
    parts = 2 if g.dtype.kind == "c" else 1
    # the numbers as rows: a matrix's own (its upper triangle alone where skew), else one
    triangle = skew and g.ndim == 2 and g.shape[0] == g.shape[1]
    flat = (g.shape[0], parts * g.shape[1]) if g.ndim == 2 else (1, -1)
    dF = _real_view(state.dF).reshape(depth, *flat)
    dG = _real_view(state.dG).reshape(depth, *flat)
    # the residual overwrites the last one (the state is consumed; start's own zeros on
    # the first update, when the last map value, the same zeros, is not read)
    f = state.f
    row = np.zeros(depth)
    g_rows = _real_view(g).reshape(flat)
    ff, gg, df_f = kernel.record(
        _real_view(x).reshape(flat), g_rows, _real_view(state.f).reshape(flat),
        _real_view(state.g).reshape(flat), _real_view(f).reshape(flat), dF, dG, slot,
        others, have, row, parts, triangle,
    )  # fmt: skip
    rel2 = ff / max(gg, smallest)
    # safeguards (module docs)
    grew = have and bool(state.mixed) and ff > float(state.norm2)
    engaged = bool(state.engaged)
    if not engaged and have and accelerates(x):
        engaged = rel2 > ENGAGE * ENGAGE * float(state.rel2)
    quiet = rel2 <= (QUIET * eps) ** 2
    gram = state.gram.copy()
    if have:
        valid[slot] = True
        gram[slot, :] = row
        gram[:, slot] = row
    if grew:
        valid = [False] * depth
    rhs = state.rhs + row
    rhs[slot] = df_f
    mix = engaged and not grew and not quiet
    x_next = g
    spare = state.spare
    use = [j for j in range(depth) if valid[j] and gram[j, j] > 0] if mix else []
    if use:
        # the normal equations of the columns used, with the Tikhonov term relative to
        # each column's squared norm (_coefficients: the same system without its unit rows)
        sub = gram[np.ix_(use, use)]
        sub.flat[:: len(use) + 1] *= 1 + REGULARIZATION
        gamma = np.linalg.solve(sub, rhs[use]).astype(real, copy=False)
        x_next = spare[1] if np.may_share_memory(x, spare[0]) else spare[0]
        columns = np.array(use, dtype=np.intp)
        rows = _real_view(x_next).reshape(flat)
        kernel.correct(g_rows, dG, columns, gamma, rows, parts, triangle)
    new = AndersonState(
        dF=state.dF,
        dG=state.dG,
        f=f,
        g=g,
        gram=gram,
        rhs=rhs,
        valid=np.array(valid),
        norm2=np.asarray(ff, dtype=real),
        gnorm2=np.asarray(gg, dtype=real),
        rel2=np.asarray(rel2, dtype=real),
        engaged=np.asarray(engaged),
        mixed=np.asarray(mix and any(valid)),
        seen=state.seen + 1,
        head=(state.head + int(have)) % depth,
        spare=spare,
    )
    return new, x_next


@functools.cache
def _precision(real: np.dtype) -> tuple[float, float]:
    """Machine epsilon and the smallest normal number of a real dtype, as floats."""
    finfo = np.finfo(real)
    return float(finfo.eps), float(finfo.smallest_normal)


@functools.cache
def _kernel() -> ModuleType | None:
    """:mod:`lieflow.solvers._anderson_kernel` where numba is installed, else ``None``."""
    if importlib.util.find_spec("numba") is None:
        return None
    from . import _anderson_kernel

    return _anderson_kernel


def _coefficients(gram: Array, rhs: Array, use: Array, xp: Any) -> Array:
    """``γ`` minimizing ``‖f - ΔF γ‖`` over the columns marked ``use`` (zero elsewhere),
    from the Gram matrix and ``ΔFᵀ f``: the normal equations with the Tikhonov term
    :data:`REGULARIZATION` relative to each column's squared norm (the normalized system
    plus ``REGULARIZATION · I``, solved unscaled: Gaussian elimination does not depend on
    the columns' scaling), unused columns replaced by unit ones."""
    eye = xp.eye(gram.shape[-1], dtype=gram.dtype, device=device_of(gram))
    diagonal = xp.sum(gram * eye, axis=-1)
    use = xp.astype(use & (diagonal > 0), gram.dtype)
    lhs = gram * (use[..., :, None] * use[..., None, :])
    lhs = lhs + (REGULARIZATION * diagonal * use + (1 - use))[..., None] * eye
    return xp.linalg.solve(lhs, (rhs * use)[..., None])[..., 0]


def _real_view(a: np.ndarray) -> np.ndarray:
    """A NumPy array's numbers as a real array (complex: real and imaginary parts
    interleaved, a view of a contiguous array)."""
    a = np.ascontiguousarray(a)
    return a.view(a.real.dtype) if a.dtype.kind == "c" else a


def _inner(history: Array, v: Array, nb: int) -> Array:
    """``Re⟨history[j], v⟩`` per problem: shape ``(*batch, m)``."""
    depth = history.shape[0]
    batch = tuple(history.shape[1 : 1 + nb])
    count = math.prod(batch)
    if is_numpy(history):
        # BLAS gemv on the real view of the numbers
        H = _real_view(history).reshape(depth, count, -1).transpose(1, 0, 2)
        out = np.matmul(H, _real_view(v).reshape(count, -1, 1))
        return out.reshape(*batch, depth)
    xp = namespace(history)
    H = xp.permute_dims(xp.reshape(history, (depth, count, -1)), (1, 0, 2))
    w = xp.reshape(v, (count, -1, 1))
    if xp.isdtype(history.dtype, "complex floating"):
        out = xp.real(xp.matmul(H, xp.conj(w)))
    else:
        out = xp.matmul(H, w)
    return xp.reshape(out, (*batch, depth))


def _correct(g: Array, gamma: Array, history: Array, nb: int) -> Array:
    """``g - Σ_j gamma[..., j] history[j]`` per problem, a new array."""
    depth = history.shape[0]
    shape = tuple(history.shape[1:])
    count = math.prod(shape[:nb])
    if is_numpy(history):
        # BLAS gemv on the real view, then the subtraction into the same memory
        H = _real_view(history).reshape(depth, count, -1)
        c = np.asarray(gamma, dtype=H.dtype).reshape(count, 1, depth)
        out = np.matmul(c, H.transpose(1, 0, 2))
        if history.dtype.kind == "c":
            out = out.view(history.dtype)
        out = out.reshape(shape)
        return np.subtract(g, out, out=out)
    xp = namespace(history)
    H = xp.permute_dims(xp.reshape(history, (depth, count, -1)), (1, 0, 2))
    c = xp.astype(xp.reshape(gamma, (count, 1, depth)), history.dtype)
    return g - xp.reshape(xp.matmul(c, H), shape)


def _dot(a: Array, b: Array, axes: tuple[int, ...]) -> Array:
    """``Re⟨a, b⟩`` over ``axes`` (the trailing ones), per problem."""
    if is_numpy(a):
        if len(axes) == a.ndim:  # one problem: BLAS dot (the C function, no wrappers)
            return vdot(_real_view(a).reshape(-1), _real_view(b).reshape(-1))
        nb = a.ndim - len(axes)
        ra = _real_view(a).reshape(*a.shape[:nb], -1)
        rb = _real_view(b).reshape(*b.shape[:nb], -1)
        return np.einsum("...i,...i->...", ra, rb)
    xp = namespace(a, b)
    product = xp.real(a * xp.conj(b)) if xp.isdtype(a.dtype, "complex floating") else a * b
    return xp.sum(product, axis=axes)
