"""The world backplane of a mock swarm: physics ground truth for the emulated proximity
sensor (docs/proximity.md), like Gazebo's world for PX4 SITL vehicles.

Every mock of a swarm reports its true state to the world over loopback UDP; the world
answers each mock with the vehicles within the sensor range of it:

    python -m mock_vehicle.world --listen 127.0.0.1:P --n N --sensor-range-m R [--lockstep]

Datagrams (little endian), one header then ``count`` entries:

    header  "<4sBBHIH"  magic b"MFGW", version 1, kind (1 report, 2 answer), vehicle id,
                        time_boot_ms (the vehicle's simulated/boot time of the state), count
    entry   "<H4f"      vehicle id, x_m, y_m, vx_m_s, vy_m_s (float32: LOCAL_POSITION_NED's
                        resolution, so the world sees exactly what the simulator's obs holds)

A report (kind 1) carries one entry, the sender's own state; an answer (kind 2) is sent to
the address the vehicle reported from and carries the sensed vehicles, sorted by id.

Lockstep (``--lockstep``): a barrier. The answer for time t goes out when every present
vehicle has reported t (all N at the start); duplicates and late reports of an answered t
get the same answer again (idempotent, so a mock simply re-sends a report it got no
answer to). If some vehicle has not reported t within ``--deadline-s`` of the first report
of t, the world logs it, answers with that vehicle's last known state (what a sensor would
still see), and stops waiting for it until it reports again.

Real time: every report is answered at once from the latest state of each vehicle, carried
forward at its velocity from the report's arrival to the answer (a sensor sees a vehicle where
it is now, not where it last reported; states older than ``--stale-s`` are dropped).

The in-range rule is ``mock_vehicle.proximity.sensed_pairs`` on all N states in id order,
exactly the simulator's query.
"""

from __future__ import annotations

import argparse
import logging
import math
import select
import signal
import socket
import struct
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from .proximity import sensed_pairs, sensed_rows

__all__ = ["WorldParams", "WorldState", "WorldClient", "Answer", "pack_report", "pack_answer", "unpack", "serve", "main",
           "MAGIC", "KIND_REPORT", "KIND_ANSWER"]

log = logging.getLogger("mock_vehicle.world")

MAGIC = b"MFGW"
VERSION = 1
KIND_REPORT = 1
KIND_ANSWER = 2
_HDR = struct.Struct("<4sBBHIH")
_ENTRY = struct.Struct("<H4f")
_ENTRY_DTYPE = np.dtype([("id", "<u2"), ("state", "<f4", (4,))])     # the same layout, unaligned (18 bytes)
assert _ENTRY_DTYPE.itemsize == _ENTRY.size
MAX_ENTRIES = (65507 - _HDR.size) // _ENTRY.size
_FAR_M = 1e12  # where a vehicle never heard of is put: it pairs with nothing


@dataclass(frozen=True)
class Answer:
    """The sensed set of vehicle ``vehicle_id`` at ``time_boot_ms``: ids (m,), states (m, 4)."""

    vehicle_id: int
    time_boot_ms: int
    ids: np.ndarray
    states: np.ndarray


def pack_report(vehicle_id: int, time_boot_ms: int, state: np.ndarray) -> bytes:
    x, y, vx, vy = np.asarray(state, dtype=np.float64).reshape(4).tolist()
    return _HDR.pack(MAGIC, VERSION, KIND_REPORT, vehicle_id, time_boot_ms & 0xFFFFFFFF, 1) + _ENTRY.pack(vehicle_id, x, y, vx, vy)


def pack_answer(a: Answer) -> bytes:
    if len(a.ids) > MAX_ENTRIES:
        raise ValueError(f"{len(a.ids)} sensed vehicles do not fit one datagram (max {MAX_ENTRIES})")
    entries = np.empty(len(a.ids), dtype=_ENTRY_DTYPE)      # the "<H4f" entries, packed by numpy in one go
    entries["id"] = a.ids
    entries["state"] = np.asarray(a.states, dtype=np.float64).reshape(-1, 4)    # float64 -> float32: round to nearest, as struct
    return _HDR.pack(MAGIC, VERSION, KIND_ANSWER, a.vehicle_id, a.time_boot_ms & 0xFFFFFFFF, len(a.ids)) + entries.tobytes()


