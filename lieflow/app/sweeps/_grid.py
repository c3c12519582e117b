"""The grid of a sweep: a base run configuration and the ``[sweep]`` table of swept keys,
parsed into :class:`Sweep` with one checked :class:`SweepRun` (and one file) per point
(:func:`parse_sweep`, :func:`load_sweep`, :func:`run_id`)."""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import attrs

from ..config import Config, ConfigError, parse_config, read_toml_file
from ..config._config import _SECTIONS
from ..config._toml import _fail, _parse_toml, _Section
from ..datasets import MANIFEST

_OPTIONS = ("directory", "zip")


@attrs.frozen
class Axis:
    """One dimension of a sweep: a key and its values, or a zipped group of keys.

    Attributes
    ----------
    name : str
        The dimension's name in :func:`lieflow.open_sweep` (short: ``"h"`` for
        ``run.h``, ``"scheme"`` for ``scheme.name``, the full key where short names clash).
    keys : tuple of str
        Dotted configuration keys set together (one, or a zipped group's).
    values : tuple of tuple
        ``values[j]`` are the values of ``keys[j]``, one per point of the axis.
    """

    name: str
    keys: tuple[str, ...]
    values: tuple[tuple[Any, ...], ...]

    @property
    def size(self) -> int:
        """Number of points."""
        return len(self.values[0])

    def point(self, i: int) -> dict[str, Any]:
        """The keys' values at point ``i``."""
        return {key: vals[i] for key, vals in zip(self.keys, self.values, strict=True)}


@attrs.frozen(eq=False)
class SweepRun:
    """One run of a sweep.

    Attributes
    ----------
    id : str
        The file stem, derived from :attr:`params` alone (readable slug + hash).
    index : tuple of int
        Position on each axis.
    params : Mapping
        Dotted key -> value of every swept key.
    config : Config
        The run's full configuration (its ``[run] output`` is :attr:`output`).
    output : Path
        The trajectory file (absolute).
    """

    id: str
    index: tuple[int, ...]
    params: Mapping[str, Any]
    config: Config = attrs.field(repr=False)
    output: Path


@attrs.frozen(eq=False)
class Sweep:
    """A parsed grid (:func:`parse_sweep`, :func:`load_sweep`)."""

    source: str
    text: str = attrs.field(repr=False)
    axes: tuple[Axis, ...]
    directory: Path
    runs: tuple[SweepRun, ...] = attrs.field(repr=False)
    base_dir: Path = attrs.field(factory=Path.cwd, repr=False)

    @property
    def shape(self) -> tuple[int, ...]:
        """Points per axis."""
        return tuple(a.size for a in self.axes)

    @property
    def manifest(self) -> Path:
        """Where the manifest is written."""
        return self.directory / MANIFEST


def _flatten_axes(
    value: Any, prefix: str, source: str, out: dict[str, list[Any]]
) -> dict[str, list[Any]]:
    """Dotted key -> list, from nested TOML tables (``[sweep.run] h = [...]`` too)."""
    if isinstance(value, dict):
        for key, item in value.items():
            _flatten_axes(item, f"{prefix}.{key}", source, out)
        return out
    if not isinstance(value, list) or not value:
        raise _fail(
            source,
            f"[sweep] {prefix}",
            f"expected a non-empty list of values, got {value!r}",
            f'write "{prefix}" = [value1, value2, ...]',
        )
    out[prefix] = value
    return out


def _sweep_keys(raw: Mapping[str, Any], source: str, where: str) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    for key, value in raw.items():
        head = key.split(".")[0]
        if head not in _SECTIONS:
            raise _fail(
                source,
                f"{where} {key}",
                "unknown key",
                f"sweep dotted configuration keys of the sections {', '.join(_SECTIONS)} "
                f'(e.g. "run.h" = [0.1, 0.05]); {where} also accepts '
                + ", ".join(_OPTIONS if where == "[sweep]" else ()),
            )
        _flatten_axes(value, key, source, out)
    for key in out:
        if key in ("run.output",):
            raise _fail(
                source,
                f"{where} {key}",
                "cannot be swept",
                "the sweep names each run's file itself (under [sweep] directory)",
            )
        if len(key.split(".")) < 2:
            raise _fail(
                source,
                f"{where} {key}",
                "is a whole section, not a key",
                f'sweep its keys, e.g. "{key}.name" = [...]',
            )
    return out


def _short_names(groups: list[list[str]]) -> list[str]:
    reserved = {
        "time",
        "step",
        "ensemble",
        "row",
        "col",
        "casimir",
        "run",
        "W",
        "energy",
        "energy_error",
        "casimirs",
        "casimir_drift",
        "iterations",
        "residual",
        "status",
    }

    def short(key: str) -> str:
        parts = key.split(".")
        return parts[0] if parts[-1] == "name" and len(parts) == 2 else parts[-1]

    names = [short(g[0]) for g in groups]
    return [
        g[0] if names.count(n) > 1 or n in reserved or n == "params" else n
        for n, g in zip(names, groups, strict=True)
    ]


