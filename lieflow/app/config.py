"""Run configurations for ``lieflow run``: TOML parsing, validation and building.

A configuration names a system, an initial condition, a scheme, a solver and the run
settings::

    [system]
    name = "rigid_body"
    params = { inertia = [1.0, 2.0, 3.0] }

    [initial]            # exactly one of: random = true (with seed), matrix, file
    random = true        # the system's own random_state(seed), checked by system.validate
    seed = 0
    scale = 1.0          # optional factor on it

    [scheme]
    name = "gauss3"

    [solver]             # optional; fixed_point with its defaults if left out
    name = "fixed_point"
    params = { rtol = 1e-15 }

    [splitting]          # optional: compose the scheme with other flows (plugins')
    method = "strang"    # lie, strang, triple_jump or suzuki5; the scheme is the inner flow
    flows = [{ name = "viscosity", params = { nu = 1e-4 } }]

    [run]
    h = 0.1
    steps = 2000         # or t_final = 200.0 (a whole number of steps h): exactly one
    save_every = 10      # keep every 10th state
    output = "rigid_body.h5"
    casimir_shift = "auto"  # optional: step on eta plus a Casimir (lieflow.integrate)
    checkpoint = 1.0     # optional: seconds between checkpoints (default 1), or "saves"

:func:`parse_config` turns the text into a frozen :class:`Config` (checking every key's
presence and type, refusing unknown keys), and :func:`build` turns a :class:`Config` into
the objects of a run (:class:`RunSetup`): system, scheme and solver from the registry, the
validated initial condition and the checked output path. Every problem raises
:class:`ConfigError`, whose one-paragraph message names the key and the fix; nothing is
written to disk by either function.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal, cast

import attrs
import numpy as np

from ..algebras import Array
from ..backends import check_device
from ..engines import ENGINES, Engine
from ..errors import InputError, LieflowError, PluginError, quote, shorten, with_fix, without_fix
from ..flows import Flow, Splitting
from ..plugins import Kind, Registry, default_registry
from ..runs import MAX_STEPS, RunSpec
from ..schemes.base import Scheme
from ..sinks import RunInfo, run_identity
from ..solvers.base import Solver
from ..systems.base import IsospectralSystem

if TYPE_CHECKING:  # pragma: no cover
    from .io import TrajectoryHeader

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = [
    "Component",
    "Config",
    "ConfigError",
    "InitialCondition",
    "Perturbation",
    "RunSettings",
    "RunSetup",
    "SplittingSettings",
    "build",
    "check_output_path",
    "identity_changes",
    "load_config",
    "parse_config",
]

_SECTIONS = ("system", "initial", "scheme", "solver", "splitting", "run")
_OPTIONAL = ("solver", "splitting")


class ConfigError(LieflowError, ValueError):
    """A run configuration is invalid.

    Attributes
    ----------
    key : str
        The offending key, written as in the file (``"[run] steps"``), or ``""`` when the
        problem is with the file as a whole.
    """

    def __init__(self, message: str, key: str = "") -> None:
        super().__init__(message)
        self.key = key


def _fail(source: str, key: str, problem: str, fix: str) -> ConfigError:
    where = f"{source}: {key}: " if key else f"{source}: "
    return ConfigError(f"{where}{problem}. To fix: {fix}.", key)


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
class SplittingSettings:
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
class RunSettings:
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
    run : RunSettings
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
    run: RunSettings
    text: str = attrs.field(repr=False)
    source: str = "<string>"
    splitting: SplittingSettings | None = None

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


@attrs.frozen(eq=False)
class RunSetup:
    """Everything a run needs, built and validated; nothing has been written yet.

    Attributes
    ----------
    config : Config
        The configuration.
    system, scheme, solver
        Built from the registry.
    W0 : ndarray
        The validated initial condition.
    output : Path
        The trajectory file (absolute).
    replace : bool
        Whether a new run may replace an existing ``output`` (``lieflow run --force``);
        if false, an existing file is refused, even one created after the check.
    flows : tuple of Flow
        The ``[splitting]`` flows (empty without one).
    """

    config: Config
    system: IsospectralSystem
    scheme: Scheme
    solver: Solver
    W0: Array = attrs.field(repr=False)
    output: Path
    replace: bool = True
    flows: tuple[Flow, ...] = ()

    def info(self) -> RunInfo:
        """What the run's file records about it (:class:`~lieflow.sinks.RunInfo`): the
        configuration's names, identity and text, the run settings and ``W0``."""
        cfg = self.config
        return RunInfo(
            system=self.system,
            system_name=cfg.system.name,
            scheme=cfg.scheme.name,
            solver=cfg.solver.name,
            h=cfg.run.h,
            save_every=cfg.run.save_every,
            requested_steps=cfg.run.steps,
            identity=cfg.identity(),
            W0=self.W0,
            checkpoint_seconds=cfg.run.checkpoint,
            device=cfg.run.device,
            config_text=cfg.text,
            config_source=cfg.source,
        )

    def spec(self) -> RunSpec:
        """The run (:class:`lieflow.runs.RunSpec`): ``W0`` placed on ``[run] device`` (a
        device that is not there is refused here, before anything is written), the scheme's
        flow on the ``[run] engine`` chosen for it, composed with the ``[splitting]`` flows
        if there are any."""
        run = self.config.run
        info = self.info()

        def compose(inner: Flow) -> Flow:
            if self.config.splitting is None:
                return inner
            return Splitting.named(self.config.splitting.method, *self.flows, inner)

        return RunSpec.build(
            self.system, self.scheme, self.W0, run.h, steps=run.steps, solver=self.solver,
            save_every=run.save_every, engine=cast(Engine, run.engine),
            checkpoint_seconds=run.checkpoint, casimir_shift=cast(Any, run.casimir_shift),
            device=run.device, compose=compose, identity=info.identity,
            names=(info.system_name, info.scheme, info.solver),
        )  # fmt: skip

    def flow(self) -> Flow:
        """What the run advances (:attr:`spec`'s flow)."""
        return self.spec().flow

    def header(self) -> TrajectoryHeader:
        """The trajectory file's header for this run (:class:`lieflow.app.io.TrajectoryHeader`):
        :meth:`info` written to :attr:`output`, whose directory is made if missing."""
        from .io import TrajectoryHeader

        fields = {f.name: getattr(self.info(), f.name) for f in attrs.fields(RunInfo)}
        return TrajectoryHeader(**fields, output=self.output, replace=self.replace,
                                make_directory=True)  # fmt: skip


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