def unpack(data: bytes) -> tuple[int, int, int, np.ndarray, np.ndarray]:
    """(kind, vehicle_id, time_boot_ms, ids (m,), states (m, 4) float64 of the float32 values).
    Raises ValueError on anything malformed."""
    if len(data) < _HDR.size:
        raise ValueError(f"datagram of {len(data)} bytes is shorter than the header")
    magic, version, kind, vid, t_ms, count = _HDR.unpack_from(data)
    if magic != MAGIC or version != VERSION or kind not in (KIND_REPORT, KIND_ANSWER):
        raise ValueError(f"not a world datagram (magic {magic!r}, version {version}, kind {kind})")
    if len(data) != _HDR.size + count * _ENTRY.size:
        raise ValueError(f"datagram of {len(data)} bytes does not hold {count} entries")
    if count == 1:                          # a report: struct is cheaper than numpy for one entry
        e = _ENTRY.unpack_from(data, _HDR.size)
        ids, states = np.array([e[0]], dtype=np.int64), np.array([e[1:]], dtype=np.float64)
    else:
        entries = np.frombuffer(data, dtype=_ENTRY_DTYPE, count=count, offset=_HDR.size)
        ids = entries["id"].astype(np.int64)
        states = entries["state"].astype(np.float64)
    if kind == KIND_REPORT and (count != 1 or ids[0] != vid):
        raise ValueError("a report carries exactly the sender's own state")
    if not np.all(np.isfinite(states)):
        raise ValueError("non-finite state")
    return kind, vid, t_ms, ids, states


@dataclass(frozen=True)
class WorldParams:
    n: int
    sensor_range_m: float
    lockstep: bool = True
    deadline_s: float = 60.0     # lockstep: wait this long for every vehicle's report of a time
    stale_s: float = 2.0         # real time: drop states older than this
    keep_times: int = 8          # lockstep: answered times kept for late/duplicate reports

    def __post_init__(self) -> None:
        if not (1 <= self.n <= 65535):
            raise ValueError(f"n must be 1..65535, got {self.n}")
        if not (self.sensor_range_m >= 0 and math.isfinite(self.sensor_range_m)):
            raise ValueError(f"sensor range must be finite and >= 0, got {self.sensor_range_m}")
        if not self.deadline_s > 0:
            raise ValueError(f"deadline must be > 0 s, got {self.deadline_s}")


