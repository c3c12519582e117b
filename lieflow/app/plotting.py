"""PNG figures: energy-error panels (``lieflow reproduce``) and trajectory-file diagnostics
(``lieflow plot``, plus the figures a plugin registers for its system with
``registry.add_plotter``).

matplotlib is imported inside the functions and only its object-oriented API is used with
the Agg canvas: no pyplot, no global backend switch, no figure registry to leak.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import attrs
import numpy as np

from ..algebras import Array
from ..errors import LieflowError, PluginError

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure

    from ..plugins import Registry

__all__ = [
    "FLOOR",
    "Curve",
    "Panel",
    "SweepGroup",
    "energy_figure",
    "plot_sweep",
    "plot_trajectory",
    "sweep_groups",
]

#: Values below this (exact zeros: the energy at roundoff) are drawn at it on log axes.
FLOOR = 1e-17


@attrs.frozen(eq=False)
class Curve:
    """One line: ``values`` against ``t``."""

    label: str
    t: Array = attrs.field(repr=False)
    values: Array = attrs.field(repr=False)


@attrs.frozen(eq=False)
class Panel:
    """One axes of a figure: a title and its curves."""

    title: str
    curves: tuple[Curve, ...]


def _figure(rows: int, width: float = 8.0, height: float = 3.0) -> tuple[Figure, list[Any]]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, squeeze=False)[:, 0]
    return fig, list(axes)


def _save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def _log_values(values: Array) -> Array:
    return np.maximum(np.asarray(values, dtype=float), FLOOR)


def energy_figure(
    panels: Sequence[Panel], path: Path | str, *, title: str = "", ylabel: str = ""
) -> Path:
    """Draw one log-scale panel per :class:`Panel`, stacked vertically, and save a PNG.

    Parameters
    ----------
    panels : sequence of Panel
        Panels from top to bottom.
    path : path
        The PNG to write (parent directories are created).
    title : str
        Figure title.
    ylabel : str
        Label of every y axis (default: relative energy error).

    Returns
    -------
    Path
        ``path``.
    """
    fig, axes = _figure(len(panels))
    for ax, panel in zip(axes, panels, strict=True):
        for curve in panel.curves:
            ax.plot(curve.t, _log_values(curve.values), label=curve.label, linewidth=1.0)
        ax.set_yscale("log")
        ax.set_title(panel.title)
        ax.set_xlabel("t")
        ax.set_ylabel(ylabel or r"$|\eta(W_k) - \eta(W_0)| / |\eta(W_0)|$")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(loc="best", fontsize="small", ncols=2)
    if title:
        fig.suptitle(title)
    return _save(fig, Path(path))


def _worst(values: Array, keep: int) -> Array:
    """Max over batch axes (an ensemble), keeping the first axis and the last ``keep - 1``."""
    v = np.asarray(values, dtype=float)
    axes = tuple(range(1, v.ndim - (keep - 1)))
    return np.max(v, axis=axes) if axes else v


def plot_trajectory(
    path: Path | str, out_dir: Path | str | None = None, *, registry: Registry | None = None
) -> list[Path]:
    """Plot a trajectory file's energy error, Casimir drift and iterations per step, and the
    figures of the plotter a plugin registered for its system (if any).

    Parameters
    ----------
    path : path
        A file written by ``lieflow run``.
    out_dir : path, optional
        Where the PNGs go (default: next to the file).
    registry : Registry, optional
        Where to look up the system's :class:`~lieflow.plugins.Plotter` (default: the
        installed plugins, :func:`~lieflow.default_registry`).

    Returns
    -------
    list of Path
        ``<stem>_energy.png``, ``<stem>_casimirs.png``, ``<stem>_iterations.png``, then the
        plotter's files.

    Raises
    ------
    PluginError
        The system's plotter failed (the message names the plugin and the reason).
    """
    from ..plugins import default_registry
    from .io import read_trajectory

    traj = read_trajectory(path)
    src = Path(path)
    if traj.completed_steps == 0:
        failure = str(traj.meta.get("failure", "")).strip()
        raise LieflowError(
            f"{str(src)!r} holds no step after the initial state (status {traj.status!r}"
            + (f": {failure}" if failure else "")
            + "), so there is nothing to plot. To fix: "
            + ("fix what made its first step fail, and run it again."
               if traj.status == "failed" else "continue the run (--resume), then plot it.")
        )  # fmt: skip
    out = src.parent if out_dir is None else Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LieflowError(
            f"{str(out)!r} is a file, not a directory. To fix: give out_dir a directory "
            "(it is created if missing)."
        )
    stem = src.stem
    meta = traj.meta
    label = f"{meta['system']}, {meta['scheme']}, h = {meta['h']:g}"
    t = traj.step_times
    written = [
        energy_figure(
            [Panel(label, (Curve("energy error", t, _worst(traj.energy_error, 1)),))],
            out / f"{stem}_energy.png",
        )
    ]

    drift = _worst(traj.casimir_drift, 2)
    powers = list(np.atleast_1d(meta.get("casimir_powers", range(drift.shape[-1]))))
    curves = tuple(
        Curve(f"tr W^{k}" if len(powers) == drift.shape[-1] else f"C{j}", t, drift[:, j])
        for j, k in enumerate(powers[: drift.shape[-1]])
    )
    written.append(
        energy_figure(
            [Panel(label, curves)],
            out / f"{stem}_casimirs.png",
            ylabel=r"$|C(W_k) - C(W_0)| / \|W_0\|^k$",
        )
    )

    fig, (ax,) = _figure(1)
    ax.step(t[1:], traj.iterations, where="post", linewidth=1.0)
    ax.set_title(label)
    ax.set_xlabel("t")
    ax.set_ylabel("solver updates per step")
    ax.grid(True, alpha=0.3)
    written.append(_save(fig, out / f"{stem}_iterations.png"))

    plotter = (registry or default_registry()).plotters.get(str(meta["system"]))
    if plotter is not None:
        try:
            written.extend(Path(p) for p in plotter.function(traj, out, stem))
        except LieflowError:
            raise
        except Exception as exc:
            raise PluginError(
                f"the lieflow plot figures for {meta['system']!r} (from {plotter.source}) "
                f"failed: {type(exc).__name__}: {exc}. The generic figures were written; "
                "fix or update that plugin for the rest"
            ) from exc
    return written


@attrs.frozen
class SweepGroup:
    """The complete runs of a sweep that differ only in their step size: a label, and per
    run its step size, largest relative energy error and seconds of stepping."""

    label: str
    h: Array = attrs.field(repr=False)
    error: Array = attrs.field(repr=False)
    seconds: Array = attrs.field(repr=False)

    def order(self) -> float | None:
        r"""The observed order: the least-squares slope of :math:`\log` error against
        :math:`\log h` over runs above the roundoff floor (``None`` with fewer than two)."""
        ok = (self.error > 1e3 * np.finfo(float).eps) & np.isfinite(self.error)
        if np.unique(self.h[ok]).size < 2:
            return None
        return float(np.polyfit(np.log(self.h[ok]), np.log(self.error[ok]), 1)[0])


def sweep_groups(directory: Path | str) -> list[SweepGroup]:
    """The complete runs of the sweep in ``directory`` (:func:`lieflow.open_sweep`),
    grouped by every swept key except the step size ``run.h``."""
    from .datasets import open_sweep

    ds = open_sweep(directory, stack=True)
    axes = json.loads(ds.attrs.get("sweep_axes", "{}"))
    names = [name for name, keys in axes.items() if "run.h" not in keys]
    done = ds["status"].values == "complete"
    labels = np.array(
        [
            ", ".join(f"{n} = {ds[n].values[j]}" for n in names) or "all runs"
            for j in range(ds.sizes["run"])
        ]
    )
    groups = []
    for label in dict.fromkeys(labels[done]):
        pick = done & (labels == label)
        h = ds["step_size"].values[pick]
        order = np.argsort(h)
        groups.append(
            SweepGroup(
                str(label),
                h[order],
                ds["max_energy_error"].values[pick][order],
                ds["wall_time"].values[pick][order],
            )
        )
    return groups


def plot_sweep(directory: Path | str, out_dir: Path | str | None = None) -> list[Path]:
    """Convergence and work–precision figures of a sweep (``lieflow plot SWEEP_DIR``).

    For each group of complete runs that differ only in their step size
    (:func:`sweep_groups`): the largest relative energy error against ``h`` on log–log axes,
    with the observed order (least-squares slope) in the legend, and the seconds of
    stepping against that error (work–precision).

    Returns
    -------
    list of Path
        ``<dir>/convergence.png`` and ``<dir>/work_precision.png`` (or in ``out_dir``).

    Raises
    ------
    LieflowError
        Not a sweep directory, or no run is complete yet.
    """
    src = Path(directory)
    out = src if out_dir is None else Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LieflowError(f"{str(out)!r} is a file, not a directory. To fix: give a directory.")
    groups = sweep_groups(src)
    if not groups:
        raise LieflowError(
            f"no run of the sweep in {str(src)!r} is complete yet. To fix: run "
            "`lieflow sweep GRID.toml` to completion first."
        )
    fig, (ax,) = _figure(1, width=6.5, height=4.5)
    for g in groups:
        p = g.order()
        suffix = "" if p is None else f" (order {p:.2f})"
        ax.loglog(g.h, _log_values(g.error), "o-", label=g.label + suffix)
    ax.set_xlabel("step size h")
    ax.set_ylabel("largest relative energy error")
    ax.set_title("Convergence")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    written = [_save(fig, out / "convergence.png")]
    fig, (ax,) = _figure(1, width=6.5, height=4.5)
    for g in groups:
        ax.loglog(_log_values(g.error), np.maximum(g.seconds, 1e-6), "o-", label=g.label)
    ax.set_xlabel("largest relative energy error")
    ax.set_ylabel("seconds of stepping")
    ax.set_title("Work–precision")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    written.append(_save(fig, out / "work_precision.png"))
    return written
