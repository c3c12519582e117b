"""``python -m benchmarks``: see :mod:`benchmarks.cli`.

BLAS runs single-threaded unless ``OPENBLAS_NUM_THREADS`` (or ``OMP_NUM_THREADS``) says
otherwise: on a shared 2-core machine OpenBLAS's threads spin against other jobs and make
small products 10–80× slower at random (measured: DOP853 on Euler–Zeitlin N = 64, 9.3 s with
default threads under load against 0.12 s with one thread), which no interleaving averages
out. It must be set before numpy is imported, hence here.
"""

import os

if "OMP_NUM_THREADS" not in os.environ:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from benchmarks.cli import main

raise SystemExit(main())
