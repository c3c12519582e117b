"""Reading quflow's HDF5 simulation files (issue 17.4): a small file in quflow's layout
(``mat``, ``time``, ``step``, the attribute ``N``, pickled attributes beside them) built
with h5py is read back exactly, never unpickling; quflow's time is fluid time (an exact
Rossby–Haurwitz wave saved at quflow times is continued by ``lieflow run`` from the imported
last state and lands on the exact solution)."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest

lz = pytest.importorskip("lieflow_zeitlin")
h5py = pytest.importorskip("h5py")

from lieflow_zeitlin import quflow  # noqa: E402

import lieflow as lf  # noqa: E402
from lieflow.app import io  # noqa: E402
from lieflow.app.cli import main  # noqa: E402


class _Tripwire:
    """Unpickling this touches a marker file: the reader must never do it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[()]]:
        return (self.marker.touch, ())


def write_quflow(
    path: Path,
    W: np.ndarray,
    times: np.ndarray,
    steps: np.ndarray,
    marker: Path,
    datapath: str = "/",
) -> None:
    """A file as quflow's ``QuSimulation`` writes it (quflow b42eede, simulation.py)."""
    N = W.shape[-1]
    with h5py.File(path, "w") as f:
        g = f if datapath == "/" else f.create_group(datapath)
        g.attrs["version"] = "1.0.0"
        g.attrs["created"] = "2026-11-23T12:00:00"
        g.attrs["qutypes"] = np.array([pickle.dumps(_Tripwire(marker))])
        g.attrs["loggers"] = np.array([pickle.dumps(_Tripwire(marker))])
        mat = g.create_dataset(
            "mat", data=W, maxshape=(None, *W.shape[1:]), chunks=(1, *W.shape[1:])
        )
        mat.attrs["qutype"] = "mat"
        fun = g.create_dataset("fun", data=np.zeros((len(W), 2 * N, N), np.float32))
        fun.attrs["qutype"] = "fun"
        g.create_dataset("time", data=times, maxshape=(None,))
        g.create_dataset("step", data=steps, maxshape=(None,))
        for name in ("tol_auto", "iterations", "number_of_maxit"):
            g.create_dataset(name, data=np.zeros(len(W)))
        g.attrs["N"] = N
        args = f.create_group(datapath.rstrip("/") + "/args" if datapath != "/" else "args")
        args.attrs["integrator"] = np.array([pickle.dumps(_Tripwire(marker))])
        args.attrs["stepsize"] = 0.1


def _states(N: int, n: int, seed: int = 0) -> np.ndarray:
    return np.stack([lz.random_vorticity(N, degree=4, seed=seed + k) for k in range(n)])


def test_round_trip_exact_and_nothing_unpickled(tmp_path: Path) -> None:
    N, marker = 6, tmp_path / "UNPICKLED"
    W = _states(N, 4)
    times = np.array([0.0, 0.25, 0.5, 0.75])
    steps = np.array([0, 5, 10, 15])
    write_quflow(tmp_path / "q.hdf5", W, times, steps, marker)
    run = lz.read_quflow(tmp_path / "q.hdf5")
    assert run.N == N and run.time_unit == "fluid"
    np.testing.assert_array_equal(run.W, W)
    np.testing.assert_array_equal(run.t, times)
    np.testing.assert_array_equal(run.step, steps)
    last = lz.read_quflow(tmp_path / "q.hdf5", index=-1)
    assert last.W.shape == (1, N, N) and last.t[0] == 0.75
    some = lz.read_quflow(tmp_path / "q.hdf5", index=[3, 1], time="matrix")
    np.testing.assert_array_equal(some.W, W[[3, 1]])
    np.testing.assert_allclose(some.t, times[[3, 1]] / lz.hbar(N), rtol=1e-15)
    ds = lz.quflow.quflow_dataset(tmp_path / "q.hdf5")
    assert ds["W"].dims == ("time", "row", "col") and list(ds["saved_step"]) == list(steps)
    assert not marker.exists()
    # ... while the attributes are live pickles: loading one runs code (touches the marker)
    with h5py.File(tmp_path / "q.hdf5", "r") as f:
        pickle.loads(f.attrs["qutypes"][0])  # the point of this line: it runs code
    assert marker.exists()


