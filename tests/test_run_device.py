"""``[run] device``: ``lieflow run`` (and sweeps, through the same run) on another array
library's device — here ``array_api_strict`` on the CPU, the device code path CI can run.

Expected values come from the NumPy engine on the host, run from the same configuration."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import rigid_body_config

import lieflow as lf
from lieflow import backends
from lieflow.app import io
from lieflow.app.cli import main

xps = pytest.importorskip("array_api_strict")


def _config(tmp_path: Path, name: str, scheme: str = "gauss2", **run: str) -> Path:
    path = tmp_path / f"{name}.toml"
    text = rigid_body_config(
        scheme=scheme, rtol=1e-14, h=0.1, steps=40, save_every=5, checkpoint="saves", **run
    )
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2"])
def test_a_run_on_a_device_library_matches_the_host(tmp_path: Path, scheme: str) -> None:
    host = _config(tmp_path, "host", scheme, engine="numpy")
    device = _config(tmp_path, "device", scheme, device="array_api_strict")
    assert main(["run", str(host), "--no-progress", "--out", str(tmp_path / "host.h5")]) == 0
    assert main(["run", str(device), "--no-progress", "--out", str(tmp_path / "dev.h5")]) == 0
    ref, got = io.read_trajectory(tmp_path / "host.h5"), io.read_trajectory(tmp_path / "dev.h5")
    assert isinstance(got.W, np.ndarray) and got.W.shape == ref.W.shape == (9, 3, 3)
    np.testing.assert_array_equal(got.iterations, ref.iterations)
    assert np.max(np.abs(got.W - ref.W)) <= 1e-14 * np.max(np.abs(ref.W))
    assert float(np.max(np.abs(got.casimir_drift))) <= 1e-14


def test_resume_on_a_device_continues_from_the_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Interrupted at step 23 on the device, resumed there: the warm start read from the
    file is placed on the device too (the resumed steps take the host's iterations)."""
    host = _config(tmp_path, "host", engine="numpy")
    device = _config(tmp_path, "device", device="array_api_strict")
    assert main(["run", str(host), "--no-progress", "--out", str(tmp_path / "host.h5")]) == 0
    from lieflow import runs

    placed: list[Any] = []
    real_place, real_advance = runs.from_host, lf.stepping.advance

    def counting(a: Any, like: Any, dtype: Any = None) -> Any:
        placed.append(a)
        return real_place(a, like, dtype)

    def interrupted(*args: Any, **kwargs: Any) -> Iterator[lf.chunks.Chunk]:
        for chunk in real_advance(*args, **kwargs):
            assert not backends.is_numpy(chunk.W)  # the steps run on the device library
            yield chunk
            if chunk.stop == 23:
                raise KeyboardInterrupt

    monkeypatch.setattr(runs, "from_host", counting)
    monkeypatch.setattr(lf.stepping, "advance", interrupted)
    out = str(tmp_path / "dev.h5")
    assert main(["run", str(device), "--no-progress", "--out", out]) == 130
    assert io.read_checkpoint(tmp_path / "dev.h5").step == 23
    monkeypatch.setattr(lf.stepping, "advance", real_advance)
    before = len(placed)
    assert main(["run", str(device), "--no-progress", "--out", out, "--resume"]) == 0
    assert len(placed) > before + 1  # the state and the warm start's arrays
    ref, got = io.read_trajectory(tmp_path / "host.h5"), io.read_trajectory(tmp_path / "dev.h5")
    np.testing.assert_array_equal(got.iterations, ref.iterations)
    assert np.max(np.abs(got.W - ref.W)) <= 1e-14 * np.max(np.abs(ref.W))
    assert got.meta["resumes"] == 1


@pytest.mark.parametrize(
    ("run", "expected"),
    [
        ({"device": "gpu"}, "unknown device 'gpu'"),
        ({"device": "cpu:1"}, "unknown device 'cpu:1'"),
        ({"device": ""}, "unknown device ''"),  # used to be taken as the CPU, silently
        ({"device": "array_api_strict", "engine": "compiled"}, "runs on the CPU only"),
    ],
)
def test_bad_devices_are_refused_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], run: dict[str, str], expected: str
) -> None:
    config = _config(tmp_path, "bad", **run)
    assert main(["run", str(config), "--no-progress", "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert expected in err and "[run]" in err
    assert not (tmp_path / "x.h5").exists()


class _TorchWithoutCuda:
    """What ``import torch`` gives on a machine without a GPU: a CPU tensor that refuses
    ``.to("cuda")`` (PyTorch's own message)."""

    class Tensor:
        def to(self, device: str) -> Any:
            raise AssertionError("Torch not compiled with CUDA enabled")

    def from_numpy(self, a: np.ndarray) -> Any:
        return self.Tensor()


@pytest.mark.parametrize("device", ["cupy", "torch:cuda:0"])
def test_a_device_that_is_not_there_writes_nothing_and_the_corrected_run_needs_no_force(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    device: str,
) -> None:
    """Issue 37 item 4: a device missing at run time (its library not installed, or no GPU
    for it) used to leave a 0-step "interrupted" file, so the rerun with ``device = "cpu"``
    was refused as "already exists" (13 of 13 cases)."""
    if device.startswith("torch"):
        monkeypatch.setitem(sys.modules, "torch", _TorchWithoutCuda())
    elif importlib.util.find_spec("cupy") is not None:  # pragma: no cover
        pytest.skip("CuPy is installed")
    out = str(tmp_path / "x.h5")
    config = _config(tmp_path, "gpu", device=device)
    assert main(["run", str(config), "--no-progress", "--out", out]) == 2
    err = capsys.readouterr().err
    assert device.split(":")[0] in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gpu.toml"]  # nothing written
    config = _config(tmp_path, "cpu", device="cpu")
    assert main(["run", str(config), "--no-progress", "--out", out]) == 0
    assert io.read_trajectory(out).status == "complete"


def test_a_device_whose_library_is_missing_says_what_to_install() -> None:
    try:
        import cupy  # noqa: F401
    except ImportError:
        with pytest.raises(lf.InputError, match="needs cupy, which is not installed"):
            backends.place(np.eye(2), "cupy")
    else:  # pragma: no cover - a machine with CuPy
        pytest.skip("CuPy is installed")
    assert backends.place(np.eye(2), "cpu") is not None
    assert backends.namespace(backends.place(np.eye(2), "array_api_strict")) is xps


def test_integrate_streams_and_resumes_a_run_on_another_array_library(tmp_path: Path) -> None:
    """``lf.integrate(out=...)`` with ``W0`` an ``array_api_strict`` array: the file is
    written from the host a chunk at a time, and a resume places the checkpoint's state and
    warm start back on the array's library (the one front door: ``lieflow.runs``)."""
    strict = pytest.importorskip("array_api_strict")
    system = lf.systems.get("generalized_rigid_body")
    W0 = system.random_state(4)
    kwargs: dict[str, Any] = dict(h=0.1, save_every=5)
    scheme = lf.schemes.get("gauss2")
    ref = lf.integrate(system, scheme, W0, steps=20, engine="numpy", **kwargs)
    lf.integrate(system, scheme, strict.asarray(W0), steps=10, out=tmp_path / "d.h5", **kwargs)
    sol = lf.integrate(system, scheme, strict.asarray(W0), steps=20, out=tmp_path / "d.h5",
                       resume=True, **kwargs)  # fmt: skip
    np.testing.assert_allclose(sol.W_final, ref.W_final, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(sol.iterations, ref.iterations)
    assert io.read_trajectory(tmp_path / "d.h5").meta["resumes"] == 1
