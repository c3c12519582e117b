"""A system's compiled maps as the compiled engine takes them: lieflow's own named
(:data:`MAPS`), a system's checked against its numpy maps on ``W0`` and off it
(:func:`_system_maps`), and what the engine keeps per system (:data:`_KEPT`: the checked
maps and the last plan, never stored on the system)."""

from __future__ import annotations

import functools
import math
import weakref
from collections.abc import Sequence
from types import ModuleType
from typing import Any

import numpy as np

from ..algebras import Array
from ..systems.base import IsospectralSystem

#: lieflow's own compiled maps ``f(W, params, out)``, attributes of :mod:`lieflow.engines.compiled`
#: (loaded, with numba, on first use) for a system's :meth:`~lieflow.IsospectralSystem.compiled_B`
#: and :meth:`~lieflow.IsospectralSystem.compiled_project` to return, or for its own
#: compiled map to call: ``hadamard_B`` (``out = S ⊙ W``, ``params = S.ravel()``),
#: ``hadamard_B_skew`` (``S ⊙ (W - W^T)/2``), ``hadamard_B_symmetric``
#: (``S ⊙ (W + W^T)/2``), ``symmetric_part`` (``(W + W^T)/2``) and ``skew_hermitian_part``
#: (``(W - W^†)/2``, minus its trace over ``n`` on the diagonal if ``params[0]``: the
#: projection onto u(n) or su(N)). The engine evaluates the Hadamard maps inline.
MAPS = (
    "hadamard_B",
    "hadamard_B_skew",
    "hadamard_B_symmetric",
    "symmetric_part",
    "skew_hermitian_part",
)


def _checked_map(
    what: str,
    got: tuple[Any, Array] | None,
    checks: Sequence[tuple[Array, Array]],
    dtype: np.dtype,
    loops: ModuleType,
) -> tuple[Any, Array] | str:
    """``(function, params)`` of a system's compiled map, compiled for
    :func:`~lieflow.engines._numba_jit.map_signature` of ``dtype`` and checked on each ``(W,
    want)``
    of ``checks`` against ``want`` (the numpy result) to roundoff; or the reason it cannot
    be used (which names the check: ``"on W0"``, then ``"off W0"``); ``loops``: the
    compiled loops' module."""
    tiny = np.finfo(float).tiny
    if not (isinstance(got, tuple) and len(got) == 2):
        return f"{what} must return (function, params), got {got!r}"
    fn, params = got
    params = np.array(params, dtype=np.float64, order="C").reshape(-1)  # a writable copy
    signature = loops.map_signature(dtype)
    for i, (W, want) in enumerate(checks):
        try:
            if (
                i == 0
                and hasattr(fn, "compile")
                and not any(sig == signature.args for sig in getattr(fn, "signatures", ()))
            ):
                fn.compile(signature)
            out = np.zeros(W.shape, dtype=dtype)
            fn(np.array(W, dtype=dtype, order="C"), params, out)
        except Exception as exc:
            return (
                f"{what} does not compile for (W, params, out) with {dtype} data: "
                f"{type(exc).__name__}: {exc}"
            )
        # the arrays' own max (not np.max's Python wrapper: 1 µs less a call)
        scale = max(float(np.abs(want).max(initial=0.0)), tiny)
        if not float(np.abs(out - want).max(initial=0.0)) <= 1e-12 * scale:
            return f"{what} does not reproduce the numpy result {'on' if i == 0 else 'off'} W0"
    try:
        return loops.function_pointer(fn, dtype), params
    except Exception as exc:
        return (
            f"{what} does not compile for (W, params, out) with {dtype} data: "
            f"{type(exc).__name__}: {exc}"
        )


