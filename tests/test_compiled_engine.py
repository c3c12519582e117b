"""The single-source compiled engine (issue 12.4): the system's B and projection as compiled
functions (a plugin's included), eligibility asked of the scheme and solver, one stopping
rule, deterministic chunks and bit-for-bit resume of ``lieflow run`` on the compiled engine."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import attrs
import numpy as np
import pytest
from helpers import import_plugin

import lieflow as lf
from lieflow import chunks, stepping
from lieflow.app import io
from lieflow.app.cli import main
from lieflow.engines import compiled, compiled_plan, map_checks

numba = pytest.importorskip("numba")


def _both(*args: Any, **kwargs: Any) -> tuple[lf.Solution, lf.Solution]:
    return (
        lf.integrate(*args, **kwargs, engine="numpy"),
        lf.integrate(*args, **kwargs, engine="compiled"),
    )


def _agree(ref: lf.Solution, fast: lf.Solution, atol: float = 1e-12) -> None:
    assert fast.status is ref.status and fast.n_steps == ref.n_steps
    np.testing.assert_allclose(fast.W, ref.W, rtol=0, atol=atol * max(1.0, np.abs(ref.W).max()))
    assert np.max(np.abs(fast.iterations - ref.iterations), initial=0) <= 1


# ------------------------------------------------------------------ products by BLAS


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2"])
@pytest.mark.parametrize(
    "system",
    [lf.systems.GeneralizedRigidBody.random_inertia(12, seed=4), lf.systems.PeriodicToda(12)],
    ids=["so(12)", "toda-12"],
)
def test_blas_products_above_n_8_agree_with_numpy(
    system: lf.IsospectralSystem, scheme: str
) -> None:
    """Above n = 8 the loops multiply through ``_compiled_loops.gemm`` (BLAS), with ``A^T B`` for
    the reduced form's stage values and, on the symmetric Toda states, ``A B^T``."""
    W0 = 0.8 * system.random_state(seed=2)
    ref, fast = _both(system, lf.schemes.get(scheme), W0, 0.02, steps=40)
    _agree(ref, fast, atol=1e-13)


# ------------------------------------------------------------------ B from the system


@pytest.mark.parametrize("scheme", ["midpoint", "gauss2", "sydirk7"])
def test_a_plugin_system_runs_compiled(scheme: str) -> None:
    """The point vortices' nonlinear B lives in the plugin (lieflow_vortices._compiled)."""
    vortices = import_plugin("lieflow_vortices")
    system = vortices.PointVortices()
    W0 = system.random_state(seed=1)
    plan = compiled.plan(system, lf.schemes.get(scheme), lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, compiled_plan.CompiledPlan)
    assert plan.B.function is vortices._compiled.vortex_B
    assert plan.project.function is vortices._compiled.vortex_project
    ref, fast = _both(system, lf.schemes.get(scheme), W0, 0.05, steps=60)
    _agree(ref, fast)
    # each new state is put back on the spheres |m_i| = |Γ_i| inside the loops
    assert float(system.phase_space_distance(fast.W).max()) < 1e-15

    # the loops take the maps and the product by address: integers, which numba types
    # without Python (a function object argument cost ~4 µs per argument and call)
    k = compiled.kernels()
    run = k.entry(f"{plan.kind}_advance", plan.dtype, skew=plan.skew)
    (args,) = run.signatures
    fields = k.LoopArguments._fields
    assert [args[fields.index(name)] for name in ("B", "project", "gemm")] == [
        numba.types.int64
    ] * 3
    # a plugin's map is resolved once per system, kept with its check while its dispatcher
    # holds the same compiled code; lieflow's own maps once per process
    again = compiled.plan(system, lf.schemes.get(scheme), lf.solvers.FixedPoint(), W0)
    assert isinstance(again, compiled_plan.CompiledPlan) and again.B is plan.B
    other = vortices.PointVortices()
    fresh = compiled.plan(other, lf.schemes.get(scheme), lf.solvers.FixedPoint(), W0)
    assert isinstance(fresh, compiled_plan.CompiledPlan) and fresh.B is not plan.B
    body = lf.systems.GeneralizedRigidBody.random_inertia(5, seed=1)
    plans = [
        compiled.plan(body, lf.schemes.get(scheme), lf.solvers.FixedPoint(), body.random_state(k))
        for k in (1, 2)
    ]
    assert all(isinstance(p, compiled_plan.CompiledPlan) for p in plans)
    assert plans[0].B is plans[1].B  # type: ignore[union-attr]


