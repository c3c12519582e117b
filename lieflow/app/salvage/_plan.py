"""The plan of the repair (:class:`_Plan`): what the rebuilt file holds (its header, step 0,
the restart point and its checkpoint, the saved states kept) and what was lost and repaired."""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ...algebras import Array
from ..io._format import _LAYOUTS, _PER_STEP, _PER_UPDATE, FORMAT, FORMAT_VERSION, _Layout
from ..io._lock import DamagedOutputError
from ..io._reader import _check_format
from ._reading import _exists, _get, _inside, _lost, _lost_rows, _ranges
from ._repairs import _attributes, _initial, _labels, _restart, _saved_steps, _step0


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
