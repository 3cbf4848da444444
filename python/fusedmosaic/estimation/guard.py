"""One call at a time on a streaming mosaicker (SequentialMosaicker, RobotPriorMosaicker)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def exclusive_call(lock: threading.Lock, owner: str, what: str) -> Iterator[None]:
    """Holds ``lock`` for the duration of the call ``owner.what``.

    A mosaicker's calls change shared state (its window, filter and anchors), so they are not
    re-entrant. A second thread calling while one call runs is a bug in the caller's loop, and
    waiting would hide it (and stall a capture thread), so it raises ``RuntimeError`` at once;
    calls from different threads one after the other are fine.
    """
    if not lock.acquire(blocking=False):
        raise RuntimeError(
            f"{owner}.{what} called while another call is running on this mosaicker (from "
            "another thread): it is not re-entrant; serialise the calls (e.g. one capture "
            "thread, or a lock around add_frame)"
        )
    try:
        yield
    finally:
        lock.release()
