"""numba loops behind :mod:`lieflow.engines.compiled` (imported only when the compiled engine runs).

One compiled driver and per-formulation map kernels:

* :func:`_entry_point` is the chunk loop: warm-start extrapolation and trust
  (:class:`~lieflow.flows.WarmStart`), the cold retry of a failed warm solve
  (:func:`lieflow.schemes.base.solve`), the per-step phase-space projection and the
  finiteness check; :func:`_solver` is the fixed-point loop, judged by
  :func:`lieflow.solvers.fixed_point.stopping_verdict` — the same function object the numpy
  path calls, compiled (:data:`~lieflow.engines._compiled_rules.verdict`);
* the formulations are a map (:func:`_midpoint_map`, :func:`_reduced_map`) and a step
  (:func:`_sydirk_step`: a composition of midpoint solves; :func:`_reduced_step`: the
  reduced stage form), each the numpy code path written out entry by entry.

This module holds the driver (the solves, the steps, the warm start's sums, the entry points
:func:`entry` and their arguments :class:`LoopArguments`); the rest of the loops is in the
modules below it: how they are compiled, and the products (:mod:`~lieflow.engines._numba_jit`);
the numpy path's rules, compiled (:mod:`~lieflow.engines._compiled_rules`); the systems'
maps, and compiled functions by address, as the loops take them
(:mod:`~lieflow.engines._compiled_maps`: the system enters as compiled functions passed as
*arguments*, by address, an ``int64``, and called as numba's first-class function type of
:func:`map_signature`); the formulations' maps and updates
(:mod:`~lieflow.engines._compiled_formulations`). It is what
:func:`lieflow.engines.compiled.kernels` loads: it re-exports the names of those modules
that :mod:`lieflow.engines.compiled` reads of it.

numba's cache tracks this file only, not the files of the functions it inlines; the entry
points (:func:`entry`: ``"sydirk_advance"``, ``"reduced_advance"``, each for the commutator
update and for the update in conjugation form) are therefore keyed by a hash of the source of
the stopping rules and of the modules of the loops below this one (:data:`SHARED_KEY`, of
:data:`SHARED_MODULES`), so editing a rule, or a function of those modules, recompiles them.

Compile time (a user's first run compiles its entry point: issue 37 item 11): each entry
point holds one formulation, one data type, one update, one kind of product (plain loops or
BLAS, below) and one kind of algebra (skew-Hermitian or general: the functions that branch
on it are made for each, :func:`_midpoint_map_of`), so a run compiles only the code it runs;
every function between an entry point and the map is inlined into it once (one call site
each: a failed warm solve is retried by the same call to the iteration), since inlining
copies a function's code into every call site; the largest (the maps, the stopping rule's
bookkeeping) are inlined by LLVM rather than by numba (:func:`_inlined_by_llvm`).

Conventions: ``float64`` or ``complex128`` data (one compilation of the loops for each; the
complex one for skew-Hermitian algebras such as su(N), where every transpose of the real code
is a conjugate transpose); an ensemble is a ``(K, n, n)`` stack advanced trajectory by
trajectory inside each step; solves return the number of updates, negated
when the stopping rule reports a failure (the caller then hands the step to numpy).
Products of ``n×n`` matrices are plain loops up to ``n = 8`` and BLAS calls (``np.dot``
from compiled code: no Python overhead) above, in entry points of their own.

The entry points are compiled without numba's reference counting (``_nrt=False``): every
view the loops take of an array (a trajectory, a stage, a scratch matrix) otherwise costs an
atomic increment and decrement, which were 80% of the time of a so(3) midpoint step
(measured with ``perf``: 2.0 µs per step with them, 0.45 µs without; the same bits). Code
compiled that way cannot allocate, so the work arrays come from :func:`workspace`, and the
BLAS products, which need reference counting inside ``np.dot``, are a function of their
own (:func:`_gemm`) passed to the loops like a system's map (:func:`gemm`).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import inspect
import types
from typing import Any, NamedTuple, cast

import numpy as np

from .. import warm_start
from ..schemes import base, conjugation
from ..schemes.conjugation import UPDATES
from ..solvers import fixed_point
from . import _compiled_formulations, _compiled_maps, _compiled_rules, _numba_jit
from ._compiled_formulations import (
    _ALGEBRAS,
    _cayley_into,
    _commutator_add,
    _lifted_into,
    _midpoint_map_general,
    _midpoint_map_skew,
    _reduced_map_general,
    _reduced_map_skew,
)
from ._compiled_maps import _at, _FunctionPointer
from ._compiled_maps import address as address
from ._compiled_maps import function_pointer as function_pointer
from ._compiled_maps import hadamard_B as hadamard_B
from ._compiled_maps import hadamard_B_skew as hadamard_B_skew
from ._compiled_maps import hadamard_B_symmetric as hadamard_B_symmetric
from ._compiled_maps import inline_code as inline_code
from ._compiled_maps import linked_function as linked_function
from ._compiled_maps import skew_hermitian_part as skew_hermitian_part
from ._compiled_maps import symmetric_part as symmetric_part
from ._compiled_rules import (
    FILLED,
    MAX_ITER,
    RETRY_COLD,
    TRUSTED,
    WARM_STARTS,
    _judge,
    _retries_cold,
    _trusted_points,
)
from ._compiled_rules import stopping_arrays as stopping_arrays
from ._numba_jit import (
    _PRODUCT_SIGNATURES,
    DTYPES,
    F,
    _abs2,
    _finite,
    _gemm,
    _helper,
    _inner,
    _matmul_hn,
    _norm,
    map_signature,
    numba,
    numba_cache,
)
from ._numba_jit import LOOP_PRODUCTS_MAX_N as LOOP_PRODUCTS_MAX_N
from ._numba_jit import compiled_map as compiled_map

_GO, _CONVERGED, _ROUNDOFF = fixed_point.GO, fixed_point.CONVERGED, fixed_point.ROUNDOFF

#: The modules whose functions and constants the entry points compile: the rules shared
#: with the numpy path and the other modules of the loops (numba's cache tracks this file
#: only, not theirs).
SHARED_MODULES = (
    fixed_point, warm_start, conjugation, base,
    _numba_jit, _compiled_rules, _compiled_maps, _compiled_formulations,
)  # fmt: skip

#: Hash of the source of :data:`SHARED_MODULES`: part of the cache key of the entry points
#: (numba's cache tracks this file only), so that editing a shared rule recompiles them.
SHARED_KEY = hashlib.sha256(
    "".join(inspect.getsource(module) for module in SHARED_MODULES).encode()
).hexdigest()


# ------------------------------------------------------------------ the one driver


def _solver(fmap: Any) -> Any:
    """The fixed-point solve of the map ``fmap`` (:func:`_midpoint_map` or
    :func:`_reduced_map`, of one kind of algebra): one source for every formulation,
    compiled once per map (the map is a closure variable, i.e. a direct call, not a value
    passed at run time)."""

    def solve(
        W0: Any, coef: Any, x: Any, xf: Any, x0f: Any, pred: Any, solved: Any, off: int,
        guessing: bool, m0: Any, m1: Any, m2: Any, m3: Any, B: Any, params: Any, gemm: Any,
        res: Any, tolerances: Any, settings: Any,
    ) -> int:  # fmt: skip
        """Fixed-point iteration ``x <- fmap(x)`` until the stopping rule stops it, from the
        warm guess ``x0 + pred[off:]`` (when ``guessing``), and once more from the cold
        guess ``x0`` if that fails and :func:`~lieflow.schemes.base.retries_cold` says so
        (where ``settings`` allow it); on success ``solved[off:] = x - x0`` (the offsets a
        warm start keeps) and the updates of both attempts are returned, else a negative
        number. ``xf``, ``x0f``: flat views of ``x`` and the cold guess."""
        m = xf.size
        total = 0
        warm = guessing
        while True:  # the warm attempt (when guessing), then the cold one if it failed
            for e in range(m):
                xf[e] = x0f[e] + pred[off + e] if warm else x0f[e]
            size0 = _norm(xf)
            k = 0
            code = _GO
            while code == _GO:
                step2, size2 = fmap(W0, coef, x, m0, m1, m2, m3, B, params, gemm)
                k += 1
                code, size0 = _judge(step2, size2, k, size0, res, tolerances, settings)
            total += k
            converged = code == _CONVERGED or code == _ROUNDOFF
            if not (settings[RETRY_COLD] != 0 and _retries_cold(converged, warm)):
                break
            warm = False
        if not converged:
            return -1
        for e in range(m):
            solved[off + e] = xf[e] - x0f[e]
        return total

    return _inner(solve, f"_solve_{fmap.__name__}")


#: The solves of each formulation, by kind of algebra (``skew``).
_solve_midpoint = {False: _solver(_midpoint_map_general), True: _solver(_midpoint_map_skew)}
_solve_reduced = {False: _solver(_reduced_map_general), True: _solver(_reduced_map_skew)}


@_inner
def _sydirk_views(work: Any, scratch: Any) -> Any:
    """Views of the work arrays for :func:`_sydirk_step`, made once per chunk: the iterate
    ``x`` and the sub-step's start ``x0`` (``n×n``, and flat), four scratch matrices."""
    x, x0 = work[0, 0, 0], work[1, 0, 0]
    m0, m1, m2, m3 = scratch[1, 0], scratch[2, 0], scratch[3, 0], scratch[4, 0]
    return x, x0, x.reshape(x.size), x0.reshape(x0.size), m0, m1, m2, m3