def _set_key(data: dict[str, Any], key: str, value: Any, source: str) -> None:
    """Set the dotted ``key`` of a run's configuration to ``value``.

    A part that is a number indexes a list of the base configuration (``[[splitting.flows]]``
    tables: ``"splitting.flows.1.params.nu"`` is the second flow's ``nu``); tables on the
    way that the base configuration lacks are created.
    """
    parts = key.split(".")
    if parts[0] == "solver" and "solver" not in data and parts[1] != "name":
        data["solver"] = {"name": "fixed_point"}  # the default of a configuration without one
    node: Any = data
    for i, part in enumerate(parts):
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise _fail(
                    source,
                    f"[sweep] {key}",
                    f"{'.'.join(parts[:i])} is a list of {len(node)} in the base "
                    f"configuration, and {part!r} is not an index of it",
                    f"index it from 0 to {len(node) - 1}, e.g. "
                    f'"{".".join([*parts[:i], "0", *parts[i + 1 :]])}"',
                )
            index: int | str = int(part)
        elif isinstance(node, dict):
            index = part
        else:
            raise _fail(
                source,
                f"[sweep] {key}",
                f"{'.'.join(parts[:i])} is {node!r} in the base configuration, not a table",
                f"sweep {'.'.join(parts[:i])} as a whole instead",
            )
        if i == len(parts) - 1:
            node[index] = copy.deepcopy(value)
        elif isinstance(node, dict):
            node = node.setdefault(part, {})
        else:
            node = node[index]


