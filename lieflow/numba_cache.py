"""Where lieflow's compiled code is cached on disk: a per-user cache directory, never the
installed package.

numba's ``cache=True`` writes its cache next to the module (``<package>/__pycache__``) when
that folder is writable. For an installed lieflow that folder is in ``site-packages``, and
the files numba leaves there are not in the wheel's record: uninstalling lieflow (e.g. to
reinstall it in editable mode, as the README's second command does after its first) leaves
a ``site-packages/lieflow/`` folder that Python then imports as an empty namespace package
in place of the editable install (``cannot import name '__version__' from 'lieflow'``).

:func:`cached_njit` compiles like ``numba.njit`` with its disk cache in
:func:`cache_directory` instead; lieflow's loops and the plugins' compiled maps use it. It
imports numba: import this module only where numba is installed.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numba
from numba.core import caching, config

F = TypeVar("F", bound=Callable[..., Any])


def cache_directory() -> Path:
    """The directory of lieflow's numba cache.

    numba's own cache directory if the user set one (``NUMBA_CACHE_DIR``, as numba read it
    at import), else ``$XDG_CACHE_HOME/lieflow/numba``, else ``~/.cache/lieflow/numba``
    (the XDG base directory specification's default). Below it, numba's cache of each
    source folder has a subfolder of its own (named by a hash of the folder's path), so two
    installations of lieflow never share cache files.
    """
    numba_dir = getattr(config, "CACHE_DIR", "")
    if numba_dir:
        return Path(numba_dir)
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "lieflow" / "numba"


class _UserCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """numba's cache locator for a function of a source file, in :func:`cache_directory`
    (numba's ``UserProvidedCacheLocator``, with lieflow's directory in place of
    ``NUMBA_CACHE_DIR``)."""

    def __init__(self, py_func: Callable[..., Any], py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        subpath = self.get_suitable_cache_subpath(py_file)
        self._cache_path = str(cache_directory() / subpath)

    def get_cache_path(self) -> str:
        return self._cache_path


class _UserCacheImpl(caching.CompileResultCacheImpl):
    """numba's cache of compiled functions, located only by :class:`_UserCacheLocator`
    (never in the source tree). An explicit ``NUMBA_CACHE_LOCATOR_CLASSES`` still wins."""

    _locator_classes = [_UserCacheLocator]  # noqa: RUF012 - numba's attribute, a list


class _UserFunctionCache(caching.FunctionCache):
    _impl_class = _UserCacheImpl


def cached_njit(func: F, *, signature: Any = None, **options: Any) -> F:
    """``numba.njit(signature, cache=True, **options)(func)``, cached in
    :func:`cache_directory`.

    Without ``signature`` the function compiles at its first call for the types it is
    called with, as ``numba.njit`` does; with one it compiles now for that signature only.
    Where no cache directory can be created or written, the function is compiled in memory
    in every process (numba's own fallback is to raise ``RuntimeError``).
    """
    dispatcher = numba.njit(**options)(func)
    try:
        cache = _UserFunctionCache(func)
    except RuntimeError:  # no writable cache location: compile in memory
        pass
    else:
        dispatcher._cache = cache  # what numba's enable_caching() does, with our locator
    if signature is not None:
        dispatcher.compile(signature)
        dispatcher.disable_compile()
    return dispatcher
