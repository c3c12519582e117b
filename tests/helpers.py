"""Test helpers: tight solver settings, small systems added by subclassing, and the marks of
the tests that need a plugin (the core's tests run without the plugins installed)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

import lieflow as lf


def _missing(module: str) -> str:
    distribution = module.replace("_", "-")
    return f"needs the {distribution} plugin (pip install -e ./plugins/{distribution})"


def _needs(module: str) -> pytest.MarkDecorator:
    return pytest.mark.skipif(importlib.util.find_spec(module) is None, reason=_missing(module))


def import_plugin(module: str) -> ModuleType:
    """The plugin ``module`` of this repository, imported inside a test; the test is skipped,
    with the command that installs it, where it is not installed."""
    return pytest.importorskip(module, reason=_missing(module))  # type: ignore[no-any-return]


#: Marks of the tests that need a plugin of this repository (plugins/*): skipped, with the
#: command that installs it, where it is not installed.
needs_zeitlin = _needs("lieflow_zeitlin")
needs_vortices = _needs("lieflow_vortices")

#: What code or a configuration names of each plugin: its module, its registry names.
_NAMES = (
    (needs_zeitlin, ("lieflow_zeitlin", "euler_zeitlin", "zeitlin_")),
    (needs_vortices, ("lieflow_vortices", "point_vortices")),
)


def plugin_marks(text: str) -> list[pytest.MarkDecorator]:
    """The marks of the plugins that ``text`` (code, a configuration, a system name) uses:
    a parameter carrying them is skipped where one is not installed."""
    return [mark for mark, names in _NAMES if any(name in text for name in names)]


def plugin_param(*values: object, id: str | None = None) -> object:
    """``pytest.param(*values)`` marked with the plugins that its values name."""
    return pytest.param(*values, marks=plugin_marks(" ".join(map(str, values))), id=id)


def tight() -> lf.solvers.FixedPoint:
    return lf.solvers.FixedPoint(rtol=1e-15)


def rigid_body_config(
    *, scheme: str = "midpoint", seed: int = 3, rtol: float = 1e-15, **run: object
) -> str:
    """A ``lieflow run`` configuration of the so(3) rigid body, inertia (1, 2, 3), from a
    seeded random state, fixed-point iteration at ``rtol``; ``run``: the ``[run]`` table's
    keys as Python values (``h``, ``steps``, ``output``, ...)."""
    table = "\n".join(f"{key} = {json.dumps(value)}" for key, value in run.items())
    return f"""
[system]
name = "rigid_body"
params = {{ inertia = [1.0, 2.0, 3.0] }}

[initial]
random = true
seed = {seed}

[scheme]
name = "{scheme}"

[solver]
name = "fixed_point"
params = {{ rtol = {rtol!r} }}

[run]
{table}
"""


class HermitianBody(lf.IsospectralSystem):
    """A test-only system on u(n): ``B(W) = -W * C`` with ``C`` real symmetric positive.

    Added by subclassing exactly as the README shows; it exercises complex arithmetic.
    """

    linear_B = True

    def __init__(self, n: int = 4) -> None:
        self.C = 1.0 / (1.0 + np.add.outer(np.arange(n), np.arange(n)))

    @property
    def algebra(self) -> lf.LieAlgebra:
        return lf.U(self.C.shape[0])

    def B(self, W: np.ndarray) -> np.ndarray:
        return -W * self.C

    def hamiltonian(self, W: np.ndarray) -> np.ndarray:
        return 0.5 * np.sum(np.abs(W) ** 2 * self.C, axis=(-2, -1))


class TracelessHermitianBody(HermitianBody):
    """The same on su(n) (B preserves the trace-free part only approximately: project)."""

    @property
    def algebra(self) -> lf.LieAlgebra:
        return lf.SU(self.C.shape[0])

    def B(self, W: np.ndarray) -> np.ndarray:
        return self.algebra.project(-W * self.C)


def zeitlin_ensemble(members: int = 3, steps: int = 12, save_every: int = 4) -> str:
    """A small Euler–Zeitlin run configuration (N = 4, complex states) whose initial
    condition is an ensemble of ``members`` perturbations of one random state."""
    return f"""
[system]
name = "euler_zeitlin"
params = {{ N = 4 }}

[initial]
random = true
seed = 2
[initial.perturb]
members = {members}
size = 1e-3
seed = 10

[scheme]
name = "midpoint"

[run]
h = 0.01
steps = {steps}
save_every = {save_every}
engine = "numpy"
"""


def damage_last_chunk(path: Path, name: str) -> None:
    """Flip a bit in the last chunk of the dataset ``name`` of an HDF5 trajectory file: what a
    process killed while it rewrote that chunk leaves (its Fletcher-32 checksum is wrong)."""
    import h5py

    with h5py.File(path, "r") as f:
        found: list[str] = []
        f.visititems(
            lambda key, obj: (
                found.append(key)
                if isinstance(obj, h5py.Dataset) and key.split("/")[-1] == name
                else None
            )
        )
        ds = f[found[0]]
        offset = int(ds.id.get_chunk_info(ds.id.get_num_chunks() - 1).byte_offset)
    data = bytearray(path.read_bytes())
    data[offset + 3] ^= 1
    path.write_bytes(bytes(data))
