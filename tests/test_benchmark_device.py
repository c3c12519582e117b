"""The GPU benchmark script, dry-run on the CPU (array_api_strict arrays: the device path)."""

from __future__ import annotations

import pytest
from helpers import needs_zeitlin

pytest.importorskip("array_api_strict")

from benchmarks import device


@needs_zeitlin
def test_dry_run_prints_the_table_and_agrees_with_the_cpu_engine(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """JAX on the CPU (the traced engine and the hand-written yardstick) and
    array_api_strict (the eager rows): every row agrees with the numpy engine."""
    pytest.importorskip("jax")
    assert device.main(["--dry-run"]) == 0
    out = capsys.readouterr().out
    table = out[out.index("| N | h |") :]
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in table.splitlines()
            if line.startswith("| 16 ")]  # fmt: skip
    engines: dict[str, int] = {}
    eager: dict[tuple[str, str], dict[str, float]] = {}
    for _, h, scheme, dtype, engine, ms, updates, per_update, per_time, diff in rows:
        assert h == "1/128" and scheme in ("midpoint", "gauss2")
        assert float(ms) > 0 and float(per_update) > 0 and 1 <= float(updates) < 50
        # ms per unit time = 128 ms per step, each printed rounded (0.01 ms, 1 ms)
        assert abs(float(per_time) - 128 * float(ms)) <= 128 * 0.005 + 0.5
        assert float(diff) <= (1e-13 if dtype == "complex128" else 1e-5), (engine, scheme, dtype)
        kind = engine.split(",")[0]
        engines[kind] = engines.get(kind, 0) + 1
        if kind == "eager":
            eager.setdefault((scheme, dtype), {})[engine] = float(updates)
    assert engines["traced"] >= 4 and engines["hand-written jit"] == 2 and engines["eager"] == 8
    for counts in eager.values():  # a group of k updates is read at once: no fewer
        one, four = counts["eager, check every 1"], counts["eager, check every 4"]
        assert one <= four < one + 4


def test_without_a_gpu_library_it_says_so(capsys: pytest.CaptureFixture[str]) -> None:
    if device.select("auto") is not None:
        pytest.skip("a GPU is present")
    assert device.main(["--library", "cupy"]) == 2
    assert "no engine runs here" in capsys.readouterr().err


@needs_zeitlin
def test_the_cpu_floor_benchmark_prints_its_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import floor

    assert floor.main(["--sizes", "16", "--steps", "2", "--repeats", "1", "--cpu-time"]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 16 ")]
    cells = [c.strip() for c in row[0].split("|")[1:-1]]
    assert len(cells) == 8 and float(cells[-1]) > 0 and float(cells[1]) >= 1


@needs_zeitlin
def test_the_anderson_benchmark_prints_its_rows(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import anderson

    argv = ["--sizes", "16", "--inv-h", "32", "--steps", "1", "--repeats", "1", "--no-small"]
    assert anderson.main(argv) == 0
    out = capsys.readouterr().out
    row = [line for line in out.splitlines() if line.startswith("| Euler–Zeitlin N = 16 ")]
    cells = [c.strip() for c in row[0].split("|")[1:-1]]
    # below anderson.MIN_SIZE: the same updates as plain
    assert len(cells) == 7 and cells[2] == cells[3] and float(cells[-2]) > 0
    assert "slowest row per step" in out
