"""lieflow's benchmark suite: speed figures as ratios against baselines run in the same process.

Run it with one command from the repository root::

    python -m benchmarks            # full run (~15 min on 2 cores), writes docs/benchmarks.md
    python -m benchmarks --quick    # tiny sizes, well under a minute

Every speed figure is a ratio of two timings taken in the same process on the same input,
interleaved, medians of the rounds (never the fastest), because shared machines are noisy;
BLAS runs single-threaded unless the environment says otherwise (``__main__``). The
baselines are

* the paper's block algorithm *as published* (:mod:`benchmarks.paper_baseline`): dense
  ``sn×sn`` block matrices built every iteration, fixed-point iteration from a cold start,
  the same relative stopping rule;
* the plain-numpy reduced stage form (:class:`benchmarks.paper_baseline.PlainScheme`):
  lieflow's algorithm as a plain prototype, so that the implementation is measured apart
  from the algorithm change;
* scipy's ``solve_ivp`` (DOP853, Radau) at equal energy error
  (:mod:`benchmarks.suites.scipy_work_precision`);
* lieflow's own earlier formulations where an optimization replaced one: the block form of
  :class:`lieflow.schemes.BlockGauss` (``3s²`` products) against the reduced stage form
  (``3s``), warm starts off against on, plain fixed-point against Anderson acceleration;
* published wall times of the paper (Tables 1, 3, 5) for the reproduction suite.
"""
