"""Rate-limited logging: a flood of the same event writes one line per period and counts the rest.

Every process logs through the standard ``logging`` module; a hostile or broken peer must not be able to fill a
log. Each *kind* of event (a short fixed string, e.g.
``"command_rejected"``) writes at most one line per ``period_s``; the next line written for that kind says how
many were suppressed since the last one, and :attr:`RateLimitedLog.suppressed` keeps the totals.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable

__all__ = ["RateLimitedLog"]


class RateLimitedLog:
    """A logger front that writes at most one line per kind per period.

    Parameters
    ----------
    logger : the logger to write to.
    period_s : shortest time between two lines of one kind [s].
    clock : monotonic clock [s] (injectable for tests).
    """

    def __init__(self, logger: logging.Logger, *, period_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.logger = logger
        self.period_s = float(period_s)
        self.suppressed: Counter[str] = Counter()
        self._clock = clock
        self._next: dict[str, float] = {}
        self._pending: Counter[str] = Counter()
        self._lock = threading.Lock()  # Zenoh callbacks log from several threads

    def log(self, level: int, kind: str, msg: str, *args: object) -> bool:
        """Write ``msg % args`` at ``level`` unless ``kind`` wrote within the period; True if written."""
        now = self._clock()
        with self._lock:
            if now < self._next.get(kind, -float("inf")):
                self._pending[kind] += 1
                self.suppressed[kind] += 1
                return False
            self._next[kind] = now + self.period_s
            n = self._pending.pop(kind, 0)
        if n:
            msg += f" ({n} more like this in the last {self.period_s:g} s not logged)"
        self.logger.log(level, msg, *args)
        return True

    def warning(self, kind: str, msg: str, *args: object) -> bool:
        """``log`` at WARNING level: written unless ``kind`` is over its rate; returns whether it was."""
        return self.log(logging.WARNING, kind, msg, *args)

    def info(self, kind: str, msg: str, *args: object) -> bool:
        """``log`` at INFO level."""
        return self.log(logging.INFO, kind, msg, *args)
