"""The controller log: JSON Lines, one record per line, flushed after each (docs/controller_log.md)."""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["ControllerLog"]

log = logging.getLogger("mfg_autopilot")


class ControllerLog:
    """JSON Lines: one object per line, flushed after each; ``type`` is start | event | step | end."""

    def __init__(self, path: str | None) -> None:
        self._fh = None
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(path, "a", buffering=1, encoding="utf-8")
        self._lock = threading.Lock()

    def write(self, record: dict) -> None:
        if self._fh is None:
            return
        line = json.dumps(record, separators=(",", ":"), allow_nan=False, default=_jsonable)
        with self._lock:
            self._fh.write(line + "\n")
            self._fh.flush()

    def event(self, what: str, **kw) -> None:
        log.info("%s %s", what, " ".join(f"{k}={v}" for k, v in kw.items()))
        self.write({"type": "event", "what": what, "wall_s": time.time(), **kw})

    def close(self) -> None:
        if self._fh is not None:
            with self._lock:
                self._fh.close()
                self._fh = None


def _jsonable(x):
    if isinstance(x, np.ndarray):
        if x.ndim > 1:
            return x.tolist()
        v = x.astype(float).ravel()
        return v.tolist() if np.isfinite(v).all() else [None if not math.isfinite(f) else f for f in v.tolist()]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x)}")