class _Section:
    """Typed access to one TOML table that remembers which keys were read."""

    def __init__(self, data: Mapping[str, Any], name: str, source: str) -> None:
        self.data = data
        self.name = name
        self.source = source
        self.seen: set[str] = set()

    def key(self, key: str) -> str:
        return f"[{self.name}] {key}"

    def error(self, key: str, problem: str, fix: str) -> ConfigError:
        return _fail(self.source, self.key(key), problem, fix)

    def has(self, key: str) -> bool:
        """Whether ``key`` is given (a key the section asks about is one it accepts: an
        unknown key's message lists it, given or not)."""
        self.seen.add(key)
        return key in self.data

    def _raw(self, key: str, required: bool, hint: str) -> Any:
        self.seen.add(key)
        if key not in self.data:
            if required:
                raise self.error(key, "missing", f"add {key} = {hint} to the [{self.name}] table")
            return None
        return self.data[key]

    def string(self, key: str, *, required: bool = True, hint: str = '"..."') -> str | None:
        value = self._raw(key, required, hint)
        if value is not None and not isinstance(value, str):
            raise self.error(key, f"expected a string, got {value!r}", f"write {key} = {hint}")
        return value

    def integer(self, key: str, *, required: bool = True, minimum: int = 1) -> int | None:
        value = self._raw(key, required, str(minimum))
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(
                key, f"expected an integer, got {value!r}", f"write {key} = {minimum} (no quotes)"
            )
        if value < minimum:
            raise self.error(
                key, f"must be at least {minimum}, got {value}", f"use an integer >= {minimum}"
            )
        return value

    def number(self, key: str, *, required: bool = True, positive: bool = True) -> float | None:
        value = self._raw(key, required, "0.1")
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(
                key, f"expected a number, got {value!r}", f"write {key} = 0.1 (no quotes)"
            )
        x = float(value)
        if not math.isfinite(x) or (positive and x <= 0):
            raise self.error(
                key,
                f"must be {'positive and ' if positive else ''}finite, got {value!r}",
                "use a positive finite number" if positive else "use a finite number",
            )
        return x

    def boolean(self, key: str, *, required: bool = True) -> bool | None:
        value = self._raw(key, required, "true")
        if value is not None and not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {value!r}", f"write {key} = true")
        return value

    def table(self, key: str) -> Mapping[str, Any]:
        value = self._raw(key, False, "{}")
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.error(
                key,
                f"expected a table of keyword parameters, got {value!r}",
                f"write {key} = {{ name = value, ... }} or a [{self.name}.{key}] table",
            )
        return value

    def matrix(self, key: str) -> tuple[tuple[float, ...], ...]:
        value = self._raw(key, True, "[[...], [...]]")
        fix = f"write {key} = [[a, b, ...], [c, d, ...], ...] with one list of numbers per row"
        if not isinstance(value, list) or not value:
            raise self.error(key, f"expected a list of rows, got {value!r}", fix)
        rows = []
        for row in value:
            if not isinstance(row, list) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in row
            ):
                raise self.error(key, f"row {row!r} is not a list of numbers", fix)
            rows.append(tuple(float(x) for x in row))
        if len({len(r) for r in rows}) != 1:
            raise self.error(key, "rows have different lengths", fix)
        return tuple(rows)

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.seen)
        if unknown:
            known = ", ".join(sorted(self.seen))
            raise self.error(
                unknown[0],
                "unknown key",
                f"remove it or correct its spelling; [{self.name}] accepts {known}",
            )