def _cubic_B(W: np.ndarray, params: np.ndarray, out: np.ndarray) -> None:
    """``B(W) = S ⊙ W (1 + c |W|²)`` of the skew part of ``W``: a nonlinear B."""
    n = W.shape[0]
    norm2 = 0.0
    for i in range(n):
        for j in range(n):
            a = 0.5 * (W[i, j] - W[j, i])
            norm2 += a * a
    f = 1.0 + params[n * n] * norm2
    for i in range(n):
        for j in range(n):
            out[i, j] = params[i * n + j] * (0.5 * (W[i, j] - W[j, i])) * f


cubic_B = numba.njit(_cubic_B)


@attrs.frozen(eq=False)
class CubicBody(lf.IsospectralSystem):
    """A system defined here, with its own compiled B (not of the form S ⊙ W)."""

    S: np.ndarray = attrs.field(
        factory=lambda: -1.0 / np.add.outer(np.arange(1.0, 5.0), np.arange(1.0, 5.0))
    )
    c: float = 0.3

    @property
    def algebra(self) -> lf.SO:
        return lf.SO(4)

    def B(self, W: np.ndarray) -> np.ndarray:
        return self.S * W * (1.0 + self.c * np.sum(W * W, axis=(-2, -1)))[..., None, None]

    def hamiltonian(self, W: np.ndarray) -> np.ndarray:
        q = np.sum(-self.S * W * W, axis=(-2, -1))
        return q  # not the exact energy of this B; only used for diagnostics

    def compiled_B(self, shift: float = 0.0) -> tuple[Any, np.ndarray] | None:
        if shift != 0.0:  # cubic_B has no slot for a Casimir shift
            return None
        return cubic_B, np.append(self.S.ravel(), self.c)


@pytest.mark.parametrize("scheme", ["midpoint", "gauss3"])
def test_a_system_with_its_own_compiled_B(scheme: str) -> None:
    system = CubicBody()
    W0 = 0.7 * system.random_state(seed=2)
    ref, fast = _both(system, lf.schemes.get(scheme), W0, 0.05, steps=80)
    _agree(ref, fast)
    assert system.hadamard_factor is None


def test_a_recompiled_map_is_checked_and_resolved_again() -> None:
    """The checked maps kept on a system hold the map's compiled code: after a recompile
    (the old code is released) the next plan checks and resolves the map again."""
    own_B = numba.njit(_cubic_B)

    @attrs.frozen(eq=False)
    class Own(CubicBody):
        def compiled_B(self, shift: float = 0.0) -> tuple[Any, np.ndarray] | None:
            return (own_B, np.append(self.S.ravel(), self.c)) if shift == 0.0 else None

    system, mid, fp = Own(), lf.schemes.get("midpoint"), lf.solvers.FixedPoint()
    W0 = 0.7 * system.random_state(seed=2)
    first = compiled.plan(system, mid, fp, W0)
    assert isinstance(first, compiled_plan.CompiledPlan)
    assert compiled.plan(system, mid, fp, W0).B is first.B  # type: ignore[union-attr]
    own_B.recompile()
    again = compiled.plan(system, mid, fp, W0)
    assert isinstance(again, compiled_plan.CompiledPlan) and again.B is not first.B
    _agree(*_both(system, mid, W0, 0.05, steps=40))


