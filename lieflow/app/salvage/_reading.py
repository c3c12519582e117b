"""Reading the damaged file: opened read-only and padded where it was cut short
(:func:`_source`, :class:`_Padded`), its datasets looked up without raising (:func:`_get`,
:func:`_exists`), and read chunk by chunk with each chunk's checksum verified
(:func:`_blocks`): the rows that do not read back become holes (:func:`_hole`), and their
ranges are listed (:func:`_lost_rows`, :func:`_inside`, :func:`_ranges`)."""

from __future__ import annotations

import contextlib
import io
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ...algebras import Array
from ..io._format import _DAMAGE, _h5py, _where
from ..io._lock import DamagedOutputError
from ..io._reader import _chunk_at

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


_AGAIN = "restore it from a backup, or run the configuration again from the start (--force)"


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


def _get(f: Any, name: str) -> Any:
    """Dataset ``name`` of ``f``, or None if it (or its HDF5 object header) is gone."""
    try:
        return f[name]
    except _DAMAGE:
        return None


def _exists(f: Any, name: str) -> bool:
    try:
        return name in f
    except _DAMAGE:
        return False


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
