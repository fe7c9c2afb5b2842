"""Rate-limited logging of rejected input (issue 10: "each rejection is logged once per
kind, not once per frame"). Used by the mock vehicle and by ``VehicleLink``."""

from __future__ import annotations

import logging
import threading
import time

__all__ = ["RejectLog"]


class RejectLog:
    """The first rejection of each kind is logged with its detail; later ones are counted
    and summarised at most every ``period_s`` (one line: how many more, the latest
    detail). ``counts`` holds the totals; ``summary()`` logs them (e.g. at shutdown).
    Thread-safe."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0, level: int = logging.WARNING) -> None:
        self._log = logger
        self._period_s = period_s
        self._level = level
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}
        self._reported: dict[str, tuple[int, float]] = {}

    def reject(self, kind: str, detail: str) -> None:
        now = time.monotonic()
        with self._lock:
            n = self.counts.get(kind, 0) + 1
            self.counts[kind] = n
            if n == 1:
                self._reported[kind] = (1, now)
                line = ("rejected %s: %s (further ones are counted)", kind, detail)
            else:
                last_n, last_t = self._reported[kind]
                if now - last_t < self._period_s:
                    return
                self._reported[kind] = (n, now)
                line = ("rejected %s: %d more (total %d), latest: %s", kind, n - last_n, n, detail)  # type: ignore[assignment]
        self._log.log(self._level, *line)

    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def summary(self) -> None:
        with self._lock:
            items = list(self.counts.items())
        for kind, n in items:
            self._log.info("rejected %s: %d in total", kind, n)