def test_a_wrong_compiled_B_is_refused() -> None:
    @attrs.frozen(eq=False)
    class Liar(CubicBody):
        def compiled_B(self, shift: float = 0.0) -> tuple[Any, np.ndarray] | None:
            return cubic_B, np.append(self.S.ravel(), 2 * self.c)  # not B

    system = Liar()
    with pytest.raises(lf.InputError, match="does not reproduce"):
        lf.integrate(system, lf.schemes.get("midpoint"), system.random_state(seed=0), 0.05,
                     steps=2, engine="compiled")  # fmt: skip
    auto = lf.integrate(system, lf.schemes.get("midpoint"), system.random_state(seed=0), 0.05,
                        steps=2)  # fmt: skip
    assert auto.success


def test_the_loops_get_only_resolved_maps_of_their_signature() -> None:
    """The entry points take their functions as bare addresses; a plan whose map is not a
    resolved function of the loops' signature for its dtype is refused before the loops
    (a wrong address would be called unchecked)."""
    body = lf.systems.GeneralizedRigidBody.random_inertia(4, seed=1)
    W0 = body.random_state(seed=3)
    plan = compiled.plan(body, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, compiled_plan.CompiledPlan)
    k = compiled.kernels()
    good = plan.advance(W0, 0.05, 3)
    assert good.done == 3
    wrong = {
        "B": k.gemm(np.float64),  # resolved, but (A, B, out, ta, tb): not a map
        "project": k.gemm(np.float64),
    }
    wrong_B_dispatcher = attrs.evolve(plan, B=compiled.hadamard_B)
    for field, value in wrong.items():
        bad = attrs.evolve(plan, **{field: value})
        with pytest.raises(TypeError, match="resolved function of signature"):
            bad.advance(W0, 0.05, 3)
    with pytest.raises(TypeError, match="resolved function of signature"):
        wrong_B_dispatcher.advance(W0, 0.05, 3)
    # the same plan, rebuilt with its own maps, gives the same bits
    same = attrs.evolve(plan, B=plan.B).advance(W0, 0.05, 3)
    assert same.states.tobytes() == good.states.tobytes()


def test_toda_is_symmetrized_every_step_inside_the_loops() -> None:
    toda = lf.systems.PeriodicToda(5)
    W0 = toda.random_state(seed=0)
    plan = compiled.plan(toda, lf.schemes.get("gauss3"), lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, compiled_plan.CompiledPlan) and plan.project is not None
    ref, fast = _both(toda, lf.schemes.get("gauss3"), W0, 0.05, steps=300)
    _agree(ref, fast, atol=1e-12)
    long = lf.integrate(toda, lf.schemes.get("gauss3"), W0, 0.05, steps=3000, engine="compiled")
    for sol in (fast, long):
        assert float(np.max(np.abs(sol.W - np.swapaxes(sol.W, -1, -2)))) == 0.0


def test_compiled_B_defaults() -> None:
    from lieflow.engines import _compiled_maps

    body = lf.systems.RigidBody()
    got = body.compiled_B()
    assert got is not None
    fn, params = got
    assert fn == "hadamard_B_skew"  # lieflow's own map, by name (the system imports no engine)
    assert map_checks._by_name(got, compiled.kernels())[0] is _compiled_maps.hadamard_B_skew
    np.testing.assert_array_equal(params, body.hadamard_factor.ravel())
    unknown = map_checks._by_name(("no_such_map", params), compiled.kernels())
    assert "no compiled map named 'no_such_map'" in unknown
    assert body.compiled_project() is None
    assert lf.systems.PeriodicToda(gl_gradient=True).compiled_B() is None
    assert CubicBody().compiled_project() is None


# ------------------------------------------------------------------ eligibility


def test_eligibility_is_asked_of_the_scheme_and_the_solver() -> None:
    @attrs.frozen
    class MySyDIRK(lf.schemes.SyDIRK):
        pass

    @attrs.frozen
    class MyFixedPoint(lf.solvers.FixedPoint):
        pass

    body = lf.systems.RigidBody()
    W0 = body.random_state(seed=0)
    assert lf.schemes.get("gauss2", form="block").compiled_form() is None
    form = lf.schemes.get("gauss2").compiled_form()
    assert form is not None
    kind, A, b = form
    assert kind == "reduced" and A.shape == (2, 2) and b.shape == (2,)
    for solver in (MyFixedPoint(), lf.solvers.Auto(first=MyFixedPoint())):
        plan = compiled.plan(body, MySyDIRK(), solver, W0)
        assert isinstance(plan, compiled_plan.CompiledPlan) and plan.kind == "sydirk"
    assert isinstance(compiled.plan(body, MySyDIRK(), lf.solvers.FrozenB(), W0), str)
    ref, fast = _both(body, MySyDIRK(), W0, 0.1, steps=50, solver=MyFixedPoint())
    _agree(ref, fast, atol=1e-13)


