"""The GPU benchmark script, dry-run on the CPU (array_api_strict arrays: the device path)."""

from __future__ import annotations

import pytest

pytest.importorskip("array_api_strict")
pytest.importorskip("lieflow_zeitlin")

from benchmarks import device


def test_dry_run_prints_the_table_and_agrees_with_the_cpu_engine(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert device.main(["--dry-run"]) == 0
    out = capsys.readouterr().out
    rows = [
        line.split("|")[1:-1]
        for line in out.splitlines()
        if line.startswith("| 16 ") or line.startswith("| 32 ")
    ]
    assert len(rows) == 2 * 2 * 2 * 3  # N x scheme x dtype x check_every
    updates_at: dict[tuple[str, str, str], dict[int, float]] = {}
    for N, scheme, dtype, k, ms, updates, diff in ([c.strip() for c in r] for r in rows):
        assert scheme in ("midpoint", "gauss2") and float(ms) > 0 and 1 <= float(updates) < 50
        assert float(diff) <= (1e-13 if dtype == "complex128" else 1e-5), (N, scheme, dtype)
        updates_at.setdefault((N, scheme, dtype), {})[int(k)] = float(updates)
    for counts in updates_at.values():  # a group of k updates is read at once: no fewer
        assert counts[1] <= counts[2] <= counts[1] + 1 and counts[1] <= counts[4] < counts[1] + 4


def test_without_a_gpu_library_it_says_so(capsys: pytest.CaptureFixture[str]) -> None:
    if device.select("cupy") is not None:
        pytest.skip("a GPU is present")
    assert device.main(["--library", "cupy"]) == 2
    assert "no GPU array library" in capsys.readouterr().err


def test_the_cpu_floor_benchmark_prints_its_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import floor

    assert floor.main(["--sizes", "16", "--steps", "2", "--repeats", "1", "--cpu-time"]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 16 ")]
    cells = [c.strip() for c in row[0].split("|")[1:-1]]
    assert len(cells) == 8 and float(cells[-1]) > 0 and float(cells[1]) >= 1


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
