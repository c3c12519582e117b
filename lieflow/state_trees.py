"""Flow states as trees of arrays: the few operations the stepping loop and checkpoints need.

A *state tree* is ``None``, an array, a Python scalar or string (a *leaf*), or a container
of state trees: a ``tuple``, a ``list``, a ``dict`` with string keys, or an ``attrs``
instance (its fields, in order). A :class:`~lieflow.flows.SchemeFlow` keeps its warm start
(:class:`~lieflow.warm_start.WarmStart`) as one; a :class:`~lieflow.flows.Splitting` keeps a
tuple of its sub-steps' states. Containers keep their shape from step to step; leaves may
change (``None`` before the first step, an array after).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import attrs
import numpy as np

from .backends import host_norms
from .solvers.base import squared_norm

__all__ = ["leaves", "map_leaves", "paths", "rebuild", "sum_of_squares"]


def _children(tree: Any) -> list[tuple[str, Any]] | None:
    """``(key, child)`` pairs of a container, ``None`` for a leaf."""
    if isinstance(tree, (tuple, list)):
        return [(str(i), v) for i, v in enumerate(tree)]
    if isinstance(tree, dict):
        return [(str(k), v) for k, v in tree.items()]
    if attrs.has(type(tree)):
        return [(f.name, getattr(tree, f.name)) for f in attrs.fields(type(tree))]
    return None


def _build(template: Any, values: list[Any]) -> Any:
    """A container like ``template`` holding ``values`` (in its children's order)."""
    if isinstance(template, tuple):
        return tuple(values)
    if isinstance(template, list):
        return list(values)
    if isinstance(template, dict):
        return dict(zip(template.keys(), values, strict=True))
    fields = attrs.fields(type(template))
    return attrs.evolve(template, **{f.name: v for f, v in zip(fields, values, strict=True)})


def map_leaves(f: Callable[..., Any], tree: Any, *others: Any) -> Any:
    """``f`` applied leaf by leaf to ``tree`` and trees of the same shape ``others``."""
    children = _children(tree)
    if children is None:
        return f(tree, *others)
    rest = [[c for _, c in _children(o) or ()] for o in others]
    values = [map_leaves(f, c, *(r[i] for r in rest)) for i, (_, c) in enumerate(children)]
    return _build(tree, values)


def leaves(tree: Any) -> Iterator[Any]:
    """The leaves of ``tree``, depth first."""
    for _, leaf in paths(tree):
        yield leaf


def paths(tree: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(path, leaf)`` pairs, paths joined with ``/`` (``""`` for a bare leaf)."""
    children = _children(tree)
    if children is None:
        yield prefix, tree
        return
    for key, child in children:
        yield from paths(child, f"{prefix}/{key}" if prefix else key)


def rebuild(template: Any, values: dict[str, Any]) -> Any:
    """A tree shaped like ``template`` whose leaf at each path is ``values[path]`` (the
    template's own leaf where ``values`` has none). Inverse of :func:`paths`."""

    def go(tree: Any, prefix: str) -> Any:
        children = _children(tree)
        if children is None:
            return values.get(prefix, tree)
        return _build(
            tree, [go(child, f"{prefix}/{key}" if prefix else key) for key, child in children]
        )

    return go(template, "")


def sum_of_squares(tree: Any) -> float:
    """``sum ||leaf||_F^2`` over the floating-point array leaves (the squared norm of the
    whole tree)."""
    total = 0.0
    for leaf in leaves(tree):
        if isinstance(leaf, np.ndarray):
            if leaf.dtype.kind in "fc":
                total += squared_norm(leaf)
        elif hasattr(leaf, "__array_namespace__"):  # another array library
            total += float(np.sum(host_norms(leaf, leaf.ndim) ** 2))
    return total
