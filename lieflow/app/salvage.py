"""Salvage a damaged trajectory file: keep every row that reads back, repair what has a copy,
and make the file resumable again.

A trajectory file (:mod:`lieflow.app.io`) whose bytes were damaged on disk — a process killed
while HDF5 rewrote a chunk, a file cut short by a full disk or a bad copy, flipped bits — is
refused by ``lieflow run --resume`` and by every reader. :func:`salvage` (``lieflow salvage
FILE``) rebuilds it from what still reads back:

1. The damaged file is only read (a file shorter than HDF5 recorded is read as if padded
   to its recorded length with bytes that fail every checksum they cover). Every
   dataset is read chunk by chunk, each chunk's Fletcher-32 checksum verified: a damaged
   chunk costs its rows only (at most 128 steps of one diagnostic, or 4 KiB of saved states:
   :data:`~lieflow.app.io._format.CHUNK_ROWS`), never the rows around it.
2. What has a copy is repaired from it: ``initial/W0`` from the saved state of step 0 (and
   that from ``W0``), a saved state's step from its time and back (``t = k h``), the step
   coordinate (``0..K``), a header attribute from the run's identity or configuration
   (``system``, ``scheme``, ``solver``, ``h``, ``save_every``, ``identity``,
   ``casimir_powers``); an attribute with no copy (``config_source``, the versions, ...) is
   set empty, and said so.
3. The restart point is a step ``k`` with a verified state and its energy and Casimirs
   intact: the later checkpoint slot whose SHA-256 digest matches (the run then continues bit
   for bit as if never stopped), or, only if neither is usable, the latest intact saved state
   (the run continues from it with a cold solver start: its later steps agree with an
   uninterrupted run to the solver's tolerance, not bit for bit), or step 0.
4. A new file is written with every row of steps ``0..k`` — the rows of damaged chunks as
   holes (``NaN``; ``-1`` solver updates), the saved states of lost steps left out — its
   checkpoint at ``k``, marked ``interrupted`` and with the attribute ``salvaged`` saying what
   was lost and repaired; ``lieflow run CONFIG --resume`` then continues it.

The damaged original is kept as ``FILE.damaged`` (or ``FILE.damaged.1``, ...) and the new file
takes its name only when it is complete, so a salvage that fails leaves the file as it was.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ..algebras import Array
from ..errors import LieflowError
from .io._format import (
    _DAMAGE,
    _EXTRA,
    _HEADER_COPY,
    _LABELS,
    _LAYOUTS,
    _PER_STEP,
    _PER_UPDATE,
    FORMAT,
    FORMAT_VERSION,
    _as_path,
    _h5py,
    _header_copy,
    _Layout,
    _plain,
    _where,
    checkpoint_digest,
)
from .io._lock import _CHUNK_CACHE_BYTES, DamagedOutputError, _check_signature, _OutputLock
from .io._new_file import _append_extra, _ensemble_labels, _lay_out
from .io._reader import (
    _check_attributes,
    _check_format,
    _check_kept,
    _check_spare,
    _chunk_at,
    _opened,
    _slot_items,
)
from .io._slots import _write_slot

__all__ = ["SalvageReport", "salvage"]

_FIX = "give a file written by `lieflow run` or `lieflow.integrate(out=...)`"

#: Salvage writes next to the file: its lock, the salvaged copy, the damaged original's name.
_WRITABLE_FIX = (
    "salvage writes in the file's directory (a lock, the salvaged copy, the backup): make it "
    "writable, or copy the file to a directory you can write to and salvage the copy"
)

_AGAIN = "restore it from a backup, or run the configuration again from the start (--force)"


@attrs.frozen
class SalvageReport:
    """What :func:`salvage` kept.

    Attributes
    ----------
    path : Path
        The salvaged file (resumable with ``lieflow run CONFIG --resume``).
    backup : Path or None
        The damaged original, kept unchanged (None: the file verified, nothing was done).
    recorded_steps : int
        Steps the damaged file claimed (its ``completed_steps``; -1 if unreadable).
    kept_steps : int
        Steps kept: the restart point ``k``.
    bit_for_bit : bool
        Whether the restart point is a verified checkpoint (a resume continues bit for bit)
        rather than a saved state (a resume restarts the solver cold).
    lost : tuple of str
        What of steps ``0..k`` did not read back (rows left as holes, saved states left out,
        attributes without a copy), one line each.
    repaired : tuple of str
        What was damaged and restored from a copy, one line each.
    """

    path: Path
    backup: Path | None
    recorded_steps: int
    kept_steps: int
    bit_for_bit: bool
    lost: tuple[str, ...] = ()
    repaired: tuple[str, ...] = ()

    def describe(self) -> str:
        """What was kept, lost and repaired, for the command line."""
        if self.backup is None:
            return (
                f"{str(self.path)!r} verifies (every row and its checkpoints read back "
                f"intact, {self.kept_steps} steps): nothing to salvage, the file is unchanged"
            )
        how = (
            "from its last verified checkpoint: --resume continues bit for bit"
            if self.bit_for_bit
            else "from its last verified saved state (no verified checkpoint there): "
            "--resume restarts the solver cold, so later steps agree with an uninterrupted "
            "run to the solver's tolerance, not bit for bit"
        )
        claimed = f" of {self.recorded_steps}" if self.recorded_steps >= 0 else ""
        lines = [
            f"salvaged {str(self.path)!r}: kept steps 0..{self.kept_steps}{claimed}, {how}; "
            f"the damaged original is {str(self.backup)!r}"
        ]
        lines += [f"  lost: {line}" for line in self.lost]
        lines += [f"  repaired: {line}" for line in self.repaired]
        if not self.lost:
            lines.append("  every row of those steps read back intact")
        return "\n".join(lines)


def salvage(path: Path | str) -> SalvageReport:
    """Rebuild a damaged trajectory file from what reads back (module doc).

    Parameters
    ----------
    path : Path or str
        The trajectory file. It is locked like a run's output, so a file another run is
        writing is refused (:class:`~lieflow.app.io.OutputBusyError`).

    Returns
    -------
    SalvageReport
        What was kept, lost and repaired; the original is kept as ``report.backup``.

    Raises
    ------
    LieflowError
        Not a lieflow trajectory file, or not even its step 0 (the initial condition, its
        energy and Casimirs) reads back: then only a new run (``--force``) helps.
    """
    p = _as_path(path)
    _check_signature(p, _FIX)
    lock = _OutputLock.acquire(p, _WRITABLE_FIX)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.salvage")
    try:
        intact = _intact_steps(p)
        if intact is not None:
            return SalvageReport(p, None, intact, intact, True)
        with _source(p) as (src, end):
            plan = _Plan.of(src, end, p)
            lost = _rebuild(src, end, plan, tmp)
        backup = _free_name(p.with_name(f"{p.name}.damaged"))
        try:
            os.link(p, backup)
        except OSError:  # no hard links here: a copy
            shutil.copyfile(p, backup)
        os.replace(tmp, p)
    except OSError as exc:
        raise LieflowError(
            f"cannot salvage {_where(p)}: {exc.strerror or exc}. To fix: salvage needs as much "
            f"free space as the file; {_WRITABLE_FIX}."
        ) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        lock.release()
    return SalvageReport(p, backup, plan.recorded, plan.k, plan.exact, lost, plan.repaired)


def _intact_steps(path: Path) -> int | None:
    """The steps of a file that passes every check of a resume (nothing to salvage), else
    None."""
    try:
        with _opened(path) as (f, ck, layout):
            _check_attributes(f, path)
            _check_kept(f, ck.step, path, layout)
            _check_spare(f, path)
            return ck.step
    except (LieflowError, *_DAMAGE):
        return None


def _free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2``, ... whichever does not exist."""
    candidate, i = path, 0
    while os.path.lexists(candidate):
        i += 1
        candidate = path.with_name(f"{path.name}.{i}")
    return candidate


