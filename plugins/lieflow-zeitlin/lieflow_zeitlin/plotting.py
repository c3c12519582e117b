r"""PNG figures of Euler–Zeitlin runs: vorticity on the sphere and conservation diagnostics.

The vorticity of a matrix ``W`` is the field ``ω = Q^{-1}(W)``
(:func:`~lieflow_zeitlin.matrix_to_grid`) sampled on an equiangular latitude–longitude grid.
It is drawn in the *equirectangular* projection (longitude, latitude as plane coordinates) or
the *orthographic* projection (the sphere seen from infinitely far away above the point
``(lat0, lon0)``), computed here directly: a pixel ``(x, y)`` of the unit disk is the point
``p = x e + y n + sqrt(1 - x² - y²) c`` with ``c`` the unit vector towards the viewer and
``e``, ``n`` the local east and north vectors at the view centre; the field is bilinearly
interpolated at ``p``'s colatitude and longitude (periodic in longitude).

Sources
-------
Functions that draw runs accept a :class:`lieflow.Solution`, the ``Trajectory`` of a
``lieflow run`` HDF5 file (``lieflow.io.read_trajectory``), or plain arrays: anything with
attributes ``t`` and ``W`` (saved times and states) and, for the drift figure,
``energy_error``, ``casimir_drift`` and either ``step_times`` or ``h``.

matplotlib (``pip install "lieflow-zeitlin[plot]"``) is imported inside the functions and
only its object-oriented API is used with the Agg canvas: no pyplot, no global state.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow

from .quantization import SphereGrid, matrix_to_grid

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

Array = NDArray[Any]
Projection = Literal["equirectangular", "orthographic"]

__all__ = [
    "drift_figure",
    "orthographic_image",
    "plot_grid",
    "plot_run",
    "plot_vorticity",
    "save_figures",
    "save_vorticity_png",
    "snapshots_figure",
    "vorticity_on_grid",
]

#: Values below this (exact zeros: conservation to roundoff) are drawn at it on log axes.
FLOOR = 1e-17
_CMAP = "RdBu_r"


def _figure(width: float, height: float) -> Figure:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise lieflow.InputError(
            'plotting needs matplotlib: pip install "lieflow-zeitlin[plot]"'
        ) from exc
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path | str, dpi: int) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=dpi)
    return p


def plot_grid(N: int, resolution: int | None = None) -> SphereGrid:
    """The equiangular plotting grid for matrices of size ``N``: ``n_lat = resolution``
    (default ``clip(2N, 90, 512)``), ``n_lon = 2 n_lat``."""
    nlat = int(resolution) if resolution is not None else int(np.clip(2 * N, 90, 512))
    return SphereGrid(nlat, 2 * nlat, "equiangular")


def vorticity_on_grid(W: ArrayLike, resolution: int | None = None) -> tuple[SphereGrid, Array]:
    """The vorticity field ``Q^{-1}(W)`` of ``W`` (``(..., N, N)``) on :func:`plot_grid`."""
    W = np.asarray(W)
    grid = plot_grid(W.shape[-1], resolution)
    return grid, matrix_to_grid(W, grid)


def _field(
    data: ArrayLike | tuple[SphereGrid, ArrayLike], resolution: int | None
) -> tuple[SphereGrid, Array]:  # a matrix or (grid, field)
    if isinstance(data, tuple) and len(data) == 2 and isinstance(data[0], SphereGrid):
        grid, f = data
        return grid, np.asarray(f)
    return vorticity_on_grid(np.asarray(data), resolution)


def orthographic_image(
    grid: SphereGrid,
    field: ArrayLike,
    center: tuple[float, float] = (30.0, 0.0),
    pixels: int = 400,
) -> np.ma.MaskedArray:
    """The field seen in orthographic projection, a ``pixels × pixels`` masked image.

    Row 0 is the top (``y = 1``); pixels outside the unit disk are masked. ``center`` is the
    view centre ``(latitude, longitude)`` in degrees. ``grid`` must be equiangular (uniform
    in colatitude): the interpolation is bilinear on grid indices.
    """
    if grid.kind != "equiangular":
        raise lieflow.InputError("orthographic_image needs an equiangular grid")
    f = np.asarray(field, dtype=float)
    lat0, lon0 = np.radians(center[0]), np.radians(center[1])
    c = np.array([np.cos(lat0) * np.cos(lon0), np.cos(lat0) * np.sin(lon0), np.sin(lat0)])
    east = np.array([-np.sin(lon0), np.cos(lon0), 0.0])
    north = np.cross(c, east)
    s = np.linspace(-1, 1, pixels)
    x, y = np.meshgrid(s, s[::-1])
    r2 = x * x + y * y
    inside = r2 <= 1.0
    z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    p = x[..., None] * east + y[..., None] * north + z[..., None] * c
    theta = np.arccos(np.clip(p[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(p[..., 1], p[..., 0]), 2 * np.pi)
    # fractional grid indices: theta_j = (j + 1/2) pi / nlat, phi_k = 2 pi k / nlon
    tj = np.clip(theta * grid.nlat / np.pi - 0.5, 0.0, grid.nlat - 1.0)
    pk = phi * grid.nlon / (2 * np.pi)
    j0 = np.minimum(np.floor(tj).astype(int), grid.nlat - 2 if grid.nlat > 1 else 0)
    k0 = np.floor(pk).astype(int) % grid.nlon
    a = tj - j0
    b = pk - np.floor(pk)
    j1 = np.minimum(j0 + 1, grid.nlat - 1)
    k1 = (k0 + 1) % grid.nlon
    top = (1 - b) * f[j0, k0] + b * f[j0, k1]
    bottom = (1 - b) * f[j1, k0] + b * f[j1, k1]
    img = (1 - a) * top + a * bottom
    return np.ma.masked_array(img, mask=~inside)


def plot_vorticity(
    ax: Axes,
    data: ArrayLike | tuple[SphereGrid, ArrayLike],
    *,
    projection: Projection = "orthographic",
    center: tuple[float, float] = (30.0, 0.0),
    vmax: float | None = None,
    resolution: int | None = None,
    cmap: str = _CMAP,
    graticule: bool = True,
) -> Any:
    """Draw a vorticity field on ``ax``; returns the image (for a colorbar).

    Parameters
    ----------
    ax : matplotlib Axes
    data : matrix ``(N, N)`` or ``(grid, field)``
        A vorticity matrix (converted with :func:`vorticity_on_grid`) or a field on an
        equiangular :class:`SphereGrid`.
    projection : {"orthographic", "equirectangular"}
    center : (lat, lon) in degrees
        View centre of the orthographic projection.
    vmax : float, optional
        Colour limits ``±vmax`` (default ``max |ω|``).
    """
    grid, f = _field(data, resolution)
    limit = float(np.max(np.abs(f))) if vmax is None else float(vmax)
    limit = limit if limit > 0 else 1.0
    if projection == "equirectangular":
        shift = grid.nlon // 2  # longitudes [-180, 180) left to right
        img = ax.imshow(
            np.roll(f, shift, axis=-1),
            extent=(-180.0, 180.0, -90.0, 90.0),
            origin="upper",
            cmap=cmap,
            vmin=-limit,
            vmax=limit,
            interpolation="bilinear",
        )
        ax.set_xticks(np.arange(-180, 181, 60))
        ax.set_yticks(np.arange(-90, 91, 30))
        ax.set_xlabel("longitude (°)")
        ax.set_ylabel("latitude (°)")
        if graticule:
            ax.grid(True, color="k", alpha=0.15, linewidth=0.5)
        return img
    if projection != "orthographic":
        raise lieflow.InputError(
            f"projection must be 'orthographic' or 'equirectangular', got {projection!r}"
        )
    img = ax.imshow(
        orthographic_image(grid, f, center),
        extent=(-1.0, 1.0, -1.0, 1.0),
        origin="upper",
        cmap=cmap,
        vmin=-limit,
        vmax=limit,
    )
    t = np.linspace(0, 2 * np.pi, 361)
    ax.plot(np.cos(t), np.sin(t), color="k", linewidth=0.8)
    if graticule:
        _draw_graticule(ax, center)
    ax.set_aspect("equal")
    ax.set_axis_off()
    return img


def _draw_graticule(ax: Axes, center: tuple[float, float], step: float = 30.0) -> None:
    """Meridians and parallels every ``step`` degrees on the visible hemisphere."""
    lat0, lon0 = np.radians(center[0]), np.radians(center[1])
    c = np.array([np.cos(lat0) * np.cos(lon0), np.cos(lat0) * np.sin(lon0), np.sin(lat0)])
    east = np.array([-np.sin(lon0), np.cos(lon0), 0.0])
    north = np.cross(c, east)
    s = np.radians(np.linspace(-180, 180, 361))
    lines = []
    for lat in np.radians(np.arange(-90 + step, 90, step)):
        lines.append((np.full_like(s, lat), s))
    for lon in np.radians(np.arange(-180, 180, step)):
        lines.append((s / 2, np.full_like(s, lon)))
    for lat, lon in lines:
        p = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)
        x, y = p @ east, p @ north
        hidden = p @ c < 0
        ax.plot(np.where(hidden, np.nan, x), np.where(hidden, np.nan, y), "k-", lw=0.3, alpha=0.35)


def save_vorticity_png(
    W: ArrayLike,
    path: Path | str,
    *,
    projection: Projection | Literal["both"] = "both",
    center: tuple[float, float] = (30.0, 0.0),
    title: str = "",
    resolution: int | None = None,
    dpi: int = 120,
) -> Path:
    """Save the vorticity of one matrix ``W`` as a PNG (one or both projections)."""
    grid, f = vorticity_on_grid(W, resolution)
    kinds: list[Projection] = (
        ["equirectangular", "orthographic"] if projection == "both" else [projection]
    )
    widths = [2.0 if k == "equirectangular" else 1.0 for k in kinds]
    fig = _figure(4.0 * sum(widths) + 1.0, 4.0)
    axes = fig.subplots(1, len(kinds), squeeze=False, width_ratios=widths)[0]
    img: Any = None
    for ax, kind in zip(axes, kinds, strict=True):
        img = plot_vorticity(ax, (grid, f), projection=kind, center=center)
    fig.colorbar(img, ax=list(axes), shrink=0.8, label="vorticity ω")
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi)


def _states(source: Any) -> tuple[Array, Array]:
    if isinstance(source, tuple):
        t, W = source
        return np.asarray(t, dtype=float), np.asarray(W)
    return np.asarray(source.t, dtype=float), np.asarray(source.W)


def _pick(n: int, count: int) -> Array:
    return np.unique(np.round(np.linspace(0, n - 1, min(count, n))).astype(int))


def snapshots_figure(
    source: Any,
    *,
    count: int = 6,
    projection: Projection = "orthographic",
    center: tuple[float, float] = (30.0, 0.0),
    resolution: int | None = None,
    title: str = "",
) -> Figure:
    """A row of vorticity snapshots, evenly spaced among the saved states, on a common
    colour scale.

    ``source`` is a :class:`lieflow.Solution`, a trajectory file's contents, or a tuple
    ``(t, W)`` of saved times ``(n,)`` and states ``(n, N, N)`` (for an ensemble, the first
    member is shown).
    """
    t, W = _states(source)
    if W.ndim > 3:
        W = W.reshape(W.shape[0], -1, *W.shape[-2:])[:, 0]
    idx = _pick(W.shape[0], count)
    grid, fields = vorticity_on_grid(W[idx], resolution)
    limit = float(np.max(np.abs(fields))) or 1.0
    per = 2.0 if projection == "equirectangular" else 1.0
    cols = len(idx)
    fig = _figure(2.6 * per * cols + 1.0, 2.9)
    axes = fig.subplots(1, cols, squeeze=False)[0]
    img: Any = None
    for ax, k, f in zip(axes, idx, fields, strict=True):
        img = plot_vorticity(ax, (grid, f), projection=projection, center=center, vmax=limit)
        ax.set_title(f"t = {t[k]:.4g}", fontsize="medium")
    fig.colorbar(img, ax=list(axes), shrink=0.8, label="vorticity ω")
    if title:
        fig.suptitle(title)
    return fig


def _worst(values: Array, keep: int) -> Array:
    """Max over ensemble axes, keeping the first axis and the last ``keep - 1``."""
    v = np.asarray(values, dtype=float)
    axes = tuple(range(1, v.ndim - (keep - 1)))
    return np.max(v, axis=axes) if axes else v


def drift_figure(
    source: Any,
    *,
    casimir_powers: Sequence[int] = (2, 3, 4),
    title: str = "",
) -> Figure:
    """Relative energy error and Casimir drift (enstrophy ``k = 2`` first) against time, on
    log axes.

    ``source`` has ``energy_error`` (``(n_steps+1, ...)``), ``casimir_drift``
    (``(n_steps+1, ..., n_casimirs)``) and ``step_times`` or ``h`` (a :class:`lieflow.Solution`
    or a trajectory file's contents); ``casimir_powers`` labels the Casimir columns.
    """
    energy = _worst(source.energy_error, 1)
    drift = _worst(source.casimir_drift, 2)
    times = getattr(source, "step_times", None)
    t = np.asarray(times) if times is not None else np.arange(energy.shape[0]) * float(source.h)
    fig = _figure(8.0, 6.0)
    ax_e, ax_c = fig.subplots(2, 1, sharex=True)
    ax_e.plot(t, np.maximum(energy, FLOOR), lw=1.0, color="C0")
    ax_e.set_yscale("log")
    ax_e.set_ylabel(r"$|H(W_k) - H(W_0)| / |H(W_0)|$")
    ax_e.set_title("energy")
    names = {2: "enstrophy tr((iW)²)"}
    for j in range(drift.shape[-1]):
        k = casimir_powers[j] if j < len(casimir_powers) else None
        label = names.get(k, f"tr((iW)^{k})") if k is not None else f"C{j}"
        ax_c.plot(t, np.maximum(drift[:, j], FLOOR), lw=1.0, label=label)
    ax_c.set_yscale("log")
    ax_c.set_ylabel(r"$|C_k(W_j) - C_k(W_0)| / \|W_0\|_F^k$")
    ax_c.set_xlabel("t")
    ax_c.set_title("Casimirs")
    ax_c.legend(loc="best", fontsize="small")
    for ax in (ax_e, ax_c):
        ax.grid(True, which="major", alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig


def _casimir_powers(source: Any) -> tuple[int, ...]:
    """The ``k`` of the Casimir columns: a trajectory file's ``casimir_powers`` attribute, a
    solution's system, else the default ``(2, 3, 4)``."""
    meta = getattr(source, "meta", None)
    if meta is not None and "casimir_powers" in meta:
        return tuple(int(k) for k in np.atleast_1d(meta["casimir_powers"]))
    system = getattr(source, "system", None)
    if system is not None and hasattr(system, "casimir_powers"):
        return tuple(int(k) for k in system.casimir_powers)
    return (2, 3, 4)


def save_figures(
    source: Any,
    out_dir: Path | str,
    *,
    prefix: str = "euler_zeitlin",
    count: int = 6,
    center: tuple[float, float] = (30.0, 0.0),
    resolution: int | None = None,
    dpi: int = 120,
) -> list[Path]:
    """Write the standard figures of a run and return their paths.

    ``<prefix>_vorticity.png`` (snapshots, orthographic), ``<prefix>_vorticity_map.png``
    (snapshots, equirectangular), ``<prefix>_vorticity_final.png`` (last state, both
    projections) and, if ``source`` carries diagnostics, ``<prefix>_drift.png`` (energy and
    Casimir drift, enstrophy first). ``source`` is a :class:`lieflow.Solution`, the
    ``Trajectory`` of a ``lieflow run`` file (``lieflow.io.read_trajectory(path)``) or a
    tuple ``(t, W)``.
    """
    out = Path(out_dir)
    t, W = _states(source)
    written = [
        _save(
            snapshots_figure((t, W), count=count, center=center, resolution=resolution),
            out / f"{prefix}_vorticity.png",
            dpi,
        ),
        _save(
            snapshots_figure(
                (t, W), count=min(count, 4), projection="equirectangular", resolution=resolution
            ),
            out / f"{prefix}_vorticity_map.png",
            dpi,
        ),
    ]
    last = W[-1].reshape(-1, *W.shape[-2:])[0]
    written.append(
        save_vorticity_png(
            last,
            out / f"{prefix}_vorticity_final.png",
            center=center,
            title=f"t = {t[-1]:.4g}",
            resolution=resolution,
            dpi=dpi,
        )
    )
    if getattr(source, "energy_error", None) is not None:
        figure = drift_figure(source, casimir_powers=_casimir_powers(source))
        written.append(_save(figure, out / f"{prefix}_drift.png", dpi))
    return written


def plot_run(trajectory: Any, out_dir: Path, stem: str) -> list[Path]:
    """The ``lieflow plot`` figures of an ``euler_zeitlin`` trajectory file.

    Registered with ``registry.add_plotter`` (:mod:`lieflow_zeitlin.plugin`): ``lieflow plot
    run.h5`` writes, after lieflow's generic figures, the four PNGs of :func:`save_figures`
    named ``<stem>_vorticity.png``, ``<stem>_vorticity_map.png``,
    ``<stem>_vorticity_final.png`` and ``<stem>_drift.png``.
    """
    return save_figures(_relative(trajectory), out_dir, prefix=stem)


class _RelativeView:
    """``trajectory`` with ``W`` replaced by the relative vorticity ``Q(Δψ)``."""

    def __init__(self, trajectory: Any, W: Array) -> None:
        self._trajectory = trajectory
        self.W = W

    def __getattr__(self, name: str) -> Any:
        return getattr(self._trajectory, name)


def _relative(trajectory: Any) -> Any:
    """For a run on a rotating sphere or of the QG model (system parameters ``rotation`` or
    ``lamb`` in the file's configuration identity), a view whose states are the relative
    vorticity (:meth:`~lieflow_zeitlin.EulerZeitlin.relative`), which is what the figures
    show; otherwise the trajectory itself."""
    import json

    from .system import EulerZeitlin

    try:
        params = dict(json.loads(str(trajectory.meta["identity"]))["system"]["params"])
    except (AttributeError, KeyError, TypeError, ValueError):
        return trajectory
    if not (params.get("rotation") or params.get("lamb")):
        return trajectory
    W = np.asarray(trajectory.W)
    system = EulerZeitlin(
        W.shape[-1], rotation=params.get("rotation", 0.0), lamb=params.get("lamb", 0.0)
    )
    return _RelativeView(trajectory, system.relative(W))
