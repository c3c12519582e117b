"""Pictures of Euler–Zeitlin runs (issue 17.3): ``lieflow plot`` draws spectra (log–log with
``l^-3`` and ``l^-5/3`` guides), the time average, the vorticity distribution and the
statistics; ``lieflow plot FILE --movie OUT`` renders one frame per saved state (read back:
GIF frames with Pillow, MP4 frames with imageio-ffmpeg when installed) and is a clear error
for a system without a movie plotter."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

lz = pytest.importorskip("lieflow_zeitlin")
pytest.importorskip("matplotlib")
pytest.importorskip("h5py")

from lieflow_zeitlin import movie as zmovie  # noqa: E402
from lieflow_zeitlin import plotting  # noqa: E402

from lieflow import InputError  # noqa: E402
from lieflow.app import io  # noqa: E402
from lieflow.app.cli import main  # noqa: E402

CONFIG = """
[system]
name = "euler_zeitlin"
params = { N = 12, rotation = 1.0, diagnostics_every = 2 }

[initial]
random = true
seed = 3

[scheme]
name = "midpoint"

[splitting]
method = "strang"
flows = [
  { name = "zeitlin_drag", params = { mu = 0.5 } },
  { name = "zeitlin_forcing", params = { amplitude = 0.3, l1 = 3, l2 = 5, seed = 1 } },
]