def _sydirk_step_of(conjugation: bool, skew: bool) -> Any:
    """:func:`_sydirk_step` for one update (SPEC §4.7) on one kind of algebra (``skew``:
    skew-Hermitian): both are constants of the compiled code, so the other update and the
    other kind's branches are neither typed nor compiled (numba prunes a branch on a closure
    constant, in the functions it inlines too)."""
    solve = _solve_midpoint[skew]

    def _sydirk_step(
        cur: Any, out: Any, pred: Any, solved: Any, guessing: bool, coefficients: Any,
        weights: Any, x: Any, x0: Any, xf: Any, x0f: Any, m0: Any, m1: Any, m2: Any, m3: Any,
        B: Any, params: Any, gemm: Any, res: Any, tolerances: Any, settings: Any,
    ) -> int:  # fmt: skip
        """One step of a composition of midpoint steps (SPEC §4.2) of sizes ``weights``
        (``h b_i``; ``coefficients[i]``: their
        :func:`~lieflow.schemes.sydirk.midpoint_coefficients`) from ``cur`` into ``out``;
        ``solved``/``pred``: the ``(s, n, n)`` offsets, flattened."""
        n = cur.shape[0]
        nn = n * n
        for a in range(n):
            for c in range(n):
                out[a, c] = cur[a, c]
        total = 0
        for i in range(weights.shape[0]):
            for a in range(n):
                for c in range(n):
                    x0[a, c] = out[a, c]
            its = solve(
                x0, coefficients[i], x, xf, x0f, pred, solved, i * nn, guessing, m0, m1, m2,
                m3, B, params, gemm, res, tolerances, settings,
            )  # fmt: skip
            if its < 0:
                return -1
            total += its
            if conjugation:
                a = coefficients[i, 0]  # the Cayley transform's h/2
                if not _cayley_into(out, a, skew, x, B, params, m0, m1, m2, m3, gemm):
                    return -1
            else:
                _commutator_add(out, weights[i], skew, x, B, params, m0, m1, m3, gemm)
        return total

    return _inner(_sydirk_step, f"_sydirk_step_{UPDATES[conjugation]}_{_ALGEBRAS[skew]}")