def _component(raw: Mapping[str, Any], name: str, source: str) -> Component:
    sec = _Section(raw, name, source)
    cname = sec.string("name", hint='"<registered name>" (see `lieflow list`)')
    assert cname is not None
    comp = Component(cname, sec.table("params"))
    sec.finish()
    return comp


def _splitting(raw: Mapping[str, Any], source: str) -> SplittingSettings:
    from ..flows import SPLITTINGS

    sec = _Section(raw, "splitting", source)
    method = sec.string("method", required=False, hint='"strang"') or "strang"
    if method not in SPLITTINGS:
        raise sec.error(
            "method",
            f"unknown splitting {method!r}",
            f"use one of {', '.join(map(repr, SPLITTINGS))}",
        )
    hint = '[{ name = "<registered flow>", params = { ... } }]'
    items = sec._raw("flows", True, hint)
    if not isinstance(items, list) or not items or not all(isinstance(i, dict) for i in items):
        raise sec.error(
            "flows",
            f"expected a non-empty list of tables, got {items!r}",
            f"write flows = {hint} (see `lieflow list --kind flow`)",
        )
    sec.finish()
    flows = tuple(_component(item, f"splitting.flows[{i}]", source) for i, item in enumerate(items))
    return SplittingSettings(method, flows)


def _initial(raw: Mapping[str, Any], source: str, base: Path) -> InitialCondition:
    sec = _Section(raw, "initial", source)
    given = [k for k in ("random", "matrix", "file") if sec.has(k)]
    if len(given) != 1:
        problem = "none of" if not given else "more than one of"
        raise _fail(
            source,
            "[initial]",
            f"{problem} random, matrix, file is given",
            "give exactly one: random = true with seed = <int>, matrix = [[...]], or "
            'file = "w0.npy"',
        )
    kind = given[0]
    if kind == "random":
        if sec.boolean("random") is not True:
            raise sec.error(
                "random", "is false", "write random = true, or give matrix or file instead"
            )
        seeds = _seeds(sec)
        seed = None if seeds is not None else sec.integer("seed", minimum=0)
        scale = sec.number("scale", required=False)
        perturb = _perturbation(sec, seeds is not None)
        sec.finish()
        return InitialCondition("random", seed=seed, scale=1.0 if scale is None else scale,
                                seeds=seeds, perturb=perturb)  # fmt: skip
    if kind == "matrix":
        rows = sec.matrix("matrix")
        imag = sec.matrix("imag") if sec.has("imag") else None
        if imag is not None and (len(imag), len(imag[0])) != (len(rows), len(rows[0])):
            raise sec.error("imag", "has a different shape than matrix", "give one entry each")
        perturb = _perturbation(sec, False)
        sec.finish()
        return InitialCondition("matrix", matrix=rows, imag=imag, perturb=perturb)
    name = sec.string("file", hint='"w0.npy"')
    assert name is not None
    path = Path(name).expanduser()
    path = path if path.is_absolute() else base / path
    if not path.is_file():
        raise sec.error(
            "file",
            f"{str(path)!r} does not exist or is not a file",
            "give the path of a .npy file (relative paths are relative to the configuration)",
        )
    perturb = _perturbation(sec, False)
    sec.finish()
    return InitialCondition("file", file=path, perturb=perturb)


