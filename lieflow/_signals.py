"""Critical sections that an interrupt cannot split.

A trajectory file's bookkeeping (rows written, states saved, the checkpoint) changes in a few
Python statements. Ctrl-C (``SIGINT``) or ``SIGTERM`` landing between two of them would
leave the writer believing something the file does not hold. Inside :func:`deferred` such a
signal is only recorded; it is delivered to the handler that was in place as soon as the
section ends, so the interrupt still happens — just not half-way.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def deferred() -> Iterator[None]:
    """Hold ``SIGINT`` and ``SIGTERM`` until the ``with`` block ends, then re-raise them.

    Outside the main thread (where Python cannot install handlers) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum: int, _frame: FrameType | None) -> None:
        received.append(signum)

    previous = {int(s): signal.signal(s, hold) for s in _SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(received):
            signal.raise_signal(s)