@_inner
def _reduced_views(work: Any, scratch: Any) -> Any:
    """Views of the work arrays for :func:`_reduced_step`, made once per chunk: the
    unknowns ``x = (G, P)`` and the cold guess ``x0 = (I, W0)`` (and flat), four scratch
    stacks."""
    x, x0 = work[0], work[1]
    xf, x0f = x.reshape(x.size), x0.reshape(x0.size)
    return x, x0, xf, x0f, scratch[0], scratch[1], scratch[2], scratch[3]


def _reduced_step_of(conjugation: bool, skew: bool) -> Any:
    """:func:`_reduced_step` for one update on one kind of algebra (as
    :func:`_sydirk_step_of`)."""
    solve = _solve_reduced[skew]

    def _reduced_step(
        cur: Any, out: Any, pred: Any, solved: Any, guessing: bool, coefficients: Any,
        weights: Any, x: Any, x0: Any, xf: Any, x0f: Any, m0: Any, m1: Any, m2: Any, m3: Any,
        B: Any, params: Any, gemm: Any, res: Any, tolerances: Any, settings: Any,
    ) -> int:  # fmt: skip
        """One step of the reduced stage form of a symplectic tableau (SPEC §4.5) from
        ``cur`` into ``out``: unknowns ``(G, P)``, cold guess ``(I, cur)``; ``coefficients``:
        :func:`~lieflow.schemes.block.reduced_coefficients`, ``weights = h b``;
        ``solved``/``pred``: the ``(2, s, n, n)`` offsets, flattened.
        ``out = cur + sum_i hb_i [B(W_i), W_i]``, ``W_i = G_i^† P_i``."""
        s, n = weights.shape[0], cur.shape[0]
        for i in range(s):
            for a in range(n):
                for c in range(n):
                    x0[0, i, a, c] = 1.0 if a == c else 0.0
                    x0[1, i, a, c] = cur[a, c]
        its = solve(cur, coefficients, x, xf, x0f, pred, solved, 0, guessing, m0, m1, m2, m3,
                    B, params, gemm, res, tolerances, settings)  # fmt: skip
        if its < 0:
            return -1
        Wi, Bi, BW, WB = m0[0], m1[0], m2[0], m3[0]
        for a in range(n):
            for c in range(n):
                out[a, c] = cur[a, c]
        if conjugation:
            lifted = _lifted_into(out, weights, skew, x, B, params, Wi, Bi, BW, WB, gemm)
            return its if lifted else -1
        for i in range(s):
            _matmul_hn(x[0, i], x[1, i], Wi, WB, gemm)
            _commutator_add(out, weights[i], skew, Wi, B, params, Bi, BW, WB, gemm)
        return its

    return _inner(_reduced_step, f"_reduced_step_{UPDATES[conjugation]}_{_ALGEBRAS[skew]}")


