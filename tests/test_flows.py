"""Flows, splittings and the one stepping loop (issue 12).

Expected values come from outside lieflow: the exact solution of a linear drag, and an
independent high-order integrator (scipy's DOP853 at rtol 1e-13) of the combined ODE
``dW/dt = [B(W), W] - mu W``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import attrs
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import lieflow as lf
from lieflow import state_trees, stepping
from lieflow.app.config import build, parse_config
from lieflow.flows import Splitting, StepStats
from lieflow.systems.shifted import CasimirShifted

MU = 0.3


@attrs.frozen
class Drag:
    """``dW/dt = -mu W``, solved exactly: ``W e^{-mu h}`` (stateless)."""

    mu: float = MU
    name: str = "drag"

    def init(self, W0: Any) -> None:
        return None

    def step(self, W: Any, t: float, h: float, state: None) -> tuple[Any, None, StepStats]:
        return W * np.exp(-self.mu * h), None, StepStats()


@attrs.frozen
class Clock:
    """Records the times and sizes of its sub-steps; does nothing to ``W``."""

    seen: list[tuple[float, float]] = attrs.field(factory=list)
    name: str = "clock"

    def init(self, W0: Any) -> dict[str, Any]:
        return {"count": np.zeros(1)}

    def step(self, W: Any, t: float, h: float, state: dict[str, Any]) -> tuple[Any, Any, StepStats]:
        self.seen.append((t, h))
        return W, {"count": state["count"] + 1}, StepStats()


def body() -> lf.IsospectralSystem:
    return lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))


def reference(system: lf.IsospectralSystem, W0: np.ndarray, T: float) -> np.ndarray:
    """``dW/dt = [B(W), W] - mu W`` by DOP853 at rtol 1e-13 (independent of lieflow)."""

    def f(_t: float, y: np.ndarray) -> np.ndarray:
        W = y.reshape(3, 3)
        B = system.B(W)
        return (B @ W - W @ B - MU * W).ravel()

    sol = solve_ivp(f, (0, T), W0.ravel(), method="DOP853", rtol=1e-13, atol=1e-15)
    return sol.y[:, -1].reshape(3, 3)


@pytest.mark.parametrize(
    ("make", "scheme", "order"),
    [
        (lambda a, b: Splitting.lie(a, b), "gauss2", 1),
        (lambda a, b: Splitting.strang(a, b), "gauss2", 2),
        (lambda a, b: Splitting.composition(a, b, method="triple_jump"), "gauss2", 4),
        (lambda a, b: Splitting.composition(a, b, method="suzuki5"), "gauss2", 4),
        (lambda a, b: Splitting.composition(a, b, method="yoshida6"), "gauss3", 6),
    ],
)
def test_splitting_order_against_an_independent_reference(
    make: Any, scheme: str, order: int
) -> None:
    system = body()
    W0 = system.random_state(3)
    T = 2.0
    ref = reference(system, W0, T)
    errors = []
    # sixth order reaches roundoff by h = T/20: larger steps there
    hs = [T / 4, T / 6, T / 8, T / 10] if order == 6 else [T / 20, T / 40, T / 80]
    for h in hs:
        split = make(Drag(), lf.SchemeFlow(system, lf.schemes.get(scheme)))
        sol = lf.integrate(system, split, W0, h, t_final=T, diagnostics=False)
        errors.append(np.linalg.norm(sol.W_final - ref) / np.linalg.norm(ref))
    observed = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert observed == pytest.approx(order, abs=0.1), errors


def test_drag_splitting_keeps_the_spectrum_shape_and_decays_exactly() -> None:
    """Drag scales the spectrum by e^{-mu t}; the isospectral step keeps it: the split run's
    eigenvalues are W0's times e^{-mu T}, to roundoff, whatever h."""
    system = body()
    W0 = system.random_state(1)
    split = Splitting.strang(Drag(), lf.SchemeFlow(system, lf.schemes.get("midpoint")))
    sol = lf.integrate(system, split, W0, 0.25, steps=40)
    expected = np.sort(np.linalg.eigvals(W0).imag) * np.exp(-MU * 10.0)
    got = np.sort(np.linalg.eigvals(sol.W_final).imag)
    assert np.max(np.abs(got - expected)) < 1e-14


