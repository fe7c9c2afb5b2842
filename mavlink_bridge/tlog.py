"""MAVLink telemetry log (.tlog) in pymavlink's format: each record is an 8-byte
big-endian UNIX time in microseconds followed by one raw MAVLink packet (issue 3).

The writer flushes at least every ``flush_interval_s`` (so a killed process loses at
most about that much) and on ``close``; it is safe to call from several threads.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from pathlib import Path

__all__ = ["TlogWriter", "read_tlog"]

log = logging.getLogger(__name__)
_STAMP = struct.Struct(">Q")


class TlogWriter:
    def __init__(self, path: str | Path, flush_interval_s: float = 1.0) -> None:
        if not (flush_interval_s > 0):
            raise ValueError(f"flush_interval_s must be > 0, got {flush_interval_s}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")
        self._lock = threading.Lock()
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self.n_records = 0

    def write(self, packet: bytes, unix_time_s: float | None = None) -> None:
        """Append one packet stamped with ``unix_time_s`` (default: now)."""
        if not packet:
            return
        t_us = int((time.time() if unix_time_s is None else unix_time_s) * 1e6)
        with self._lock:
            if self._f.closed:
                return
            self._f.write(_STAMP.pack(t_us) + packet)
            self.n_records += 1
        self.maybe_flush()

    def write_many(self, packets: list[bytes], unix_time_s: float | None = None) -> None:
        """Append several packets with one stamp (sent or received together): one record each,
        as ``write`` would give them, under one lock and one file write."""
        packets = [p for p in packets if p]
        if not packets:
            return
        stamp = _STAMP.pack(int((time.time() if unix_time_s is None else unix_time_s) * 1e6))
        with self._lock:
            if self._f.closed:
                return
            self._f.write(stamp + stamp.join(packets))
            self.n_records += len(packets)
        self.maybe_flush()

    def maybe_flush(self) -> None:
        """Flush if ``flush_interval_s`` has passed since the last flush."""
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval_s:
            self.flush()

    def flush(self) -> None:
        with self._lock:
            if not self._f.closed:
                self._f.flush()
            self._last_flush = time.monotonic()

    def close(self) -> None:
        with self._lock:
            if not self._f.closed:
                self._f.flush()
                self._f.close()

    def __enter__(self) -> "TlogWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_tlog(path: str | Path, only: tuple[str, ...] | None = None):
    """All packets of a tlog as a list of ``(unix_time_s, Received)``, read with
    pymavlink's ``mavutil.mavlink_connection`` (the pymavlink tools' reader). With ``only``
    (MAVLink message names, e.g. ``("LOCAL_POSITION_NED",)``) just those packets, framed
    from the record headers and parsed alone: much faster on a long tlog."""
    from .codec import MAVLINK_MSG_ID, read_tlog_raw, read_tlog_selected

    if only is not None:
        ids = frozenset(MAVLINK_MSG_ID[name] for name in only)
        got = read_tlog_selected(str(path), ids)
        if got is not None:
            return got
        log.warning("%s does not frame as TlogWriter records; reading it with pymavlink", path)
        return [(t, r) for t, r in read_tlog_raw(str(path)) if r.msg.MSG_NAME in only]
    return list(read_tlog_raw(str(path)))
