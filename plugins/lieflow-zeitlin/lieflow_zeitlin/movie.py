"""Movies of the vorticity on the sphere: one frame per saved state, orthographic and
equirectangular side by side.

``lieflow plot run.h5 --movie out.mp4`` (or ``out.gif``) calls :func:`save_movie` through the
``movie`` attribute of the plugin's plotter. An ``.mp4`` is encoded by ffmpeg: the binary of
``imageio-ffmpeg`` (``pip install "lieflow-zeitlin[movie]"``) or one on ``PATH``; without
either, the movie is written as a GIF next to the requested name (matplotlib's
``PillowWriter``; Pillow comes with matplotlib) and a warning says so. The colour scale is
fixed over the movie (``±`` the largest ``|ω|`` of a few sampled frames) so that colours mean
the same value in every frame. Fields are computed frame by frame (memory of one frame).
"""

from __future__ import annotations

import shutil
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import lieflow

from .plotting import _draw_graticule, _figure, _pick, _relative, orthographic_image, plot_grid
from .quantization import matrix_to_grid

Progress = Callable[[int, int], None]

__all__ = ["ffmpeg_path", "save_movie"]


def ffmpeg_path() -> str | None:
    """The ffmpeg binary: imageio-ffmpeg's if installed, else one on ``PATH``, else ``None``."""
    try:
        import imageio_ffmpeg

        return str(imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError):
        return shutil.which("ffmpeg")


def _writer(path: Path, fps: int) -> tuple[Any, Path]:
    from matplotlib import animation, rcParams

    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise lieflow.InputError(f"a movie is .mp4 or .gif, got {str(path)!r}")
    if suffix == ".mp4":
        exe = ffmpeg_path()
        if exe is not None:
            rcParams["animation.ffmpeg_path"] = exe
            return animation.FFMpegWriter(fps=fps, codec="libx264", bitrate=-1,
                                          extra_args=["-pix_fmt", "yuv420p"]), path  # fmt: skip
        gif = path.with_suffix(".gif")
        warnings.warn(
            f"no ffmpeg found (pip install 'lieflow-zeitlin[movie]' installs one): writing "
            f"{str(gif)!r} instead of {str(path)!r}",
            stacklevel=3,
        )
        path = gif
    return animation.PillowWriter(fps=fps), path


def save_movie(
    source: Any,
    path: Path | str,
    *,
    fps: int = 10,
    resolution: int | None = None,
    center: tuple[float, float] = (30.0, 0.0),
    dpi: int = 100,
    max_frames: int | None = None,
    progress: Progress | None = None,
) -> Path:
    """Render the vorticity of every saved state of ``source`` as a movie.

    Parameters
    ----------
    source : Trajectory, Solution or (t, W)
        The run (relative vorticity is shown on rotating spheres and for the QG model).
    path : path
        ``*.mp4`` (ffmpeg) or ``*.gif`` (Pillow).
    fps : int
        Frames per second.
    resolution : int, optional
        Latitudes of the plotting grid (default :func:`~lieflow_zeitlin.plotting.plot_grid`).
    center : (lat, lon)
        View centre of the orthographic panel, degrees.
    max_frames : int, optional
        At most this many frames, evenly spaced over the saved states.
    progress : callable, optional
        ``progress(done, total)`` after each frame (the command line's progress bar).

    Returns
    -------
    Path
        The file written (a ``.gif`` beside ``path`` if an ``.mp4`` was asked for and no
        ffmpeg was found).
    """
    out = Path(path)
    src = _relative(source) if not isinstance(source, tuple) else None
    t, W = (np.asarray(source[0]), np.asarray(source[1])) if src is None else (
        np.asarray(src.t), np.asarray(src.W))  # fmt: skip
    W = W.reshape(W.shape[0], -1, *W.shape[-2:])[:, 0]  # first member of an ensemble
    frames = np.arange(len(t)) if max_frames is None else _pick(len(t), max_frames)
    grid = plot_grid(W.shape[-1], resolution)
    vmax = max(float(np.abs(matrix_to_grid(W[j], grid)).max()) for j in _pick(len(frames), 5))
    vmax = vmax if vmax > 0 else 1.0
    writer, out = _writer(out, fps)
    out.parent.mkdir(parents=True, exist_ok=True)

    fig = _figure(11.0, 4.2)
    ax0, ax1 = fig.subplots(1, 2, width_ratios=[1.0, 2.0])
    f0 = matrix_to_grid(W[frames[0]], grid)
    kw: dict[str, Any] = {"cmap": "RdBu_r", "vmin": -vmax, "vmax": vmax, "origin": "upper"}
    ortho = ax0.imshow(orthographic_image(grid, f0, center), extent=(-1, 1, -1, 1), **kw)
    circle = np.linspace(0, 2 * np.pi, 361)
    ax0.plot(np.cos(circle), np.sin(circle), "k-", lw=0.8)
    _draw_graticule(ax0, center)
    ax0.set_aspect("equal")
    ax0.set_axis_off()
    shift = grid.nlon // 2
    equi = ax1.imshow(np.roll(f0, shift, axis=-1), extent=(-180, 180, -90, 90),
                      interpolation="bilinear", **kw)  # fmt: skip
    ax1.set_xticks(np.arange(-180, 181, 60))
    ax1.set_yticks(np.arange(-90, 91, 30))
    ax1.set_xlabel("longitude (°)")
    ax1.set_ylabel("latitude (°)")
    fig.colorbar(equi, ax=[ax0, ax1], shrink=0.8, label="vorticity ω")
    title = fig.suptitle("")
    with writer.saving(fig, str(out), dpi):
        for done, j in enumerate(frames, start=1):
            f = matrix_to_grid(W[j], grid)
            ortho.set_data(orthographic_image(grid, f, center))
            equi.set_data(np.roll(f, shift, axis=-1))
            title.set_text(f"t = {float(t[j]):.4g}")
            writer.grab_frame()
            if progress is not None:
                progress(done, len(frames))
    return out
