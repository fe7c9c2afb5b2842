"""Zenoh swarm exchange: the t = 0 state exchange (MFG), per-step neighbour gossip (HJB_d),
membership by liveliness, and the communication count (SPEC section 6).

Nothing happens at import time; a session is opened by :class:`SwarmExchange` (a context
manager) from a :class:`~.zenoh_config.ZenohSettings` value built once at the command line. The
wire contract (key expressions, the payload, the errors) is :mod:`.wire`; this module re-exports
it, so ``mfg_autopilot.runtime.exchange`` is the one name a caller needs.

Key expressions and payload: :mod:`.wire` and docs/zenoh.md.

Threading: zenoh invokes callbacks on its own threads. All shared state lives behind one
``threading.Condition``; zenoh is never called while that lock is held (a local put delivers
to local subscribers synchronously on the calling thread). Every wait has a deadline.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Callable, Iterable, Sequence

import zenoh

from mfg_autopilot.runtime.wire import (
    _U32_MAX,
    MAX_STEP,
    PAYLOAD_FORMAT,
    PAYLOAD_MAGIC,
    PAYLOAD_SIZE,
    PAYLOAD_VERSION,
    ExchangeError,
    ExchangeStopped,
    ExchangeTimeout,
    PayloadError,
    StateMsg,
    _as_state,
    _check_swarm,
    _id_from_key,
    alive_key,
    init_key,
    state_key,
)
from mfg_autopilot.runtime.zenoh_config import ZenohSettings, open_session, run_router

__all__ = [
    "MAX_BUFFERED_STEPS",
    "MAX_STEP",
    "PAYLOAD_FORMAT",
    "PAYLOAD_MAGIC",
    "PAYLOAD_SIZE",
    "PAYLOAD_VERSION",
    "ExchangeError",
    "ExchangeStopped",
    "ExchangeTimeout",
    "PayloadError",
    "StateMsg",
    "SwarmExchange",
    "ZenohSettings",
    "alive_key",
    "init_key",
    "open_session",
    "run_router",
    "state_key",
]

log = logging.getLogger(__name__)

# At most this many distinct future steps are buffered for lockstep gossip (memory bound
# against a sender that publishes many future steps); lockstep needs two.
MAX_BUFFERED_STEPS = 1024

# How often initial_exchange re-queries the init queryables of vehicles still missing (s).
INIT_QUERY_PERIOD_S = 0.25
INIT_QUERY_MAX_PERIOD_S = 4.0
"""The t = 0 exchange queries ``init/*`` at once, then after 0.25 s, doubling the period up
to this: every waiting vehicle's query is answered by every vehicle, so a fixed 0.25 s
period costs O(N^2) replies four times a second while the slowest vehicle starts (at
N = 81 through a router that storm kept the exchange from ever completing). States
published after a vehicle subscribed reach it at once by the subscription anyway."""
STOP_POLL_S = 0.25


# --------------------------------------------------------------------------------------
# The exchange
# --------------------------------------------------------------------------------------
class SwarmExchange:
    """One vehicle's view of the swarm over Zenoh.

    Use as a context manager: ``__enter__`` opens the session, declares the liveliness token
    ``mfg/<swarm>/alive/<vehicle_id>``, the state subscriber ``mfg/<swarm>/state/*``, the
    liveliness subscriber (with history) and the init queryable; ``__exit__`` closes the
    session on every exit path.

    Expected vehicles are ids ``0 .. n_expected - 1`` unless ``expected_ids`` is given.

    Communication count (SPEC section 6): ``states_received_by_step[step]`` is the number of
    *distinct other vehicles' states* this vehicle received and kept at that step (all N - 1
    at t = 0 in :meth:`initial_exchange`; in-range ones in :meth:`gossip`);
    ``states_received_total`` is their sum. ``states_heard_total`` counts every well-formed
    state sample that arrived from another vehicle, in range or not, duplicates included.
    """

    def __init__(self, settings: ZenohSettings, swarm: str, vehicle_id: int, n_expected: int,
                 *, expected_ids: Iterable[int] | None = None,
                 on_vehicle_lost: Callable[[int], None] | None = None):
        _check_swarm(swarm)
        if not (0 <= int(vehicle_id) <= _U32_MAX):
            raise ValueError(f"vehicle_id {vehicle_id} not in u32")
        if n_expected < 1:
            raise ValueError(f"n_expected must be >= 1, got {n_expected}")
        self.settings = settings
        self.swarm = swarm
        self.vehicle_id = int(vehicle_id)
        self.expected_ids: frozenset[int] = frozenset(
            int(i) for i in (expected_ids if expected_ids is not None else range(n_expected)))
        if len(self.expected_ids) != n_expected:
            raise ValueError(f"expected_ids has {len(self.expected_ids)} ids, n_expected={n_expected}")
        self.n_expected = int(n_expected)

        self._cond = threading.Condition(threading.Lock())
        self._present: set[int] = set()
        self._lost: set[int] = set()
        self._lost_callbacks: list[Callable[[int], None]] = []
        if on_vehicle_lost is not None:
            self._lost_callbacks.append(on_vehicle_lost)
        self._init_states: dict[int, StateMsg] = {}      # step-0 states by vehicle
        self._by_step: dict[int, dict[int, StateMsg]] = {}  # gossip buffer: step -> sender -> msg
        self._latest: dict[int, StateMsg] = {}           # highest-step state by sender
        self._last_counted_step: dict[int, int] = {}     # real-time mode: no double counting
        self._silent: set[int] = set()                   # missed a lockstep deadline
        self._min_step_kept = 0
        self._own_init: bytes | None = None

        self.states_received_total = 0
        self.states_received_by_step: dict[int, int] = {}
        self.states_heard_total = 0
        self.malformed_counts: dict[str, int] = {}
        self.buffer_overflow_count = 0  # lockstep buffer full (MAX_BUFFERED_STEPS): step dropped

        self._session: zenoh.Session | None = None
        self._publisher = None
        self._entities: list = []

    # ---- lifecycle -------------------------------------------------------------------
    def __enter__(self) -> "SwarmExchange":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        if self._session is not None:
            raise ExchangeError("exchange already open")
        session = open_session(self.settings)
        self._session = session
        try:
            sw, me = self.swarm, self.vehicle_id
            self._publisher = session.declare_publisher(state_key(sw, me))
            self._entities.append(session.declare_subscriber(state_key(sw, "*"), self._on_state_sample))
            self._entities.append(session.declare_queryable(init_key(sw, me), self._on_init_query))
            self._entities.append(session.liveliness().declare_subscriber(
                alive_key(sw, "*"), self._on_alive_sample, history=True))
            self._entities.append(session.liveliness().declare_token(alive_key(sw, me)))
            with self._cond:
                self._present.add(me)
                self._cond.notify_all()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        session, self._session = self._session, None
        if session is None:
            return
        self._entities.clear()
        self._publisher = None
        try:
            session.close()
        except Exception as exc:  # a close that times out must not mask why we are closing
            log.warning("vehicle %d: zenoh session close failed: %s", self.vehicle_id, exc)
        finally:
            if self.malformed_counts:
                log.warning("vehicle %d: dropped malformed state payloads: %s",
                            self.vehicle_id, dict(self.malformed_counts))

    def _require_session(self) -> zenoh.Session:
        if self._session is None:
            raise ExchangeError("exchange is not open (use it as a context manager)")
        return self._session

    # ---- membership ------------------------------------------------------------------
    def present(self) -> frozenset[int]:
        """Vehicles whose liveliness token is alive (including this one)."""
        with self._cond:
            return frozenset(self._present)

    def lost(self) -> frozenset[int]:
        """Vehicles seen present once whose token has since disappeared (and not come back)."""
        with self._cond:
            return frozenset(self._lost)

    def on_vehicle_lost(self, callback: Callable[[int], None]) -> None:
        """Register ``callback(vehicle_id)``, called on a zenoh thread when a token vanishes."""
        with self._cond:
            self._lost_callbacks.append(callback)

    def wait_present(self, ids: Iterable[int], timeout_s: float, stop: threading.Event | None = None) -> frozenset[int]:
        """Wait until every vehicle in ``ids`` is present; raise :class:`ExchangeTimeout`
        (or :class:`ExchangeStopped` once ``stop`` is set)."""
        want = frozenset(int(i) for i in ids)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                missing = want - self._present
                if not missing:
                    return frozenset(self._present)
                if stop is not None and stop.is_set():
                    raise ExchangeStopped(f"vehicle {self.vehicle_id}: stopped while waiting for vehicles {sorted(missing)}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ExchangeTimeout(
                        f"vehicle {self.vehicle_id}: vehicles {sorted(missing)} not present "
                        f"after {timeout_s:.1f} s", missing)
                self._cond.wait(left if stop is None else min(left, STOP_POLL_S))

    def _on_alive_sample(self, sample) -> None:
        vid = _id_from_key(str(sample.key_expr))
        if vid is None:
            return
        callbacks: list[Callable[[int], None]] = []
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._present.add(vid)
                self._lost.discard(vid)
            elif vid in self._present and vid != self.vehicle_id:
                # (the own token is held until close; its DELETE seen when the client loses
                # its router is not a departure of this vehicle)
                self._present.discard(vid)
                self._lost.add(vid)
                callbacks = list(self._lost_callbacks)
            self._cond.notify_all()
        if callbacks:
            log.info("vehicle %d: vehicle %d is gone (liveliness token lost)", self.vehicle_id, vid)
            for cb in callbacks:
                try:
                    cb(vid)
                except Exception:  # a user callback must not kill the zenoh thread
                    log.exception("on_vehicle_lost callback failed for vehicle %d", vid)

    # ---- receiving -------------------------------------------------------------------
    def _drop(self, kind: str, detail: str) -> None:
        with self._cond:
            n = self.malformed_counts.get(kind, 0) + 1
            self.malformed_counts[kind] = n
        if n == 1:  # rate limit: log the first of each kind; the counts are logged at close
            log.warning("vehicle %d: dropped malformed state (%s): %s (further ones of this "
                        "kind are only counted)", self.vehicle_id, kind, detail)

    def _on_state_sample(self, sample) -> None:
        try:
            self._ingest(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:  # never let anything escape into zenoh
            log.exception("vehicle %d: state callback failed", self.vehicle_id)

    def _on_init_reply(self, reply) -> None:
        try:
            if reply.ok is not None:
                self._ingest(str(reply.ok.key_expr), reply.ok.payload.to_bytes())
        except Exception:
            log.exception("vehicle %d: init reply callback failed", self.vehicle_id)

    def _ingest(self, key: str, payload: bytes) -> None:
        try:
            msg = StateMsg.decode(payload)
        except PayloadError as e:
            self._drop(e.kind, f"{key}: {e}")
            return
        if _id_from_key(key) != msg.vehicle_id:
            self._drop("key", f"{key} carries vehicle_id {msg.vehicle_id}")
            return
        if msg.vehicle_id == self.vehicle_id:
            return
        if msg.vehicle_id not in self.expected_ids:
            self._drop("unknown_id", f"{key}: vehicle {msg.vehicle_id} is not in this swarm")
            return
        overflow = False
        with self._cond:
            self.states_heard_total += 1
            if msg.step == 0:
                self._init_states.setdefault(msg.vehicle_id, msg)
            if msg.step >= self._min_step_kept:
                keep = True
                if msg.step not in self._by_step and len(self._by_step) >= MAX_BUFFERED_STEPS:
                    # full: keep the nearest steps (lockstep needs the next one); drop the
                    # farthest future step, or this one if it is the farthest
                    overflow = True
                    farthest = max(self._by_step)
                    keep = msg.step < farthest
                    if keep:
                        del self._by_step[farthest]
                if keep:
                    self._by_step.setdefault(msg.step, {})[msg.vehicle_id] = msg
            prev = self._latest.get(msg.vehicle_id)
            if prev is None or msg.step >= prev.step:
                self._latest[msg.vehicle_id] = msg
            if msg.vehicle_id in self._silent and msg.step >= self._min_step_kept:
                self._silent.discard(msg.vehicle_id)
                log.info("vehicle %d: vehicle %d publishes again (step %d)",
                         self.vehicle_id, msg.vehicle_id, msg.step)
            self._cond.notify_all()
            if overflow:
                self.buffer_overflow_count += 1
                first_overflow = self.buffer_overflow_count == 1
        if overflow and first_overflow:
            log.warning("vehicle %d: %d future steps already buffered (state of vehicle %d "
                        "step %d); the farthest step not buffered for lockstep (further "
                        "overflows only counted)",
                        self.vehicle_id, MAX_BUFFERED_STEPS, msg.vehicle_id, msg.step)

    def _on_init_query(self, query) -> None:
        payload = self._own_init
        if payload is not None:
            try:
                query.reply(init_key(self.swarm, self.vehicle_id), payload)
            except Exception:
                log.exception("vehicle %d: init reply failed", self.vehicle_id)

    # ---- sending ---------------------------------------------------------------------
    def publish_state(self, step: int, time_s: float, state: Sequence[float]) -> None:
        """Put this vehicle's state for ``step`` on ``mfg/<swarm>/state/<vehicle_id>``."""
        self._require_session()
        payload = StateMsg(self.vehicle_id, int(step), float(time_s), _as_state(state)).encode()
        self._publisher.put(payload)

    def finish_lockstep(self, step: int, time_s: float, own_state: Sequence[float], timeout_s: float) -> frozenset[int]:
        """Lockstep HJB_d, after the mission's last gossip step ``step - 1``: publish the own
        state for ``step`` and wait until every present vehicle has done the same (or left),
        at most ``timeout_s``. A vehicle that closed its session right after its last step
        would leave ``present()`` possibly before its last state reached a slower vehicle
        (the liveliness undeclaration and the state travel independently), which would then
        stop waiting for that state and count one neighbour less than the simulator. Counts
        nothing. Returns the vehicles that did not finish in time."""
        self.publish_state(step, time_s, own_state)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            return frozenset(self._await_step(step, deadline))

    def _await_step(self, step: int, deadline: float) -> set[int]:
        """Caller holds ``_cond``: wait until every present, expected, not-silent vehicle has
        published its state for ``step``, or the deadline; returns those still missing."""
        while True:
            waiting = ((self._present & self.expected_ids) - {self.vehicle_id} - self._silent
                       - set(self._by_step.get(step, {})))
            left = deadline - time.monotonic()
            if not waiting or left <= 0:
                return waiting
            self._cond.wait(left)

    # ---- MFG: the t = 0 exchange -----------------------------------------------------
    def initial_exchange(self, state: Sequence[float], timeout_s: float,
                         time_s: float = 0.0, stop: threading.Event | None = None) -> dict[int, StateMsg]:
        """The MFG t = 0 exchange; returns the step-0 states of all expected vehicles (incl. own).

        Publishes the own step-0 state and from then on answers queries on
        ``mfg/<swarm>/init/<vehicle_id>`` with it. Waits until every expected vehicle is
        present and its step-0 state is known; states published before this vehicle
        subscribed are fetched by querying ``mfg/<swarm>/init/*`` while some are missing: at
        once, then after ``INIT_QUERY_PERIOD_S``, the period doubling up to
        ``INIT_QUERY_MAX_PERIOD_S``. Counts N - 1 states at step 0.
        Raises :class:`ExchangeTimeout` naming the missing vehicles, or
        :class:`ExchangeStopped` once ``stop`` is set.
        """
        session = self._require_session()
        own = StateMsg(self.vehicle_id, 0, float(time_s), _as_state(state))
        payload = own.encode()
        self._own_init = payload
        self._publisher.put(payload)
        deadline = time.monotonic() + timeout_s
        next_query = 0.0
        period = INIT_QUERY_PERIOD_S
        while True:
            with self._cond:
                others = self.expected_ids - {self.vehicle_id}
                no_state = others - set(self._init_states)
                absent = self.expected_ids - self._present
                if not no_state and not absent:
                    result = {i: self._init_states[i] for i in others}
                    break
                now = time.monotonic()
                if now >= deadline:
                    missing = no_state | absent
                    raise ExchangeTimeout(
                        f"vehicle {self.vehicle_id}: t=0 exchange timed out after {timeout_s:.1f} s;"
                        f" missing vehicles {sorted(missing)} (not present: {sorted(absent)},"
                        f" no state: {sorted(no_state)})", missing)
                if stop is not None and stop.is_set():
                    raise ExchangeStopped(f"vehicle {self.vehicle_id}: t=0 exchange stopped; still missing "
                                          f"{sorted(no_state | absent)}")
                if now < next_query:
                    wait = min(next_query, deadline) - now
                    self._cond.wait(wait if stop is None else min(wait, STOP_POLL_S))
                    continue
            # outside the lock: zenoh may deliver replies on this thread
            next_query = time.monotonic() + period
            period = min(2.0 * period, INIT_QUERY_MAX_PERIOD_S)
            if no_state:
                session.get(init_key(self.swarm, "*"), self._on_init_reply,
                            target=zenoh.QueryTarget.ALL, timeout=max(INIT_QUERY_PERIOD_S, 0.1))
        result[self.vehicle_id] = own
        self._count(0, len(result) - 1)
        return result

    def _count(self, step: int, n: int) -> None:
        with self._cond:
            self.states_received_by_step[step] = self.states_received_by_step.get(step, 0) + n
            self.states_received_total += n

    # ---- HJB_d: per-step gossip ------------------------------------------------------
    def gossip(self, step: int, time_s: float, own_state: Sequence[float], range_m: float,
               timeout_s: float, lockstep: bool = True) -> list[StateMsg]:
        """Publish the own state for ``step``; return other vehicles' states within ``range_m``.

        Lockstep: wait until the states of ``step`` from every vehicle currently present
        (except ones already marked silent) have arrived, or ``timeout_s`` passes; vehicles
        still missing at the deadline are logged once and not waited for again until they
        publish again. Real time (``lockstep=False``): no waiting, take the latest state of
        each present sender. Only senders within ``range_m`` (Euclidean distance between
        positions) of ``own_state`` are kept (radio range emulation); they are counted in
        ``states_received_by_step[step]`` (real time: each sender's state counted once).
        """
        own = _as_state(own_state)
        self.publish_state(step, time_s, own)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            if lockstep:
                waiting = self._await_step(step, deadline)
                if waiting:
                    self._silent |= waiting
                    log.warning("vehicle %d: no state for step %d from vehicles %s within "
                                "%.2f s; not waiting for them until they publish again",
                                self.vehicle_id, step, sorted(waiting), timeout_s)
                candidates = list(self._by_step.get(step, {}).values())
                # keep the buffer small: drop steps older than this one
                self._min_step_kept = max(self._min_step_kept, step)
                for s in [s for s in self._by_step if s < step]:
                    del self._by_step[s]
            else:
                candidates = [m for v, m in self._latest.items() if v in self._present]
            kept = [m for m in candidates
                    if math.hypot(m.state[0] - own[0], m.state[1] - own[1]) <= range_m]
            kept.sort(key=lambda m: m.vehicle_id)
            if lockstep:
                n_new = len(kept)
            else:
                n_new = 0
                for m in kept:
                    if self._last_counted_step.get(m.vehicle_id, -1) < m.step:
                        self._last_counted_step[m.vehicle_id] = m.step
                        n_new += 1
            self.states_received_by_step[step] = self.states_received_by_step.get(step, 0) + n_new
            self.states_received_total += n_new
        return kept