# -- reading what reads back -----------------------------------------------------------------


#: What a file cut short reads as past its end (:class:`_Padded`): bytes that fail every
#: checksum they meet (zeros would not: a chunk of zeros with a zero Fletcher-32 checksum
#: reads back as valid zeros), a fixed pseudo-random pattern of prime length.
_PAD = np.random.default_rng(37).integers(0, 256, 251, dtype=np.uint8).tobytes()


class _Padded(io.RawIOBase):
    """A file read as if it were ``size`` bytes long, :data:`_PAD` past its real end (a
    file cut short, read without copying or changing it)."""

    def __init__(self, path: Path, size: int) -> None:
        self._file = open(path, "rb")
        self._size, self._pos = size, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = 0) -> int:
        base = (0, self._pos, self._size)[whence]
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buffer: Any) -> int:
        n = min(len(buffer), max(0, self._size - self._pos))
        self._file.seek(self._pos)
        data = self._file.read(n)
        buffer[: len(data)] = data
        if len(data) < n:  # past the end: the pattern, where it falls in the file
            start = self._pos + len(data)
            pad = _PAD * ((n - len(data)) // len(_PAD) + 2)
            buffer[len(data) : n] = pad[start % len(_PAD) :][: n - len(data)]
        self._pos += n
        return n

    def close(self) -> None:
        self._file.close()
        super().close()


@contextlib.contextmanager
def _source(path: Path) -> Iterator[tuple[Any, int]]:
    """The damaged file open read-only (a file shorter than HDF5 recorded: padded with
    zeros to its recorded length, in memory only), and its size on disk."""
    h5py = _h5py()
    padded = None
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        found = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", str(exc))
        if found is None or int(found.group(2)) <= int(found.group(1)):
            raise _lost(path, exc) from None
        padded = _Padded(path, int(found.group(2)))
        try:
            f = h5py.File(padded, "r")
        except OSError as exc2:
            padded.close()
            raise _lost(path, exc2) from None
    try:
        yield f, os.path.getsize(path)
    finally:
        f.close()  # before the padded view it reads
        if padded is not None:
            padded.close()


def _lost(path: Path, exc: BaseException) -> DamagedOutputError:
    return DamagedOutputError(
        f"{_where(path)} cannot be salvaged: its HDF5 structure (not only its data) is "
        f"damaged ({type(exc).__name__}: {exc}), so no step of it can be verified. To fix: "
        f"{_AGAIN}."
    )


def _hole(dtype: np.dtype) -> Any:
    """What a row that did not read back holds: NaN, or -1 for integers."""
    return -1 if np.dtype(dtype).kind in "iu" else np.nan


def _located(ds: Any, end: int) -> set[int]:
    """The first rows of the chunks of ``ds`` that HDF5's chunk index finds (as a read does:
    a chunk it has lost reads as zeros) wholly inside the file's ``end`` bytes on disk (a
    file cut short reads as padding past its end): the chunks whose rows may be taken for
    data."""
    size, rest = ds.chunks[0], (0,) * (ds.ndim - 1)
    located = set()
    for c in range(0, ds.shape[0], size):
        try:
            _chunk_at(ds, c)
            info = ds.id.get_chunk_info_by_coord((c, *rest))
        except _DAMAGE:
            continue
        if info.byte_offset is not None and int(info.byte_offset) + int(info.size) <= end:
            located.add(c)
    return located


def _blocks(
    ds: Any, start: int, stop: int, end: int
) -> Iterator[tuple[int, int, Array, list[tuple[int, int]]]]:
    """Rows ``start..stop-1`` of ``ds`` (in a file of ``end`` bytes on disk) in blocks
    ``(a, b, rows, lost)``: the rows of chunks that fail their checksum, or that the chunk
    index does not place inside the file, hold :func:`_hole`, and ``lost`` lists their
    ranges. Blocks of 64 chunks are read at once,
    and chunk by chunk only where one fails."""
    size = (ds.chunks or (max(stop - start, 1),))[0]
    located = _located(ds, end) if ds.chunks else None
    block = 64 * size
    a = start
    while a < stop:
        b = min((a // block + 1) * block, stop)
        whole = located is not None and all(c in located for c in range(a // size * size, b, size))
        if whole or not ds.chunks:
            try:
                yield a, b, ds[a:b], []
                a = b
                continue
            except _DAMAGE:
                pass
        rows = np.empty((b - a, *ds.shape[1:]), dtype=ds.dtype)
        lost: list[tuple[int, int]] = []
        c = a
        while c < b:  # chunk by chunk: [c, d) within one chunk
            d = min((c // size + 1) * size, b)
            try:
                if located is None or c // size * size not in located:
                    raise KeyError("chunk not in the file")
                rows[c - a : d - a] = ds[c:d]
            except _DAMAGE:
                rows[c - a : d - a] = _hole(ds.dtype)
                lost.append((c, d))
            c = d
        yield a, b, rows, lost
        a = b


def _lost_rows(ds: Any, rows: int, end: int) -> list[tuple[int, int]]:
    """Ranges of the first ``rows`` rows of ``ds`` that do not read back."""
    return [r for _, _, _, lost in _blocks(ds, 0, min(rows, ds.shape[0]), end) for r in lost]


def _inside(k: int, ranges: list[tuple[int, int]]) -> bool:
    return any(a <= k < b for a, b in ranges)


def _ranges(ranges: list[tuple[int, int]], shift: int = 0) -> str:
    """``a..b`` of each range (inclusive, shifted to steps)."""
    return ", ".join(f"{a + shift}..{b - 1 + shift}" for a, b in ranges)


def _get(f: Any, name: str) -> Any:
    """Dataset ``name`` of ``f``, or None if it (or its HDF5 object header) is gone."""
    try:
        return f[name]
    except _DAMAGE:
        return None


#: Header attributes that no copy restores: their value when they do not read back.
_NO_COPY = {"config": "", "config_source": "", "created": "", "failure": "", "resumes": 0,
            "wall_time": 0.0}  # fmt: skip


@attrs.frozen(eq=False)
class _Plan:
    """What the rebuilt file holds: its header, step 0, the restart point ``k`` and its
    checkpoint items, and what was lost and repaired."""

    layout: _Layout
    meta: Mapping[str, Any]
    W0: Array = attrs.field(repr=False)
    H0: Array = attrs.field(repr=False)
    C0: Array = attrs.field(repr=False)
    labels: list[Array]
    casimir_labels: Array
    recorded: int
    k: int
    exact: bool
    items: Mapping[str, Any] = attrs.field(repr=False)
    saved: Array = attrs.field(repr=False)  # the rows of the saved states kept
    saved_steps: Array = attrs.field(repr=False)
    lost: tuple[str, ...]
    repaired: tuple[str, ...]

    @classmethod
    def of(cls, f: Any, end: int, path: Path) -> _Plan:
        lost: list[str] = []
        repaired: list[str] = []
        meta = _attributes(f, lost, repaired, path)
        if meta.get("format") != FORMAT:
            with contextlib.suppress(DamagedOutputError):
                _check_format(f, path)  # raises: not a lieflow trajectory file
            raise _lost(path, KeyError("its header attributes and their copies"))
        version = meta.get("format_version")
        layout = _LAYOUTS.get(version) if isinstance(version, int) else None
        if layout is None:
            layout = _LAYOUTS[2 if _exists(f, "saved_step") else 1]
            repaired.append("attribute format_version (from the file's layout)")
        meta["format_version"] = FORMAT_VERSION  # the layout the new file is written in
        at = layout.paths
        h = float(meta["h"])
        # step 0: W0 (or its copy, the saved state of step 0), its energy and Casimirs
        W_ds, saved_ds, time_ds = _get(f, at["W"]), _get(f, at["saved_step"]), _get(f, at["time"])
        saved_steps, saved_ok = _saved_steps(saved_ds, time_ds, h, end, lost, repaired)
        n_saved = saved_steps.size
        W_lost = [(0, n_saved)] if W_ds is None else _lost_rows(W_ds, n_saved, end)
        W0 = _initial(f, at, W_ds, saved_steps, W_lost, repaired, path)
        H0, C0 = _step0(f, at, path)
        # the per-step rows: how many, and which are lost
        per_step = {n: _get(f, at[n]) for n in (*_PER_STEP, *_PER_UPDATE)}
        row0 = {n: (layout.update_row0 if n in _PER_UPDATE else 0) for n in per_step}
        last = min(
            (ds.shape[0] - 1 - row0[n] for n, ds in per_step.items() if ds is not None),
            default=-1,
        )
        holes = {  # a dataset whose HDF5 structure is lost: all its rows after step 0
            n: [(1 + row0[n], last + 1 + row0[n])] if ds is None else
            _lost_rows(ds, last + 1 + row0[n], end)
            for n, ds in per_step.items()
        }  # fmt: skip
        invariant = holes["energy"] + holes["casimirs"]
        # the restart point
        recorded = int(meta.get("completed_steps", -1))
        k, items, exact = _restart(f, W_ds, saved_steps, saved_ok, W_lost, last, invariant, W0)
        for name, ranges in holes.items():
            steps = [(a - row0[name], b - row0[name]) for a, b in ranges if a - row0[name] <= k]
            steps = [(max(a, 0), min(b, k + 1)) for a, b in steps]
            if steps:
                lost.append(f"{name} of steps {_ranges(steps)} (NaN or -1 in the file)")
        wanted = [int(i) for i in np.flatnonzero(saved_ok & (saved_steps <= k))]
        keep = [i for i in wanted if i == 0 or not _inside(i, W_lost)]  # row 0: W0, a copy
        dropped = [int(saved_steps[i]) for i in wanted if i not in keep]
        if dropped:
            lost.append(f"the saved states of steps {_list(dropped)} (left out)")
        if keep[:1] == [0] and _inside(0, W_lost):
            repaired.append("the saved state of step 0 (from initial/W0)")
        labels, casimir_labels = _labels(f, meta, W0, C0, repaired)
        kept = np.asarray(keep, dtype=np.int64)
        return cls(layout, meta, W0, H0, C0, labels, casimir_labels, recorded, k, exact, items,
                   kept, saved_steps[kept], tuple(lost), tuple(repaired))  # fmt: skip


def _list(steps: list[int]) -> str:
    return ", ".join(map(str, steps[:12])) + (
        f", ... ({len(steps)} in all)" if len(steps) > 12 else ""
    )


def _attributes(f: Any, lost: list[str], repaired: list[str], path: Path) -> dict[str, Any]:
    """The header attributes, each read on its own; one that does not read back is taken
    from its copy (the identity, the configuration), else set empty (``lost``)."""
    try:
        keys = list(f.attrs.keys())
    except _DAMAGE:
        keys = []
    meta: dict[str, Any] = {}
    bad: list[str] = []
    for key in keys:
        try:
            meta[key] = _plain(f.attrs[key])
        except _DAMAGE:
            bad.append(key)
    meta.pop("_NCProperties", None)
    copy = _header_of(f)
    for key, value in (copy or {}).items():  # the copy written with the file wins
        now = json.loads(_header_copy({key: meta[key]})).get(key) if key in meta else None
        if key in bad or key not in meta or now != value:
            why = "unreadable" if key in bad else "missing" if key not in meta else "changed"
            repaired.append(f"attribute {key} ({why}; from its copy in initial/W0)")
            meta[key] = value
            if key in bad:
                bad.remove(key)
    identity = _identity(meta, bad, repaired)
    copies: dict[str, Any] = {}
    if isinstance(identity, dict):
        for key in ("system", "scheme", "solver"):
            part = identity.get(key)
            if isinstance(part, Mapping) and isinstance(part.get("name"), str):
                copies[key] = part["name"]
        for key in ("h", "save_every"):
            if key in identity:
                copies[key] = identity[key]
    wanted = [*bad, "format", "h", "save_every", "system", "scheme", "solver", "identity"]
    for key in dict.fromkeys(wanted):
        if key in meta and key not in bad:
            continue
        if key in copies:
            meta[key] = copies[key]
            repaired.append(f"attribute {key} (from the run's identity)")
        elif key in _NO_COPY or key in ("system", "scheme", "solver", "identity"):
            meta[key] = _NO_COPY.get(key, "")
            lost.append(f"attribute {key} (it has no copy: set to {meta[key]!r})")
        elif key in ("h", "save_every"):
            raise DamagedOutputError(
                f"{_where(path)} cannot be salvaged: its header attribute {key} does not read "
                "back, nor its copies (the run's identity and configuration, the copy in "
                f"initial/W0): its HDF5 structure is lost. To fix: {_AGAIN}."
            )
        elif key == "format" and _exists(f, "initial/W0") and _exists(f, "checkpoint"):
            meta[key] = FORMAT
            repaired.append("attribute format (from the file's layout)")
        elif key not in ("completed_steps", "status"):
            meta[key] = ""  # a version or platform recorded at creation
            lost.append(f"attribute {key} (it has no copy: set to '')")
    meta.setdefault("requested_steps", 0)
    return meta


def _header_of(f: Any) -> dict[str, Any] | None:
    """The copy of the root attributes written with the file (``initial/W0``'s
    :data:`~lieflow.app.io._format._HEADER_COPY`), or None (a file written before it, or
    damaged there)."""
    try:
        raw = f["initial/W0"].attrs.get(_HEADER_COPY)
        copy = None if raw is None else json.loads(_plain(raw))
    except (*_DAMAGE, json.JSONDecodeError):
        return None
    return copy if isinstance(copy, dict) else None


def _identity(meta: dict[str, Any], bad: list[str], repaired: list[str]) -> Any:
    """The run's identity as a mapping: the attribute, or (if it does not read back) the
    identity of the configuration the file holds (``lieflow run``'s files)."""
    if "identity" in meta and "identity" not in bad:
        with contextlib.suppress(ValueError, TypeError):
            return json.loads(str(meta["identity"]))
        bad.append("identity")
    config = meta.get("config") if "config" not in bad else None
    if config:
        from .config import parse_config

        with contextlib.suppress(LieflowError, ValueError, TypeError):
            identity = parse_config(str(config)).identity()
            meta["identity"] = identity
            if "identity" in bad:
                bad.remove("identity")
                repaired.append("attribute identity (from the configuration it holds)")
            return json.loads(identity)
    return None


def _saved_steps(saved: Any, time: Any, h: float, end: int, lost: list[str],
                 repaired: list[str]) -> tuple[Array, Array]:  # fmt: skip
    """The steps of the saved states, each from ``saved_step`` or (where that is lost) from
    its time ``t = k h``, and which are known."""
    n = 0 if saved is None else saved.shape[0]
    if time is not None:
        n = max(n, time.shape[0]) if saved is None else min(n, time.shape[0])
    steps = np.full(n, -1, dtype=np.int64)
    known = np.zeros(n, dtype=bool)
    if saved is not None:
        for a, b, rows, bad in _blocks(saved, 0, n, end):
            steps[a:b] = rows
            known[a:b] = True
            for c, d in bad:
                known[c:d] = False
    if time is not None and not known.all():
        fixed = 0
        for a, b, rows, bad in _blocks(time, 0, n, end):
            ok = np.ones(b - a, dtype=bool)
            for c, d in bad:
                ok[c - a : d - a] = False
            mend = ok & ~known[a:b]
            steps[a:b][mend] = np.rint(rows[mend] / h).astype(np.int64)
            known[a:b] |= mend
            fixed += int(mend.sum())
        if fixed:
            repaired.append(f"the steps of {fixed} saved states (from their times)")
    if n:  # the first saved state is always step 0's
        steps[0], known[0] = 0, True
    unknown = int((~known).sum())
    if unknown:
        lost.append(f"{unknown} saved states whose step and time are both lost (left out)")
    return steps, known


def _initial(f: Any, at: Mapping[str, str], W: Any, saved_steps: Array,
             W_lost: list[tuple[int, int]], repaired: list[str], path: Path) -> Array:  # fmt: skip
    """``initial/W0``, or its copy: the saved state of step 0 (the first saved row)."""
    ds = _get(f, at["W0"])
    try:
        if ds is None:
            raise KeyError(at["W0"])
        return np.asarray(ds[()])
    except _DAMAGE:
        if W is not None and saved_steps.size and saved_steps[0] == 0 and not _inside(0, W_lost):
            repaired.append("initial/W0 (from the saved state of step 0)")
            return np.asarray(W[0])
    raise DamagedOutputError(
        f"{_where(path)} cannot be salvaged: its initial condition reads back neither from "
        f"initial/W0 nor from the saved state of step 0. To fix: {_AGAIN}."
    )


def _step0(f: Any, at: Mapping[str, str], path: Path) -> tuple[Array, Array]:
    """Step 0's energy and Casimirs (every energy error is measured from them)."""
    try:
        return np.asarray(f[at["energy"]][0]), np.asarray(f[at["casimirs"]][0])
    except _DAMAGE:
        raise DamagedOutputError(
            f"{_where(path)} cannot be salvaged: not even its first step (the energy and "
            "Casimirs of the initial condition, from which every error is measured) reads "
            f"back intact. To fix: {_AGAIN}."
        ) from None


def _restart(f: Any, W: Any, saved_steps: Array, known: Array, W_lost: list[tuple[int, int]],
             last: int, invariant: list[tuple[int, int]],
             W0: Array) -> tuple[int, Mapping[str, Any], bool]:  # fmt: skip
    """The restart point ``(k, checkpoint items, bit for bit)``: the later verified checkpoint
    slot, else the latest intact saved state, else step 0; each with its step's energy and
    Casimirs intact (a resume checks the state against them) and within the recorded rows."""
    slots: list[tuple[int, dict[str, Any]]] = []
    for i in (0, 1):
        try:
            slot = f["checkpoint"][f"slot{i}"]
            step, t = int(slot.attrs["step"]), float(slot.attrs["t"])
            items = _slot_items(slot)
            digest = _plain(slot.attrs.get("sha256"))
        except _DAMAGE:
            continue
        if (
            "W" in items
            and digest == checkpoint_digest(step, t, items)
            and step <= last
            and not _inside(step, invariant)
        ):
            slots.append((step, items))
    if slots:
        step, items = max(slots, key=lambda s: s[0])
        return step, items, True
    for i in range(saved_steps.size - 1 if W is not None else 0, 0, -1):
        s = int(saved_steps[i])
        if known[i] and 0 < s <= last and not _inside(i, W_lost) and not _inside(s, invariant):
            return s, {"W": np.asarray(W[i])}, False
    return 0, {"W": W0}, True  # from step 0 a run starts cold: the same steps, bit for bit


def _labels(f: Any, meta: Mapping[str, Any], W0: Array, C0: Array,
            repaired: list[str]) -> tuple[list[Array], Array]:  # fmt: skip
    """The ensemble axes' labels and the Casimirs' (coordinate variables, or their copies:
    the configuration's seeds, the attribute ``casimir_powers``)."""
    batch = W0.shape[:-2]
    names = ["ensemble"] if len(batch) == 1 else [f"ensemble_{i}" for i in range(len(batch))]
    labels = []
    for name, n in zip(names, batch, strict=True):
        try:
            labels.append(np.asarray(f[name][()], dtype=np.int64))
        except _DAMAGE:
            if _exists(f, name):
                repaired.append(f"the labels {name} (from the configuration)")
            config = str(meta.get("config", ""))
            labels.append(_ensemble_labels(config, n) if len(batch) == 1 else np.arange(n))
    powers = np.asarray(meta.get("casimir_powers", []), dtype=np.int64).reshape(-1)
    try:
        casimir = np.asarray(f[_LABELS[1]][()], dtype=np.int64)
    except _DAMAGE:
        casimir = powers if powers.size == C0.shape[-1] else np.arange(C0.shape[-1])
        if _exists(f, _LABELS[1]):
            repaired.append("the labels casimir (from the attribute casimir_powers)")
    return labels, casimir


def _exists(f: Any, name: str) -> bool:
    try:
        return name in f
    except _DAMAGE:
        return False


# -- writing the new file ----------------------------------------------------------------------


def _rebuild(src: Any, end: int, plan: _Plan, tmp: Path) -> tuple[str, ...]:
    """Write the salvaged file to ``tmp``: the header, step 0, every row of steps
    ``1..k`` (holes where they were lost), the saved states kept, the system's extra
    diagnostics, and the checkpoint at ``k``; returns all that was lost."""
    h5py = _h5py()
    at, k = plan.layout.paths, plan.k
    h = float(plan.meta["h"])
    with h5py.File(tmp, "w", rdcc_nbytes=_CHUNK_CACHE_BYTES) as f:
        _lay_out(f, plan.meta, plan.W0, plan.H0, plan.C0, plan.labels, plan.casimir_labels)
        for name in (*_PER_STEP, *_PER_UPDATE):
            ds, out = _get(src, at[name]), f[name]
            out.resize(k + 1, axis=0)
            if ds is None:  # its structure is lost: every row a hole
                out[1:] = _hole(out.dtype)
                continue
            shift = plan.layout.update_row0 if name in _PER_UPDATE else 0
            start = 1 + shift  # the source rows of steps 1..k
            for a, b, rows, _ in _blocks(ds, start, min(k + 1 + shift, ds.shape[0]), end):
                out[a - shift : b - shift] = rows
        f["step"].resize(k + 1, axis=0)
        f["step"][:] = np.arange(k + 1)
        keep = plan.saved
        for name in ("saved_step", "time", "W"):
            f[name].resize(keep.size, axis=0)
        f["saved_step"][:] = plan.saved_steps
        f["time"][:] = plan.saved_steps * h
        if keep.size:
            f["W"][0] = plan.W0  # row 0 is always step 0 (its copy, where it was lost)
            where = {int(i): j for j, i in enumerate(keep)}
            for a, b, rows, _ in _blocks(src[at["W"]], 1, int(keep[-1]) + 1, end):
                mine = [i for i in range(a, b) if i in where]
                if mine:
                    out = [where[i] for i in mine]
                    f["W"][out[0] : out[-1] + 1] = rows[np.asarray(mine) - a]
        lost = (*plan.lost, *_copy_extra(src, end, f, k))
        group = f["checkpoint"]
        _write_slot(group["slot1"], k, k * h, plan.items, {})
        group.attrs["current"] = 1
        f.attrs["completed_steps"] = k
        f.attrs["requested_steps"] = max(int(plan.meta.get("requested_steps", 0)), k)
        f.attrs["status"] = "interrupted"
        said = "; ".join([*lost, *(f"repaired {r}" for r in plan.repaired)])
        f.attrs["salvaged"] = (
            f"rebuilt by `lieflow salvage` from steps 0..{k} of the {plan.recorded} recorded "
            + ("(a verified checkpoint)" if plan.exact else "(a saved state: cold restart)")
            + (f"; lost: {said}" if said else "")
        )
    return lost


def _copy_extra(src: Any, end: int, f: Any, k: int) -> list[str]:
    """Copy the system's extra diagnostics of steps ``0..k`` whose row reads back in every
    column (a sample with any column lost is left out); returns what was lost."""
    try:
        group = src[_EXTRA]
        columns = {name: ds for name, ds in group.items() if not _is_dimension(ds)}
        n = min(ds.shape[0] for ds in columns.values())
    except _DAMAGE:
        return ["the system's extra diagnostics"] if _exists(src, _EXTRA) else []
    ok = np.ones(n, dtype=bool)
    values: dict[str, Array] = {}
    for name, ds in columns.items():
        parts = []
        for _, _, block, bad in _blocks(ds, 0, n, end):
            parts.append(block)
            for c, d in bad:
                ok[c:d] = False
        values[name] = np.concatenate(parts) if parts else np.zeros((0, *ds.shape[1:]))
    steps = values["step"]
    ok &= (steps >= 0) & (steps <= k)
    _append_extra(f, [
        (int(steps[i]), float(values["t"][i]),
         {name: v[i] for name, v in values.items() if name not in ("step", "t")})
        for i in np.flatnonzero(ok)
    ])  # fmt: skip
    dropped = int(((steps <= k) & ~ok).sum())
    return [f"{dropped} samples of the system's extra diagnostics"] if dropped else []


def _is_dimension(ds: Any) -> bool:
    h5py = _h5py()
    return not isinstance(ds, h5py.Dataset) or bool(h5py.h5ds.is_scale(ds.id))
