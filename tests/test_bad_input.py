"""Bad inputs give one clear lieflow error, never a traceback or a silent wrong result
(issue 15, items 2, 6 and 7): configurations, the command line and the Python API."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import needs_vortices

import lieflow as lf
from lieflow import tableaus
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.app.config import ConfigError, build, identity_changes, parse_config
from lieflow.errors import InputError, PluginError, TableauError

RUN = 'h = 0.1\nsteps = 30\nsave_every = 10\noutput = "traj.h5"'


def config_text(
    system: str = 'name = "rigid_body"\nparams = { inertia = [1.0, 2.0, 3.0] }',
    initial: str = "random = true\nseed = 0",
    scheme: str = 'name = "midpoint"',
    run: str = RUN,
) -> str:
    return (
        f"[system]\n{system}\n\n[initial]\n{initial}\n\n[scheme]\n{scheme}\n\n"
        f'[solver]\nname = "fixed_point"\nparams = {{ rtol = 1e-15 }}\n\n[run]\n{run}\n'
    )


def cli(tmp_path: Path, text: str, *args: str, name: str = "run.toml") -> int:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return main(["run", str(path), "--no-progress", *args])


def one_line_error(err: str) -> str:
    assert err.startswith("lieflow: error: "), err
    assert "Traceback" not in err and err.count("\n") == 1, err
    return err


# -- item 2: [initial] random = true is the system's own random_state, validated ----------


def test_random_initial_condition_is_the_systems_own(tmp_path: Path) -> None:
    """Toda used to get a non-symmetric state from gl(4) and diverge at step 11."""
    toda = 'name = "periodic_toda"\nparams = { n = 4 }'
    text = config_text(system=toda, initial="random = true\nseed = 5")
    setup = build(parse_config(text, base_dir=tmp_path))
    assert np.array_equal(setup.W0, setup.system.random_state(5))
    assert np.array_equal(setup.W0, setup.W0.T)  # on the Toda phase space


def test_random_initial_condition_scale_multiplies_the_random_state(tmp_path: Path) -> None:
    text = config_text(initial="random = true\nseed = 2\nscale = 3.0")
    setup = build(parse_config(text, base_dir=tmp_path))
    assert np.allclose(setup.W0, 3.0 * setup.system.random_state(2), rtol=0, atol=0)
    assert np.isclose(np.linalg.norm(setup.W0), 3.0)


class _PickyBody(lf.systems.RigidBody):
    """A plugin system with its own initial-condition rule."""

    def random_state(self, seed: Any = None) -> np.ndarray:
        return lf.systems.hat(np.array([0.0, 0.0, 1.0 + (seed or 0)]))


class _BrokenBody(lf.systems.RigidBody):
    """A plugin whose random_state is off the algebra (validate must catch it)."""

    def random_state(self, seed: Any = None) -> np.ndarray:
        return np.eye(3)


def _plugin_registry(**systems: Any) -> lf.Registry:
    class Plugin:
        @lf.hookimpl
        def lieflow_register(self, registry: lf.RegistryBuilder) -> None:
            for name, factory in systems.items():
                registry.add_system(name, factory, "test system")

    return lf.load_registry(autoload=False, plugins=[("test", Plugin())])


def test_a_plugins_random_state_is_used_and_validated(tmp_path: Path) -> None:
    reg = _plugin_registry(picky=_PickyBody, broken=_BrokenBody)
    text = config_text(system='name = "picky"', initial="random = true\nseed = 1")
    setup = build(parse_config(text, base_dir=tmp_path), registry=reg)
    assert np.array_equal(setup.W0, lf.systems.hat(np.array([0.0, 0.0, 2.0])))
    with pytest.raises(ConfigError, match=r"\[initial\] random.*so\(3\)"):
        build(parse_config(config_text(system='name = "broken"'), base_dir=tmp_path), registry=reg)


@needs_vortices
def test_point_vortices_random_state_from_a_config(tmp_path: Path) -> None:
    """Point vortices used to get a state from so(3)^K that validate refused."""
    text = config_text(system='name = "point_vortices"', initial="random = true\nseed = 0")
    setup = build(parse_config(text, base_dir=tmp_path))
    assert np.array_equal(setup.W0, setup.system.random_state(0))
    initial = "random = true\nseed = 0\nscale = 2.0"
    bad = config_text(system='name = "point_vortices"', initial=initial)
    with pytest.raises(ConfigError, match=r"scale = 1\.0"):
        build(parse_config(bad, base_dir=tmp_path))


# -- item 7: t_final ---------------------------------------------------------------------


def test_t_final_gives_a_whole_number_of_steps(tmp_path: Path) -> None:
    cfg = parse_config(config_text(run="h = 0.1\nt_final = 3.0\nsave_every = 10"))
    assert cfg.run.steps == 30 and cfg.run.t_final == 3.0
    assert cfg.identity() == parse_config(config_text()).identity()  # length is not identity
    assert cli(tmp_path, config_text(run='h = 0.1\nt_final = 1.0\noutput = "x.h5"')) == 0
    assert io.read_trajectory(tmp_path / "x.h5").completed_steps == 10


@pytest.mark.parametrize(
    ("run", "message"),
    [
        ('h = 0.1\nsteps = 3\nt_final = 0.3\noutput = "x.h5"', "both steps and t_final"),
        ('h = 0.1\noutput = "x.h5"', "neither steps nor t_final"),
        ('h = 0.1\nt_final = 0.35\noutput = "x.h5"', "not a whole number of steps"),
        ('h = 0.1\nt_final = 0.01\noutput = "x.h5"', "not a whole number of steps"),
        ('h = 0.1\nt_final = -1.0\noutput = "x.h5"', "positive"),
        ('h = 0.1\nt_final = "3"\noutput = "x.h5"', "expected a number"),
        ('h = 1e-300\nt_final = 1e300\noutput = "x.h5"', "too many steps"),
        ('h = 0.1\nsteps = 3\noutput = ""', "[run] output: is empty"),
    ],
)
def test_bad_t_final(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], run: str, message: str
) -> None:
    assert cli(tmp_path, config_text(run=run)) == 2
    err = one_line_error(capsys.readouterr().err)
    assert message in err and "To fix" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


def test_py_typed_is_shipped() -> None:
    assert resources.files("lieflow").joinpath("py.typed").is_file()


# -- item 6: tracebacks that became messages -----------------------------------------------


@pytest.mark.parametrize("where", ["/sys/lieflow-test.h5", "/proc/lieflow/x.h5", "/dev/x.h5"])
def test_output_under_system_directories(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    assert cli(tmp_path, config_text(), "--out", where) == 2
    assert "not files" in one_line_error(capsys.readouterr().err)


def test_plot_out_is_an_existing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(tmp_path, config_text()) == 0
    capsys.readouterr()
    (tmp_path / "file.txt").write_text("x")
    assert main(["plot", str(tmp_path / "traj.h5"), "--out", str(tmp_path / "file.txt")]) == 2
    assert "is a file, not a directory" in one_line_error(capsys.readouterr().err)
    assert (tmp_path / "file.txt").read_text() == "x"


def test_plot_out_that_cannot_be_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli(tmp_path, config_text()) == 0
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "traj.h5"), "--out", "/proc/lieflow-figures"]) == 2
    assert "cannot write the figures" in one_line_error(capsys.readouterr().err)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seed", "-1"], "seed must be a non-negative integer"),
        (["--out", "FILE"], "is a file, not a directory"),
        (["--out", "FILE/sub"], "is a file, not a directory"),
        (["--out", "/proc/lieflow-out"], "cannot write"),
    ],
)
def test_reproduce_arguments(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    (tmp_path / "FILE").write_text("keep")
    args = [str(tmp_path / a) if a.startswith("FILE") else a for a in args]
    assert main(["reproduce", "--quick", "-q", *args]) == 2
    assert message in one_line_error(capsys.readouterr().err)
    assert (tmp_path / "FILE").read_text() == "keep"


def test_block_gauss_form_is_an_input_error() -> None:
    with pytest.raises(InputError, match="form must be one of 'reduced', 'block', got 'dense'"):
        lf.schemes.BlockGauss(form="dense")  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", [-1, 1.5, "0", True])
def test_algebra_random_seed(seed: Any) -> None:
    with pytest.raises(InputError, match="seed must be None, a non-negative integer"):
        lf.algebras.SO(3).random(seed=seed)
    lf.algebras.SO(3).random(seed=np.random.default_rng(0))  # a Generator is fine


def test_a_plugin_factory_that_returns_a_non_system(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`systems.get` used to return the list; `lieflow run` died with AttributeError."""

    def factory(n: int = 3, *, size: int) -> list[int]:
        return [n, size]

    reg = _plugin_registry(listy=factory)
    with pytest.raises(PluginError, match="made a list, not a IsospectralSystem"):
        reg.create("system", "listy", size=2)
    text = config_text(system='name = "listy"\nparams = { size = 2 }')
    with pytest.raises(ConfigError, match=r"\[system\] name.*made a list"):
        build(parse_config(text, base_dir=tmp_path), registry=reg)


