"""lieflow's compiled code is cached in the user's cache directory, never in the installed
package (issue 29.1): numba's files left in ``site-packages/lieflow/__pycache__`` by a
non-editable install survive its uninstall and shadow a later editable install."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

#: The compiled functions of lieflow and of each installed plugin of this repository.
COMPILED = {"lieflow": 2, "lieflow_vortices": 2, "lieflow_zeitlin": 4}

#: Prints where the cache of each compiled function of lieflow and its installed plugins
#: lives (no compilation), then compiles a function of a module in ``sys.argv[1]`` and calls
#: it.
PROBE = """
import importlib.util, json, sys
from lieflow.engines import _compiled_maps, _compiled_rules
from lieflow.numba_cache import cache_directory

sys.path.insert(0, sys.argv[1])
import probe_module

functions = [_compiled_maps.hadamard_B_skew, _compiled_rules.verdict]
if importlib.util.find_spec("lieflow_vortices"):
    import lieflow_vortices._compiled as vortices
    functions += [vortices.vortex_B, vortices.vortex_project]
if importlib.util.find_spec("lieflow_zeitlin"):
    import lieflow_zeitlin._compiled as zeitlin
    from lieflow_zeitlin import _recurrences, laplacian
    functions += [zeitlin.zeitlin_B, _recurrences._harmonic_compiled.dispatcher(),
                  _recurrences._legendre_sweep_compiled.dispatcher(),
                  laplacian.sweep_kernel("d")]
print(json.dumps({
    "directory": str(cache_directory()),
    "paths": [f.stats.cache_path for f in functions],
    "value": probe_module.twice(21.0),
    "probe": probe_module.twice.stats.cache_path,
}))
"""

MODULE = """
from lieflow.numba_cache import cached_njit

@cached_njit
def twice(x):
    return 2.0 * x
"""


def _probe(tmp_path: Path, **env: str) -> dict[str, object]:
    module_dir = tmp_path / "src"
    module_dir.mkdir(exist_ok=True)
    (module_dir / "probe_module.py").write_text(MODULE)
    environ = {
        k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")
    }
    environ.update(env)
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, str(module_dir)],
        env=environ,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    result: dict[str, object] = json.loads(proc.stdout.strip().splitlines()[-1])
    installed = [m for m in COMPILED if importlib.util.find_spec(m) is not None]
    assert len(result["paths"]) == sum(COMPILED[m] for m in installed)  # type: ignore[arg-type]
    return result


def _inside(path: object, directory: Path) -> bool:
    return Path(str(path)).resolve().is_relative_to(directory.resolve())


def test_cache_in_the_xdg_cache_directory_not_the_package(tmp_path: Path) -> None:
    xdg = tmp_path / "xdg"
    out = _probe(tmp_path, XDG_CACHE_HOME=str(xdg))
    assert Path(str(out["directory"])) == xdg / "lieflow" / "numba"
    for path in out["paths"]:  # type: ignore[attr-defined]
        assert _inside(path, xdg / "lieflow" / "numba"), path
        assert "site-packages" not in str(path) and not str(path).endswith("__pycache__")
    assert out["value"] == 42.0
    # the compiled probe was written there, and nothing next to its source
    assert _inside(out["probe"], xdg / "lieflow" / "numba")
    assert list(Path(str(out["probe"])).glob("probe_module.twice-*.nbi"))
    assert not (tmp_path / "src" / "__pycache__").exists() or not list(
        (tmp_path / "src" / "__pycache__").glob("*.nb*")
    )


def test_numba_cache_dir_wins(tmp_path: Path) -> None:
    mine = tmp_path / "mine"
    out = _probe(tmp_path, NUMBA_CACHE_DIR=str(mine), XDG_CACHE_HOME=str(tmp_path / "xdg"))
    assert Path(str(out["directory"])) == mine
    for path in [*out["paths"], out["probe"]]:  # type: ignore[misc]
        assert _inside(path, mine), path


def test_home_cache_by_default_and_in_memory_where_unwritable(tmp_path: Path) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")  # ~/.cache cannot be created below a file
    out = _probe(tmp_path, HOME=str(blocked))
    assert Path(str(out["directory"])) == blocked / ".cache" / "lieflow" / "numba"
    assert out["value"] == 42.0  # compiled in memory
    assert not (tmp_path / "src" / "__pycache__").exists() or not list(
        (tmp_path / "src" / "__pycache__").glob("*.nb*")
    )


#: Compiles ``locked_module.twice`` for one signature through ``cached_njit`` and prints its
#: cache statistics; with ``gate`` it first takes the compile lock, says ``locked`` and waits
#: for a line on stdin before compiling (the other process must find the lock held).
LOCKED = """
import contextlib, json, logging, sys
from lieflow import numba_cache

sys.path.insert(0, sys.argv[1])
import locked_module

if sys.argv[2] == "gate":
    held = numba_cache._compiling

    @contextlib.contextmanager
    def gated(cache, name):
        with held(cache, name):
            print("locked", flush=True)
            sys.stdin.readline()
            yield

    numba_cache._compiling = gated
else:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    numba_cache.COMPILE_WAIT = 120.0  # a broken lock fails the test, it does not hang it
f = numba_cache.cached_njit(locked_module.twice, signature="float64(float64)")
stats = f.stats
print(json.dumps({"value": f(21.0), "hits": sum(stats.cache_hits.values()),
                  "misses": sum(stats.cache_misses.values())}), flush=True)
"""


def test_processes_compiling_one_function_at_once_compile_it_once(tmp_path: Path) -> None:
    """Two processes ask for the same function on an empty cache: the first holds the lock
    (and waits, so the second certainly asks while it is held); the second waits for the
    lock instead of compiling, then loads the first one's result from the disk cache."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "locked_module.py").write_text("def twice(x):\n    return 2.0 * x\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    command = [sys.executable, "-c", LOCKED, str(src)]
    first = subprocess.Popen(
        [*command, "gate"], env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    second = None
    try:
        assert first.stdout is not None and first.stdin is not None
        assert first.stdout.readline().strip() == "locked"
        second = subprocess.Popen(
            [*command, "plain"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        assert second.stderr is not None
        logged = []
        for line in second.stderr:  # until it says it waits (or exits: end of the stream)
            logged.append(line)
            if "waiting for its cache" in line:
                break
        assert "waiting for its cache" in "".join(logged), "".join(logged)
        first.stdin.write("go\n")
        first.stdin.flush()
        out_first, _ = first.communicate(timeout=600)
        out_second, err = second.communicate(timeout=600)
        assert first.returncode == 0 and second.returncode == 0, err
        compiled = json.loads(out_first.strip().splitlines()[-1])
        loaded = json.loads(out_second.strip().splitlines()[-1])
        assert compiled == {"value": 42.0, "hits": 0, "misses": 1}
        assert loaded == {"value": 42.0, "hits": 1, "misses": 0}
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
