"""First-run compile time of the compiled engine (issue 37 item 11).

``python -m benchmarks.compile_time [--cases so3-midpoint,...] [--save DIR]`` runs each
case in a fresh interpreter with an empty temporary numba cache (``NUMBA_CACHE_DIR``, which
:func:`lieflow.numba_cache.cache_directory` follows), then a second fresh interpreter on the
cache the first one left, and prints per case the wall and CPU seconds of each process
(CPU: user + system of the child, ``resource.getrusage(RUSAGE_CHILDREN)``, robust to other
jobs on the machine; wall is not) and the seconds of the ``lf.integrate`` call inside it.

The cases, each ``lf.integrate(..., engine="compiled")`` of a few steps with the update in
conjugation form (``lf.schemes.get(name, update="conjugation")``):

* ``so3-midpoint``: the rigid body on so(3), midpoint (``sydirk``, float64);
* ``so10-gauss2``: the generalized rigid body on so(10), Gauss-2 (reduced form, float64);
* ``zeitlin16-gauss2``: Euler–Zeitlin N = 16, Gauss-2 (reduced form, complex128, the
  plugin's compiled ``B``).

Target (issue 37): the first run of each ≤ 20 s on an idle 2-core machine.
``--save DIR`` writes each first run's states to ``DIR/<case>.npy`` (to compare two
versions of the loops bit for bit).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.timing import run_process

#: The cases: name -> (system, scheme, steps).
CASES = {
    "so3-midpoint": "midpoint",
    "so10-gauss2": "gauss2",
    "zeitlin16-gauss2": "gauss2",
}
STEPS = 5


def _child(case: str, save: str) -> None:
    """Run ``case`` in this process and print the seconds of the ``lf.integrate`` call."""
    import numpy as np

    import lieflow as lf

    scheme = lf.schemes.get(CASES[case], update="conjugation")
    system: Any
    if case == "so3-midpoint":
        system = lf.systems.RigidBody((1.0, 2.0, 3.0))
        W0, h = lf.algebras.SO(3).random(seed=0), 0.1
    elif case == "so10-gauss2":
        system = lf.systems.GeneralizedRigidBody.random_inertia(10, seed=0)
        W0, h = lf.algebras.SO(10).random(seed=1), 0.01
    else:
        import lieflow_zeitlin as lz

        system = lz.EulerZeitlin(16)
        W0, h = lz.random_vorticity(16, 6, seed=1), 0.05
    start = time.perf_counter()
    sol = lf.integrate(system, scheme, W0, h, steps=STEPS, engine="compiled")
    seconds = time.perf_counter() - start
    if save:
        np.save(Path(save) / f"{case}.npy", sol.W)
    print(json.dumps({"integrate": seconds}))


def _process(case: str, cache: str, save: str) -> dict[str, float]:
    """Wall and CPU seconds of one fresh interpreter running ``case`` on the numba cache
    ``cache``, and the seconds of its ``lf.integrate`` call."""
    env = {**os.environ, "NUMBA_CACHE_DIR": cache, "OPENBLAS_NUM_THREADS": "1"}
    timed = run_process(
        [sys.executable, "-m", "benchmarks.compile_time", "--child", case, "--save", save],
        capture_output=True, text=True, check=True, env=env,
    )  # fmt: skip
    inner = json.loads(timed.done.stdout.strip().splitlines()[-1])
    return {"wall": timed.wall, "cpu": timed.cpu, "integrate": inner["integrate"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--save", default="", help="write each first run's states here")
    parser.add_argument("--child", default="", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args.child, args.save)
        return 0
    if args.save:
        Path(args.save).mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {os.getloadavg()[0]:.2f} (2-core target: idle)")
    print("| case | first: wall s | first: CPU s | first: integrate s "
          "| warm: wall s | warm: CPU s |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for case in args.cases.split(","):
        with tempfile.TemporaryDirectory(prefix="lieflow-numba-") as cache:
            first = _process(case, cache, args.save)
            warm = _process(case, cache, "")
        print(
            f"| {case} | {first['wall']:.1f} | {first['cpu']:.1f} | {first['integrate']:.1f} "
            f"| {warm['wall']:.1f} | {warm['cpu']:.1f} |",
            flush=True,
        )
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