@_helper
def _predict(history: Any, kk: int, points: int, extrapolation: Any, out: Any) -> None:
    """The warm-start prediction from the last ``points`` solutions of trajectory ``kk``
    (:meth:`WarmStart.prediction <lieflow.warm_start.WarmStart.prediction>`):
    ``out = sum_j extrapolation[points - 1, j] history[j, kk]``, 1-D."""
    m = out.size
    w0 = extrapolation[points - 1, 0]
    for e in range(m):
        out[e] = w0 * history[0, kk, e]
    for j in range(1, points):
        w = extrapolation[points - 1, j]
        for e in range(m):
            out[e] += w * history[j, kk, e]


@_helper
def _commit(
    solved: Any, history: Any, warm_counts: Any, extrapolation: Any, acc: Any, err2: Any
) -> None:
    """:meth:`WarmStart.advance <lieflow.warm_start.WarmStart.advance>` for the whole stack:
    the squared errors of the predictions of ``solved`` from ``0 .. filled`` points (summed
    over the stack), the number of points trusted next by
    :func:`~lieflow.warm_start.trusted_points`, and ``solved`` into the history
    (``(depth, K, m)``, most recent first)."""
    depth, K, m = history.shape
    filled = warm_counts[FILLED]
    for u in range(filled + 1):
        err2[u] = 0.0
    for kk in range(K):
        for e in range(m):
            err2[0] += _abs2(solved[kk, e])
        for u in range(1, filled + 1):
            _predict(history, kk, u, extrapolation, acc)
            for e in range(m):
                err2[u] += _abs2(solved[kk, e] - acc[e])
    warm_counts[TRUSTED] = _trusted_points(err2, filled, depth)
    for j in range(depth - 1, 0, -1):
        for kk in range(K):
            for e in range(m):
                history[j, kk, e] = history[j - 1, kk, e]
    for kk in range(K):
        for e in range(m):
            history[0, kk, e] = solved[kk, e]
    warm_counts[FILLED] = min(filled + 1, depth)


