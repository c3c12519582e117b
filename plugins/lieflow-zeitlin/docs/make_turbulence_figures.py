"""Figures of the docs page ``docs/turbulence.md`` (run from the repository root).

    python plugins/lieflow-zeitlin/docs/make_turbulence_figures.py   # -> docs/img/turbulence_*

Runs ``plugins/lieflow-zeitlin/examples/turbulence_n24.toml`` (the run of the page) in a
temporary directory, then ``lieflow plot`` with a GIF movie, and copies
``turbulence_spectra.png``, ``turbulence_statistics.png``, ``turbulence_distribution.png``
and the movie's last frame (:func:`lieflow_zeitlin.movie.save_still`) as
``turbulence_movie_still.png`` into ``docs/img``. Needs
matplotlib; about 20 s on one core.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from lieflow_zeitlin.movie import save_still
from PIL import Image

from lieflow.app.cli import main
from lieflow.app.io import read_trajectory

ROOT = Path(__file__).resolve().parents[3]
EXAMPLE = ROOT / "plugins" / "lieflow-zeitlin" / "examples" / "turbulence_n24.toml"
OUT = ROOT / "docs" / "img"


def make() -> list[Path]:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        shutil.copy(EXAMPLE, d / EXAMPLE.name)
        assert main(["run", str(d / EXAMPLE.name), "--no-progress"]) == 0
        run = d / "turbulence_n24.h5"
        movie = d / "movie.gif"
        assert main(["plot", str(run), "--out", str(d / "png"), "--movie", str(movie)]) == 0
        written = []
        for name in ("spectra", "statistics", "distribution"):
            target = OUT / f"turbulence_{name}.png"
            shutil.copy(d / "png" / f"turbulence_n24_{name}.png", target)
            written.append(target)
        with Image.open(movie) as im:
            assert im.n_frames == len(read_trajectory(run).step)
        written.append(save_still(read_trajectory(run), OUT / "turbulence_movie_still.png"))
        return written


if __name__ == "__main__":
    for path in make():
        print(path)
