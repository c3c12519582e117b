"""Building a run from its configuration: system, scheme, solver and flows from the registry,
the validated initial condition, the checked output path (:func:`build`, :class:`BuiltRun`);
nothing is written."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, cast

import attrs
import numpy as np

from ...algebras import Array
from ...engines import Engine
from ...errors import LieflowError, PluginError, quote, shorten, with_fix, without_fix
from ...flows import Flow, Splitting
from ...plugins import Kind, Registry, default_registry
from ...runs import RunSpec
from ...schemes.base import Scheme
from ...sinks import RunInfo
from ...solvers.base import Solver
from ...systems.base import IsospectralSystem
from ._config import Component, Config, Perturbation
from ._toml import ConfigError


@attrs.frozen(eq=False)
class BuiltRun:
    """Everything a run needs, built and validated; nothing has been written yet.

    Attributes
    ----------
    config : Config
        The configuration.
    system, scheme, solver
        Built from the registry.
    W0 : ndarray
        The validated initial condition.
    output : Path
        The trajectory file (absolute).
    replace : bool
        Whether a new run may replace an existing ``output`` (``lieflow run --force``);
        if false, an existing file is refused, even one created after the check.
    flows : tuple of Flow
        The ``[splitting]`` flows (empty without one).
    """

    config: Config
    system: IsospectralSystem
    scheme: Scheme
    solver: Solver
    W0: Array = attrs.field(repr=False)
    output: Path
    replace: bool = True
    flows: tuple[Flow, ...] = ()

    def info(self) -> RunInfo:
        """What the run's file records about it (:class:`~lieflow.sinks.RunInfo`): the
        configuration's names, identity and text, the run settings and ``W0``."""
        cfg = self.config
        return RunInfo(
            system=self.system,
            system_name=cfg.system.name,
            scheme=cfg.scheme.name,
            solver=cfg.solver.name,
            h=cfg.run.h,
            save_every=cfg.run.save_every,
            requested_steps=cfg.run.steps,
            identity=cfg.identity(),
            W0=self.W0,
            config_text=cfg.text,
            config_source=cfg.source,
        )

    def spec(self) -> RunSpec:
        """The run (:class:`lieflow.runs.RunSpec`): ``W0`` placed on ``[run] device`` (a
        device that is not there is refused here, before anything is written), the scheme's
        flow on the ``[run] engine`` chosen for it, composed with the ``[splitting]`` flows
        if there are any."""
        run = self.config.run
        info = self.info()

        def compose(inner: Flow) -> Flow:
            if self.config.splitting is None:
                return inner
            return Splitting.named(self.config.splitting.method, *self.flows, inner)

        return RunSpec.build(
            self.system, self.scheme, self.W0, run.h, steps=run.steps, solver=self.solver,
            save_every=run.save_every, engine=cast(Engine, run.engine),
            checkpoint_seconds=run.checkpoint, casimir_shift=cast(Any, run.casimir_shift),
            device=run.device, compose=compose, identity=info.identity,
            names=(info.system_name, info.scheme, info.solver),
        )  # fmt: skip

    def flow(self) -> Flow:
        """What the run advances (:meth:`spec`'s flow)."""
        return self.spec().flow


def check_output_path(path: Path, key: str, source: str = "") -> Path:
    """Check that a file can be created at ``path`` without creating anything.

    The path must not be a directory; its nearest existing ancestor must be a writable
    directory (missing directories are created when the run starts).
    """
    prefix = f"{source}: " if source else ""
    path = Path(path).expanduser().absolute()
    real = os.path.realpath(path)
    system_dirs = ("/proc", "/sys", "/dev")
    if os.name == "posix" and any(real == d or real.startswith(d + "/") for d in system_dirs):
        raise ConfigError(
            f"{prefix}{key}: {str(path)!r} is under {', '.join(system_dirs)}, which hold "
            "the system's devices and kernel interfaces, not files. To fix: choose an output "
            "path in a directory of your own.",
            key,
        )
    if path.is_dir():
        raise ConfigError(
            f"{prefix}{key}: {str(path)!r} is a directory. To fix: give a file name such as "
            f"{str(path / 'trajectory.h5')!r}.",
            key,
        )
    ancestor = path.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(
            f"{prefix}{key}: cannot create {str(path)!r}: {str(ancestor)!r} is not a writable "
            "directory. To fix: choose an output path in a directory you can write to.",
            key,
        )
    return path


def _create(
    registry: Registry,
    kind: Kind,
    comp: Component,
    source: str,
    section: str = "",
    **context: Any,
) -> Any:
    """Build ``comp`` from the registry (``context``: arguments beyond its params, e.g. a
    flow's ``system``); ``section`` names it in messages (default ``[kind]``)."""
    section = section or f"[{kind}]"
    entry_key = f"{section} name"
    try:
        entry = registry.entry(kind, comp.name)
    except LieflowError as exc:
        raise ConfigError(
            with_fix(f"{source}: {entry_key}: {exc}", "use a known name"), entry_key
        ) from None
    params_key = f"{section} params"
    try:
        return entry.create(**context, **comp.params)
    except PluginError as exc:
        raise ConfigError(f"{source}: {entry_key}: {exc}.", entry_key) from None
    except Exception as exc:
        raise ConfigError(
            f"{source}: {params_key}: {kind} {comp.name!r} rejected its parameters "
            f"{quote(dict(comp.params))}: {shorten(exc)}. To fix: correct {params_key}.",
            params_key,
        ) from None