def test_each_flow_runs_on_its_own_clock() -> None:
    system = body()
    clock = Clock()
    split = Splitting.strang(clock, lf.SchemeFlow(system, lf.schemes.get("midpoint")))
    lf.integrate(system, split, system.random_state(0), 0.5, steps=2)
    assert clock.seen == [(0.0, 0.25), (0.25, 0.25), (0.5, 0.25), (0.75, 0.25)]


def test_composition_sub_steps_and_checks() -> None:
    a, b = Drag(), Clock()
    split = Splitting.composition(a, b, method="triple_jump")
    assert [i for i, _ in split.sequence] == [0, 1, 0, 1, 0, 1, 0]  # half steps merged
    assert sum(c for i, c in split.sequence if i == 0) == pytest.approx(1.0, abs=1e-15)
    assert split.order == 4
    with pytest.raises(lf.InputError, match="add up to"):
        Splitting((a, b), [(0, 0.5), (1, 1.0)])
    with pytest.raises(lf.InputError, match="only 2 flows"):
        Splitting((a, b), [(0, 1.0), (1, 1.0), (2, 1.0)])
    with pytest.raises(lf.InputError, match="must be a Flow"):
        Splitting.strang(a, lf.schemes.get("midpoint"))  # type: ignore[arg-type]
    with pytest.raises(lf.InputError, match="unknown splitting"):
        Splitting.named("yoshida8", a, b)


@pytest.mark.parametrize("method", lf.tableaus.COMPOSITIONS)
def test_splittings_and_sydirk_schemes_share_the_composition_coefficients(method: str) -> None:
    """One table of composition weights (lieflow.tableaus): a composition splitting's inner
    (last) flow takes exactly the SyDIRK tableau's sub-steps ``b``, and the weights are the
    50-digit values rounded once (triple jump: ``x = 1/(2 - 2^{1/3})``)."""
    split = Splitting.composition(Drag(), Clock(), method=method)
    inner = [c for i, c in split.sequence if i == 1]
    scheme = lf.schemes.get("sydirk7" if method == "yoshida6" else method)
    assert tuple(inner) == tuple(scheme.tableau.b)
    assert split.order == scheme.order
    if method == "triple_jump":
        x = 1 / (2 - 2 ** (1 / 3))
        np.testing.assert_allclose(inner, [x, 1 - 2 * x, x], rtol=1e-15)
    with pytest.raises(lf.InputError, match="unknown composition"):
        Splitting.composition(Drag(), Clock(), method="yoshida8")


def test_a_flow_with_solver_options_is_refused() -> None:
    system = body()
    split = Splitting.strang(Drag(), lf.SchemeFlow(system, lf.schemes.get("midpoint")))
    with pytest.raises(lf.InputError, match="Flow carries its own"):
        lf.integrate(system, split, system.random_state(0), 0.1, steps=2, engine="numpy")


def test_warm_starts_of_sub_steps_are_kept_apart() -> None:
    """Each Strang slot has its own warm start: fewer iterations than cold starts."""
    system = body()
    W0 = system.random_state(0)

    def iterations(warm: bool) -> int:
        inner = lf.SchemeFlow(system, lf.schemes.get("gauss3"), warm_start=warm)
        split = Splitting.composition(Drag(), inner)
        return int(lf.integrate(system, split, W0, 0.05, steps=100).iterations.sum())

    assert iterations(True) < 0.8 * iterations(False)


