"""Timing contenders on one case: warm-up, interleaved rounds (medians), peak memory."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from lieflow import IsospectralSystem
from lieflow.app import reproduce
from lieflow.app.reproduce import Case

from .contenders import Contender, RunStats
from .timing import Timing, compare, peak_memory


def warm_up(contenders: Sequence[Contender]) -> None:
    """Two untimed steps of every contender on a tiny problem, after the paper's schemes on
    both engines (:func:`lieflow.app.reproduce.warm_up`): first-call costs, numba's
    compilation or cache load of the loops included, which a contender's two steps would
    not pay (``engine="auto"`` runs them on numpy)."""
    reproduce.warm_up(0)
    system, W0 = Case("generalized_rigid_body", "warm-up", 4, 0.01, 2, 1e-14).build(0)
    for contender in contenders:
        contender.run(system, W0, 0.01, 2)


def time_contenders(
    contenders: Sequence[Contender],
    system: IsospectralSystem,
    W0: np.ndarray,
    h: float,
    steps: int,
    repeats: int,
    keep: bool = False,
) -> dict[str, Timing[RunStats]]:
    """Interleaved timings of every contender on the same input, ``repeats`` rounds (the
    page reports their medians)."""
    fns = {c.label: functools.partial(c.run, system, W0, h, steps, keep) for c in contenders}
    return compare(fns, repeats)


def step_memory(contender: Contender, system: IsospectralSystem, W0: np.ndarray, h: float) -> int:
    """Peak bytes allocated by one step of ``contender`` (traced, untimed)."""
    return peak_memory(lambda: contender.run(system, W0, h, 1))


def stats(timing: Timing[RunStats]) -> RunStats:
    """The run statistics of a timing that must have succeeded."""
    return timing.value
