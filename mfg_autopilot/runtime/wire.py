"""The swarm exchange's wire contract: key expressions, the state payload, and the exchange's errors.

No zenoh here: what two vehicles must agree on to talk (docs/zenoh.md), testable without a
session. :mod:`.exchange` moves these bytes over Zenoh.

Key expressions:

- ``mfg/<swarm>/state/<vehicle_id>``  state payloads (:class:`StateMsg`, layout below), one put
  per control step.
- ``mfg/<swarm>/alive/<vehicle_id>``  liveliness token held for the session's lifetime.
- ``mfg/<swarm>/init/<vehicle_id>``   queryable answering the vehicle's step-0 state once
  :meth:`SwarmExchange.initial_exchange` has been called (so late joiners get earlier states).
Payload v1 (56 bytes, little-endian, ``struct`` format ``<2sBBIqd4d``):

====== ==== ======== =============================================================
offset size type     field
====== ==== ======== =============================================================
0      2    bytes    magic ``b"MF"``
2      1    u8       version = 1
3      1    u8       flags = 0 (reserved)
4      4    u32      vehicle_id (0-based instance index)
8      8    i64      step (control step, >= 0; 0 = the t = 0 exchange)
16     8    f64      time_s (simulated time of the state, s; step 0 in real time: the Unix time it was published)
24     32   4 x f64  state [x_m, y_m, vx_m_s, vy_m_s] in the swarm frame (N, E; docs/mission.md)
====== ==== ======== =============================================================
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass
from typing import Iterable, Sequence

__all__ = ["MAX_STEP", "PAYLOAD_FORMAT", "PAYLOAD_MAGIC", "PAYLOAD_SIZE", "PAYLOAD_VERSION", "ExchangeError", "ExchangeStopped",
           "ExchangeTimeout", "PayloadError", "StateMsg", "alive_key", "init_key", "state_key"]

PAYLOAD_MAGIC = b"MF"
PAYLOAD_VERSION = 1
PAYLOAD_FORMAT = "<2sBBIqd4d"
PAYLOAD_SIZE = struct.calcsize(PAYLOAD_FORMAT)  # 56
_PAYLOAD = struct.Struct(PAYLOAD_FORMAT)
_U32_MAX = 2**32 - 1
# Highest valid step (2**53 - 1: exact as a float64 / JSON number). Larger steps are rejected
# ("range"): an absurd step would otherwise pin a sender's latest state.
MAX_STEP = 2**53 - 1
_SWARM_RE = re.compile(r"^[A-Za-z0-9_\-.]+$")


# --------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------
class ExchangeError(RuntimeError):
    """A failure of the Zenoh swarm exchange (session, membership or protocol)."""


class ExchangeStopped(ExchangeError):
    """A wait of the exchange was abandoned because its ``stop`` event was set (a signal)."""


class ExchangeTimeout(ExchangeError, TimeoutError):
    """A wait of the exchange ran past its deadline. ``missing`` names the vehicles waited for."""

    def __init__(self, message: str, missing: Iterable[int] = ()):
        super().__init__(message)
        self.missing: tuple[int, ...] = tuple(sorted(missing))


class PayloadError(ExchangeError, ValueError):
    """A state payload does not parse. ``kind`` is one of: length, magic, version, flags,
    non_finite, range; on the wire also key (key id != payload id, or not a canonical
    decimal) and unknown_id (a vehicle id outside the swarm's expected ids)."""

    def __init__(self, kind: str, message: str):
        super().__init__(f"bad state payload ({kind}): {message}")
        self.kind = kind


# --------------------------------------------------------------------------------------
# Key expressions
# --------------------------------------------------------------------------------------
def _check_swarm(swarm: str) -> str:
    if not _SWARM_RE.match(swarm):
        raise ValueError(f"swarm name must match {_SWARM_RE.pattern} (one key chunk), got {swarm!r}")
    return swarm


def state_key(swarm: str, vehicle_id: int | str) -> str:
    return f"mfg/{_check_swarm(swarm)}/state/{vehicle_id}"


def alive_key(swarm: str, vehicle_id: int | str) -> str:
    return f"mfg/{_check_swarm(swarm)}/alive/{vehicle_id}"


def init_key(swarm: str, vehicle_id: int | str) -> str:
    return f"mfg/{_check_swarm(swarm)}/init/{vehicle_id}"


def _id_from_key(key: str) -> int | None:
    """The vehicle id of a key's last chunk, if it is a canonical decimal ("7", not "07")."""
    last = key.rsplit("/", 1)[-1]
    if not (last.isascii() and last.isdigit()) or str(int(last)) != last:
        return None
    return int(last)


# --------------------------------------------------------------------------------------
# Payload
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StateMsg:
    """One vehicle's state at one control step (payload v1, see the module docstring).

    ``state`` is ``[x_m, y_m, vx_m_s, vy_m_s]`` in the swarm frame (north, east: a mission's datum; without one the vehicles' shared LOCAL_NED).
    """

    vehicle_id: int
    step: int
    time_s: float
    state: tuple[float, float, float, float]

    def encode(self) -> bytes:
        st = tuple(float(v) for v in self.state)
        if len(st) != 4:
            raise PayloadError("length", f"state must have 4 entries, got {len(st)}")
        if not (0 <= int(self.vehicle_id) <= _U32_MAX):
            raise PayloadError("range", f"vehicle_id {self.vehicle_id} not in u32")
        if not (0 <= int(self.step) <= MAX_STEP):
            raise PayloadError("range", f"step {self.step} not in [0, {MAX_STEP}]")
        if not all(math.isfinite(v) for v in (float(self.time_s), *st)):
            raise PayloadError("non_finite", f"non-finite time/state {self.time_s} {st}")
        return _PAYLOAD.pack(PAYLOAD_MAGIC, PAYLOAD_VERSION, 0, int(self.vehicle_id),
                             int(self.step), float(self.time_s), *st)

    @staticmethod
    def decode(b: bytes) -> "StateMsg":
        """Parse a payload; raise :class:`PayloadError` on anything malformed."""
        if len(b) != PAYLOAD_SIZE:
            raise PayloadError("length", f"{len(b)} bytes, expected {PAYLOAD_SIZE}")
        magic, version, flags, vid, step, time_s, x, y, vx, vy = _PAYLOAD.unpack(b)
        if magic != PAYLOAD_MAGIC:
            raise PayloadError("magic", f"magic {magic!r}, expected {PAYLOAD_MAGIC!r}")
        if version != PAYLOAD_VERSION:
            raise PayloadError("version", f"version {version}, expected {PAYLOAD_VERSION}")
        if flags != 0:
            raise PayloadError("flags", f"flags {flags:#x}, expected 0")
        if not (0 <= step <= MAX_STEP):
            raise PayloadError("range", f"step {step} not in [0, {MAX_STEP}]")
        if not all(math.isfinite(v) for v in (time_s, x, y, vx, vy)):
            raise PayloadError("non_finite", f"time/state not finite: {time_s} {(x, y, vx, vy)}")
        return StateMsg(vid, step, time_s, (x, y, vx, vy))

    @property
    def pos_m(self) -> tuple[float, float]:
        return (self.state[0], self.state[1])


def _as_state(state: Sequence[float]) -> tuple[float, float, float, float]:
    st = tuple(float(v) for v in state)
    if len(st) != 4:
        raise ValueError(f"state must be [x_m, y_m, vx_m_s, vy_m_s], got {len(st)} entries")
    return st  # type: ignore[return-value]
