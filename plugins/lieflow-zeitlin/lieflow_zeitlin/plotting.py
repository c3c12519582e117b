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
``lieflow run`` HDF5 file (``lieflow.app.io.read_trajectory``), or plain arrays: anything with
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
    "distribution_figure",
    "drift_figure",
    "orthographic_image",
    "plot_grid",
    "plot_run",
    "plot_vorticity",
    "run_samples",
    "save_figures",
    "save_turbulence_figures",
    "save_vorticity_png",
    "snapshots_figure",
    "spectra_figure",
    "statistics_figure",
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
    ``Trajectory`` of a ``lieflow run`` file (``lieflow.app.io.read_trajectory(path)``) or a
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


def _guide(ax: Axes, l: Array, spectrum: Array, slope: float, label: str, style: str) -> None:
    """A power law ``l^slope`` through the spectrum's value at the geometric middle of the
    plotted degrees (a guide to the eye)."""
    good = (l > 0) & (spectrum > 0)
    if good.sum() < 2:
        return
    lg, sg = l[good], spectrum[good]
    j = len(lg) // 2
    x = np.array([lg[0], lg[-1]], dtype=float)
    ax.loglog(x, sg[j] * (x / lg[j]) ** slope, style, color="0.35", lw=1.0, label=label)


def spectra_figure(
    samples: dict[str, Array], *, t_start: float | None = None, curves: int = 6
) -> Figure:
    """Energy and enstrophy spectra by degree (log–log): ``curves`` samples coloured by time,
    the time average over ``t >= t_start`` (default: the second half of the samples) in
    black, and ``l^{-3}`` and ``l^{-5/3}`` guide lines (the enstrophy- and energy-cascade
    ranges of 2D turbulence; ``l^{-1}`` and ``l^{1/3}`` in the enstrophy spectrum).

    ``samples``: ``t``, ``energy_spectrum``, ``enstrophy_spectrum`` (rows per sample), as
    :func:`lieflow.app.io.read_extra` returns them.
    """
    from .diagnostics import time_mean

    t = np.asarray(samples["t"], dtype=float)
    if t_start is None:
        t_start = float(t[len(t) // 2]) if len(t) > 1 else float(t[0])
    fig = _figure(11.0, 4.4)
    axes = fig.subplots(1, 2)
    cmap = _colormap("viridis")
    for ax, key, name, slopes in (
        (axes[0], "energy_spectrum", "energy E(l)", (-3.0, -5.0 / 3.0)),
        (axes[1], "enstrophy_spectrum", "enstrophy Z(l)", (-1.0, 1.0 / 3.0)),
    ):
        S = np.asarray(samples[key], dtype=float)
        l = np.arange(S.shape[-1])
        for j in _pick(len(t), curves):
            positive = np.where(S[j, 1:] > 0, S[j, 1:], np.nan)
            ax.loglog(l[1:], positive, color=cmap(j / max(len(t) - 1, 1)), lw=0.8, alpha=0.8,
                      label=f"t = {t[j]:.3g}")  # fmt: skip
        mean = time_mean(t, S, t_start)
        ax.loglog(l[1:], np.where(mean[1:] > 0, mean[1:], np.nan), "k-", lw=2.0,
                  label=f"mean over t ≥ {t_start:.3g}")  # fmt: skip
        _guide(ax, l, mean, slopes[0], f"l^{slopes[0]:.3g}", "--")
        _guide(ax, l, mean, slopes[1], f"l^{slopes[1]:.3g}", ":")
        top = float(np.nanmax(np.where(mean > 0, mean, np.nan))) if np.any(mean > 0) else 1.0
        ax.set_ylim(top * 1e-7, top * 10)  # seven decades below the mean's peak
        ax.set_xlabel("degree l")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.2)
        ax.legend(fontsize=7, loc="best")
    return fig


def _colormap(name: str) -> Any:
    from matplotlib import colormaps

    return colormaps[name]


def distribution_figure(samples: dict[str, Array]) -> Figure:
    """The vorticity distribution: the levels (eigenvalues of ``-iW``) against the area
    fraction they stand for, and their histogram, first and last sample (at the times
    ``levels_t`` when the levels were not sampled with the rest, :func:`run_samples`)."""
    t = np.asarray(samples.get("levels_t", samples["t"]), dtype=float)
    levels = np.asarray(samples["vorticity_levels"], dtype=float)
    N = levels.shape[-1]
    fig = _figure(10.0, 4.0)
    ax0, ax1 = fig.subplots(1, 2)
    area = (np.arange(N) + 0.5) / N
    bins = np.linspace(levels.min(), levels.max(), max(10, min(60, N // 2)) + 1)
    for j, style in ((0, "C0"), (len(t) - 1, "C3")):
        ax0.plot(area, levels[j], color=style, lw=1.2, label=f"t = {t[j]:.3g}")
        ax1.hist(levels[j], bins=bins, density=True, histtype="step", color=style,
                 lw=1.2, label=f"t = {t[j]:.3g}")  # fmt: skip
    ax0.set_xlabel("area fraction (level j ↔ (j + ½)/N)")
    ax0.set_ylabel("level λ_j of -iW (≈ values of q)")
    ax1.set_xlabel("vorticity level")
    ax1.set_ylabel("density")
    for ax in (ax0, ax1):
        ax.grid(True, alpha=0.2)
        ax.legend(fontsize=8)
    return fig


def statistics_figure(samples: dict[str, Array]) -> Figure:
    """Energy and enstrophy of the relative vorticity against time, with their running
    means (the approach to a statistically steady state)."""
    from .diagnostics import running_mean

    t = np.asarray(samples["t"], dtype=float)
    fig = _figure(10.0, 3.8)
    axes = fig.subplots(1, 2)
    for ax, key in zip(axes, ("energy", "enstrophy"), strict=True):
        v = np.asarray(samples[key], dtype=float)
        ax.plot(t, v, "C0-", lw=1.0, label=key)
        ax.plot(t, running_mean(v), "k--", lw=1.2, label="running mean")
        ax.set_xlabel("t")
        ax.set_ylabel(key)
        ax.grid(True, alpha=0.2)
        ax.legend(fontsize=8)
    return fig


def run_samples(trajectory: Any) -> dict[str, Array]:
    """The diagnostics samples of a run: the file's ``/diagnostics/extra`` rows
    (:func:`lieflow.app.io.read_extra`) or, for files without them, the diagnostics of its
    saved states (:func:`lieflow_zeitlin.diagnostics.snapshot`). A run sampled without the
    levels (``diagnostics_levels = false``) gets the levels and Casimirs of its saved
    states, at their times ``levels_t``. For an ensemble run the spectra, energy and
    enstrophy are ensemble means, the levels and Casimirs the first member's."""
    from lieflow.app.io import read_extra

    from .diagnostics import snapshot

    path = getattr(trajectory, "path", None)
    out = read_extra(path) if path is not None else {}
    if not out or "vorticity_levels" not in out:
        system = _file_system(trajectory)
        W = np.asarray(trajectory.W)
        rows = [snapshot(system, w) for w in W]
        saved = {name: np.stack([r[name] for r in rows]) for name in rows[0]}
        saved["t"] = np.asarray(trajectory.t, dtype=float)
        saved["step"] = np.asarray(getattr(trajectory, "step", np.arange(len(W))))
        if out:
            saved = {
                **out,
                "vorticity_levels": saved["vorticity_levels"],
                "casimirs": saved["casimirs"],
                "levels_t": saved["t"],
            }
        out = saved
    return _ensemble_view(out)


def _ensemble_view(samples: dict[str, Array]) -> dict[str, Array]:
    """For an ensemble run (samples with a member axis after the time axis): spectra, energy
    and enstrophy averaged over the members, levels and Casimirs of the first member."""
    if np.ndim(samples["energy"]) < 2:
        return samples
    out = dict(samples)
    for name in ("energy_spectrum", "enstrophy_spectrum", "energy", "enstrophy"):
        out[name] = np.asarray(samples[name]).mean(axis=1)
    for name in ("vorticity_levels", "casimirs"):
        out[name] = np.asarray(samples[name])[:, 0]
    return out


def save_turbulence_figures(
    samples: dict[str, Array], out_dir: Path | str, prefix: str, dpi: int = 120
) -> list[Path]:
    """``<prefix>_spectra.png``, ``<prefix>_distribution.png``, ``<prefix>_statistics.png``."""
    out = Path(out_dir)
    return [
        _save(spectra_figure(samples), out / f"{prefix}_spectra.png", dpi),
        _save(distribution_figure(samples), out / f"{prefix}_distribution.png", dpi),
        _save(statistics_figure(samples), out / f"{prefix}_statistics.png", dpi),
    ]


def plot_run(trajectory: Any, out_dir: Path, stem: str) -> list[Path]:
    """The ``lieflow plot`` figures of an ``euler_zeitlin`` trajectory file.

    Registered with ``registry.add_plotter`` (:mod:`lieflow_zeitlin.plugin`): ``lieflow plot
    run.h5`` writes, after lieflow's generic figures, the four PNGs of :func:`save_figures`
    named ``<stem>_vorticity.png``, ``<stem>_vorticity_map.png``,
    ``<stem>_vorticity_final.png`` and ``<stem>_drift.png``, then the turbulence figures of
    :func:`save_turbulence_figures` (``<stem>_spectra.png``, ``<stem>_distribution.png``,
    ``<stem>_statistics.png``) from the diagnostics sampled during the run. ``lieflow plot
    run.h5 --movie out.mp4`` calls this function's ``movie`` attribute
    (:func:`lieflow_zeitlin.movie.save_movie`).
    """
    written = save_figures(_relative(trajectory), out_dir, prefix=stem)
    return written + save_turbulence_figures(run_samples(trajectory), out_dir, stem)


def _file_system(trajectory: Any) -> Any:
    """The :class:`~lieflow_zeitlin.EulerZeitlin` of a trajectory file (size, rotation and
    Lamb parameter from its configuration identity; defaults otherwise)."""
    import json

    from .system import EulerZeitlin

    N = np.asarray(trajectory.W).shape[-1]
    try:
        params = dict(json.loads(str(trajectory.meta["identity"]))["system"]["params"])
    except (AttributeError, KeyError, TypeError, ValueError):
        params = {}
    return EulerZeitlin(N, rotation=params.get("rotation", 0.0), lamb=params.get("lamb", 0.0))


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
