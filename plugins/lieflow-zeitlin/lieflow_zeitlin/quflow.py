r"""Reading quflow's HDF5 simulation files (``quflow.QuSimulation``), to analyse or continue
a quflow run with lieflow.

quflow's layout (checked against quflow commit b42eede, ``quflow/simulation.py``): in the
group ``datapath`` (default ``/``)

* ``mat`` — the vorticity matrices, shape ``(n, [k,] N, N)``, complex (present when the
  simulation's ``qutypes`` include ``'mat'``, quflow's default);
* ``time`` — float64 ``(n,)``, the time of each saved state;
* ``step`` — int ``(n,)``, the step counter;
* the attribute ``N``;
* other datasets (``fun``, ``shr``, loggers, ``iterations`` ...), and *pickled* attributes
  (``qutypes``, ``loggers``, the integrator and callbacks under ``args``).

This module opens the file with h5py and reads ``mat``, ``time``, ``step`` and ``N`` only:
it **never unpickles** anything (unpickling runs arbitrary code from the file).

Conventions. The matrices need no conversion: lieflow-zeitlin's quantization is quflow's
(same matrix for the same field, docs page "Euler–Zeitlin"). quflow's ``time`` is in
"seconds" with ``dt = ħ · stepsize``, and its step is ``W ← W + stepsize [P, W] + ...``
with ``P = Δ_N^{-1} W``, i.e. ``dW/dt = (1/ħ)[P, W]``: quflow's time **is** lieflow's fluid
time (:class:`~lieflow_zeitlin.EulerZeitlin` with ``time="fluid"``, the default). For a
system in matrix time (``time="matrix"``) the times are divided by ``ħ``.

To continue a quflow run with ``lieflow run``: write its last state with
:func:`import_quflow` (or ``python -m lieflow_zeitlin.quflow FILE.h5 --out W0.npy``), use
``[initial] file = "W0.npy"`` and add the printed time to lieflow's ``t`` (a lieflow run
starts at ``t = 0``).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import NDArray

import lieflow

from .quantization import hbar

Array = NDArray[Any]

__all__ = ["QuflowRun", "import_quflow", "quflow_dataset", "read_quflow"]


@attrs.frozen(eq=False)
class QuflowRun:
    """States and times read from a quflow file (:func:`read_quflow`).

    Attributes
    ----------
    path : Path
    N : int
    W : ndarray, shape (n, [k,] N, N)
        The ``mat`` dataset (as stored; no conversion is needed).
    t : ndarray, shape (n,)
        Times in the requested lieflow unit (fluid time: quflow's ``time`` itself).
    step : ndarray, shape (n,)
        quflow's step counter.
    quflow_time : ndarray, shape (n,)
        quflow's ``time`` dataset as stored.
    time_unit : {"fluid", "matrix"}
    """

    path: Path
    N: int
    W: Array = attrs.field(repr=False)
    t: Array = attrs.field(repr=False)
    step: Array = attrs.field(repr=False)
    quflow_time: Array = attrs.field(repr=False)
    time_unit: str = "fluid"


def _h5py() -> Any:
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise lieflow.InputError(
            f"reading quflow files needs h5py ({exc}): pip install 'lieflow[cli]'"
        ) from None
    return h5py


def _bad(path: Path, what: str) -> lieflow.InputError:
    return lieflow.InputError(
        f"{str(path)!r} is not a readable quflow simulation file: {what}. (quflow's "
        "QuSimulation writes the datasets mat, time and step and the attribute N; save with "
        "qutypes including 'mat'.)"
    )


def read_quflow(
    path: Path | str,
    *,
    datapath: str = "/",
    time: Literal["fluid", "matrix"] = "fluid",
    index: int | slice | Sequence[int] | None = None,
) -> QuflowRun:
    """Read the states and times of a quflow simulation file (module docs).

    Parameters
    ----------
    path : path
    datapath : str
        The group quflow wrote into (``QuSimulation(datapath=...)``, default ``/``).
    time : {"fluid", "matrix"}
        The lieflow time unit of :attr:`QuflowRun.t` (the unit of the system that continues
        the run).
    index : int, slice or indices, optional
        Which saved states to read (default all; ``-1``: the last only, kept as a length-1
        axis). Only these are read from the file.

    Raises
    ------
    lieflow.InputError
        Missing file, not HDF5, or missing/inconsistent ``mat``, ``time``, ``step``, ``N``.
    """
    h5py = _h5py()
    p = Path(path)
    if time not in ("fluid", "matrix"):
        raise lieflow.InputError(f'time must be "fluid" or "matrix", got {time!r}')
    if not p.is_file():
        raise lieflow.InputError(f"{str(p)!r}: no such file")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise _bad(p, f"not HDF5 ({exc})") from None
    with f:
        group = f.get(datapath)
        if group is None or not isinstance(group, h5py.Group):
            raise _bad(p, f"no group {datapath!r}")
        for name in ("mat", "time", "step"):
            if not isinstance(group.get(name), h5py.Dataset):
                raise _bad(p, f"no dataset {name!r} in {datapath!r}")
        if "N" not in group.attrs:
            raise _bad(p, f"no attribute 'N' on {datapath!r}")
        N = int(np.asarray(group.attrs["N"]))  # a plain integer attribute: nothing unpickled
        mat, times, steps = group["mat"], group["time"], group["step"]
        if mat.ndim < 3 or mat.shape[-2:] != (N, N):
            raise _bad(p, f"'mat' has shape {mat.shape}, expected (n, ..., {N}, {N})")
        if not np.issubdtype(mat.dtype, np.complexfloating):
            raise _bad(p, f"'mat' has dtype {mat.dtype}, expected complex")
        n = min(mat.shape[0], times.shape[0], steps.shape[0])  # a run stopped mid-write
        rows = np.arange(n)
        if index is not None:
            rows = np.atleast_1d(rows[index])
        unique, inverse = np.unique(rows, return_inverse=True)
        if unique.size == n:
            W = mat[:n][inverse]
        elif unique.size:
            W = mat[unique.tolist()][inverse]  # h5py: increasing indices, read once each
        else:
            W = np.zeros((0, *mat.shape[1:]), mat.dtype)
        q_time = np.asarray(times[()], dtype=np.float64)[rows]
        step = np.asarray(steps[()], dtype=np.int64)[rows]
    t = q_time if time == "fluid" else q_time / hbar(N)
    return QuflowRun(p, N, W, t, step, q_time, time)


def quflow_dataset(path: Path | str, *, datapath: str = "/", time: str = "fluid") -> Any:
    """A quflow file as an :class:`xarray.Dataset` laid out like :func:`lieflow.open_run`'s
    states: ``W`` over ``(time, [ensemble,] row, col)`` with coordinates ``time`` (lieflow
    time, module docs) and ``saved_step`` (quflow's step counter); attributes
    ``source = "quflow"``, ``N``, ``time_unit``. Reads every state (``read_quflow``)."""
    import xarray as xr

    run = read_quflow(path, datapath=datapath, time=time)  # type: ignore[arg-type]
    dims = ("time", *(["ensemble"] if run.W.ndim == 4 else []), "row", "col")
    return xr.Dataset(
        {"W": (dims, run.W)},
        coords={"time": ("time", run.t), "saved_step": ("time", run.step)},
        attrs={"source": "quflow", "path": str(run.path), "N": run.N, "time_unit": time},
    )


def import_quflow(
    path: Path | str,
    out: Path | str,
    *,
    index: int = -1,
    datapath: str = "/",
    time: Literal["fluid", "matrix"] = "fluid",
) -> tuple[Path, float]:
    """Write state ``index`` of a quflow file as a ``.npy`` for ``[initial] file`` and
    return ``(path, t)``: its time in the lieflow unit ``time``.

    The state is projected onto su(N) (skew-Hermitian part, trace removed), as lieflow's
    initial conditions must be; for quflow's own states that changes only roundoff.
    """
    run = read_quflow(path, datapath=datapath, time=time, index=index)
    W = np.asarray(run.W[0], dtype=np.complex128)
    W = 0.5 * (W - np.conj(np.swapaxes(W, -1, -2)))
    trace = np.trace(W, axis1=-2, axis2=-1)[..., None, None] / run.N
    W = W - trace * np.eye(run.N)
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    np.save(target, W)
    return target, float(run.t[0])


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m lieflow_zeitlin.quflow FILE.h5 --out W0.npy [--index -1]``."""
    parser = argparse.ArgumentParser(
        prog="python -m lieflow_zeitlin.quflow",
        description="Write a state of a quflow simulation file as a .npy for lieflow's "
        "[initial] file, and print its fluid time.",
    )
    parser.add_argument("file", type=Path)
    parser.add_argument("--out", type=Path, required=True, metavar="W0.npy")
    parser.add_argument("--index", type=int, default=-1, help="saved state (default: last)")
    parser.add_argument("--datapath", default="/")
    parser.add_argument("--time", choices=("fluid", "matrix"), default="fluid")
    args = parser.parse_args(argv)
    try:
        out, t = import_quflow(
            args.file, args.out, index=args.index, datapath=args.datapath, time=args.time
        )
    except lieflow.InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{out}: state at t = {t!r} ({args.time} time){_note(t)}")
    return 0


def _note(t: float) -> str:
    return "" if math.isfinite(t) else " (quflow wrote a non-finite time)"


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
