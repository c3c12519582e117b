"""Reading TOML for lieflow's files (run configurations, sweep grids): the text of a file,
its tables with typed, checked keys (:class:`_Section`), and :class:`ConfigError`, whose
one-paragraph message names the key and the fix."""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...errors import LieflowError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


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


def _parse_toml(text: str, source: str) -> dict[str, Any]:
    """The tables of the TOML ``text`` (from ``source``), or :class:`ConfigError`."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _fail(source, "", f"is not valid TOML ({exc})", "correct the syntax") from None


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