# ------------------------------------------------------------------ one stepping loop, chunks


@attrs.frozen(eq=False)
class _Recorder:
    """A multi-step flow that records the chunk sizes asked of it (steps do nothing)."""

    asked: list[int] = attrs.field(factory=list)
    name = "recorder"

    def init(self, W0: np.ndarray) -> None:
        return None

    def step(self, W: np.ndarray, t: float, h: float, state: Any) -> Any:
        return W, state, lf.StepStats()

    def step_many(self, W: np.ndarray, start: int, h: float, steps: int, state: Any) -> Any:
        self.asked.append(steps)
        n = np.zeros(steps, dtype=np.int64)
        return chunks.Chunk(start, h, np.repeat(W[None], steps, 0), n, n * 0.0,
                            ("",) * steps, state)  # fmt: skip


def test_chunks_end_at_multiples_of_the_chunk_size_wherever_the_run_starts() -> None:
    W0 = np.zeros((3, 3))
    size = stepping.chunk_steps(W0)
    flow = _Recorder()
    ends = [c.stop for c in stepping.advance(flow, W0, 0.1, 2 * size + 100, start=23)]
    assert ends == [size, 2 * size, 2 * size + 100]
    assert flow.asked == [size - 23, size, 100]


def test_a_complete_chunk_is_not_followed_by_a_numpy_step() -> None:
    from lieflow.engines import scheme_flow

    body = lf.systems.RigidBody()
    W0 = body.random_state(0)
    flow = scheme_flow(body, lf.schemes.get("midpoint"), lf.solvers.FixedPoint(), W0, 2500,
                       engine="compiled")  # fmt: skip
    chunks = list(stepping.advance(flow, W0, 0.1, 2500))
    assert [c.size for c in chunks] == [1024, 1024, 452]
    assert all(np.isnan(c.residuals).all() for c in chunks)  # every step compiled


# ------------------------------------------------------------------ inside a Splitting


@attrs.frozen
class _Drag:
    """``dW/dt = -mu W``, exactly (a stateless sub-flow)."""

    mu: float = 0.3
    name: str = "drag"

    def init(self, W0: np.ndarray) -> None:
        return None

    def step(self, W: np.ndarray, t: float, h: float, state: None) -> Any:
        return W * np.exp(-self.mu * h), None, lf.StepStats()


def _split_run(flow: lf.Flow, W0: np.ndarray, h: float, steps: int) -> tuple[Any, Any]:
    chunks = list(stepping.advance(flow, W0, h, steps))
    return np.concatenate([c.W for c in chunks]), np.concatenate([c.iterations for c in chunks])


def _numpy_steps(monkeypatch: pytest.MonkeyPatch, scheme: lf.Scheme) -> list[int]:
    """Count the scheme's numpy steps (``Scheme.step``) from now on."""
    calls: list[int] = []
    numpy_step = type(scheme).step

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return numpy_step(*args, **kwargs)

    monkeypatch.setattr(type(scheme), "step", counted)
    return calls