# -- TOML text of a run's configuration (stored in its file) ----------------------------------

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_key(key: str) -> str:
    return key if _BARE.match(key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        items = ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        return "{ " + items + " }" if items else "{}"
    return json.dumps(str(value))  # dates and times: as text (no configuration key takes one)


def _toml(data: Mapping[str, Any], header: str) -> str:
    lines = [f"# {line}" for line in header.splitlines()]
    for section in _SECTIONS:
        if section not in data:
            continue
        lines.append(f"\n[{section}]")
        for key, value in data[section].items():
            lines.append(f"{_toml_key(key)} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def _label(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return "-".join(_label(v) for v in value)
    if isinstance(value, dict):
        return "-".join(f"{k}{_label(v)}" for k, v in value.items())
    return str(value)


def run_id(params: Mapping[str, Any]) -> str:
    """The file stem of a run: a readable slug of its parameters (each value after its key's
    last part; a ``name`` bare) and 10 hex digits of the SHA-256 of their canonical JSON,
    independent of the order of the grid's keys.

    >>> run_id({"scheme.name": "gauss2", "run.h": 0.1})
    'gauss2_h0.1_3a718b93ce'
    """
    digest = hashlib.sha256(
        json.dumps(dict(params), sort_keys=True, default=str).encode()
    ).hexdigest()[:10]
    parts = []
    for key, value in params.items():
        short = key.split(".")[-1]
        parts.append(f"{'' if short == 'name' else short}{_label(value)}")
    slug = re.sub(r"[^A-Za-z0-9.=+-]+", "_", "_".join(parts)).strip("_.")[:80]
    return f"{slug}_{digest}" if slug else digest


def parse_sweep(
    text: str,
    *,
    source: str = "<string>",
    base_dir: Path | str | None = None,
    directory: Path | str | None = None,
) -> Sweep:
    """Parse and check a grid: the base configuration, the ``[sweep]`` table and every run.

    Parameters
    ----------
    text : str
        TOML text.
    source : str
        Where it came from (a path), for messages; its stem names the default directory.
    base_dir : path, optional
        What relative paths are relative to (default: the current directory).
    directory : path, optional
        The sweep's directory, overriding ``[sweep] directory``.

    Raises
    ------
    ConfigError
        Invalid TOML; a missing, ill-typed or unknown key in the base configuration, in
        ``[sweep]``, or in any run's configuration (the message names the run).
    """
    if not isinstance(text, str):
        raise ConfigError(
            f"{source}: a sweep grid must be TOML text (str), got "
            f"{type(text).__name__}. To fix: use load_sweep(path) for a file."
        )
    data = _parse_toml(text, source)
    base = Path.cwd() if base_dir is None else Path(base_dir)
    raw = data.pop("sweep", None)
    if raw is None:
        raise _fail(
            source,
            "[sweep]",
            "missing section",
            'add a [sweep] table of lists, e.g. "run.h" = [0.1, 0.05]; '
            "for a single run use `lieflow run`",
        )
    if not isinstance(raw, dict):
        raise _fail(source, "sweep", "must be a table", "write it as a [sweep] section")
    if isinstance(data.get("run"), dict) and "output" in data["run"]:
        raise _fail(
            source,
            "[run] output",
            "is not used by a sweep",
            "remove it: each run's file is DIRECTORY/runs/<id>.h5 ([sweep] directory)",
        )
    sec = _Section(raw, "sweep", source)
    dir_name = sec.string("directory", required=False, hint='"study"')
    zips = sec._raw("zip", False, '[{ "run.h" = [...], "run.steps" = [...] }]')
    sec.seen.update(k for k in raw if k.split(".")[0] in _SECTIONS)
    sec.finish()
    groups: list[dict[str, list[Any]]] = [
        {k: v}
        for k, v in _sweep_keys(
            {k: v for k, v in raw.items() if k not in _OPTIONS}, source, "[sweep]"
        ).items()
    ]
    if zips is not None:
        if isinstance(zips, dict):
            zips = [zips]
        if not isinstance(zips, list) or not all(isinstance(z, dict) and z for z in zips):
            raise _fail(
                source,
                "[sweep] zip",
                f"expected tables of lists, got {zips!r}",
                'write [[sweep.zip]] tables with "key" = [values] of equal length',
            )
        for i, z in enumerate(zips):
            keys = _sweep_keys(z, source, f"[[sweep.zip]] #{i + 1}")
            lengths = {k: len(v) for k, v in keys.items()}
            if len(set(lengths.values())) != 1:
                raise _fail(
                    source,
                    f"[[sweep.zip]] #{i + 1}",
                    f"lists of different lengths {lengths}",
                    "give every key of a zipped group one value per point",
                )
            groups.append(keys)
    for g in groups:
        points = [json.dumps(p, sort_keys=True) for p in zip(*g.values(), strict=True)]
        twice = next((p for i, p in enumerate(points) if p in points[:i]), None)
        if twice is not None:
            raise _fail(
                source,
                f"[sweep] {next(iter(g))}",
                f"the point {twice} is listed twice",
                "list each value once (two runs would be the same run)",
            )
    all_keys = [k for g in groups for k in g]
    for a, b in itertools.permutations(all_keys, 2):
        if a == b or b.startswith(a + "."):
            raise _fail(
                source,
                f"[sweep] {b}",
                f"is swept twice (also as {a})",
                "sweep each key once, in one axis or one zipped group",
            )
    names = _short_names([list(g) for g in groups])
    axes = tuple(
        Axis(name, tuple(g), tuple(tuple(v) for v in g.values()))
        for name, g in zip(names, groups, strict=True)
    )
    stem = Path(source).stem if source != "<string>" else "sweep"
    where = Path(directory) if directory is not None else Path(dir_name or stem)
    where = (
        (where if where.is_absolute() else (Path.cwd() if directory is not None else base) / where)
        .expanduser()
        .absolute()
    )
    runs = []
    for index in itertools.product(*(range(a.size) for a in axes)):
        params: dict[str, Any] = {}
        for axis, i in zip(axes, index, strict=True):
            params.update(axis.point(i))
        merged = copy.deepcopy(data)
        for key, value in params.items():
            _set_key(merged, key, value, source)
        rid = run_id(params)
        output = where / "runs" / f"{rid}.h5"
        merged.setdefault("run", {})["output"] = str(output)
        shown = ", ".join(f"{k} = {_toml_value(v)}" for k, v in params.items())
        header = f"run {rid} of the sweep {source}\n{shown}" if shown else f"sweep {source}"
        run_text = _toml(merged, header)
        try:
            config = parse_config(run_text, source=source, base_dir=base)
        except ConfigError as exc:
            raise ConfigError(
                f"{exc} (in the run with {shown or 'no swept keys'})", exc.key
            ) from None
        runs.append(SweepRun(rid, tuple(index), MappingProxyType(params), config, output))
    ids = [r.id for r in runs]
    if len(set(ids)) != len(ids):  # pragma: no cover - needs a SHA-256 collision
        raise _fail(source, "[sweep]", "two runs have the same id", "report this")
    return Sweep(source, text, axes, where, tuple(runs), base.absolute())


def load_sweep(path: Path | str, *, directory: Path | str | None = None) -> Sweep:
    """Read and parse the grid file ``path`` (:func:`parse_sweep`); relative paths in it
    are relative to its directory, and so is the default sweep directory (its stem)."""
    p, text = read_toml_file(path, "grid")
    return parse_sweep(text, source=str(p), base_dir=p.resolve().parent, directory=directory)