def test_string_step_size_from_python() -> None:
    system = lf.systems.RigidBody()
    with pytest.raises(InputError, match="step size h must be a real number"):
        lf.integrate(system, lf.schemes.get("midpoint"), system.random_state(0), "0.1", steps=2)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "make",
    [
        lambda: tableaus.ButcherTableau(A=[[0.5]], b=[1.0], order=3, name="midpoint3"),
        lambda: tableaus.composition(tableaus.triple_jump().b, 6, "triple6"),
        lambda: tableaus.composition(tableaus.yoshida6().b, 8, "yoshida8"),
        lambda: tableaus.ButcherTableau(
            A=tableaus.gauss(3).A, b=tableaus.gauss(3).b, order=7, name="gauss3_7"
        ),
    ],
)
def test_a_tableau_claiming_a_wrong_order_is_refused(make: Any) -> None:
    with pytest.raises(TableauError, match=r"claims order .* but does not have it"):
        make()


def test_the_shipped_tableaus_have_their_orders() -> None:
    for s in range(1, 6):
        assert tableaus.gauss(s).order == 2 * s
    for make in (tableaus.midpoint, tableaus.triple_jump, tableaus.suzuki5, tableaus.yoshida6):
        tab = make()  # checked tree by tree (order <= 6)
        assert not tableaus._order_defects(tab.A, tab.b, tab.order)
        assert tableaus._order_defects(tab.A, tab.b, tab.order + 1)  # and not one more
    assert tableaus.radau_iia2().order == 3