@pytest.mark.parametrize("scheme_name", ["midpoint", "gauss2"])
def test_a_compiled_flow_stays_compiled_inside_a_splitting(
    monkeypatch: pytest.MonkeyPatch, scheme_name: str
) -> None:
    """Issue 26.3: the sub-steps of a compiled scheme flow inside a Splitting (and a
    Projected) are taken by the compiled loops — the scheme's numpy step never runs — and
    agree with the numpy engine's to roundoff (the reference: the same splitting on numpy)."""
    from lieflow.engines import scheme_flow

    body = lf.systems.RigidBody(inertia=(1.0, 2.0, 3.0))
    W0 = body.random_state(3)
    scheme, solver = lf.schemes.get(scheme_name), lf.solvers.FixedPoint(rtol=1e-14)
    flows = {e: scheme_flow(body, scheme, solver, W0, 10, engine=e) for e in ("numpy", "compiled")}
    assert isinstance(flows["compiled"], compiled_plan.CompiledSchemeFlow)
    ref = _split_run(lf.Splitting.strang(_Drag(), flows["numpy"]), W0, 0.1, 60)
    calls = _numpy_steps(monkeypatch, scheme)
    got = _split_run(lf.Splitting.strang(_Drag(), flows["compiled"]), W0, 0.1, 60)
    projected = _split_run(lf.Projected(flows["compiled"], body), W0, 0.1, 5)
    assert calls == []  # fails when the splitting steps the compiled flow through numpy
    np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-14)
    assert np.max(np.abs(got[1] - ref[1])) <= 1
    assert np.all(np.isfinite(projected[0]))
    # a step the loops do not accept still goes to the numpy path (max_iter = 2 fails)
    strict = lf.solvers.FixedPoint(rtol=1e-14, max_iter=2)
    flow = scheme_flow(body, scheme, strict, W0, 10, engine="compiled")
    with pytest.raises(lf.ConvergenceError):
        _split_run(lf.Splitting.strang(_Drag(), flow), W0, 0.1, 3)
    assert calls  # the failed step was retried on numpy, which raised


