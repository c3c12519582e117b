"""The rules the numpy path runs as plain Python, compiled for the compiled engine's loops
(the same function objects; imported with :mod:`lieflow.engines._compiled_loops`):

* the stopping rule, :func:`lieflow.solvers.fixed_point.stopping_verdict`: :data:`verdict`
  (cached, for calls from Python) and the loops' own compilation of it, which
  :func:`_judge` calls after the :class:`~lieflow.solvers.fixed_point.IterationMonitor`
  bookkeeping of an update;
* the warm start's trust rule (:func:`lieflow.warm_start.trusted_points`) and the cold retry
  of a failed warm solve (:func:`lieflow.schemes.base.retries_cold`);
* the Newton–Schulz iteration's decisions and unitarity test of the conjugation updates
  (:func:`lieflow.schemes.conjugation.newton_schulz_step`,
  :func:`~lieflow.schemes.conjugation.skew_to_roundoff`);
* the layout of the loops' ``tolerances``, ``settings`` and ``warm_counts`` arrays
  (:data:`RTOL`, :data:`MAX_ITER`, :data:`FILLED`; :func:`stopping_arrays`).

Their modules' source, and this module's, are part of the cache key of the entry points
(:data:`lieflow.engines._compiled_loops.SHARED_KEY`), so that editing a rule recompiles them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import warm_start
from ..schemes import base, conjugation
from ..solvers import fixed_point
from ._numba_jit import _inlined_by_llvm, _inner, _jit

_TINY = float(np.finfo(float).tiny)


# ------------------------------------------------------------------ the shared rules
# The rules the numpy path runs as plain Python, compiled here (the same function objects):
# the stopping rule, the warm start's trust rule, the cold retry, and the Newton–Schulz
# iteration's decisions and unitarity test of the conjugation updates.

#: :func:`lieflow.solvers.fixed_point.stopping_verdict`, compiled (the same function object):
#: cached, for calls from Python; the loops inline their own compilation of it (``_rule``).
verdict = _jit(fixed_point.stopping_verdict)
_rule = _inner(fixed_point.stopping_verdict)
_trusted_points = _inner(warm_start.trusted_points)
_retries_cold = _inner(base.retries_cold)
_schulz_step = _inner(conjugation.newton_schulz_step)
_skew_to_roundoff_rule = _inner(conjugation.skew_to_roundoff)

#: Entries of the loops' ``tolerances`` (float64): the stopping rule's
#: (:class:`~lieflow.solvers.StoppingRule`) ...
RTOL, ATOL, ROUNDOFF_FLOOR, DIVERGENCE_FACTOR = range(4)
#: ... and of their ``settings`` (int64): the stopping rule's counts and its rate test
#: (``StoppingRule.project``), then whether a failed warm-started solve is retried cold
#: (:func:`~lieflow.schemes.base.retries_cold`) and whether steps are warm-started.
MAX_ITER, PATIENCE, WINDOW, RATE_TEST, RETRY_COLD, WARM_STARTS = range(6)
#: Entries of their ``warm_counts`` (int64, updated in place): how many solutions the
#: history holds, and how many the next prediction extrapolates from
#: (:class:`~lieflow.warm_start.WarmStart`).
FILLED, TRUSTED = range(2)


def stopping_arrays(
    rule: fixed_point.StoppingRule, retry_cold: bool, warm_starts: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The loops' ``tolerances`` and ``settings`` (see :data:`RTOL`, :data:`MAX_ITER`) for
    the stopping ``rule`` of a fixed-point solve, whether a failed warm solve is retried
    cold and whether steps are warm-started (writable: the loops' type)."""
    tolerances = np.empty(4)
    tolerances[[RTOL, ATOL, ROUNDOFF_FLOOR, DIVERGENCE_FACTOR]] = (
        rule.rtol, rule.atol, rule.roundoff_floor, rule.divergence_factor,
    )  # fmt: skip
    settings = np.empty(6, dtype=np.int64)
    settings[[MAX_ITER, PATIENCE, WINDOW, RATE_TEST, RETRY_COLD, WARM_STARTS]] = (
        rule.max_iter, rule.patience, rule.window, rule.project, retry_cold, warm_starts,
    )  # fmt: skip
    return tolerances, settings


@_inlined_by_llvm
def _judge(
    step2: float, size2: float, k: int, size0: float, res: Any, tolerances: Any, settings: Any
) -> tuple[int, float]:
    """Record the ``k``-th update, of squared norm ``step2`` to an iterate of squared norm
    ``size2`` (the :class:`~lieflow.solvers.fixed_point.IterationMonitor` bookkeeping),
    and judge it with :data:`verdict`.

    Returns the verdict's code and the (possibly updated) reference size for the growth
    test (``tolerances``, ``settings``: :func:`stopping_arrays`).
    """
    step, size = math.sqrt(step2), math.sqrt(size2)
    if not (math.isfinite(step) and math.isfinite(size)):
        return fixed_point.NON_FINITE, size0
    if k == 1:
        size0 = max(size0, size, _TINY)
    res[k - 1] = step / max(size, _TINY)
    met = step <= tolerances[ATOL] + tolerances[RTOL] * size
    code = _rule(
        res, k, met, size / size0, tolerances[RTOL], tolerances[ROUNDOFF_FLOOR],
        tolerances[DIVERGENCE_FACTOR], settings[MAX_ITER], settings[PATIENCE],
        settings[WINDOW], settings[RATE_TEST] != 0,
    )  # fmt: skip
    return code, size0
