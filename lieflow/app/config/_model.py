"""What a run configuration holds, parsed and type-checked: :class:`Config` and its
sections (:class:`Component`, :class:`InitialCondition`, :class:`RunSection`, ...), and the
identity of a run (:meth:`Config.identity`, :func:`identity_changes`)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Literal

import attrs

from ...sinks import run_identity


def _frozen_params(value: Mapping[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(dict(value))


@attrs.frozen
class Component:
    """A registry name with keyword parameters: a ``[system]``, ``[scheme]`` or ``[solver]``
    section."""

    name: str
    params: Mapping[str, Any] = attrs.field(factory=dict, converter=_frozen_params)

    def as_dict(self) -> dict[str, Any]:
        """A plain (JSON-able) dictionary."""
        return {"name": self.name, "params": dict(self.params)}


@attrs.frozen
class SplittingSection:
    """The optional ``[splitting]`` section: the scheme composed with other flows.

    Attributes
    ----------
    method : str
        ``"lie"``, ``"strang"``, ``"triple_jump"`` or ``"suzuki5"``
        (:meth:`lieflow.Splitting.named`).
    flows : tuple of Component
        Registered flows (``lieflow list --kind flow``) in the order of
        :meth:`lieflow.Splitting.strang`; the scheme is the last, inner flow.
    """

    method: str
    flows: tuple[Component, ...]

    def as_dict(self) -> dict[str, Any]:
        """A plain (JSON-able) dictionary."""
        return {"method": self.method, "flows": [c.as_dict() for c in self.flows]}


@attrs.frozen
class InitialCondition:
    """The ``[initial]`` section: a seeded random element, an explicit matrix or a file.

    Attributes
    ----------
    kind : {"random", "matrix", "file"}
        Which of the three forms was given.
    seed : int or None
        Seed of the system's :meth:`~lieflow.IsospectralSystem.random_state`
        (``kind == "random"``).
    scale : float
        Factor applied to the random state (the default ``random_state`` has unit
        Frobenius norm; a system may restrict the scale, e.g. point vortices, whose state
        norms are their strengths, accept only 1).
    matrix : tuple of tuple of float, or None
        Rows of the explicit matrix; ``imag`` holds its imaginary part, if any.
    file : Path or None
        A ``.npy`` file, resolved against the configuration's directory.
    seeds : tuple of int, or None
        An ensemble of random states, one per seed (``seeds = [0, 1, 2]`` instead of
        ``seed``): ``W0`` has shape ``(K, n, n)`` and the run advances all ``K`` at once.
    perturb : Perturbation or None
        An ensemble of perturbations of the initial condition (``[initial.perturb]``).
    """

    kind: Literal["random", "matrix", "file"]
    seed: int | None = None
    scale: float = 1.0
    matrix: tuple[tuple[float, ...], ...] | None = None
    imag: tuple[tuple[float, ...], ...] | None = None
    file: Path | None = None
    seeds: tuple[int, ...] | None = None
    perturb: Perturbation | None = None

    @property
    def members(self) -> int | None:
        """The ensemble size ``K``, or ``None`` for a single initial condition."""
        if self.seeds is not None:
            return len(self.seeds)
        return None if self.perturb is None else self.perturb.members

    def as_dict(self) -> dict[str, Any]:
        """A plain (JSON-able) dictionary."""
        return {
            "kind": self.kind,
            "seed": self.seed,
            "scale": self.scale,
            "matrix": self.matrix,
            "imag": self.imag,
            "file": None if self.file is None else str(self.file),
            **({} if self.seeds is None else {"seeds": list(self.seeds)}),
            **({} if self.perturb is None else {"perturb": attrs.asdict(self.perturb)}),
        }


@attrs.frozen
class Perturbation:
    """``[initial.perturb]``: an ensemble of ``members`` initial conditions
    ``W0 + size * R_k``, ``R_k`` the system's ``random_state(seed + k)`` (unit Frobenius
    norm by default), each checked by ``system.validate``.

    Attributes
    ----------
    members : int
        Ensemble size ``K``.
    size : float
        Factor on the random perturbations.
    seed : int
        Seed of the first member's perturbation.
    """

    members: int
    size: float
    seed: int = 0


@attrs.frozen
class RunSection:
    """The ``[run]`` section: step size, number of steps, save cadence and output file.

    Attributes
    ----------
    h : float
        Step size.
    steps : int
        Number of steps (given, or ``t_final / h``).
    save_every : int
        Keep every ``save_every``-th state (the last is always kept).
    output : Path
        The trajectory file.
    t_final : float or None
        The final time, when the section gave ``t_final`` instead of ``steps``.
    engine : {"auto", "numpy", "compiled", "jax"}
        How the scheme's steps are computed (:func:`lieflow.integrate`'s ``engine``). Not
        part of the run's identity: a file may be resumed with another engine (the steps
        then agree to roundoff, not bit for bit).
    casimir_shift : float or "auto"
        Step the scheme on the Hamiltonian plus a Casimir (:func:`lieflow.integrate`'s
        ``casimir_shift``); ``0`` (default): the scheme as defined. Part of the identity
        when not 0.
    checkpoint : float or None
        Seconds between checkpoints (the resume point; saved states are written in blocks
        between them), ``None`` (``checkpoint = "saves"``): at every saved state. Not part
        of the identity.
    device : str
        Where the steps run (:func:`lieflow.backends.place`): ``"cpu"`` (default; NumPy),
        ``"cupy"``, ``"cupy:1"``, ``"torch"``, ``"torch:cuda:1"``, ``"jax"``, ... The state
        (and, on resume, the warm start) is placed there once; states reach the file a chunk
        at a time. Other than ``"cpu"`` the steps run on the array library: compiled by
        JAX where it runs on that device (the traced engine, :mod:`lieflow.engines`), else
        eagerly (``engine = "compiled"`` is refused). Not part of the identity.
    """

    h: float
    steps: int
    save_every: int
    output: Path
    t_final: float | None = None
    engine: str = "auto"
    casimir_shift: float | str = 0.0
    checkpoint: float | None = 1.0
    device: str = "cpu"


@attrs.frozen
class Config:
    """A parsed, type-checked run configuration (see the module docstring).

    Attributes
    ----------
    system, scheme, solver : Component
        Registry names and parameters.
    initial : InitialCondition
        How to make ``W0``.
    run : RunSection
        Step size, steps, save cadence, output path.
    text : str
        The configuration's full text (stored in the output file).
    source : str
        Where the text came from (a path, or ``"<string>"``).
    """

    system: Component
    initial: InitialCondition
    scheme: Component
    solver: Component
    run: RunSection
    text: str = attrs.field(repr=False)
    source: str = "<string>"
    splitting: SplittingSection | None = None

    def identity(self) -> str:
        """JSON of everything that defines the trajectory except its length and location
        (:func:`lieflow.sinks.run_identity` of the configuration's tables).

        Two configurations with the same identity (and the same ``W0``) compute the same
        steps, so one may resume the other's file, possibly with more steps.
        """
        splitting = None if self.splitting is None else self.splitting.as_dict()
        return run_identity(system=self.system.as_dict(), scheme=self.scheme.as_dict(),
                            solver=self.solver.as_dict(), h=self.run.h,
                            save_every=self.run.save_every, splitting=splitting,
                            casimir_shift=self.run.casimir_shift or None)  # fmt: skip


def _flatten(value: Any, prefix: str, out: dict[str, Any]) -> dict[str, Any]:
    if isinstance(value, dict) and value:
        for key, item in value.items():
            _flatten(item, f"{prefix}.{key}" if prefix else str(key), out)
    else:
        out[prefix] = value
    return out


def _toml_key(path: str) -> str:
    """``"scheme.params.form"`` -> ``"[scheme] params.form"``; ``"h"`` -> ``"[run] h"``."""
    head, _, rest = path.partition(".")
    if head in ("system", "scheme", "solver") and rest:
        return f"[{head}] {rest}"
    return f"[run] {path}"


def identity_changes(old: str, new: str) -> list[str]:
    """The keys in which two :meth:`Config.identity` strings differ, as readable lines.

    Examples
    --------
    >>> a = '{"h": 0.1, "scheme": {"name": "gauss2", "params": {}}}'
    >>> b = '{"h": 0.05, "scheme": {"name": "gauss3", "params": {}}}'
    >>> identity_changes(a, b)
    ['[run] h: 0.1 -> 0.05', "[scheme] name: 'gauss2' -> 'gauss3'"]
    """
    try:
        before, after = _flatten(json.loads(old), "", {}), _flatten(json.loads(new), "", {})
    except (ValueError, TypeError):
        return []
    missing = object()
    lines = []
    for path in sorted(set(before) | set(after)):
        a, b = before.get(path, missing), after.get(path, missing)
        if a != b:
            shown = ["(not set)" if v is missing else repr(v) for v in (a, b)]
            lines.append(f"{_toml_key(path)}: {shown[0]} -> {shown[1]}")
    return lines
