"""What the damaged file lost, taken from its copies: the header attributes
(:func:`_attributes`: the header copy in ``initial/W0``, the run's identity or
configuration), step 0 (:func:`_initial`, :func:`_step0`, :func:`_labels`), the steps of
the saved states (:func:`_saved_steps`), and the restart point among the checkpoint slots
and those states (:func:`_restart`)."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ...algebras import Array
from ...errors import LieflowError
from ..io._format import (
    _DAMAGE,
    _HEADER_COPY,
    _LABELS,
    FORMAT,
    _header_copy,
    _plain,
    _where,
    checkpoint_digest,
)
from ..io._lock import DamagedOutputError
from ..io._new_file import _ensemble_labels
from ..io._reader import _slot_items
from ._reading import _AGAIN, _blocks, _exists, _get, _inside

#: Header attributes that no copy restores: their value when they do not read back.
_NO_COPY = {"config": "", "config_source": "", "created": "", "failure": "", "resumes": 0,
            "wall_time": 0.0}  # fmt: skip


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
        from ..config import parse_config

        with contextlib.suppress(LieflowError, ValueError, TypeError):
            identity = parse_config(str(config)).identity()
            meta["identity"] = identity
            if "identity" in bad:
                bad.remove("identity")
                repaired.append("attribute identity (from the configuration it holds)")
            return json.loads(identity)
    return None


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