def _seeds(sec: _Section) -> tuple[int, ...] | None:
    """``[initial] seeds``: a non-empty list of distinct seeds >= 0 (an ensemble), or None."""
    if not sec.has("seeds"):
        return None
    if sec.has("seed"):
        raise sec.error(
            "seeds",
            "both seed and seeds are given",
            "give seed = <int> for one run or seeds = [0, 1, ...] for an ensemble",
        )
    value = sec._raw("seeds", True, "[0, 1, 2, 3]")
    ok = (
        isinstance(value, list)
        and value
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value)
    )
    if not ok or len(set(value)) != len(value):
        raise sec.error(
            "seeds",
            f"expected a non-empty list of distinct integers >= 0, got {value!r}",
            "write seeds = [0, 1, 2, 3]",
        )
    return tuple(value)


def _perturbation(sec: _Section, has_seeds: bool) -> Perturbation | None:
    """``[initial.perturb]``: members, size and (optional) seed; or None."""
    if not sec.has("perturb"):
        return None
    if has_seeds:
        raise sec.error(
            "perturb",
            "both seeds and perturb are given",
            "make the ensemble either from seeds or from perturbations of one state",
        )
    sub = _Section(sec.table("perturb"), "initial.perturb", sec.source)
    members = sub.integer("members", minimum=1)
    size = sub.number("size")
    seed = sub.integer("seed", required=False, minimum=0)
    sub.finish()
    assert members is not None and size is not None
    return Perturbation(members, size, 0 if seed is None else seed)


#: ``t_final / h`` must be this close to a whole number (relative): ``t_final = 1.0`` with
#: ``h = 0.1`` is 10 steps although ``1.0 / 0.1`` is not exactly 10 in floating point.
_WHOLE_STEPS_RTOL = 1e-9


def _steps(sec: _Section, h: float) -> tuple[int, float | None]:
    """``[run] steps``, or ``t_final`` as a whole number of steps ``h`` (exactly one)."""
    given = [k for k in ("steps", "t_final") if sec.has(k)]
    if len(given) != 1:
        raise _fail(
            sec.source,
            "[run] steps",
            "neither steps nor t_final is given"
            if not given
            else "both steps and t_final are given",
            "give exactly one: steps = <number of steps> or t_final = <final time>",
        )
    if given[0] == "steps":
        steps = sec.integer("steps")
        assert steps is not None
        if steps > MAX_STEPS:  # as lieflow.integrate: indices and times exact in 64 bits
            raise sec.error(
                "steps", f"{steps} is more than {MAX_STEPS} (2**53) steps, too many to count",
                "use fewer steps or a larger h",
            )  # fmt: skip
        return steps, None
    t_final = sec.number("t_final")
    assert t_final is not None
    ratio = t_final / h
    if not math.isfinite(ratio) or ratio > MAX_STEPS:
        raise sec.error(
            "t_final",
            f"t_final / h = {t_final!r} / {h!r} is too many steps to count",
            "use a larger h or a smaller t_final",
        )
    steps = round(ratio)
    if steps < 1 or abs(ratio - steps) > _WHOLE_STEPS_RTOL * max(ratio, 1.0):
        lower = max(math.floor(ratio), 1) * h
        raise sec.error(
            "t_final",
            f"t_final / h = {t_final!r} / {h!r} = {ratio:.12g} is not a whole number of steps",
            f"use a multiple of h (e.g. t_final = {lower:.12g} or "
            f"{(max(math.floor(ratio), 1) + 1) * h:.12g}), or give steps instead",
        )
    return steps, t_final