class LoopArguments(NamedTuple):
    """The arguments of an entry point (:func:`entry`), by name and in order: the loops'
    interface. The loops read the inputs and write ``states``, ``iterations`` and the warm
    start (``history``, ``warm_counts``) in place, and return how many steps they took.

    Attributes
    ----------
    start : ndarray
        The states the chunk starts from, ``(K, n, n)`` (``K`` trajectories).
    coefficients : ndarray
        The formulation's stage coefficients, ``float64``: rows ``(q, q^2)`` per sub-step
        of a midpoint composition (:func:`~lieflow.schemes.sydirk.midpoint_coefficients`),
        ``(C_G; C_P)`` of the reduced form (:func:`~lieflow.schemes.block.reduced_coefficients`).
    weights : ndarray
        ``h b``: the sub-steps' sizes, or the stage weights of the update.
    B, project, gemm : int
        Addresses of the system's compiled ``B``, of its compiled projection (``B``'s when
        there is none: not called) and of the BLAS product (:func:`address`; ``0`` for
        the entry points of plain-loop products, which do not read it).
    B_params, project_params : ndarray
        Their ``params``; ``B_params`` led by :func:`inline_code`.
    projecting : bool
        Whether each new state is mapped by ``project``.
    tolerances, settings : ndarray
        The stopping rule and the step's switches (:func:`stopping_arrays`).
    history : ndarray
        The warm start's kept solutions, ``(depth, K, m)``, most recent first (updated).
    extrapolation : ndarray
        :func:`~lieflow.warm_start.extrapolation_matrix` of ``depth`` points.
    warm_counts : ndarray
        ``(filled, trusted)`` of the warm start (:data:`FILLED`, :data:`TRUSTED`; updated).
    states : ndarray
        Out: the states after each step, ``(steps, K, n, n)``.
    iterations : ndarray
        Out: fixed-point updates per step (max over the stack), ``(steps,)``.
    workspace, real_workspace : ndarray
        The work arrays (:func:`workspace`): the loops allocate nothing.
    """

    start: np.ndarray
    coefficients: np.ndarray
    weights: np.ndarray
    B: int
    B_params: np.ndarray
    project: int
    project_params: np.ndarray
    projecting: bool
    tolerances: np.ndarray
    settings: np.ndarray
    history: np.ndarray
    extrapolation: np.ndarray
    warm_counts: np.ndarray
    states: np.ndarray
    iterations: np.ndarray
    gemm: int
    workspace: np.ndarray
    real_workspace: np.ndarray


if numba is not None:
    _map_at = _at(map_signature)
    _product_at = _at(lambda dtype: _PRODUCT_SIGNATURES[np.dtype(dtype)])


#: The steps of each formulation, update and kind of algebra, and the views of the work
#: arrays they take: ``(sydirk, conjugation, skew) -> (step, views)`` (:func:`_entry_point`).
_STEPS = {
    (sydirk, conjugation, skew): (
        (_sydirk_step_of if sydirk else _reduced_step_of)(conjugation, skew),
        _sydirk_views if sydirk else _reduced_views,
    )
    for sydirk in (True, False)
    for conjugation in (False, True)
    for skew in _ALGEBRAS
}