def test_an_eighth_order_composition_is_checked_tree_by_tree() -> None:
    """Yoshida's 15-stage order-8 composition (solution D, 15 digits): all 200 rooted-tree
    conditions up to order 8 hold to roundoff, and order 9 fails."""
    w = [0.102799849391985, -1.96061023297549, 1.93813913762276, -0.158240635368243]
    w += [-1.44485223686048, 0.253693336566229, 0.914844246229740]
    b = [*w[::-1], 1 - 2 * sum(w), *w]
    assert tableaus.composition(b, 8, "yoshida8").order == 8
    with pytest.raises(TableauError, match="at most 8"):
        tableaus.composition(b, 10, "yoshida8")


def test_resume_with_fewer_steps_is_refused_without_writing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It used to print "complete: 200/100 steps"."""
    assert cli(tmp_path, config_text()) == 0
    capsys.readouterr()
    before = (tmp_path / "traj.h5").read_bytes()
    fewer = config_text(run=RUN.replace("steps = 30", "steps = 20"))
    assert cli(tmp_path, fewer, "--resume") == 2
    err = one_line_error(capsys.readouterr().err)
    assert "already holds 30 steps, more than the 20 asked for" in err
    assert (tmp_path / "traj.h5").read_bytes() == before
    assert cli(tmp_path, config_text(), "--resume") == 0  # the same number: nothing to do
    assert "complete: 30/30 steps (0 new" in capsys.readouterr().out


def test_resume_with_a_changed_configuration_names_the_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli(tmp_path, config_text()) == 0
    capsys.readouterr()
    changed = config_text(scheme='name = "gauss2"', run=RUN.replace("h = 0.1", "h = 0.05"))
    assert cli(tmp_path, changed, "--resume") == 2
    err = one_line_error(capsys.readouterr().err)
    assert "changed: [run] h: 0.1 -> 0.05; [scheme] name: 'midpoint' -> 'gauss2'" in err


def test_identity_changes_of_parameters() -> None:
    a = parse_config(config_text()).identity()
    b = parse_config(
        config_text(system='name = "rigid_body"\nparams = { inertia = [1.0, 2.0, 4.0] }')
    ).identity()
    assert identity_changes(a, b) == ["[system] params.inertia: [1.0, 2.0, 3.0] -> [1.0, 2.0, 4.0]"]
    assert identity_changes(a, a) == []
    assert identity_changes("not json", a) == []


# -- the sweep: bad inputs to public functions and commands ----------------------------------


@pytest.mark.parametrize("path", [None, 3, ""])
def test_readers_refuse_non_paths(path: Any) -> None:
    for read in (io.read_trajectory, io.read_checkpoint):
        with pytest.raises(InputError, match="must be a file path"):
            read(path)


def test_config_functions_refuse_wrong_types() -> None:
    with pytest.raises(ConfigError, match="must be TOML text"):
        parse_config(b"[run]\nh = 0.1")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="must be a file path"):
        lf.app.config.load_config(None)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "make",
    [
        lambda: tableaus.ButcherTableau(A=[["a"]], b=[1.0], order=1, name="x"),
        lambda: tableaus.composition("abc", 2, "x"),  # type: ignore[arg-type]
    ],
)
def test_tableau_coefficients_must_be_numbers(make: Any) -> None:
    with pytest.raises(TableauError, match="numbers"):
        make()


def test_a_factory_value_error_becomes_an_input_error() -> None:
    with pytest.raises(InputError, match="rejected its parameters"):
        lf.systems.get("rigid_body", inertia="x")


@pytest.mark.parametrize("victim", ["config", "w0"])
def test_output_may_not_be_an_input_of_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], victim: str
) -> None:
    """`--out CONFIG --force` used to replace the configuration with the trajectory."""
    np.save(tmp_path / "w0.npy", lf.systems.RigidBody().random_state(0))
    text = config_text(initial='file = "w0.npy"')
    target = tmp_path / ("run.toml" if victim == "config" else "w0.npy")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    (tmp_path / "run.toml").write_text(text)
    before["run.toml"] = text.encode()
    assert cli(tmp_path, text, "--out", str(target), "--force") == 2
    assert "would destroy it" in one_line_error(capsys.readouterr().err)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
