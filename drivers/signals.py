"""Signal handlers that stop a long-running command without deadlocking it.

A Python signal handler runs in the main thread between two bytecodes. A main loop that waits on a
`threading.Event` (`stop.wait(0.05)`) holds that Event's internal lock for a moment on every wait; a handler that
calls `stop.set()` while it is held waits for a lock its own thread holds, for good. `vio run` once hung that
way for 10 s after SIGTERM (killed; no status written, a map to save would have been lost). The handler here only
starts a thread that does the stopping, which takes the lock once the main thread lets go of it."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any


def stop_on_signal(request_stop: Callable[[int], Any]) -> Callable[[int, Any], None]:
    """A handler for signal.signal() that calls `request_stop(signum)` in a thread of its own."""
    def handler(signum: int, _frame: Any) -> None:
        threading.Thread(target=request_stop, args=(signum,), name=f"signal-{signum}", daemon=True).start()
    return handler