def _run(raw: Mapping[str, Any], source: str, base: Path, default_output: str) -> RunSettings:
    sec = _Section(raw, "run", source)
    h = sec.number("h")
    assert h is not None
    steps, t_final = _steps(sec, h)
    save_every = sec.integer("save_every", required=False)
    output = sec.string("output", required=False, hint='"trajectory.h5"')
    if output is not None and not output.strip():
        raise sec.error("output", "is empty", 'give a file name such as output = "run.h5"')
    engine = sec.string("engine", required=False, hint='"auto"') or "auto"
    if engine not in ENGINES:
        raise sec.error(
            "engine", f"must be one of {', '.join(map(repr, ENGINES))}, got {engine!r}",
            'engine = "auto" (compiled where supported and faster, else numpy)',
        )  # fmt: skip
    shift: float | str = 0.0
    if isinstance(sec.data.get("casimir_shift"), str):
        shift = str(sec.string("casimir_shift"))
        if shift != "auto":
            raise sec.error(
                "casimir_shift",
                f'expected "auto" or a number, got {shift!r}',
                'write casimir_shift = "auto" (the least-squares shift of W0) or a number',
            )
    elif sec.has("casimir_shift"):
        shift = sec.number("casimir_shift", positive=False) or 0.0
    checkpoint: float | None = 1.0
    if isinstance(sec.data.get("checkpoint"), str):
        if sec.string("checkpoint") != "saves":
            raise sec.error(
                "checkpoint",
                f'expected a number of seconds or "saves", got {sec.data["checkpoint"]!r}',
                'write checkpoint = 1.0 (seconds between checkpoints) or "saves"',
            )
        checkpoint = None
    elif sec.has("checkpoint"):
        checkpoint = sec.number("checkpoint", positive=False)
        if checkpoint is None or checkpoint < 0:
            raise sec.error(
                "checkpoint", f"must be >= 0 seconds, got {checkpoint!r}",
                'write checkpoint = 1.0 (seconds between checkpoints) or "saves"',
            )  # fmt: skip
    device = sec.string("device", required=False, hint='"cpu"')
    device = "cpu" if device is None else device  # an empty string is refused, not the CPU
    try:
        check_device(device)
    except InputError as exc:
        raise sec.error(
            "device", str(exc), 'device = "cpu" (or "cupy", "torch:cuda:0", ...)'
        ) from exc
    if device != "cpu" and engine == "compiled":
        raise sec.error(
            "engine", f'"compiled" runs on the CPU only, not on device {device!r}',
            'leave engine out (or "auto") with a device: the array library runs the steps',
        )  # fmt: skip
    sec.finish()
    out = Path(output or default_output).expanduser()
    return RunSettings(
        h,
        steps,
        save_every or 1,
        out if out.is_absolute() else base / out,
        t_final,
        engine,
        shift,
        checkpoint,
        device,
    )


def parse_config(
    text: str, *, source: str = "<string>", base_dir: Path | str | None = None
) -> Config:
    """Parse and type-check a TOML run configuration.

    Parameters
    ----------
    text : str
        The TOML text.
    source : str
        Where it came from, for messages (a path, or ``"<string>"``).
    base_dir : path, optional
        Directory that relative ``[initial] file`` and ``[run] output`` paths are relative
        to (default: the current directory).

    Returns
    -------
    Config

    Raises
    ------
    ConfigError
        Invalid TOML, a missing, ill-typed or unknown key.
    """
    if not isinstance(text, str):
        raise ConfigError(
            f"{source}: the configuration must be TOML text (str), got "
            f"{type(text).__name__}. To fix: pass a str (decode bytes with .decode('utf-8')), "
            "or use load_config(path) for a file."
        )
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _fail(source, "", f"is not valid TOML ({exc})", "correct the syntax") from None
    base = Path.cwd() if base_dir is None else Path(base_dir)
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise _fail(
            source,
            f"[{unknown[0]}]",
            "unknown section",
            f"remove it or correct its spelling; sections are {', '.join(_SECTIONS)}",
        )
    for name in _SECTIONS:
        if name not in data and name not in _OPTIONAL:
            raise _fail(
                source,
                f"[{name}]",
                "missing section",
                f"add a [{name}] table (see `lieflow run --help`)",
            )
        if name in data and not isinstance(data[name], dict):
            raise _fail(source, name, "must be a table", f"write it as a [{name}] section")
    stem = Path(source).stem if source != "<string>" else "trajectory"
    return Config(
        system=_component(data["system"], "system", source),
        initial=_initial(data["initial"], source, base),
        scheme=_component(data["scheme"], "scheme", source),
        solver=(
            _component(data["solver"], "solver", source)
            if "solver" in data
            else Component("fixed_point")
        ),
        run=_run(data["run"], source, base, f"{stem}.h5"),
        text=text,
        source=source,
        splitting=_splitting(data["splitting"], source) if "splitting" in data else None,
    )


