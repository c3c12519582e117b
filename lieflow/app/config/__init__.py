"""Run configurations for ``lieflow run``: TOML parsing, validation and building.

A configuration names a system, an initial condition, a scheme, a solver and the run
settings::

    [system]
    name = "rigid_body"
    params = { inertia = [1.0, 2.0, 3.0] }

    [initial]            # exactly one of: random = true (with seed), matrix, file
    random = true        # the system's own random_state(seed), checked by system.validate
    seed = 0
    scale = 1.0          # optional factor on it

    [scheme]
    name = "gauss3"

    [solver]             # optional; fixed_point with its defaults if left out
    name = "fixed_point"
    params = { rtol = 1e-15 }

    [splitting]          # optional: compose the scheme with other flows (plugins')
    method = "strang"    # lie, strang, triple_jump or suzuki5; the scheme is the inner flow
    flows = [{ name = "viscosity", params = { nu = 1e-4 } }]

    [run]
    h = 0.1
    steps = 2000         # or t_final = 200.0 (a whole number of steps h): exactly one
    save_every = 10      # keep every 10th state
    output = "rigid_body.h5"
    casimir_shift = "auto"  # optional: step on eta plus a Casimir (lieflow.integrate)
    checkpoint = 1.0     # optional: seconds between checkpoints (default 1), or "saves"

:func:`parse_config` turns the text into a frozen :class:`Config` (checking every key's
presence and type, refusing unknown keys), and :func:`build` turns a :class:`Config` into
the objects of a run (:class:`BuiltRun`): system, scheme and solver from the registry, the
validated initial condition and the checked output path. Every problem raises
:class:`ConfigError`, whose one-paragraph message names the key and the fix; nothing is
written to disk by either function.
"""

from __future__ import annotations

from ._build import BuiltRun, build, check_output_path
from ._config import (
    Component,
    Config,
    InitialCondition,
    Perturbation,
    RunSection,
    SplittingSection,
    identity_changes,
    load_config,
    parse_config,
)
from ._toml import ConfigError, read_toml_file

__all__ = [
    "BuiltRun",
    "Component",
    "Config",
    "ConfigError",
    "InitialCondition",
    "Perturbation",
    "RunSection",
    "SplittingSection",
    "build",
    "check_output_path",
    "identity_changes",
    "load_config",
    "parse_config",
    "read_toml_file",
]