def _entry_point(key: str, sydirk: bool, conjugation: bool, blas: bool, skew: bool) -> Any:
    """The entry point of one formulation (``sydirk``: a composition of midpoint steps, else
    the reduced stage form), update, kind of product (``blas``: the BLAS product
    :func:`gemm`, for ``n > LOOP_PRODUCTS_MAX_N``; else plain loops, :func:`_loops`, and
    the product's address is not read) and kind of algebra (``skew``: skew-Hermitian,
    ``M B = (B M)^†``; a run of the other kind compiles none of its branches, e.g. a
    conjugation update on su(N) no Gauss–Jordan solve): the chunk loop over the steps of
    :data:`_STEPS` (:func:`_sydirk_step_of` or :func:`_reduced_step_of`, with views of the
    work arrays from :func:`_sydirk_views` or :func:`_reduced_views`). It takes the
    :class:`LoopArguments`, the system's maps and the product by address (``int64``, see
    :func:`_at`).

    One source for all: the step, the views and the kind of product are the globals
    ``_step``, ``_views`` and ``_blas`` of the function, which is made with a namespace of
    its own (this module's globals and those three; numba prunes the branch on ``_blas`` it
    does not take, so a run types and compiles only the products it calls), so that numba
    compiles the loop as the entry point itself rather than inlining it into one (numba's
    inlining deep-copies the inlined code block by block, a cost that grows with the square
    of its size: about a fifth of the CPU time of a first so(3) run, measured with
    ``benchmarks/compile_time.py``). Its closure holds
    ``key`` (:data:`SHARED_KEY`) alone, which numba's cache key hashes (with the bytecode),
    so that editing a shared rule recompiles it; the name (one cache file per entry point)
    tells them apart."""

    def advance(
        start: Any, coefficients: Any, weights: Any, B_address: Any, B_params: Any,
        project_address: Any, project_params: Any, projecting: bool, tolerances: Any,
        settings: Any, history: Any, extrapolation: Any, warm_counts: Any, states: Any,
        iterations: Any, gemm_address: Any, workspace: Any, real_workspace: Any,
    ) -> int:  # fmt: skip
        """Advance the stack ``start`` (``(K, n, n)``) by up to ``states.shape[0]`` steps of
        ``_step``. Writes each step's states and its iteration count (max over the stack)
        and returns how many steps completed; fewer than asked means the next step failed
        and nothing of it was committed.
        """
        key  # noqa: B018 - part of the cache key
        B = _map_at(B_address, start)
        project = _map_at(project_address, start)
        # _blas: a global of the entry point's own namespace (see above), pruned
        if _blas:  # type: ignore[name-defined] # noqa: F821
            gemm = _product_at(gemm_address, start)
        else:
            gemm = None
        K, n, s = start.shape[0], start.shape[1], weights.shape[0]
        warm = settings[WARM_STARTS] != 0
        depth, m = history.shape[0], history.shape[2]
        # the work arrays, carved out as workspace() sizes them
        solved = workspace[: K * m].reshape((K, m))
        pred = workspace[K * m : K * m + m]
        acc = workspace[K * m + m : K * m + 2 * m]
        o = K * m + 2 * m
        work = workspace[o : o + 4 * s * n * n].reshape((2, 2, s, n, n))
        scratch = workspace[o + 4 * s * n * n : o + 9 * s * n * n].reshape((5, s, n, n))
        err2 = real_workspace[: depth + 1]
        res = real_workspace[depth + 1 : depth + 1 + settings[MAX_ITER]]
        # _views and _step: globals of the entry point's own namespace (see above)
        parts = _views(work, scratch)  # type: ignore[name-defined] # noqa: F821
        x, x0, xf, x0f, m0, m1, m2, m3 = parts
        for step in range(states.shape[0]):
            points = min(warm_counts[FILLED], warm_counts[TRUSTED])
            guessing = warm and points > 0
            most = 0
            for kk in range(K):
                if guessing:
                    _predict(history, kk, points, extrapolation, pred)
                cur = start[kk] if step == 0 else states[step - 1, kk]
                out = states[step, kk]
                total = _step(  # type: ignore[name-defined] # noqa: F821
                    cur, out, pred, solved[kk], guessing, coefficients, weights, x, x0, xf,
                    x0f, m0, m1, m2, m3, B, B_params, gemm, res, tolerances, settings,
                )  # fmt: skip
                if total < 0:
                    return step
                if projecting:
                    project(out, project_params, out)
                for a in range(n):
                    for c in range(n):
                        if not _finite(out[a, c]):
                            return step
                most = max(most, total)
            if warm:
                _commit(solved, history, warm_counts, extrapolation, acc, err2)
            iterations[step] = most
        return states.shape[0]

    step, views = _STEPS[sydirk, conjugation, skew]
    name = f"{'sydirk' if sydirk else 'reduced'}_advance{'_conjugation' if conjugation else ''}"
    name += ("_blas" if blas else "") + ("_skew" if skew else "")
    namespace = {**globals(), "_step": step, "_views": views, "_blas": blas}
    made = types.FunctionType(advance.__code__, namespace, name, None, advance.__closure__)
    made.__qualname__ = name  # one cache file per entry point
    return made