def read_toml_file(path: Path | str, what: str = "configuration") -> tuple[Path, str]:
    """The path and UTF-8 text of a TOML file (a run ``configuration``, a sweep's ``grid``),
    or :class:`ConfigError` naming what is wrong with it."""
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise ConfigError(
            f"the {what} path must be a file path (str or pathlib.Path), got {path!r}. "
            "To fix: pass the path of a .toml file."
        )
    p = Path(path)
    try:
        return p, p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(
            f"cannot read the {what} {str(p)!r}: {exc.strerror or exc}. To fix: check the "
            "path and its permissions."
        ) from None
    except UnicodeDecodeError:
        raise ConfigError(
            f"the {what} {str(p)!r} is not UTF-8 text. To fix: save it as UTF-8 TOML."
        ) from None


def load_config(path: Path | str) -> Config:
    """Read and parse the configuration file ``path`` (relative paths inside it are relative
    to its directory)."""
    p, text = read_toml_file(path)
    return parse_config(text, source=str(p), base_dir=p.resolve().parent)


def check_output_path(path: Path, key: str, source: str = "") -> Path:
    """Check that a file can be created at ``path`` without creating anything.

    The path must not be a directory; its nearest existing ancestor must be a writable
    directory (missing directories are created when the run starts).
    """
    prefix = f"{source}: " if source else ""
    path = Path(path).expanduser().absolute()
    real = os.path.realpath(path)
    system_dirs = ("/proc", "/sys", "/dev")
    if os.name == "posix" and any(real == d or real.startswith(d + "/") for d in system_dirs):
        raise ConfigError(
            f"{prefix}{key}: {str(path)!r} is under {', '.join(system_dirs)}, which hold "
            "the system's devices and kernel interfaces, not files. To fix: choose an output "
            "path in a directory of your own.",
            key,
        )
    if path.is_dir():
        raise ConfigError(
            f"{prefix}{key}: {str(path)!r} is a directory. To fix: give a file name such as "
            f"{str(path / 'trajectory.h5')!r}.",
            key,
        )
    ancestor = path.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(
            f"{prefix}{key}: cannot create {str(path)!r}: {str(ancestor)!r} is not a writable "
            "directory. To fix: choose an output path in a directory you can write to.",
            key,
        )
    return path


def _create(
    registry: Registry,
    kind: Kind,
    comp: Component,
    source: str,
    section: str = "",
    **context: Any,
) -> Any:
    """Build ``comp`` from the registry (``context``: arguments beyond its params, e.g. a
    flow's ``system``); ``section`` names it in messages (default ``[kind]``)."""
    section = section or f"[{kind}]"
    entry_key = f"{section} name"
    try:
        entry = registry.entry(kind, comp.name)
    except LieflowError as exc:
        raise ConfigError(
            with_fix(f"{source}: {entry_key}: {exc}", "use a known name"), entry_key
        ) from None
    params_key = f"{section} params"
    try:
        return entry.create(**context, **comp.params)
    except PluginError as exc:
        raise ConfigError(f"{source}: {entry_key}: {exc}.", entry_key) from None
    except Exception as exc:
        raise ConfigError(
            f"{source}: {params_key}: {kind} {comp.name!r} rejected its parameters "
            f"{quote(dict(comp.params))}: {shorten(exc)}. To fix: correct {params_key}.",
            params_key,
        ) from None