def test_a_forced_dissipative_euler_zeitlin_run_is_compiled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``lieflow run`` of a [splitting] configuration with engine = "compiled" (drag,
    stochastic forcing and the isospectral step on complex data) never takes a numpy step,
    and agrees with engine = "numpy" to roundoff."""
    import_plugin("lieflow_zeitlin")
    from lieflow.app.config import build, parse_config

    forcing = '{ name = "zeitlin_forcing", params = { amplitude = 0.2, l1 = 2, l2 = 4, seed = 1 } }'

    def setup(engine: str) -> Any:
        text = f"""
            [system]
            name = "euler_zeitlin"
            params = {{ N = 8, time = "fluid" }}
            [initial]
            random = true
            seed = 2
            [scheme]
            name = "midpoint"
            [solver]
            name = "fixed_point"
            params = {{ rtol = 1e-14 }}
            [splitting]
            method = "strang"
            flows = [
              {{ name = "zeitlin_drag", params = {{ mu = 0.1 }} }},
              {forcing},
            ]
            [run]
            h = 0.05
            steps = 40
            engine = "{engine}"
            """
        return build(
            parse_config(textwrap.dedent(text), source="forced.toml"), output=tmp_path / "x.h5"
        )

    fast, slow = setup("compiled"), setup("numpy")
    ref = _split_run(slow.flow(), slow.W0, 0.05, 40)
    flow = fast.flow()
    assert isinstance(flow, lf.Splitting)
    assert isinstance(flow.flows[-1], compiled_plan.CompiledSchemeFlow)
    calls = _numpy_steps(monkeypatch, fast.scheme)
    got = _split_run(flow, fast.W0, 0.05, 40)
    assert calls == []
    np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-13 * np.abs(ref[0]).max())
    assert np.max(np.abs(got[1] - ref[1])) <= 1


@pytest.mark.parametrize(
    ("system", "scheme", "h"),
    [
        ('name = "rigid_body"\nparams = { inertia = [1.0, 2.0, 3.0] }', "midpoint", 0.1),
        ('name = "euler_zeitlin"\nparams = { N = 8 }', "gauss2", 0.05),  # complex loops
    ],
    ids=["rigid_body", "euler_zeitlin"],
)
def test_compiled_run_interrupted_and_resumed_is_bit_for_bit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, system: str, scheme: str, h: float
) -> None:
    if "zeitlin" in system:
        import_plugin("lieflow_zeitlin")
    config = tmp_path / "run.toml"
    config.write_text(
        textwrap.dedent(
            """
            [system]
            {system}
            [initial]
            random = true
            seed = 0
            [scheme]
            name = "{scheme}"
            [run]
            h = {h}
            steps = 2500
            save_every = 250
            engine = "compiled"
            output = "a.h5"
            """
        ).format(system=system, scheme=scheme, h=h),
        encoding="utf-8",
    )
    assert main(["run", str(config), "--no-progress", "--out", str(tmp_path / "ref.h5")]) == 0
    real_advance = stepping.advance

    def interrupted(*args: Any, **kwargs: Any) -> Iterator[chunks.Chunk]:
        for chunk in real_advance(*args, **kwargs):
            yield chunk
            if chunk.stop == 1024:
                raise KeyboardInterrupt

    monkeypatch.setattr(stepping, "advance", interrupted)
    assert main(["run", str(config), "--no-progress"]) == 130
    assert io.read_checkpoint(tmp_path / "a.h5").step == 1024
    monkeypatch.setattr(stepping, "advance", real_advance)
    assert main(["run", str(config), "--no-progress", "--resume"]) == 0
    a, ref = io.read_trajectory(tmp_path / "a.h5"), io.read_trajectory(tmp_path / "ref.h5")
    assert a.completed_steps == ref.completed_steps == 2500
    assert np.array_equal(a.checkpoint.W, ref.checkpoint.W)  # bit for bit
    assert np.array_equal(a.W, ref.W)
    assert np.array_equal(a.iterations, ref.iterations)


# ------------------------------------------------------------------ the disk cache


def test_the_loops_load_from_the_disk_cache_in_a_new_process() -> None:
    """A typed function argument keeps numba's cache valid: a second process loads the
    loops instead of compiling them (an untyped dispatcher argument would recompile)."""
    code = textwrap.dedent(
        """
        import pathlib, sys
        import lieflow as lf
        from lieflow.engines import _compiled_loops
        body = lf.systems.RigidBody()
        lf.integrate(body, lf.schemes.get("midpoint"), body.random_state(0), 0.1, steps=5,
                     engine="compiled")
        print(sum(_compiled_loops.entry("sydirk_advance").stats.cache_hits.values()),
              sum(_compiled_loops.entry("sydirk_advance").stats.cache_misses.values()))
        """
    )
    for _ in range(2):  # the first may compile (a fresh checkout); the second must not
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             check=True, timeout=600)  # fmt: skip
    hits, misses = (int(v) for v in out.stdout.split()[-2:])
    assert (hits, misses) == (1, 0)


def test_the_entry_points_cache_key_covers_the_modules_of_the_loops() -> None:
    """numba's cache of an entry point tracks its own file (``_compiled_loops.py``) only, not
    the files of the functions it compiles into it: every other module of lieflow.engines the
    loops take a function or a constant from is hashed into the entry points' cache key
    (``SHARED_KEY``), so that editing a helper there recompiles them."""
    from lieflow.engines import _compiled_loops

    def sources(module: Any) -> set[str]:
        """The lieflow.engines modules ``module`` takes a function, constant or module from."""
        names = {
            getattr(getattr(value, "py_func", value), "__module__", None)
            for value in vars(module).values()
        } | {m.__name__ for m in vars(module).values() if isinstance(m, type(sys))}
        return {m for m in names if m and m.startswith("lieflow.engines.")}

    below, todo = set(), [_compiled_loops.__name__]
    while todo:  # what the loops compile, and what that compiles, ...
        for name in sources(sys.modules[todo.pop()]) - below - {_compiled_loops.__name__}:
            below.add(name)
            todo.append(name)
    assert {"lieflow.engines._compiled_formulations", "lieflow.engines._numba_jit"} <= below
    assert {"lieflow.engines._compiled_rules", "lieflow.engines._compiled_maps"} <= below
    assert below <= {m.__name__ for m in _compiled_loops.SHARED_MODULES}


# ------------------------------------------------------------------ what a plan keeps


def test_a_kept_plan_serves_calls_of_other_step_sizes_and_warm_starts() -> None:
    """A plan is kept on its system with the flow built last and ``h A``, ``h b`` of the
    last step size (issue 27 item 5): calls that change ``h`` or ``warm_start`` between
    them on one system get the runs of a system seen for the first time, bit for bit."""
    J = (1.0, 1.3, 1.7, 2.2, 2.8, 3.1)
    body = lf.systems.get("generalized_rigid_body", J=J)
    scheme, W0 = lf.schemes.get("gauss2"), body.random_state(4)
    calls = [(0.1, True), (0.05, True), (0.1, 2), (0.1, False), (0.05, True), (0.1, True)]
    for h, warm in calls:
        kept = lf.integrate(body, scheme, W0, h, steps=6, engine="compiled", warm_start=warm)
        fresh_body = lf.systems.get("generalized_rigid_body", J=J)
        fresh = lf.integrate(fresh_body, scheme, W0, h, steps=6, engine="compiled",
                             warm_start=warm)  # fmt: skip
        np.testing.assert_array_equal(kept.W, fresh.W)
        np.testing.assert_array_equal(kept.iterations, fresh.iterations)
    # the warm starts matter here: a cold run takes more updates than a warm one
    cold = lf.integrate(body, scheme, W0, 0.1, steps=6, engine="compiled", warm_start=False)
    warm_run = lf.integrate(body, scheme, W0, 0.1, steps=6, engine="compiled")
    assert cold.iterations[1:].sum() > warm_run.iterations[1:].sum()


def test_the_bare_loop_call_is_the_engines_first_step() -> None:
    """``CompiledPlan.loop_call`` (what the call-cost benchmark times as the bare step):
    called on its own from the cold start, repeatably, it takes the engine's first step."""
    body = lf.systems.get("generalized_rigid_body", J=(1.0, 1.3, 1.7, 2.2, 2.8))
    scheme, W0, h = lf.schemes.get("midpoint"), body.random_state(2), 0.05
    plan = compiled.plan(body, scheme, lf.solvers.FixedPoint(), W0)
    assert isinstance(plan, compiled_plan.CompiledPlan)
    run, args = plan.loop_call(W0, h, 1, depth=0)
    sol = lf.integrate(body, scheme, W0, h, steps=1, engine="compiled")
    for _ in range(2):
        assert run(*args) == 1
        np.testing.assert_array_equal(body.project(args.states[0, 0]), sol.W[-1])
        assert int(args.iterations[0]) == sol.iterations[0]