def _entry_signature(dtype: np.dtype) -> Any:
    """numba's signature of an entry point for data of ``dtype``: the types of
    :class:`LoopArguments`, by name."""
    t = numba.types
    f8, i8, d = t.float64, t.int64, numba.from_dtype(dtype)
    types = {
        "start": d[:, :, ::1], "coefficients": f8[:, ::1], "weights": f8[::1], "B": i8,
        "B_params": f8[::1], "project": i8, "project_params": f8[::1],
        "projecting": t.boolean, "tolerances": f8[::1], "settings": i8[::1],
        "history": d[:, :, ::1], "extrapolation": f8[:, ::1], "warm_counts": i8[::1],
        "states": d[:, :, :, ::1], "iterations": i8[::1], "gemm": i8, "workspace": d[::1],
        "real_workspace": f8[::1],
    }  # fmt: skip
    return t.int64(*(types[name] for name in LoopArguments._fields))


def _compile_entry(func: F, dtype: np.dtype) -> F:
    """An entry point compiled for its one signature for data of ``dtype`` (loaded from the
    disk cache if there)."""
    if numba is None:  # pragma: no cover
        return func
    # without reference counting (see the module's docstring) where this numba has the
    # (private) option; with it the same loops are correct, only slower; called from
    # Python only (no C wrapper)
    options: dict[str, Any] = {"error_model": "numpy", "no_cfunc_wrapper": True}
    cpu = importlib.import_module("numba.core.cpu")
    if hasattr(getattr(cpu, "CPUTargetOptions", None), "_nrt"):
        options["_nrt"] = False
    return cast(F, numba_cache.cached_njit(func, signature=_entry_signature(dtype), **options))


def gemm(dtype: np.dtype) -> Any:
    """:func:`_gemm` for data of ``dtype``, compiled (or loaded from the disk cache) on first
    use, as the loops take it (an address, like a system's map)."""
    return _gemm_pointer(np.dtype(dtype))


@functools.cache
def _gemm_pointer(dtype: np.dtype) -> Any:
    signature = _PRODUCT_SIGNATURES[dtype]
    cast(Any, _gemm).compile(signature)  # a numba dispatcher (_jit)
    return _FunctionPointer(_gemm, dtype, signature)


def workspace(
    dtype: np.dtype, K: int, m: int, s: int, n: int, depth: int, max_iter: int
) -> tuple[np.ndarray, np.ndarray]:
    """The work arrays of the loops (``workspace``, ``real_workspace`` of
    :class:`LoopArguments`), which allocate nothing themselves: ``solved (K, m)``,
    ``pred (m)``, ``acc (m)``, ``work (2, 2, s, n, n)`` and ``scratch (5, s, n, n)`` end to
    end in ``dtype``, then ``err2 (depth + 1)`` and the residual history ``res (max_iter)``
    in float64; ``m``: one trajectory's warm offsets, ``depth``: the history's length."""
    return (
        np.zeros(K * m + 2 * m + 9 * s * n * n, dtype=dtype),
        np.zeros(depth + 1 + max_iter),
    )


def entry(
    name: str,
    dtype: np.dtype = DTYPES[0],
    conjugation: bool = False,
    blas: bool = False,
    skew: bool = False,
) -> Any:
    """The entry point ``name`` (``"sydirk_advance"`` or ``"reduced_advance"``) for data of
    ``dtype`` (one of :data:`DTYPES`), the update in conjugation form or not, products by
    BLAS (``blas``: for ``n > LOOP_PRODUCTS_MAX_N``, :func:`gemm`) or by plain loops and a
    skew-Hermitian algebra (``skew``) or not, compiled (or loaded from the disk cache) on
    first use, so that importing this module (as :func:`lieflow.engines.compiled.plan` does
    to check a system's maps) loads no loops, and a run compiles and loads only the loop of
    its own formulation, data type, update, products and kind of algebra."""
    if name not in ("sydirk_advance", "reduced_advance"):
        raise ValueError(f"no entry point {name!r}")
    return _entry(name, np.dtype(dtype), bool(conjugation), bool(blas), bool(skew))


@functools.cache
def _entry(name: str, dtype: np.dtype, conjugation: bool, blas: bool, skew: bool) -> Any:
    """:func:`entry`, compiled once per process and key."""
    source = _entry_point(SHARED_KEY, name == "sydirk_advance", conjugation, blas, skew)
    return _compile_entry(source, dtype)
