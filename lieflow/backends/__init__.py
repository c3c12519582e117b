"""Arrays of other libraries: the namespace of an array, host copies, constants on a device.

lieflow's numerics are written once against the Python array API standard
(https://data-apis.org/array-api/): a function that receives arrays asks :func:`namespace` for
the module ``xp`` that operates on them and calls ``xp.matmul``, ``xp.conj``, ... NumPy arrays
get ``numpy`` itself (no wrapper, no import of anything optional: the core stays
numpy/scipy/attrs/pluggy); arrays of any other library (CuPy, PyTorch, JAX,
``array_api_strict``) get the standard-conforming namespace of ``array-api-compat``, the
optional extra ``lieflow[array]``. The library is selected by the array passed in: a state on
a GPU stays there, and data reach the host through :func:`to_numpy` (the stepping loop, once per
chunk of states; sinks, for a checkpoint's warm start; the traced engine returns NumPy for
a NumPy state).
"""

from __future__ import annotations

import importlib
import math
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = [
    "all_finite",
    "copy",
    "device_norms",
    "device_of",
    "from_host",
    "host_norms",
    "identity",
    "is_foreign_array",
    "is_numpy",
    "is_traced",
    "machine_epsilon",
    "namespace",
    "place",
    "put",
    "to_numpy",
]

#: The array libraries a device name may start with (:func:`place`).
DEVICE_LIBRARIES = ("cpu", "cupy", "torch", "jax", "array_api_strict")


def is_numpy(x: Any) -> bool:
    """Whether ``x`` is a NumPy array or scalar (or a Python number)."""
    # an exact ndarray first: a type comparison, a third of an isinstance with a tuple
    return type(x) is np.ndarray or isinstance(x, (np.ndarray, np.generic, int, float, complex))


def is_foreign_array(x: Any) -> bool:
    """Whether ``x`` is an array of a library other than NumPy (CuPy, PyTorch, JAX,
    ``array_api_strict``, ...): what :func:`namespace` serves through array-api-compat.
    Lists, scalars and NumPy arrays are not."""
    if is_numpy(x) or isinstance(x, (list, tuple)):
        return False
    if hasattr(x, "__array_namespace__"):
        return True
    try:
        import array_api_compat
    except ImportError:
        return False
    return bool(array_api_compat.is_array_api_obj(x))


def _compat() -> ModuleType:
    try:
        import array_api_compat
    except ImportError as exc:  # pragma: no cover - the extra is installed in CI
        raise InputError(
            "arrays of a library other than NumPy need array-api-compat: install the "
            "optional extra with `pip install 'lieflow[array]'` (or pass NumPy arrays)"
        ) from exc
    return array_api_compat


def namespace(*arrays: Any) -> ModuleType:
    """The array namespace of ``arrays``: ``numpy`` for NumPy arrays (and Python numbers),
    else the array API namespace of their library (``array_api_compat.array_namespace``).

    Raises :class:`~lieflow.errors.InputError` for arrays of two different libraries or of
    a library the array API does not cover.
    """
    others = [a for a in arrays if a is not None and not is_numpy(a)]
    if not others:
        return np
    try:
        return _compat().array_namespace(*others)
    except TypeError as exc:
        kinds = sorted({type(a).__module__ + "." + type(a).__name__ for a in others})
        raise InputError(
            f"no array API namespace for arrays of type {', '.join(kinds)} ({exc}); pass "
            "arrays of one library that follows the array API standard (NumPy, CuPy, "
            "PyTorch, JAX, array_api_strict)"
        ) from exc


def is_traced(x: Any) -> bool:
    """Whether ``x`` is an abstract value of a program being traced (``jax.jit``): it has
    no data, and what is computed from it belongs to that one trace — a cache must not keep
    it (it would leak out of the trace)."""
    jax = sys.modules.get("jax")  # not imported unless JAX arrays are in use
    return jax is not None and isinstance(x, jax.core.Tracer)


def device_of(x: Any) -> Any:
    """The device ``x`` lives on (``"cpu"`` for NumPy arrays)."""
    if is_numpy(x):
        return "cpu"
    return _compat().device(x)


def from_host(a: Any, like: Any, dtype: Any = None) -> Any:
    """The host (NumPy) array ``a`` as an array of ``like``'s library on ``like``'s device
    (``dtype``: a dtype of that library, default ``a``'s). ``a`` itself for NumPy ``like``.

    One host-to-device copy: callers cache the result of constants (e.g. per operator).
    The cast happens on the host where ``dtype`` is a NumPy dtype (NumPy's, JAX's and
    CuPy's are), so that the result is a concrete array even while ``like`` is being traced
    (``jax.jit``): a constant of the program, which a cache may keep; other libraries'
    dtypes are cast on the device.
    """
    if is_numpy(like):
        return a if dtype is None else np.asarray(a, dtype=dtype)
    xp = namespace(like)
    host = np.ascontiguousarray(a)
    if dtype is not None:
        try:
            host, dtype = host.astype(np.dtype(dtype), copy=False), None
        except TypeError:  # not a NumPy dtype (PyTorch's)
            pass
    out = xp.asarray(host, device=device_of(like))
    return out if dtype is None else xp.astype(out, dtype)


