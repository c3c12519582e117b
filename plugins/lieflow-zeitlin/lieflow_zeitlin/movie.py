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

__all__ = ["ffmpeg_path", "save_movie", "save_still"]


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


def _vorticity_states(source: Any) -> tuple[Any, Any]:
    """``(t, W)`` of an Euler–Zeitlin run (relative vorticity on a rotating sphere and for
    the QG model).

    Raises
    ------
    lieflow.InputError
        If ``source`` is a run of another system (its ``system``, or the system named in a
        trajectory file's configuration identity), or its states are not a stack of
        matrices in su(N): the movie would draw them as vorticity, silently.
    """
    import json

    from .system import EulerZeitlin

    if isinstance(source, tuple):
        if len(source) != 2:
            raise lieflow.InputError(
                f"a movie's source is a trajectory, a solution or (t, W); got a tuple of "
                f"{len(source)}"
            )
        t, W = np.asarray(source[0]), np.asarray(source[1])
    else:
        system = getattr(source, "system", None)  # a Solution's
        if system is not None:
            name = "euler_zeitlin" if isinstance(system, EulerZeitlin) else str(system)
        else:  # a trajectory file's configuration identity
            try:
                name = json.loads(str(source.meta["identity"]))["system"]["name"]
            except (AttributeError, KeyError, TypeError, ValueError):
                name = "euler_zeitlin"  # no record: the states are checked below
        if name != "euler_zeitlin":
            raise lieflow.InputError(
                f"a movie draws the vorticity of an euler_zeitlin run, but this is a run of "
                f"{name}; plot it with lieflow.app.plotting (lieflow plot FILE)"
            )
        src = _relative(source)
        t, W = np.asarray(src.t), np.asarray(src.W)
    if t.ndim != 1 or W.ndim < 3 or W.shape[-1] != W.shape[-2] or len(t) != W.shape[0]:
        raise lieflow.InputError(
            f"a movie needs states of shape (steps, ..., N, N) with one time each, got "
            f"times of shape {t.shape} and states of shape {W.shape}"
        )
    algebra = lieflow.SU(W.shape[-1])
    for j in range(W.shape[0]):  # frame by frame: the memory of one frame
        algebra.validate(W[j], name=f"the movie's state {j}")
    return t, W


class _Frames:
    """The movie's figure (orthographic and equirectangular panels, one colour scale) and
    a way to draw saved state ``j`` into it."""

    def __init__(self, source: Any, resolution: int | None, center: tuple[float, float]) -> None:
        t, W = _vorticity_states(source)
        self.t = t
        self.W = W.reshape(W.shape[0], -1, *W.shape[-2:])[:, 0]  # first member of an ensemble
        self.grid = grid = plot_grid(self.W.shape[-1], resolution)
        self.center = center
        sample = _pick(len(t), 5)
        vmax = max(float(np.abs(matrix_to_grid(self.W[j], grid)).max()) for j in sample)
        vmax = vmax if vmax > 0 else 1.0
        self.fig = fig = _figure(11.0, 4.2)
        ax0, ax1 = fig.subplots(1, 2, width_ratios=[1.0, 2.0])
        f0 = np.zeros((grid.nlat, grid.nlon))
        kw: dict[str, Any] = {"cmap": "RdBu_r", "vmin": -vmax, "vmax": vmax, "origin": "upper"}
        self.ortho = ax0.imshow(orthographic_image(grid, f0, center), extent=(-1, 1, -1, 1), **kw)
        circle = np.linspace(0, 2 * np.pi, 361)
        ax0.plot(np.cos(circle), np.sin(circle), "k-", lw=0.8)
        _draw_graticule(ax0, center)
        ax0.set_aspect("equal")
        ax0.set_axis_off()
        self.shift = grid.nlon // 2
        self.equi = ax1.imshow(f0, extent=(-180, 180, -90, 90), interpolation="bilinear", **kw)
        ax1.set_xticks(np.arange(-180, 181, 60))
        ax1.set_yticks(np.arange(-90, 91, 30))
        ax1.set_xlabel("longitude (°)")
        ax1.set_ylabel("latitude (°)")
        fig.colorbar(self.equi, ax=[ax0, ax1], shrink=0.8, label="vorticity ω")
        self.title = fig.suptitle("")

    def draw(self, j: int) -> None:
        f = matrix_to_grid(self.W[j], self.grid)
        self.ortho.set_data(orthographic_image(self.grid, f, self.center))
        self.equi.set_data(np.roll(f, self.shift, axis=-1))
        self.title.set_text(f"t = {float(self.t[j]):.4g}")


def save_still(
    source: Any,
    path: Path | str,
    index: int = -1,
    *,
    resolution: int | None = None,
    center: tuple[float, float] = (30.0, 0.0),
    dpi: int = 100,
) -> Path:
    """Frame ``index`` of the movie of :func:`save_movie` (same layout and colour scale) as
    a PNG."""
    frames = _Frames(source, resolution, center)
    frames.draw(int(np.arange(len(frames.t))[index]))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames.fig.savefig(out, dpi=dpi)
    return out


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
    writer, out = _writer(Path(path), fps)
    frames = _Frames(source, resolution, center)
    chosen = np.arange(len(frames.t)) if max_frames is None else _pick(len(frames.t), max_frames)
    out.parent.mkdir(parents=True, exist_ok=True)
    with writer.saving(frames.fig, str(out), dpi):
        for done, j in enumerate(chosen, start=1):
            frames.draw(int(j))
            writer.grab_frame()
            if progress is not None:
                progress(done, len(chosen))
    return out