@functools.cache
def _wave(shape: tuple[int, ...], complex_data: bool) -> Array:
    """The direction ``cos(j) (+ i sin(j))`` (``j``: the entries' flat indices) along which
    :func:`~lieflow.engines.compiled.plan` checks a system's compiled maps off ``W0``; read-only,
    one per shape (a function of its immutable arguments alone, cached)."""
    wave = np.arange(math.prod(shape)).reshape(shape)
    off = np.cos(wave) + (1j * np.sin(wave) if complex_data else 0.0)
    off.setflags(write=False)
    return off


def _identity(got: Any, signature: Any) -> tuple[Any, Any, bytes | None]:
    """What the cache of checked maps compares of a hook's ``(function, params)``: the
    function, its compiled code for the data's dtype (a numba dispatcher's overload for
    :func:`~lieflow.engines._numba_jit.map_signature`: a recompiled function is checked and
    resolved
    again) and the ``params`` as float64 bytes; ``(got, None, None)`` if malformed (never
    taken from the cache)."""
    if got is None:
        return None, None, b""
    if not (isinstance(got, tuple) and len(got) == 2):
        return got, None, None
    fn = got[0]
    overloads = getattr(fn, "overloads", None)
    code = overloads.get(signature.args) if overloads is not None else None
    try:
        return fn, code, np.asarray(got[1], dtype=np.float64).tobytes()
    except (TypeError, ValueError):
        return got, None, None


def _unchanged(kept: tuple[Any, Any, bytes | None], got: Any) -> bool:
    """Whether a hook's ``(function, params)`` (``got``) is what was checked (``kept``, its
    :func:`_identity` then): the same function object, its checked compiled code still
    among its overloads (not recompiled), the same ``params``."""
    fn, code, params = kept
    if got is None or fn is None:
        return got is None and fn is None
    if params is None or not (isinstance(got, tuple) and len(got) == 2) or got[0] is not fn:
        return False
    overloads = getattr(fn, "overloads", None)
    # dict.values: an OrderedDict's own values() looks every key up again, hashing each
    # signature's numba types in Python (~1 µs a map and call)
    if overloads is not None:
        codes = dict.values(overloads) if isinstance(overloads, dict) else overloads.values()
        if not any(c is code for c in codes):
            return False
    try:
        return np.asarray(got[1], dtype=np.float64).tobytes() == params
    except (TypeError, ValueError):
        return False


def _by_name(got: Any, loops: ModuleType) -> Any:
    """A hook's ``(function, params)`` with a function named by a string (one of
    lieflow's own maps, :data:`MAPS`) replaced by that map; a name that is none of them
    gives the reason (a string); anything else as it is (the checks that follow name what
    is wrong with it)."""
    if isinstance(got, tuple) and len(got) == 2 and isinstance(got[0], str):
        if got[0] not in MAPS:
            return f"no compiled map named {got[0]!r} (lieflow's own: {', '.join(MAPS)})"
        return getattr(loops, got[0]), got[1]
    return got


class _Kept:
    """What the compiled engine keeps of the systems it ran, held by the engine (:data:`_KEPT`)
    and never on a system: per live system, a dictionary of the values
    :func:`~lieflow.engines.compiled.plan` derives from it (its checked compiled maps and its last
    plan, per dtype).

    Process-local values (compiled functions' addresses), so they cannot live in a system, which is
    copied, pickled and sent to other processes; and kept, because checking a system's maps again on
    every call would cost what the call-overhead benchmark (``benchmarks/suites/call_cost.py``)
    counts. A system is identified by its identity while it lives (a weak reference: an entry goes
    with its system; a copy or a pickle is another system and starts without one). Only
    :func:`~lieflow.engines.compiled.plan` reads and writes it; what it hands out (a
    :class:`~lieflow.engines.compiled_plan.CompiledPlan`) is read-only.
    """

    def __init__(self) -> None:
        self._systems: dict[int, tuple[weakref.ref[Any], dict[Any, Any]]] = {}

    def of(self, system: IsospectralSystem) -> dict[Any, Any]:
        """The values kept for ``system`` (an empty dictionary the first time; a fresh one,
        not kept, for a system that cannot be referenced weakly)."""
        key = id(system)
        held = self._systems.get(key)
        if held is not None and held[0]() is system:
            return held[1]
        values: dict[Any, Any] = {}
        try:
            ref = weakref.ref(system, functools.partial(self._forget, key))
        except TypeError:  # not weakly referenceable (a class with __slots__): not kept
            return values
        self._systems[key] = (ref, values)
        return values

    def _forget(self, key: int, ref: weakref.ref[Any]) -> None:
        """Drop a collected system's values (its weak reference's callback)."""
        held = self._systems.get(key)
        if held is not None and held[0] is ref:
            del self._systems[key]