def to_numpy(x: Any) -> np.ndarray:
    """``x`` as a NumPy array on the host: the array itself for NumPy input, else one
    device-to-host copy (CuPy ``.get()``, PyTorch ``.cpu()``, DLPack otherwise)."""
    if is_numpy(x):
        return np.asarray(x)
    compat = _compat()
    if compat.is_cupy_array(x):
        return np.asarray(x.get())
    if compat.is_torch_array(x):
        return np.asarray(x.detach().cpu().numpy())
    try:
        return np.asarray(np.from_dlpack(compat.to_device(x, "cpu")))
    except (TypeError, ValueError, AttributeError, RuntimeError, BufferError):
        return np.asarray(x)


def copy(x: Any) -> Any:
    """A new array equal to ``x`` (same library, device and dtype)."""
    if is_numpy(x):
        return np.array(x, copy=True)
    return namespace(x).asarray(x, copy=True)


def identity(n: int, like: Any) -> Any:
    """The ``n×n`` identity matrix in ``like``'s library, dtype and device."""
    if is_numpy(like):
        return np.eye(n, dtype=like.dtype)
    return namespace(like).eye(n, dtype=like.dtype, device=device_of(like))


def put(stack: Any, index: Any, value: Any, minus: Any = None) -> tuple[Any, Any]:
    """``stack`` with ``stack[index]`` set to ``value`` (or ``value - minus``), and that
    entry: ``(stack, stack[index])``. ``index`` (a Python or 0-d integer array) indexes the
    first axis. The one way lieflow writes into an array a traced program carries (the
    Anderson history, :mod:`lieflow.solvers.anderson`).

    In place for NumPy (the difference computed into the entry, no temporary; the entry
    returned is a view), CuPy and PyTorch (the ``stack`` passed in is changed); a new
    array ``stack.at[index].set(...)`` for JAX (immutable arrays: under ``jax.jit`` the
    compiler updates the buffer in place); other libraries (``array_api_strict``) assign
    in place at ``int(index)`` (eager only). The entry returned for all but NumPy is the
    value written (``value - minus`` computed once).
    """
    if is_numpy(stack):
        entry = stack[int(index)]
        if minus is None:
            entry[...] = value
        else:
            np.subtract(value, minus, out=entry)
        return stack, entry
    entry = value if minus is None else value - minus
    compat = _compat()
    if compat.is_jax_array(stack):
        return stack.at[index].set(entry), entry
    if compat.is_torch_array(stack) or compat.is_cupy_array(stack):
        stack[index] = entry  # a 0-d device index: no synchronisation
    else:
        stack[int(index), ...] = entry
    return stack, entry


def device_norms(x: Any, core_ndim: int) -> Any:
    """Frobenius norms of ``x`` over its trailing ``core_ndim`` axes, an array of the batch
    shape on ``x``'s device (no synchronisation: a library that queues work returns at once)."""
    xp = namespace(x)
    axes = tuple(range(-core_ndim, 0))
    squares = xp.real(x * xp.conj(x)) if xp.isdtype(x.dtype, "complex floating") else x * x
    return xp.sqrt(xp.sum(squares, axis=axes))


def host_norms(x: Any, core_ndim: int) -> np.ndarray:
    """:func:`device_norms` as a float64 NumPy array: one small device-to-host copy (a
    synchronisation)."""
    return np.asarray(to_numpy(device_norms(x, core_ndim)), dtype=np.float64)


def machine_epsilon(dtype: Any, like: Any) -> float:
    """Machine epsilon of the floating ``dtype`` of ``like``'s library."""
    if is_numpy(like):
        return float(np.finfo(dtype).eps)
    return float(namespace(like).finfo(dtype).eps)


#: Up to this many entries a float64 array's norm is ``math.hypot`` of its entries as Python
#: floats (no NumPy reduction): :func:`all_finite` here, the fixed-point check's norms in
#: :mod:`lieflow.solvers.fixed_point`.
HYPOT_SIZE = 64