def test_datapath_group_and_errors(tmp_path: Path) -> None:
    N, marker = 4, tmp_path / "UNPICKLED"
    W = _states(N, 2)
    write_quflow(tmp_path / "g.h5", W, np.array([0.0, 1.0]), np.array([0, 1]), marker, "/sim/")
    np.testing.assert_array_equal(lz.read_quflow(tmp_path / "g.h5", datapath="/sim/").W, W)
    with pytest.raises(lf.InputError, match="no dataset 'mat'"):
        lz.read_quflow(tmp_path / "g.h5")
    (tmp_path / "x.h5").write_bytes(b"not hdf5")
    with pytest.raises(lf.InputError, match="not HDF5"):
        lz.read_quflow(tmp_path / "x.h5")
    with pytest.raises(lf.InputError, match="no such file"):
        lz.read_quflow(tmp_path / "missing.h5")
    with h5py.File(tmp_path / "n.h5", "w") as f:
        f.create_dataset("mat", data=W)
        f.create_dataset("time", data=[0.0, 1.0])
        f.create_dataset("step", data=[0, 1])
        f.attrs["N"] = N + 1
    with pytest.raises(lf.InputError, match="expected"):
        lz.read_quflow(tmp_path / "n.h5")
    assert not marker.exists()


def _rh_matrix(N: int, l: int, t: float, a: float = 1.0, eps: float = 0.2) -> np.ndarray:
    """``Q(ζ(t))`` of the Rossby–Haurwitz wave ``a cos θ + ε sin^l θ cos l(φ - c t)`` (exact
    for Euler and for Zeitlin's model, docs page "Euler–Zeitlin")."""
    c = 0.5 * a * (1 - 2 / (l * (l + 1)))
    coeffs = np.zeros(N * N, complex)
    coeffs[lz.lm_index(1, 0)] = a * math.sqrt(4 * math.pi / 3)
    # sin^l θ e^{ilφ} = (-1)^l sqrt(4π (2l+1)!) / (2^l l!) Y_ll
    k = (-1) ** l * math.sqrt(4 * math.pi * math.factorial(2 * l + 1)) / (2**l * math.factorial(l))
    shift = np.exp(-1j * l * c * t)
    coeffs[lz.lm_index(l, l)] = 0.5 * eps * k * shift
    coeffs[lz.lm_index(l, -l)] = (-1) ** l * np.conj(coeffs[lz.lm_index(l, l)])
    return lz.sh_to_matrix(coeffs)


def test_a_quflow_run_continues_in_lieflow_on_the_exact_solution(tmp_path: Path) -> None:
    N, l = 10, 3
    times = np.array([0.0, 0.5, 1.0])  # quflow's time
    W = np.stack([_rh_matrix(N, l, t) for t in times])
    write_quflow(tmp_path / "rh.hdf5", W, times, np.array([0, 10, 20]), tmp_path / "UNPICKLED")
    assert quflow.main([str(tmp_path / "rh.hdf5"), "--out", str(tmp_path / "W0.npy")]) == 0
    t0 = lz.read_quflow(tmp_path / "rh.hdf5", index=-1).t[0]
    assert t0 == 1.0
    (tmp_path / "run.toml").write_text(
        '[system]\nname = "euler_zeitlin"\nparams = { N = 10 }\n'
        '[initial]\nfile = "W0.npy"\n[scheme]\nname = "gauss2"\n'
        '[solver]\nname = "fixed_point"\nparams = { rtol = 1e-14 }\n'
        '[run]\nh = 0.05\nsteps = 20\nsave_every = 20\noutput = "run.h5"\n'
    )
    assert main(["run", str(tmp_path / "run.toml"), "--no-progress"]) == 0
    traj = io.read_trajectory(tmp_path / "run.h5")
    exact = _rh_matrix(N, l, t0 + traj.t[-1])  # lieflow's t counts from the quflow state
    assert np.abs(traj.W[-1] - exact).max() < 1e-6 * np.abs(exact).max()
    # with the time misread as matrix time the wave would be far off
    wrong = _rh_matrix(N, l, t0 / lz.hbar(N) + traj.t[-1])
    assert np.abs(traj.W[-1] - wrong).max() > 1e-2 * np.abs(exact).max()
    assert not (tmp_path / "UNPICKLED").exists()


def test_command_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert quflow.main([str(tmp_path / "none.h5"), "--out", str(tmp_path / "w.npy")]) == 2
    assert "no such file" in capsys.readouterr().err
