"""What the reproductions write besides their own tables (:mod:`lieflow.app.reproduce`,
:mod:`lieflow.app.studies`): their output directory, Markdown tables, and a description of
the machine the numbers were measured on."""

from __future__ import annotations

import os
import platform
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError
from .io import environment

__all__ = ["machine_description", "md_table", "output_dir"]


def machine_description() -> dict[str, str]:
    """Platform, CPU count, Python, numpy/scipy versions and the BLAS numpy was built with."""
    info = environment()
    info["processor"] = platform.processor() or platform.machine()
    info["cpu_count"] = str(os.cpu_count())
    try:
        config = np.show_config(mode="dicts")  # numpy >= 1.25
        blas = config["Build Dependencies"]["blas"]
        info["blas"] = f"{blas.get('name', '?')} {blas.get('version', '')}".strip()
    except Exception:  # pragma: no cover - older numpy or unusual builds
        info["blas"] = "unknown"
    threads = [
        f"{var}={os.environ[var]}"
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
        if var in os.environ
    ]
    info["blas_threads"] = ", ".join(threads) or "default"
    return info


def output_dir(out_dir: Path | str) -> Path:
    """Create the output directory, or raise :class:`InputError` saying why it cannot be."""
    out = Path(out_dir).expanduser()
    for parent in (out, *out.parents):
        if parent.exists():
            if not parent.is_dir():
                raise InputError(
                    f"reproduce: output directory {str(out)!r}: {str(parent)!r} is a file, not "
                    "a directory. To fix: give a directory with --out (it is created if "
                    "missing)"
                )
            break
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".lieflow-write-test-{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        raise InputError(
            f"reproduce: cannot write to {str(out)!r}: {exc.strerror or exc}. To fix: give a "
            "directory you can write to with --out"
        ) from None
    return out


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A Markdown table of ``rows`` under ``header``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)
