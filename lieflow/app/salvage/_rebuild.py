"""Writing the salvaged file from its :class:`~lieflow.app.salvage._plan._Plan`
(:func:`_rebuild`): every row kept, holes where rows were lost, the system's extra
diagnostics (:func:`_copy_extra`) and the checkpoint at the restart point."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...algebras import Array
from ..io._format import _DAMAGE, _EXTRA, _PER_STEP, _PER_UPDATE, _h5py
from ..io._lock import _CHUNK_CACHE_BYTES
from ..io._new_file import _append_extra, _lay_out
from ..io._slots import _write_slot
from ._plan import _Plan
from ._reading import _blocks, _exists, _get, _hole


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