#: The compiled engine's values per system (:class:`_Kept`).
_KEPT = _Kept()


def _system_maps(
    system: IsospectralSystem, W0: Array, dtype: np.dtype, loops: ModuleType
) -> tuple[tuple[Any, Array], tuple[Any, Array] | None] | str:
    """The system's compiled ``B`` as the loops take it (its address, and its ``params``
    led by :func:`~lieflow.engines._compiled_maps.inline_code`) and its compiled projection (or
    ``None``), checked against ``system.B(system.project_stage(V))`` and
    ``system.project(V)`` (:func:`_checked_map`) on ``V = W0`` and off it; or the reason
    they cannot be used.

    The check is of the system's maps, not of ``W0``: its result is kept by the engine
    (:data:`_KEPT`, per system and dtype) together with the maps and their ``params`` it was
    made for, and reused while :meth:`compiled_B` and :meth:`compiled_project` return the
    same functions and ``params``.
    """
    try:
        got_B = _by_name(system.compiled_B(), loops)
    except Exception as exc:  # a broken plugin: refuse the case, name the failure
        return f"{system.name}.compiled_B() raised {type(exc).__name__}: {exc}"
    if got_B is None:
        hint = " (hadamard_factor is None)" if system.hadamard_factor is None else ""
        return f"{system.name} has no compiled B{hint}: see IsospectralSystem.compiled_B"
    if isinstance(got_B, str):
        return f"{system.name}.compiled_B(): {got_B}"
    try:
        got_P = _by_name(system.compiled_project(), loops)
        P_error = (
            None if not isinstance(got_P, str) else f"{system.name}.compiled_project(): {got_P}"
        )
    except Exception as exc:  # reported after the check of B, as before
        got_P, P_error = (
            None,
            f"{system.name}.compiled_project() raised {type(exc).__name__}: {exc}",
        )
    values = _KEPT.of(system)
    key = ("compiled maps", dtype)
    kept = values.get(key)
    if (
        P_error is None
        and kept is not None
        and _unchanged(kept[0], got_B)
        and _unchanged(kept[1], got_P)
    ):
        return kept[2]
    W = np.ascontiguousarray(W0.reshape(-1, *W0.shape[-2:])[0])
    Wp = W + 1e-3 * float(np.abs(W).max(initial=1.0)) * _wave(W.shape, dtype.kind == "c")
    Bw = _checked_map(
        f"{system.name}.compiled_B()",
        got_B,
        [(V, system.B(system.project_stage(V))) for V in (W, Wp)],
        dtype,
        loops,
    )
    if isinstance(Bw, str):
        return Bw
    if P_error is not None:
        return P_error
    P: tuple[Any, Array] | None = None
    if got_P is not None:
        Pw = _checked_map(
            f"{system.name}.compiled_project()", got_P, [(Wp, system.project(Wp))], dtype, loops
        )
        if isinstance(Pw, str):
            return Pw
        P = Pw
    params = np.concatenate([[float(loops.inline_code(got_B[0]))], Bw[1]])
    maps = ((Bw[0], params), P)
    # what the maps are now that the check compiled them
    signature = loops.map_signature(dtype)
    values[key] = (_identity(got_B, signature), _identity(got_P, signature), maps)
    return maps
