"""Bounded memory: peak memory of a run streamed to a trajectory file (``integrate(...,
out=path)``) against the size of one state, for Euler–Zeitlin at N = 512.

Each measurement runs in a fresh subprocess (so nothing else shares its heap): a two-step
warm-up run builds the plugin's caches, then the peak resident set (``VmHWM`` of
``/proc/self/status``, reset through ``/proc/self/clear_refs``) and the tracemalloc peak of
the streamed run are taken relative to the process before it. Two lengths show that the
peak does not grow with the run.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

from ..config import BenchContext
from ..report import Section, Table, TargetCheck, mebibytes

#: Issue 18: peak memory of a streamed run at most this many states.
TARGET_STATES = 20.0

_SCRIPT = textwrap.dedent(
    """
    import json, sys, tracemalloc
    import lieflow as lf
    import lieflow_zeitlin as lz

    N, steps, scheme, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]

    def status():
        d = {}
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(("VmHWM", "VmRSS")):
                    d[line.split(":")[0]] = int(line.split()[1]) * 1024
        return d

    system = lf.systems.get("euler_zeitlin", N=N, time="fluid")
    W0 = lz.random_vorticity(N, degree=8, seed=0)
    h = 1.0 / N
    lf.integrate(system, lf.schemes.get(scheme), W0, h, steps=2, out=out + ".warm")
    base = status()["VmRSS"]
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        reset = True
    except OSError:
        reset = False
    tracemalloc.start()
    sol = lf.integrate(system, lf.schemes.get(scheme), W0, h, steps=steps, out=out)
    traced = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(json.dumps({"state": W0.nbytes, "rss_base": base, "hwm": status()["VmHWM"],
                      "reset": reset, "traced": traced, "seconds": sol.wall_time,
                      "steps": int(sol.n_steps)}))
    """
)


def measure(N: int, steps: int, scheme: str) -> dict[str, float]:
    """One streamed run in a subprocess; its memory figures (bytes) and seconds."""
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "run.h5")
        res = subprocess.run(
            [sys.executable, "-c", _SCRIPT, str(N), str(steps), scheme, out],
            capture_output=True,
            text=True,
            check=True,
        )
    data: dict[str, float] = json.loads(res.stdout.strip().splitlines()[-1])
    return data


def run(ctx: BenchContext) -> Section:
    """Two run lengths at the largest size; the ≤ 20 states target."""
    start = time.perf_counter()
    title = "Bounded memory: a run streamed to a trajectory file"
    try:
        import lieflow_zeitlin  # noqa: F401
    except ImportError:
        return Section(title, "Skipped: the `lieflow-zeitlin` plugin is not installed.")
    quick = ctx.config.quick
    N = 16 if quick else 512
    lengths = (4, 12) if quick else (40, 200)
    scheme = "midpoint"
    rows, results = [], []
    for steps in lengths:
        r = measure(N, steps, scheme)
        results.append(r)
        state = r["state"]
        rss = max(0.0, r["hwm"] - r["rss_base"])
        rows.append(
            (
                str(N),
                str(steps),
                mebibytes(state),
                f"{mebibytes(rss)} ({rss / state:.1f} states)",
                f"{mebibytes(r['traced'])} ({r['traced'] / state:.1f} states)",
                mebibytes((steps + 1) * state),
                f"{r['seconds']:.1f} s",
            )
        )
    table = Table(
        (
            "N",
            "steps",
            "one state",
            "peak RSS increase",
            "tracemalloc peak",
            "every state in memory would be",
            "stepping",
        ),
        tuple(rows),
        caption=f"Euler–Zeitlin, {scheme}, rms-1 vorticity, fluid time, h = 1/N, "
        "integrate(..., out=path), save_every = 1 (every state goes to the file).",
    )
    worst = max(max(r["hwm"] - r["rss_base"], r["traced"]) / r["state"] for r in results)
    target = TargetCheck(
        target=f"streamed Euler–Zeitlin run at N = {N}: peak memory ≤ {TARGET_STATES:g} states",
        measured=f"{worst:.1f} states at most (peak RSS increase and tracemalloc peak, "
        f"{lengths[0]} and {lengths[1]} steps)",
        met=worst <= TARGET_STATES,
        gap="" if worst <= TARGET_STATES else f"{worst / TARGET_STATES:.1f}× over",
        limit="the solve's working set and the write buffers; the peak does not grow with "
        "the run's length, so a 10⁵-step run needs the same",
    )
    notes = [
        "Peak RSS increase: VmHWM after the run (reset through /proc/self/clear_refs before "
        "it) minus VmRSS before it, in a fresh process after a 2-step warm-up that builds "
        "the plugin's caches; tracemalloc sees numpy's buffers.",
        "Without out=, integrate keeps every saved state in memory and refuses a run whose "
        "states exceed half the available memory, naming save_every and out= as the fixes.",
    ]
    if not results[0]["reset"]:
        notes.append("/proc/self/clear_refs was not writable: the RSS peak includes the warm-up.")
    return Section(
        title=title,
        intro='`integrate(..., out="run.h5")` streams every saved state into the trajectory '
        "format of `lieflow run` (resumable with `resume=True`) and keeps one chunk of steps "
        "in memory; the returned Solution holds the first and last states and the per-step "
        "diagnostics.",
        tables=(table,),
        targets=(target,),
        notes=tuple(notes),
        seconds=time.perf_counter() - start,
    )
