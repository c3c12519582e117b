"""The systems' maps as the compiled engine's loops take them (imported with
:mod:`lieflow.engines._compiled_loops`): the compiled forms of the built-in systems' ``B``
and projections (:func:`hadamard_B`, :func:`hadamard_B_skew`, :func:`hadamard_B_symmetric`,
:func:`symmetric_part`, :func:`skew_hermitian_part`), the loops' evaluation of ``B``
(:func:`_apply_B`: the Hadamard maps inline, :func:`inline_code`) and a compiled function in
the form the loops take it (:func:`function_pointer`, :func:`address`), or as a value of
numba's first-class function type in compiled code (:func:`_at`: from an address;
:func:`linked_function`: from a linker's symbol, for a map that calls another compiled
function).

The system enters as compiled functions passed as *arguments*, by address (an ``int64``,
:func:`address`), and called as numba's first-class function type of
:func:`~lieflow.engines._numba_jit.map_signature` (``B(W, params, out)`` and
``project(W, params, out)``, see :meth:`lieflow.IsospectralSystem.compiled_B`): a typed
function argument keeps the loops in numba's on-disk cache whatever the system (an untyped
dispatcher argument would make numba recompile them in every process), and an integer costs
the call no Python-level typing. ``B`` is the stage-value ``B`` of
:class:`~lieflow.schemes.base.StageProblem`, i.e. ``B(project_stage(W))``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from ._numba_jit import _inner, compiled_map, map_signature, numba

# ------------------------------------------------------------------ systems' maps
# Compiled forms of the built-in systems' B and projections (map_signature); ``params`` is
# the flattened factor S for the Hadamard maps.

#: How the loops evaluate ``B`` (the first entry of the ``params`` they are given; the
#: system's own ``params`` follow): through the system's map, or — for the built-in
#: Hadamard maps — the same loop inline. A call through a function pointer cannot be
#: inlined; on so(3) it cost ~165 ns of a ~900 ns midpoint step (measured).
CALL_MAP, INLINE_HADAMARD, INLINE_HADAMARD_SKEW, INLINE_HADAMARD_SYMMETRIC = 0, 1, 2, 3


@_inner
def _hadamard(W: Any, S: Any, out: Any, code: int) -> None:
    """``out = S ⊙ part(W)`` (``S`` flattened), ``part`` by ``code``: ``W`` itself
    (:data:`INLINE_HADAMARD`), its skew part ``(W - W^T)/2`` or its symmetric part
    ``(W + W^T)/2``: the Hadamard maps below, and :func:`_apply_B`'s inline form of them."""
    n = W.shape[0]
    for i in range(n):
        for j in range(n):
            if code == INLINE_HADAMARD:
                w = W[i, j]
            elif code == INLINE_HADAMARD_SKEW:
                w = 0.5 * (W[i, j] - W[j, i])
            else:
                w = 0.5 * (W[i, j] + W[j, i])
            out[i, j] = S[i * n + j] * w


@compiled_map
def hadamard_B(W: Any, params: Any, out: Any) -> None:
    """``out = S ⊙ W`` (``params = S.ravel()``): ``B`` on gl(n)."""
    _hadamard(W, params, out, INLINE_HADAMARD)


@compiled_map
def hadamard_B_skew(W: Any, params: Any, out: Any) -> None:
    """``out = S ⊙ (W - W^T)/2``: ``B`` of a stage value on so(n) (projected first)."""
    _hadamard(W, params, out, INLINE_HADAMARD_SKEW)


@compiled_map
def hadamard_B_symmetric(W: Any, params: Any, out: Any) -> None:
    """``out = S ⊙ (W + W^T)/2``: ``B`` of a stage value on the symmetric matrices."""
    _hadamard(W, params, out, INLINE_HADAMARD_SYMMETRIC)


@compiled_map
def symmetric_part(W: Any, params: Any, out: Any) -> None:
    """``out = (W + W^T)/2`` (``out`` may be ``W``; ``params`` unused)."""
    n = W.shape[0]
    for i in range(n):
        out[i, i] = W[i, i]
        for j in range(i + 1, n):
            a = 0.5 * (W[i, j] + W[j, i])
            out[i, j] = a
            out[j, i] = a


@compiled_map
def skew_hermitian_part(W: Any, params: Any, out: Any) -> None:
    """``out = (W - W^†)/2``, then, if ``params[0]``, minus its trace over ``n`` on the
    diagonal: the projection onto u(n), or su(N) (``out`` may be ``W``)."""
    n = W.shape[0]
    trace = 0.0j
    for i in range(n):
        d = 0.5 * (W[i, i] - np.conj(W[i, i]))
        out[i, i] = d
        trace += d
        for j in range(i + 1, n):
            a = 0.5 * (W[i, j] - np.conj(W[j, i]))
            out[i, j] = a
            out[j, i] = -np.conj(a)
    if params[0] != 0.0:
        trace = trace / n
        for i in range(n):
            out[i, i] -= trace


@_inner
def _apply_B(B: Any, params: Any, W: Any, out: Any) -> None:
    """``out = B(W)``: inline for the codes of :data:`CALL_MAP`, else
    ``B(W, params[1:], out)``."""
    code = int(params[0])
    S = params[1:]
    if code == CALL_MAP:
        B(W, S, out)
        return
    _hadamard(W, S, out, code)