def _initial_state(config: Config, system: IsospectralSystem) -> Array:
    init, source = config.initial, config.source
    key = f"[initial] {init.kind}"
    W: Any

    def random_state(seed: int | None, key: str = key) -> Any:
        try:
            return np.asarray(system.random_state(seed))
        except Exception as exc:
            raise ConfigError(
                f"{source}: {key}: {system.name}.random_state(seed={seed}) failed "
                f"({type(exc).__name__}: {exc}). To fix: give the initial condition as "
                "matrix or file instead, or report it to the system's author.",
                key,
            ) from None

    if init.kind == "random":
        if init.seeds is not None:  # an ensemble: one member per seed
            W = np.stack([random_state(seed) for seed in init.seeds])
        else:
            W = random_state(init.seed)
        if init.scale != 1.0:
            W = init.scale * W
    elif init.kind == "matrix":
        W = np.array(init.matrix)
        if init.imag is not None:
            W = W + 1j * np.array(init.imag)
    else:
        assert init.file is not None
        try:
            with open(init.file, "rb") as fh:
                magic = fh.read(6)
        except OSError as exc:
            raise ConfigError(
                f"{source}: {key}: cannot read {str(init.file)!r} ({exc.strerror or exc}). "
                "To fix: check the path and its permissions.",
                key,
            ) from None
        if magic != b"\x93NUMPY":
            raise ConfigError(
                f"{source}: {key}: {str(init.file)!r} exists but is not a .npy file (it does "
                "not start with numpy's .npy header; text, .npz archives and pickles are not "
                "read). To fix: save W0 with numpy.save(path, W0).",
                key,
            )
        try:
            W = np.load(init.file, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ConfigError(
                f"{source}: {key}: cannot read {str(init.file)!r} as a .npy array ({exc}). "
                "To fix: save W0 with numpy.save.",
                key,
            ) from None
    try:
        W = system.validate(W)
    except LieflowError as exc:
        fix = (
            "keep scale = 1.0 (this system accepts only states of its own size)"
            if init.kind == "random" and init.scale != 1.0
            else f"give an initial condition for {system.name} on {system.algebra}"
        )
        raise ConfigError(with_fix(f"{source}: {key}: {exc}", fix), key) from None
    return W if init.perturb is None else _perturbed(W, init.perturb, system, source, random_state)


def _perturbed(W: Array, rule: Perturbation, system: IsospectralSystem, source: str,
               random_state: Any) -> Array:  # fmt: skip
    """The ensemble ``W + size * random_state(seed + k)``, ``k < members``, validated."""
    key = "[initial] perturb"
    if W.ndim != 2:
        raise ConfigError(
            f"{source}: {key}: perturbs one initial condition, but W0 has shape {W.shape}. "
            "To fix: give a single n x n state (or drop perturb).",
            key,
        )
    members = np.stack([W + rule.size * random_state(rule.seed + k, key)
                        for k in range(rule.members)])  # fmt: skip
    try:
        return system.validate(members.astype(W.dtype, copy=False))
    except LieflowError as exc:
        raise ConfigError(
            f"{source}: {key}: a perturbed state is not a valid initial condition "
            f"({without_fix(exc)}). "
            f"To fix: {system.name} may not accept additive perturbations; make the ensemble "
            "from seeds = [...] instead, or use a smaller size.",
            key,
        ) from None


def build(
    config: Config,
    *,
    output: Path | str | None = None,
    registry: Registry | None = None,
    replace: bool = True,
) -> BuiltRun:
    """Build and validate every object of a run; write nothing.

    Parameters
    ----------
    config : Config
        A parsed configuration.
    output : path, optional
        Output file overriding ``[run] output`` (the command line's ``--out``).
    registry : Registry, optional
        Where names are looked up (default: :func:`lieflow.default_registry`).
    replace : bool
        Whether the run may replace an existing output file (:attr:`BuiltRun.replace`;
        ``lieflow run`` passes its ``--force``).

    Raises
    ------
    ConfigError
        Unknown names, rejected parameters, a wrong initial condition, an unwritable output.
    """
    reg = default_registry() if registry is None else registry
    source = config.source
    system = _create(reg, "system", config.system, source)
    scheme = _create(reg, "scheme", config.scheme, source)
    solver = _create(reg, "solver", config.solver, source)
    flows = tuple(
        _create(reg, "flow", comp, source, f"[splitting] flows[{i}]", system=system)
        for i, comp in enumerate(() if config.splitting is None else config.splitting.flows)
    )
    W0 = _initial_state(config, system)
    if output is None:
        key, out = "[run] output", check_output_path(config.run.output, "[run] output", source)
    else:
        key, out = "--out", check_output_path(Path(output), "--out")
    inputs = [("the configuration", Path(source))]
    if config.initial.file is not None:
        inputs.append(("the [initial] file", config.initial.file))
    for what, path in inputs:
        if out.exists() and path.exists() and os.path.samefile(out, path):
            raise ConfigError(
                f"{source}: {key}: {str(out)!r} is {what} of this run; writing the trajectory "
                "there would destroy it. To fix: choose another output file.",
                key,
            )
    return BuiltRun(config, system, scheme, solver, W0, out, replace, flows)