def test_projected_flow_lands_on_the_phase_space() -> None:
    toda = lf.systems.get("periodic_toda", n=4)

    @attrs.frozen
    class Skew:
        name: str = "skew"

        def init(self, W0: Any) -> None:
            return None

        def step(self, W: Any, t: float, h: float, s: None) -> tuple[Any, None, StepStats]:
            noise = np.triu(np.full(W.shape, 1e-9), 1)
            return W + noise, None, StepStats()

    W0 = toda.random_state(0)
    W1, _, _ = Skew().step(W0, 0.0, 0.1, None)
    assert toda.phase_space_distance(W1) > 1e-10  # the flow leaves symmetric matrices ...
    W2, _, _ = lf.Projected(Skew(), toda).step(W0, 0.0, 0.1, None)
    assert toda.phase_space_distance(W2) == 0.0  # ... and the projection brings it back
    assert np.max(np.abs(W2 - W0)) == pytest.approx(5e-10, rel=1e-6)


def test_projected_scheme_flow_projects_once_per_step() -> None:
    """One projection policy: a SchemeFlow's steps end with its system's projection, so
    ``Projected`` of it (on the same system, or the Casimir-shifted one it steps) adds none
    — bit-for-bit the scheme flow alone, one ``project`` call per step — while a flow that
    does not project is projected."""

    @attrs.frozen(eq=False)
    class Counting(lf.systems.RigidBody):  # type: ignore[misc]
        calls: list[int] = attrs.field(factory=list)

        def project(self, W: Any) -> Any:
            self.calls.append(1)
            return super().project(W)

    system = Counting(inertia=(1.0, 2.0, 3.0))
    W0 = system.random_state(1)
    flow = lf.SchemeFlow(system, lf.schemes.get("midpoint"))
    alone = [c.W for c in stepping.advance(flow, W0, 0.1, 5)]
    system.calls.clear()
    wrapped = [c.W for c in stepping.advance(lf.Projected(flow, system), W0, 0.1, 5)]
    assert len(system.calls) == 5
    np.testing.assert_array_equal(np.concatenate(wrapped), np.concatenate(alone))
    shifted = CasimirShifted(system, 0.5)
    assert not lf.Projected(
        lf.SchemeFlow(shifted, lf.schemes.get("midpoint")), system
    ).projects_again
    assert lf.Projected(Drag(), system).projects_again
    assert not lf.Projected(lf.Projected(Drag(), system), system).projects_again


def test_tree_round_trip() -> None:
    state = (lf.WarmStart(np.ones((2, 3)), None, False), None, {"k": np.arange(3.0), "x": 1.5})
    flat = dict(state_trees.paths(state))
    assert sorted(flat) == ["0/last", "0/previous", "0/trusted", "1", "2/k", "2/x"]
    template = (lf.WarmStart(), None, {"k": None, "x": 0.0})
    back = state_trees.rebuild(template, flat)
    assert back[0].trusted is False and back[1] is None and back[2]["x"] == 1.5
    assert np.array_equal(back[0].last, np.ones((2, 3)))
    assert state_trees.sum_of_squares(state) == pytest.approx(6 + 5)


def test_driver_reports_the_failing_step() -> None:
    @attrs.frozen
    class Blow:
        name: str = "blow"

        def init(self, W0: Any) -> None:
            return None

        def step(self, W: Any, t: float, h: float, s: None) -> tuple[Any, None, StepStats]:
            return (np.full_like(W, np.nan) if t >= 0.3 - 1e-12 else W), None, StepStats()

    chunks = []
    with pytest.raises(lf.ConvergenceError) as info:
        for chunk in stepping.advance(Blow(), np.eye(2), 0.1, 10):
            chunks.append(chunk)
    assert [c.stop for c in chunks] == [1, 2, 3]
    assert info.value.step == 4 and info.value.reason == "non_finite"