[run]
h = 0.05
steps = 13
save_every = 6
output = "run.h5"
"""


@pytest.fixture(scope="module")
def run_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("zeitlin_plots")
    (d / "run.toml").write_text(CONFIG)
    assert main(["run", str(d / "run.toml"), "--no-progress"]) == 0
    return d / "run.h5"


def test_lieflow_plot_draws_spectra_distribution_and_statistics(
    run_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["plot", str(run_file), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out.split()
    for name in ("spectra", "distribution", "statistics", "vorticity", "drift"):
        p = tmp_path / f"run_{name}.png"
        assert str(p) in printed and p.read_bytes().startswith(b"\x89PNG")


def test_spectra_figure_has_the_guides_and_the_time_average(run_file: Path) -> None:
    samples = io.read_extra(run_file)
    fig = plotting.spectra_figure(samples, t_start=0.3)
    energy, enstrophy = fig.axes[:2]
    labels = [line.get_label() for line in energy.get_lines()]
    assert "l^-3" in labels and "l^-1.67" in labels and "mean over t ≥ 0.3" in labels
    assert energy.get_xscale() == energy.get_yscale() == "log"
    mean = next(line for line in energy.get_lines() if line.get_label().startswith("mean"))
    sel = samples["t"] >= 0.3
    np.testing.assert_allclose(mean.get_ydata(), samples["energy_spectrum"][sel, 1:].mean(0))
    # the -3 guide has slope -3 in log-log
    guide = next(line for line in energy.get_lines() if line.get_label() == "l^-3")
    x, y = guide.get_xdata(), guide.get_ydata()
    assert abs(np.log(y[1] / y[0]) / np.log(x[1] / x[0]) + 3) < 1e-12
    assert "l^-1" in [line.get_label() for line in enstrophy.get_lines()]


def test_movie_gif_has_one_frame_per_saved_state(
    run_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from PIL import Image

    out = tmp_path / "movie.gif"
    assert main(["plot", str(run_file), "--out", str(tmp_path), "--movie", str(out)]) == 0
    assert str(out) in capsys.readouterr().out.split()
    saved = io.read_trajectory(run_file).step
    assert list(saved) == [0, 6, 12, 13]
    with Image.open(out) as im:
        assert im.n_frames == len(saved)
        assert im.size[0] > 2 * im.size[1]  # orthographic and equirectangular side by side


def test_movie_mp4_frame_count(run_file: Path, tmp_path: Path) -> None:
    if zmovie.ffmpeg_path() is None:
        pytest.skip("no ffmpeg (pip install lieflow-zeitlin[movie])")
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    calls: list[tuple[int, int]] = []
    traj = io.read_trajectory(run_file)
    out = zmovie.save_movie(traj, tmp_path / "m.mp4", progress=lambda d, n: calls.append((d, n)))
    assert out == tmp_path / "m.mp4"
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(out))
    assert frames == len(traj.step) == 4
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]


def test_mp4_without_ffmpeg_falls_back_to_gif(
    run_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from PIL import Image

    monkeypatch.setattr(zmovie, "ffmpeg_path", lambda: None)
    traj = io.read_trajectory(run_file)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = zmovie.save_movie(traj, tmp_path / "m.mp4", max_frames=3)
    assert out == tmp_path / "m.gif" and any("no ffmpeg" in str(w.message) for w in caught)
    with Image.open(out) as im:
        assert im.n_frames == 3


def test_movie_refuses_other_suffixes_and_systems(
    run_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(InputError, match=r"\.mp4 or \.gif"):
        zmovie.save_movie(io.read_trajectory(run_file), tmp_path / "m.avi")
    cfg = tmp_path / "rb.toml"
    cfg.write_text(
        '[system]\nname = "rigid_body"\n[initial]\nrandom = true\nseed = 0\n'
        '[scheme]\nname = "midpoint"\n[run]\nh = 0.1\nsteps = 2\noutput = "rb.h5"\n'
    )
    assert main(["run", str(cfg), "--no-progress"]) == 0
    capsys.readouterr()
    code = main(["plot", str(tmp_path / "rb.h5"), "--movie", str(tmp_path / "rb.gif")])
    err = capsys.readouterr().err
    assert code == 2 and "no plugin draws movies of 'rigid_body' runs" in err
    assert not (tmp_path / "rb.gif").exists()
    # from Python (issue 29.4: drawn as vorticity before): the file, a solution, the states
    rigid = io.read_trajectory(tmp_path / "rb.h5")
    with pytest.raises(InputError, match="a run of rigid_body"):
        zmovie.save_movie(rigid, tmp_path / "rb.gif")
    import lieflow as lf

    body = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
    sol = lf.integrate(body, lf.schemes.get("midpoint"), body.random_state(0), 0.1, steps=2)
    with pytest.raises(InputError, match="a run of RigidBody"):
        zmovie.save_still(sol, tmp_path / "rb.png")
    with pytest.raises(InputError, match="not in su"):
        zmovie.save_movie((rigid.t, np.ones((3, 4, 4))), tmp_path / "ones.gif")
    assert not any(tmp_path.glob("rb.*g")) and not (tmp_path / "ones.gif").exists()


def test_run_samples_of_a_file_without_extra_diagnostics(tmp_path: Path) -> None:
    """Files without ``/diagnostics/extra`` (older files, ``diagnostics_every = 0``): the
    samples are the diagnostics of the saved states."""
    (tmp_path / "run.toml").write_text(
        CONFIG.replace("diagnostics_every = 2", "diagnostics_every = 0")
    )
    assert main(["run", str(tmp_path / "run.toml"), "--no-progress"]) == 0
    traj = io.read_trajectory(tmp_path / "run.h5")
    samples = plotting.run_samples(traj)
    assert list(samples["step"]) == [0, 6, 12, 13]
    system = lz.EulerZeitlin(12, rotation=1.0)
    np.testing.assert_allclose(
        samples["enstrophy"][-1], lz.diagnostics.snapshot(system, traj.W[-1])["enstrophy"]
    )


def test_a_run_sampled_without_levels_plots_the_levels_of_its_saved_states(
    tmp_path: Path,
) -> None:
    """``diagnostics_levels = false``: the samples hold the spectra only; the plots take the
    levels (and Casimirs) of the saved states, at their own times."""
    (tmp_path / "run.toml").write_text(
        CONFIG.replace("diagnostics_every = 2", "diagnostics_every = 2, diagnostics_levels = false")
    )
    assert main(["run", str(tmp_path / "run.toml"), "--no-progress"]) == 0
    extra = io.read_extra(tmp_path / "run.h5")
    assert sorted(extra) == ["energy", "energy_spectrum", "enstrophy", "enstrophy_spectrum",
                             "step", "t"]  # fmt: skip
    traj = io.read_trajectory(tmp_path / "run.h5")
    samples = plotting.run_samples(traj)
    assert list(samples["step"]) == list(extra["step"]) == [0, 2, 4, 6, 8, 10, 12]
    np.testing.assert_array_equal(samples["levels_t"], traj.t)
    np.testing.assert_allclose(samples["vorticity_levels"], lz.vorticity_levels(traj.W))
    assert main(["plot", str(tmp_path / "run.h5"), "--out", str(tmp_path)]) == 0
    assert (tmp_path / "run_distribution.png").stat().st_size > 1000


def test_ensemble_run_plots_ensemble_mean_spectra(tmp_path: Path) -> None:
    (tmp_path / "run.toml").write_text(
        CONFIG.replace("seed = 3", "seeds = [3, 4]").replace("steps = 13", "steps = 6")
    )
    assert main(["run", str(tmp_path / "run.toml"), "--no-progress"]) == 0
    extra = io.read_extra(tmp_path / "run.h5")
    assert extra["energy_spectrum"].shape == (4, 2, 12)
    samples = plotting.run_samples(io.read_trajectory(tmp_path / "run.h5"))
    np.testing.assert_allclose(samples["energy_spectrum"], extra["energy_spectrum"].mean(1))
    np.testing.assert_array_equal(samples["vorticity_levels"], extra["vorticity_levels"][:, 0])
    assert main(["plot", str(tmp_path / "run.h5"), "--movie", str(tmp_path / "m.gif")]) == 0
    assert (tmp_path / "run_spectra.png").exists() and (tmp_path / "m.gif").exists()


def test_movie_still_is_a_png_frame(run_file: Path, tmp_path: Path) -> None:
    from matplotlib.image import imread

    out = zmovie.save_still(io.read_trajectory(run_file), tmp_path / "still.png", index=1)
    image = imread(out)
    assert image.ndim == 3 and image.shape[1] > 2 * image.shape[0]
