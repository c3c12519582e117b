"""Start-up of ``lieflow run``: what a short rigid-body run pays for plugins it does not use.

Each case is a fresh interpreter (``python -c``), timed from this process, the cases
alternated round by round so that the machine's load hits them alike (best of the rounds):

* *import*: ``import lieflow.app.cli`` — the interpreter and the command line, the floor;
* *run*: ``lieflow run`` on ``examples/rigid_body.toml`` cut to 10 steps (gauss3, an HDF5
  file), as shipped: the registry loads lieflow's own plugins only
  (:func:`lieflow.load_registry`, ``lazy``);
* *run, all plugins*: the same run after loading every installed plugin and importing numba,
  what ``lieflow run`` did before the registry loaded plugins on demand (issue 27: 161 ms).

Each case also reports which third-party plugin modules (and numba) it imported.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ..config import BenchContext
from ..report import Section, Table, TargetCheck

#: Modules a rigid-body run has no use for.
THIRD_PARTY = ("lieflow_zeitlin", "lieflow_vortices", "numba")

#: The rigid body example; the run is cut to :data:`STEPS` steps.
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rigid_body.toml"
STEPS = 10


def _short_config(directory: Path) -> Path:
    """The example with ``steps = STEPS``, written into ``directory`` (its output too)."""
    text, count = re.subn(r"(?m)^steps = \d+", f"steps = {STEPS}", EXAMPLE.read_text("utf-8"))
    if count != 1:
        raise RuntimeError(f"{EXAMPLE} has no single 'steps = ...' line to shorten")
    config = directory / EXAMPLE.name
    config.write_text(text, encoding="utf-8")
    return config


_REPORT = f"import json, sys\nprint(json.dumps([m for m in {THIRD_PARTY!r} if m in sys.modules]))\n"
_RUN = (
    "from lieflow.app.cli import main\n"
    "assert main(['run', '--no-progress', '--force', {config!r}]) == 0\n"
)
_ALL_PLUGINS = (
    "import lieflow as lf\n"
    "lf.systems.available()\n"
    "try:\n"
    "    import numba\n"
    "except ImportError:\n"
    "    pass\n"
)


def _cases(config: Path) -> dict[str, str]:
    run = _RUN.format(config=str(config))
    return {
        "import lieflow.app.cli": "import lieflow.app.cli\n" + _REPORT,
        "lieflow run": run + _REPORT,
        "lieflow run, all plugins loaded first": _ALL_PLUGINS + run + _REPORT,
    }


def _time(code: str) -> tuple[float, list[str]]:
    """Wall time of a fresh ``python -c code`` and the modules it reported."""
    start = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300
    )
    elapsed = time.perf_counter() - start
    return elapsed, list(json.loads(out.stdout.strip().splitlines()[-1]))


def run(ctx: BenchContext) -> Section:
    """The three cases, alternated; the saving and what each imported."""
    began = time.perf_counter()
    rounds = 3 if ctx.config.quick else 10
    with tempfile.TemporaryDirectory() as tmp:
        cases = _cases(_short_config(Path(tmp)))
        best = dict.fromkeys(cases, float("inf"))
        imported: dict[str, list[str]] = {}
        for _ in range(rounds):
            for name, code in cases.items():
                elapsed, imported[name] = _time(code)
                best[name] = min(best[name], elapsed)
    floor = best["import lieflow.app.cli"]
    rows = tuple(
        (name, f"{best[name] * 1e3:.0f} ms", f"{(best[name] - floor) * 1e3:.0f} ms",
         ", ".join(imported[name]) or "none")
        for name in cases
    )  # fmt: skip
    shipped, eager = best["lieflow run"], best["lieflow run, all plugins loaded first"]
    saving = eager - shipped
    table = Table(
        ("case", "wall time", "over the import", "third-party modules imported"),
        rows,
        caption=f"A fresh interpreter per case, best of {rounds} alternated rounds; the run: "
        f"examples/rigid_body.toml cut to {STEPS} steps (gauss3, into an HDF5 file).",
    )
    clean = not imported["lieflow run"]
    targets = (
        TargetCheck(
            target="`lieflow run` on a rigid body imports no other plugin and no numba",
            measured=f"imported: {', '.join(imported['lieflow run']) or 'none'}; "
            f"{saving * 1e3:.0f} ms less than with every plugin loaded "
            f"({eager / shipped:.2f}× the wall time)",
            met=clean,
            gap="" if clean else "a third-party plugin is still loaded",
            limit="the registry loads lieflow's own plugins first and the others only for a "
            "name that is not lieflow's",
        ),
    )
    return Section(
        title="Start-up of `lieflow run`",
        intro="A short run pays for the interpreter, lieflow and what its registry loads. "
        "The registry loads lieflow's own plugins first and every other plugin only when a "
        "name is not lieflow's or a table is listed; the fluids plugin compiles its kernels "
        "(and imports numba) at their first use.",
        tables=(table,),
        targets=targets,
        notes=(
            f"Cut to {STEPS} steps, the run takes the numpy engine. The example's own 2000 "
            'steps take `engine = "auto"`\'s compiled loops, which import numba themselves: '
            "there the saving is the other plugins' own import only.",
        ),
        seconds=time.perf_counter() - began,
    )
