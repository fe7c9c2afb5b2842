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
from dataclasses import dataclass
from pathlib import Path

from .errors import BridgeError

__all__ = ["TlogWriter", "read_tlog", "check_tlog", "TlogCheck", "TlogError"]

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


class TlogError(BridgeError, ValueError):
    """A tlog that does not frame as records (8-byte stamp + one MAVLink 1/2 packet): corrupt or truncated."""


@dataclass(frozen=True)
class TlogCheck:
    """What :func:`check_tlog` found: every record framed."""

    n_records: int
    first_unix_s: float | None
    last_unix_s: float | None


_EARLIEST_US = 946_684_800 * 1_000_000      # 2000-01-01: a stamp before it is not a tlog stamp
_LATEST_US = 4_102_444_800 * 1_000_000      # 2100-01-01


def check_tlog(path: str | Path) -> TlogCheck:
    """Frame every record of a tlog (``TlogWriter``'s format) without parsing the packets; raise
    :class:`TlogError` naming the byte offset if a record is cut short (a truncated file), a packet
    does not start with a MAVLink 1 (0xFE) or 2 (0xFD) magic byte, or a stamp is not a plausible
    UNIX time in microseconds (2000-2100), i.e. the file is not a tlog or is corrupt. The packets'
    checksums are not verified (pymavlink does that when it reads them)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise TlogError(f"{p}: cannot read: {exc}") from None
    n, i, count = len(data), 0, 0
    first = last = None
    while i < n:
        j = i + _STAMP.size
        if j + 2 > n:
            raise TlogError(f"{p}: truncated: {n - i} byte(s) at offset {i} are not a whole record")
        t_us = _STAMP.unpack_from(data, i)[0]
        if not (_EARLIEST_US <= t_us <= _LATEST_US):
            raise TlogError(f"{p}: corrupt: record {count} at offset {i} has no UNIX time stamp ({t_us} us)")
        magic = data[j]
        if magic == 0xFD:
            if j + 3 > n:
                raise TlogError(f"{p}: truncated: record {count} at offset {i} is cut short")
            size = 10 + data[j + 1] + 2 + (13 if data[j + 2] & 0x01 else 0)
        elif magic == 0xFE:
            size = 6 + data[j + 1] + 2
        else:
            raise TlogError(f"{p}: corrupt: record {count} at offset {i} does not hold a MAVLink packet "
                            f"(byte 0x{magic:02X}, not 0xFD or 0xFE)")
        if j + size > n:
            raise TlogError(f"{p}: truncated: record {count} at offset {i} needs {_STAMP.size + size} bytes, "
                            f"the file ends {n - i} bytes after its start")
        first = t_us * 1e-6 if first is None else first
        last = t_us * 1e-6
        count += 1
        i = j + size
    return TlogCheck(count, first, last)