def numpy_c_function(name: str, public: Callable[..., Any]) -> Callable[..., Any]:
    """The C function ``name`` behind the NumPy function ``public`` (``c_einsum`` behind
    :func:`numpy.einsum`, ``vdot`` behind :func:`numpy.vdot`): the same kernels, hence the
    same bits, without the Python or dispatch layers in front of it (array-function
    dispatch; ``einsum``'s ``optimize`` branch): about 1 µs of a 2 µs ``einsum`` call on a
    3×3 matrix, 0.2 µs of a 0.5 µs ``vdot``. ``public`` itself where a NumPy version lacks
    it."""
    for module in (
        "numpy._core.multiarray",
        "numpy._core._multiarray_umath",
        "numpy.core.multiarray",
        "numpy.core._multiarray_umath",
    ):
        try:
            found = getattr(importlib.import_module(module), name, None)
        except ImportError:
            continue
        if callable(found) and found is not public:
            return found
    return public


#: ``vdot(a, b)`` of two float64 vectors as :func:`numpy.vdot` computes it (a constant):
#: BLAS ``ddot``, the bits of ``a.dot(b)``, but without NumPy's floating-point error check:
#: where squares of finite entries overflow, ``vdot(x, x)`` is ``inf`` and no warning is
#: raised (``ndarray.dot`` warns).
vdot: Callable[..., Any] = numpy_c_function("vdot", np.vdot)


def all_finite(x: Any) -> bool:
    """Whether every entry of ``x`` is finite (one scalar to the host)."""
    if type(x) is np.ndarray and x.dtype.char == "d" and x.size <= HYPOT_SIZE:
        # a small float64 array (a state checked after each step): its norm by math.hypot
        # of the entries as Python floats (3×3: 0.3 against 1.5 µs), finite exactly when
        # every entry is (an inf or nan entry makes it inf or nan, and hypot does not
        # overflow before the norm itself does); an infinite norm is checked entrywise
        try:
            if math.hypot(*x.ravel().tolist()) < math.inf:
                return True
        except OverflowError:
            pass
        return bool(np.isfinite(x).all())
    if type(x) is np.ndarray and x.dtype.char == "d":
        # a larger one: the same test on its squared norm by vdot (BLAS, no warning where
        # the squares overflow; so(10): 0.65 against 1.6 µs for isfinite and all)
        flat = x.ravel()
        if vdot(flat, flat) < math.inf:
            return True
        return bool(np.isfinite(x).all())
    if is_numpy(x):
        return bool(np.isfinite(x).all())  # the method: np.all's Python layers cost 1 µs
    xp = namespace(x)
    return bool(xp.all(xp.isfinite(x)))


def check_device(name: str) -> str:
    """``name`` if it names a device :func:`place` knows (``"cpu"``, ``"cupy"``,
    ``"cupy:1"``, ``"torch"``, ``"torch:cuda:1"``, ``"jax"``, ``"jax:gpu:0"``,
    ``"array_api_strict"``), without importing its library; else
    :class:`~lieflow.errors.InputError`."""
    library, _, rest = name.partition(":")
    if library not in DEVICE_LIBRARIES or (library in ("cpu", "array_api_strict") and rest):
        raise InputError(
            f"unknown device {name!r}: use one of 'cpu', 'cupy' or 'cupy:<index>', 'torch' or "
            "'torch:<torch device>' (e.g. 'torch:cuda:1'), 'jax' or 'jax:<platform>:<index>', "
            "'array_api_strict' (the CPU reference of the array API, for tests)"
        )
    return name


def place(a: Any, device: str) -> Any:
    """The host array ``a`` on ``device`` (:func:`check_device`): ``"cpu"`` returns ``a``
    itself; ``"cupy[:i]"`` a CuPy array on GPU ``i`` (default: the current one);
    ``"torch[:dev]"`` a PyTorch tensor on ``dev`` (default ``"cuda"``); ``"jax[:platform[:i]]"``
    a JAX array (default: JAX's default device; double precision is switched on, as
    ``jax_enable_x64``, since lieflow's states are float64/complex128); ``"array_api_strict"``
    an ``array_api_strict`` array (the CPU, through the array API: what the tests run).

    Raises :class:`~lieflow.errors.InputError` when the library is not installed or the
    device does not exist.
    """
    library, _, rest = check_device(device).partition(":")
    if library == "cpu":
        return a
    data = np.ascontiguousarray(a)
    try:
        module = importlib.import_module(library)
    except ImportError as exc:
        raise InputError(
            f"device {device!r} needs {library}, which is not installed: install it (with "
            "CUDA for a GPU) or choose another device"
        ) from exc
    try:
        if library == "cupy":
            with module.cuda.Device(int(rest) if rest else module.cuda.Device().id):
                return module.asarray(data)
        if library == "torch":
            return module.from_numpy(data).to(rest or "cuda")
        if library == "jax":
            module.config.update("jax_enable_x64", True)
            platform, _, index = rest.partition(":")
            devices = module.devices(platform) if platform else module.devices()
            return module.device_put(data, devices[int(index) if index else 0])
        return module.asarray(data)
    except (RuntimeError, ValueError, IndexError, AttributeError, AssertionError) as exc:
        raise InputError(f"cannot place the state on device {device!r}: {exc}") from exc