SPLIT_CONFIG = """
[system]
name = "rigid_body"
params = {{ inertia = [1.0, 2.0, 3.0] }}
[initial]
random = true
seed = 0
[scheme]
name = "gauss2"
[splitting]
method = "{method}"
flows = [{{ name = "drag", params = {{ mu = 0.3 }} }}]
[run]
h = 0.05
steps = {steps}
save_every = 10
"""


class DragPlugin:
    @lf.hookimpl
    def lieflow_register(self, registry: lf.RegistryBuilder) -> None:
        registry.add_flow("drag", lambda system, mu: Drag(mu), "linear drag, exact")


def _setup(tmp_path: Path, name: str, steps: int, method: str = "strang") -> Any:
    reg = lf.load_registry(autoload=False, plugins=[("drag", DragPlugin())])
    config = parse_config(SPLIT_CONFIG.format(method=method, steps=steps), source="split.toml")
    return build(config, output=tmp_path / name, registry=reg)


def test_lieflow_run_with_a_splitting_resumes_bit_for_bit(tmp_path: Path) -> None:
    from lieflow.app import io

    io.run(_setup(tmp_path, "ref.h5", 60))
    io.run(_setup(tmp_path, "a.h5", 25))  # an early stop, then more steps asked for
    io.run(_setup(tmp_path, "a.h5", 60), resume=True)
    a, ref = io.read_trajectory(tmp_path / "a.h5"), io.read_trajectory(tmp_path / "ref.h5")
    assert np.array_equal(a.checkpoint.W, ref.checkpoint.W)  # bit for bit
    common = np.isin(a.step, ref.step)
    assert a.step[~common].tolist() == [25]  # the first run's last state
    assert np.array_equal(a.W[common], ref.W)
    assert np.array_equal(a.iterations, ref.iterations)
    assert np.array_equal(a.energy_error, ref.energy_error)
    # the checkpoint holds one warm start per Strang slot (the drag's slots hold nothing)
    ck = a.checkpoint
    assert {k.split("/")[0] for k in ck.leaves} == {"0", "1", "2"}
    # and the physics: the spectrum decays by e^{-mu t}, exactly
    lam0 = np.sort(np.linalg.eigvals(a.W[0]).imag)
    lam = np.sort(np.linalg.eigvals(a.W[-1]).imag)
    assert np.max(np.abs(lam - lam0 * np.exp(-MU * 3.0))) < 1e-14
    with pytest.raises(lf.app.config.ConfigError, match="splitting"):
        io.run(_setup(tmp_path, "a.h5", 80, method="lie"), resume=True)


def test_splitting_config_errors() -> None:
    bad = SPLIT_CONFIG.format(method="yoshida8", steps=10)
    with pytest.raises(lf.app.config.ConfigError, match=r"\[splitting\] method"):
        parse_config(bad)
    bad = SPLIT_CONFIG.format(method="strang", steps=10).replace('name = "drag"', 'name = "dragg"')
    reg = lf.load_registry(autoload=False, plugins=[("drag", DragPlugin())])
    with pytest.raises(lf.app.config.ConfigError, match=r"\[splitting\] flows\[0\] name"):
        build(parse_config(bad), registry=reg)


def test_a_run_that_cannot_fit_in_memory_is_refused_before_it_starts() -> None:
    import importlib

    runs_module = importlib.import_module("lieflow.runs")

    zeitlin_like = lf.systems.get("generalized_rigid_body", J=np.linspace(1.0, 2.0, 256))
    W0 = zeitlin_like.random_state(0)  # 512 KiB a state
    available = runs_module._available_memory()
    assert available is not None and available > 0
    steps = int(available / W0.nbytes) + 1  # the saved states alone exceed the memory
    with pytest.raises(lf.InputError, match="save_every=") as info:
        lf.integrate(zeitlin_like, lf.schemes.get("midpoint"), W0, 0.01, steps=steps)
    assert "out=" in str(info.value) and "lieflow run" in str(info.value)