def inline_code(function: Any) -> int:
    """The code :func:`_apply_B` evaluates ``function`` by (a built-in Hadamard map inline,
    anything else through its pointer)."""
    codes = {
        hadamard_B: INLINE_HADAMARD,
        hadamard_B_skew: INLINE_HADAMARD_SKEW,
        hadamard_B_symmetric: INLINE_HADAMARD_SYMMETRIC,
    }
    return next((c for f, c in codes.items() if f is function), CALL_MAP)


class _FunctionPointer:
    """A compiled function as the loops take it: its address, resolved once (numba's
    C-callable wrapper of the compiled ``signature``), with the function, which keeps the
    compiled code alive. The entry points take the address as an integer (:func:`address`,
    :func:`_at`)."""

    def __init__(self, function: Any, dtype: np.dtype, signature: Any = None) -> None:
        from numba.experimental.function_type import _get_wrapper_address

        self.function = function  # keeps the compiled code alive
        self.dtype = np.dtype(dtype)
        self._signature = map_signature(self.dtype) if signature is None else signature
        self.address = _get_wrapper_address(function, self._signature)

    def signature(self) -> Any:
        return self._signature


def function_pointer(function: Any, dtype: np.dtype) -> Any:
    """``function`` (a numba dispatcher compiled for :func:`map_signature` of ``dtype``) in
    the form the loops take it, cheaply converted on every call.

    The maps of this module (the built-in systems' ``B`` and projections: objects that live
    as long as the process and are compiled once) are resolved once per process, like
    :func:`gemm`; any other function on every call (~15 µs), since its dispatcher could be
    recompiled."""
    if isinstance(function, _FunctionPointer) and function.dtype == dtype:
        return function
    name = getattr(getattr(function, "py_func", None), "__name__", "")
    if globals().get(name) is not function:
        return _FunctionPointer(function, dtype)
    return _module_map_pointer(function, np.dtype(dtype))


@functools.cache
def _module_map_pointer(function: Any, dtype: np.dtype) -> Any:
    """:func:`function_pointer` of one of this module's maps, made once per process."""
    return _FunctionPointer(function, dtype)


def address(pointer: Any, signature: Any) -> int:
    """The address of ``pointer`` (a :class:`_FunctionPointer`: :func:`function_pointer`,
    :func:`gemm`) for the entry points, which take their functions as integers (:func:`_at`)
    and so cannot check them: raises ``TypeError`` unless ``pointer`` is a resolved function
    of exactly ``signature`` (the type the loops call it with)."""
    if not (isinstance(pointer, _FunctionPointer) and pointer.signature() == signature):
        raise TypeError(
            f"the compiled loops take a resolved function of signature {signature}, got {pointer!r}"
        )
    return int(pointer.address)


def _at(signature_of: Callable[[np.dtype], Any]) -> Any:
    """An intrinsic ``f(address, like)``: the compiled function at ``address`` (an
    ``int64``: a :class:`_FunctionPointer`'s :attr:`~_FunctionPointer.address`) as a value of
    the first-class function type of ``signature_of(like.dtype)`` — the value numba unboxes
    from a :class:`_FunctionPointer` argument (the address in its C-callable slot, the
    others null), made in compiled code: the entry points take the addresses as integers,
    which their dispatcher types without Python (a function object is typed by a Python
    call per argument and call, ~4 µs each)."""

    def at(typingctx: Any, address: Any, like: Any) -> Any:
        from numba.core import cgutils
        from numba.np.numpy_support import as_dtype

        if not isinstance(address, numba.types.Integer):
            return None
        ftype = numba.types.FunctionType(signature_of(as_dtype(like.dtype)))

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            value = cgutils.create_struct_proxy(ftype)(context, builder)
            pointer = context.get_value_type(numba.types.voidptr)
            value.c_addr = builder.inttoptr(args[0], pointer)
            value.py_addr = cgutils.get_null_value(pointer)
            value.jit_addr = cgutils.get_null_value(pointer)
            return value._getvalue()

        return ftype(address, like), codegen

    return numba.extending.intrinsic(at)


def linked_function(symbol: str, function: Any, signature: Any) -> Any:
    """``function`` (a numba dispatcher, compiled for ``signature`` with its C wrapper: not
    :func:`_helper`'s options) under the linker's name ``symbol``, for compiled code to call
    through the intrinsic returned, ``f(like)``, which gives that function as a value of
    numba's first-class function type of ``signature`` (``like``: any value, unused but for
    typing).

    A compiled function that calls another by name has numba link the callee's code into
    its own and optimize and generate it again (a second compilation of the callee's code,
    in every caller: issue 37 item 11). Called through its symbol, the callee's code is
    compiled once; the caller's code (also as loaded from numba's disk cache) holds only the
    symbol, which the linker resolves in each process to the address registered here (as
    numba's own runtime functions are), so no process-local address is stored anywhere.
    Register before any function that calls it is compiled or loaded."""
    from llvmlite import binding
    from numba.experimental.function_type import _get_wrapper_address

    if signature.args not in function.overloads:
        function.compile(signature)
    binding.add_symbol(symbol, _get_wrapper_address(function, signature))

    def at(typingctx: Any, like: Any) -> Any:
        from llvmlite import ir
        from numba.core import cgutils

        ftype = numba.types.FunctionType(signature)

        def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
            declared = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), []), symbol
            )
            value = cgutils.create_struct_proxy(ftype)(context, builder)
            pointer = context.get_value_type(numba.types.voidptr)
            value.c_addr = builder.bitcast(declared, pointer)
            value.py_addr = cgutils.get_null_value(pointer)
            value.jit_addr = cgutils.get_null_value(pointer)
            return value._getvalue()

        return ftype(like), codegen

    return numba.extending.intrinsic(at)
