"""A run configuration: what it holds, parsed and type-checked (:class:`Config` and its
sections :class:`Component`, :class:`InitialCondition`, :class:`RunSection`, ...; the run's
identity, :meth:`Config.identity`, :func:`identity_changes`), and how TOML text becomes one
(:func:`parse_config`, :func:`load_config`): every key checked for presence and type, unknown
keys refused. Nothing is built, nothing read but the text (and whether an ``[initial] file``
exists)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Literal

import attrs

from ...backends import check_device
from ...engines import ENGINES
from ...errors import InputError
from ...flows import SPLITTINGS
from ...runs import MAX_STEPS
from ...sinks import run_identity
from ._toml import ConfigError, _fail, _parse_toml, _Section, read_toml_file


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


_SECTIONS = ("system", "initial", "scheme", "solver", "splitting", "run")
_OPTIONAL = ("solver", "splitting")


def _component(raw: Mapping[str, Any], name: str, source: str) -> Component:
    sec = _Section(raw, name, source)
    cname = sec.string("name", hint='"<registered name>" (see `lieflow list`)')
    assert cname is not None
    comp = Component(cname, sec.table("params"))
    sec.finish()
    return comp


def _splitting(raw: Mapping[str, Any], source: str) -> SplittingSection:
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
    return SplittingSection(method, flows)


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


def _run(raw: Mapping[str, Any], source: str, base: Path, default_output: str) -> RunSection:
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
    return RunSection(
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
    data = _parse_toml(text, source)
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


def load_config(path: Path | str) -> Config:
    """Read and parse the configuration file ``path`` (relative paths inside it are relative
    to its directory)."""
    p, text = read_toml_file(path)
    return parse_config(text, source=str(p), base_dir=p.resolve().parent)