@pytest.mark.slow  # compiles one entry point from an empty cache (~20 s)
def test_a_run_compiles_only_the_loop_of_its_own_update(tmp_path: Path) -> None:
    """Issue 37 item 11: the first compiled run of a fresh installation compiled the loops of
    both updates (the update was a flag read at run time), doubling its compile time. Now
    each update has its entry point: a commutator run, from an empty cache, never compiles
    the conjugation update's helpers (the Gauss–Jordan solve, Newton–Schulz), and a
    conjugation run loads only its own entry point. Nor does a run of ``n <= 8`` (plain-loop
    products) compile the BLAS product."""
    code = textwrap.dedent(
        """
        import pathlib, sys
        import lieflow as lf
        from lieflow.engines import _compiled_formulations, _numba_jit
        body = lf.systems.RigidBody()
        for update in ("commutator", "conjugation"):
            lf.integrate(body, lf.schemes.get("midpoint", update=update), body.random_state(0),
                         0.1, steps=5, engine="compiled")
            print(update, len(_compiled_formulations._gauss_jordan.signatures),
                  len(_compiled_formulations._orthonormalize.signatures),
                  sorted(p.name.split("-")[0].split(".")[-1]
                         for p in pathlib.Path(sys.argv[1]).rglob("*sydirk_advance*.nbi")),
                  len(_numba_jit._gemm.signatures))
        """
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}  # an empty cache: all compiled
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True,
                         text=True, check=True, timeout=900, env=env)  # fmt: skip
    lines = out.stdout.splitlines()
    # the entry points in the cache, by name (so(3): skew, plain-loop products)
    assert lines[-2] == "commutator 0 0 ['sydirk_advance_skew'] 0"
    assert lines[-1] == (
        "conjugation 1 1 ['sydirk_advance_conjugation_skew', 'sydirk_advance_skew'] 0"
    )
