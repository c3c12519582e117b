"""Critical sections that an interrupt cannot split.

A trajectory file's bookkeeping (rows written, states saved, the checkpoint) changes in a few
Python statements. Ctrl-C (``SIGINT``) or ``SIGTERM`` landing between two of them would
leave the writer believing something the file does not hold. Inside :func:`deferred` such a
signal is only recorded; it is delivered to the handler that was in place as soon as the
section ends, so the interrupt still happens — just not half-way.
"""

from __future__ import annotations

import _signal  # signal's C core: what signal.signal calls, without its enum conversions
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

_SIGNALS = (int(signal.SIGINT), int(signal.SIGTERM))


@contextmanager
def deferred() -> Iterator[None]:
    """Hold ``SIGINT`` and ``SIGTERM`` until the ``with`` block ends, then re-raise them.

    Outside the main thread (where Python cannot install handlers) it does nothing.

    The handlers are swapped through ``_signal``, the C module :func:`signal.signal` wraps:
    the wrapper converts every handler it is given or returns to an enum, by raising and
    catching an exception for a Python function (14 µs for the four swaps, against 1.3 µs;
    every :func:`lieflow.integrate` call enters this section once).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum: int, _frame: FrameType | None) -> None:
        received.append(signum)

    previous = {s: _signal.signal(s, hold) for s in _SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            _signal.signal(s, handler)
        for s in dict.fromkeys(received):
            signal.raise_signal(s)


class Interrupts:
    """Ctrl-C (``SIGINT``) held while a run sets up its file, raised once it can be handled.

    ``with Interrupts() as stop:`` installs a handler that records every ``SIGINT``; it
    raises :class:`KeyboardInterrupt` only while the run is :meth:`arm`-ed (stepping, inside
    the ``try`` that marks the file "interrupted"). An interrupt that arrives while the file
    is created, opened or closed is held and raised by :meth:`arm` (or :meth:`check`), so the
    file is never left marked "running" and the interrupt is never lost — even when Python
    swallows a ``KeyboardInterrupt`` raised inside a finalizer. ``SIGTERM`` reaches it
    through ``lieflow``'s own SIGTERM handler, which calls the SIGINT handler in force.

    On exit the previous handler is restored; an interrupt recorded but never raised (the
    block ended normally before :meth:`arm`) is raised then, unless :meth:`consume` was
    called. Outside the main thread, or where SIGINT is ignored (a sweep's worker: its
    coordinator stops it), it does nothing.
    """

    def __init__(self) -> None:
        self.received = False
        self._armed = False
        self._consumed = False
        self._previous: Any = None
        self._installed = False

    def __enter__(self) -> Interrupts:
        main = threading.current_thread() is threading.main_thread()
        if main and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        self.received = True
        if self._armed:
            self._armed = False  # once: the handler of the interrupt runs unarmed
            raise KeyboardInterrupt

    def arm(self) -> None:
        """From now on an interrupt raises at once; one already received raises now."""
        self._armed = True
        self.check()

    def disarm(self) -> None:
        """Hold interrupts again (while the file is checkpointed and closed)."""
        self._armed = False

    def check(self) -> None:
        """Raise :class:`KeyboardInterrupt` if an interrupt was received and not raised."""
        if self.received and not self._consumed:
            self._consumed = True
            self._armed = False
            raise KeyboardInterrupt

    def consume(self) -> None:
        """The caller has handled the interrupt (or finished anyway): do not raise it."""
        self._consumed = True

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self._armed = False
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False
        if kind is None:
            self.check()