def _initial_state(config: Config, system: IsospectralSystem) -> Array:
    init, source = config.initial, config.source
    key = f"[initial] {init.kind}"
    W: Any

    def random_state(seed: int | None, key: str = key) -> Any:
        try:
            return np.asarray(system.random_state(seed))
        except Exception as exc:
            raise ConfigError(
                f"{source}: {key}: {system.name}.random_state(seed={seed}) failed "
                f"({type(exc).__name__}: {exc}). To fix: give the initial condition as "
                "matrix or file instead, or report it to the system's author.",
                key,
            ) from None

    if init.kind == "random":
        if init.seeds is not None:  # an ensemble: one member per seed
            W = np.stack([random_state(seed) for seed in init.seeds])
        else:
            W = random_state(init.seed)
        if init.scale != 1.0:
            W = init.scale * W
    elif init.kind == "matrix":
        W = np.array(init.matrix)
        if init.imag is not None:
            W = W + 1j * np.array(init.imag)
    else:
        assert init.file is not None
        try:
            with open(init.file, "rb") as fh:
                magic = fh.read(6)
        except OSError as exc:
            raise ConfigError(
                f"{source}: {key}: cannot read {str(init.file)!r} ({exc.strerror or exc}). "
                "To fix: check the path and its permissions.",
                key,
            ) from None
        if magic != b"\x93NUMPY":
            raise ConfigError(
                f"{source}: {key}: {str(init.file)!r} exists but is not a .npy file (it does "
                "not start with numpy's .npy header; text, .npz archives and pickles are not "
                "read). To fix: save W0 with numpy.save(path, W0).",
                key,
            )
        try:
            W = np.load(init.file, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ConfigError(
                f"{source}: {key}: cannot read {str(init.file)!r} as a .npy array ({exc}). "
                "To fix: save W0 with numpy.save.",
                key,
            ) from None
    try:
        W = system.validate(W)
    except LieflowError as exc:
        fix = (
            "keep scale = 1.0 (this system accepts only states of its own size)"
            if init.kind == "random" and init.scale != 1.0
            else f"give an initial condition for {system.name} on {system.algebra}"
        )
        raise ConfigError(with_fix(f"{source}: {key}: {exc}", fix), key) from None
    return W if init.perturb is None else _perturbed(W, init.perturb, system, source, random_state)


def _perturbed(W: Array, rule: Perturbation, system: IsospectralSystem, source: str,
               random_state: Any) -> Array:  # fmt: skip
    """The ensemble ``W + size * random_state(seed + k)``, ``k < members``, validated."""
    key = "[initial] perturb"
    if W.ndim != 2:
        raise ConfigError(
            f"{source}: {key}: perturbs one initial condition, but W0 has shape {W.shape}. "
            "To fix: give a single n x n state (or drop perturb).",
            key,
        )
    members = np.stack([W + rule.size * random_state(rule.seed + k, key)
                        for k in range(rule.members)])  # fmt: skip
    try:
        return system.validate(members.astype(W.dtype, copy=False))
    except LieflowError as exc:
        raise ConfigError(
            f"{source}: {key}: a perturbed state is not a valid initial condition "
            f"({without_fix(exc)}). "
            f"To fix: {system.name} may not accept additive perturbations; make the ensemble "
            "from seeds = [...] instead, or use a smaller size.",
            key,
        ) from None


def build(
    config: Config,
    *,
    output: Path | str | None = None,
    registry: Registry | None = None,
    replace: bool = True,
) -> RunSetup:
    """Build and validate every object of a run; write nothing.

    Parameters
    ----------
    config : Config
        A parsed configuration.
    output : path, optional
        Output file overriding ``[run] output`` (the command line's ``--out``).
    registry : Registry, optional
        Where names are looked up (default: :func:`lieflow.default_registry`).
    replace : bool
        Whether the run may replace an existing output file (:attr:`RunSetup.replace`;
        ``lieflow run`` passes its ``--force``).

    Raises
    ------
    ConfigError
        Unknown names, rejected parameters, a wrong initial condition, an unwritable output.
    """
    reg = default_registry() if registry is None else registry
    source = config.source
    system = _create(reg, "system", config.system, source)
    scheme = _create(reg, "scheme", config.scheme, source)
    solver = _create(reg, "solver", config.solver, source)
    flows = tuple(
        _create(reg, "flow", comp, source, f"[splitting] flows[{i}]", system=system)
        for i, comp in enumerate(() if config.splitting is None else config.splitting.flows)
    )
    W0 = _initial_state(config, system)
    if output is None:
        key, out = "[run] output", check_output_path(config.run.output, "[run] output", source)
    else:
        key, out = "--out", check_output_path(Path(output), "--out")
    inputs = [("the configuration", Path(source))]
    if config.initial.file is not None:
        inputs.append(("the [initial] file", config.initial.file))
    for what, path in inputs:
        if out.exists() and path.exists() and os.path.samefile(out, path):
            raise ConfigError(
                f"{source}: {key}: {str(out)!r} is {what} of this run; writing the trajectory "
                "there would destroy it. To fix: choose another output file.",
                key,
            )
    return RunSetup(config, system, scheme, solver, W0, out, replace, flows)