class WorldState:
    """The world's logic, no sockets: ``report`` and ``poll`` return the answers to send."""

    def __init__(self, params: WorldParams) -> None:
        self.p = params
        self._latest: dict[int, tuple[int, np.ndarray, float]] = {}    # vid -> (t_ms, state, received)
        self._reports: dict[int, dict[int, np.ndarray]] = {}            # lockstep: t -> vid -> state
        self._first_seen: dict[int, float] = {}
        self._answered: dict[int, dict[int, Answer]] = {}               # lockstep: t -> vid -> answer
        self.absent: set[int] = set()
        self.n_reports = 0
        self.n_deadlines = 0

    def report(self, vehicle_id: int, time_boot_ms: int, state: np.ndarray, now: float) -> list[Answer]:
        if not (0 <= vehicle_id < self.p.n):
            raise ValueError(f"vehicle id {vehicle_id} is not in this swarm of {self.p.n}")
        state = np.asarray(state, dtype=np.float64).reshape(4).copy()
        self.n_reports += 1
        prev = self._latest.get(vehicle_id)
        if prev is None or time_boot_ms >= prev[0] or not self.p.lockstep:
            self._latest[vehicle_id] = (time_boot_ms, state, now)
        if not self.p.lockstep:
            return [self._answer_realtime(vehicle_id, time_boot_ms, now)]
        if vehicle_id in self.absent:
            self.absent.discard(vehicle_id)
            log.warning("vehicle %d reports again (t = %d ms): waiting for it from now on", vehicle_id, time_boot_ms)
        done = self._answered.get(time_boot_ms)
        if done is not None:
            return [done[vehicle_id]]
        reps = self._reports.setdefault(time_boot_ms, {})
        reps[vehicle_id] = state
        self._first_seen.setdefault(time_boot_ms, now)
        if all(v in reps for v in range(self.p.n) if v not in self.absent):
            return self._close(time_boot_ms)
        return []

    def poll(self, now: float) -> list[Answer]:
        """Lockstep deadlines: close every time whose first report is older than deadline_s."""
        out: list[Answer] = []
        for t in sorted(t for t, t0 in self._first_seen.items() if now - t0 > self.p.deadline_s):
            missing = [v for v in range(self.p.n) if v not in self._reports[t] and v not in self.absent]
            self.n_deadlines += 1
            log.warning("t = %d ms: no report from vehicle(s) %s within %.1f s; answering with their last known state "
                        "and no longer waiting for them", t, missing, self.p.deadline_s)
            self.absent.update(missing)
            out += self._close(t)
        return out

    def pending_times(self) -> list[int]:
        return sorted(self._reports)

    def _array(self, states: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """All N states in id order (n, 4) and which are known (n,); unknown rows are far away."""
        arr = np.empty((self.p.n, 4))
        known = np.zeros(self.p.n, dtype=bool)
        for v in range(self.p.n):
            if v in states:
                arr[v], known[v] = states[v], True
            else:
                arr[v] = (_FAR_M * (v + 1), _FAR_M, 0.0, 0.0)
        return arr, known

    def _sets(self, vids: list[int], t: int, arr: np.ndarray, known: np.ndarray) -> dict[int, Answer]:
        owner, other = sensed_rows(sensed_pairs(arr, self.p.sensor_range_m))
        keep = known[other] & known[owner]
        owner, other = owner[keep], other[keep]
        bounds = np.searchsorted(owner, np.arange(self.p.n + 1))     # rows are sorted by owner: one slice per vehicle
        sensed = arr[other]
        return {v: Answer(v, t, other[bounds[v]:bounds[v + 1]], sensed[bounds[v]:bounds[v + 1]]) for v in vids}

    def _close(self, t: int) -> list[Answer]:
        """Answer time t: reporters' states of t, everyone else's last known state."""
        reps = self._reports.pop(t, {})
        self._first_seen.pop(t, None)
        states = {v: st for v, (_t, st, _r) in self._latest.items()}
        states.update(reps)
        arr, known = self._array(states)
        answers = self._sets(list(range(self.p.n)), t, arr, known)
        self._answered[t] = answers
        while len(self._answered) > self.p.keep_times:
            self._answered.pop(min(self._answered))
        return [answers[v] for v in reps]

    def _answer_realtime(self, vehicle_id: int, t: int, now: float) -> Answer:
        # a sensor sees the others where they are now: each last report (up to 1 / traffic rate old, 0.2 s at 5 Hz)
        # carried forward at its velocity to this answer (the reporter's own state is its report's). Without it the
        # others looked ~0.3 m behind themselves at 2 m/s, and a formation whose UAVs each saw the others lag braked
        # together, ever further behind its plan (mfg-swarm run --realtime, twenty-seventh session)
        ages = np.zeros(self.p.n)
        states = {}
        for v, (_t, st, r) in self._latest.items():
            if now - r <= self.p.stale_s or v == vehicle_id:
                states[v] = st
                ages[v] = 0.0 if v == vehicle_id else max(0.0, now - r)
        arr, known = self._array(states)
        arr[:, 0:2] += arr[:, 2:4] * ages[:, None]          # unknown rows have age 0 (and no velocity)
        return self._sets([vehicle_id], t, arr, known)[vehicle_id]


def serve(params: WorldParams, listen: tuple[str, int], stop: threading.Event, sock: socket.socket | None = None) -> WorldState:
    """Run the world on UDP ``listen`` until ``stop`` is set."""
    world = WorldState(params)
    own = sock is None
    if sock is None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        sock.bind(listen)
    sock.setblocking(False)
    addr_of: dict[int, tuple] = {}
    bad = 0
    log.info("world on %s:%d: n = %d, sensor range %.3g m, %s", *sock.getsockname()[:2], params.n, params.sensor_range_m,
             "lockstep" if params.lockstep else "real time")

    def send(answers: list[Answer]) -> None:
        for a in answers:
            addr = addr_of.get(a.vehicle_id)
            if addr is not None:
                try:
                    sock.sendto(pack_answer(a), addr)
                except OSError as exc:
                    log.warning("cannot answer vehicle %d at %s: %s", a.vehicle_id, addr, exc)

    try:
        while not stop.is_set():
            r, _, _ = select.select([sock], [], [], 0.1)
            if r:
                for _ in range(1024):
                    try:
                        data, addr = sock.recvfrom(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    try:
                        kind, vid, t_ms, _ids, states = unpack(data)
                        if kind != KIND_REPORT:
                            raise ValueError("only reports are accepted")
                        if not (0 <= vid < params.n):
                            raise ValueError(f"vehicle id {vid} is not in this swarm of {params.n}")
                    except ValueError as exc:
                        bad += 1
                        if bad <= 5 or bad % 1000 == 0:
                            log.warning("ignored datagram from %s (%d so far): %s", addr, bad, exc)
                        continue
                    addr_of[vid] = addr
                    send(world.report(vid, t_ms, states[0], time.monotonic()))
            if params.lockstep:
                send(world.poll(time.monotonic()))
    finally:
        log.info("world stops: %d reports, %d deadlines, %d bad datagrams", world.n_reports, world.n_deadlines, bad)
        if own:
            sock.close()
    return world


class WorldClient:
    """The mock vehicle's end: report states, receive answers (non-blocking, select-able)."""

    def __init__(self, url: str) -> None:
        self.address = parse_world_url(url)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.sock.connect(self.address)
        self.n_bad = 0

    def fileno(self) -> int:
        return self.sock.fileno()

    def report(self, vehicle_id: int, time_boot_ms: int, state: np.ndarray) -> None:
        try:
            self.sock.send(pack_report(vehicle_id, time_boot_ms, np.asarray(state, dtype=np.float32)))
        except OSError as exc:  # e.g. ECONNREFUSED before the world is up: the report is re-sent
            log.debug("world report failed: %s", exc)

    def receive(self) -> list[Answer]:
        out = []
        for _ in range(256):
            try:
                data = self.sock.recv(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # ECONNREFUSED from an earlier send
                continue
            try:
                kind, vid, t_ms, ids, states = unpack(data)
                if kind != KIND_ANSWER:
                    raise ValueError("not an answer")
            except ValueError as exc:
                self.n_bad += 1
                log.warning("ignored world datagram: %s", exc)
                continue
            out.append(Answer(vid, t_ms, ids, states))
        return out

    def close(self) -> None:
        self.sock.close()


def parse_world_url(url: str) -> tuple[str, int]:
    """``udp:127.0.0.1:P`` (or ``127.0.0.1:P``) -> (host, port)."""
    text = url[len("udp:"):] if url.startswith("udp:") else url
    host, _, port = text.rpartition(":")
    try:
        p = int(port)
    except ValueError:
        p = -1
    if not host or not (0 < p < 65536):
        raise ValueError(f"world url must be udp:HOST:PORT, got {url!r}")
    return host, p


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mock-world", description="ground truth for the mock swarm's proximity sensors")
    p.add_argument("--listen", required=True, help="HOST:PORT to listen on (UDP), e.g. 127.0.0.1:14600")
    p.add_argument("--n", type=int, required=True, help="number of vehicles (ids 0..N-1)")
    p.add_argument("--sensor-range-m", type=float, required=True, help="proximity sensor range, m")
    p.add_argument("--lockstep", action="store_true", help="barrier: answer time t once every vehicle reported it")
    p.add_argument("--deadline-s", type=float, default=WorldParams.deadline_s, help="lockstep: wait for a silent vehicle this long")
    p.add_argument("--stale-s", type=float, default=WorldParams.stale_s, help="real time: drop states older than this")
    p.add_argument("--log-level", default="INFO")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s mock-world %(levelname)s %(message)s", stream=sys.stderr)
    try:
        params = WorldParams(args.n, args.sensor_range_m, args.lockstep, args.deadline_s, args.stale_s)
        listen = parse_world_url(args.listen)
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    stop = threading.Event()

    def on_signal(signum, _frame) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        serve(params, listen, stop)
    except OSError as exc:
        log.error("world failed: %s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
