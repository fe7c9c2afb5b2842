"""The controller side of the bridge: a link to one vehicle (issue 4; SPEC section 4).

``VehicleLink`` owns a ``MavlinkPort``, a receive thread that keeps the latest typed
telemetry of its target vehicle, a 1 Hz companion HEARTBEAT, and an optional thread
streaming a held setpoint (PX4 enters OFFBOARD only with a setpoint younger than COM_OF_LOSS_T and
fails safe when they stop for that long; its docs ask for > 2 Hz).
Commands follow the MAVLink command protocol: COMMAND_LONG, retransmitted with an
incremented ``confirmation`` until a COMMAND_ACK arrives or ``timeout_s`` passes; mode
and arming changes are then confirmed by the vehicle's HEARTBEAT. Every wait takes
``timeout_s`` and raises a typed ``BridgeError``.

Setpoints only ever go to ``target_system``/``target_component``: no method takes
another target, and ``target_system`` 0 (broadcast) is refused at open.

Signing (issue 10, docs/security.md): with ``signing_key`` every packet sent is signed
(MAVLink 2 signing, ``link_id`` = ``signing_link_id``), and a received packet is used
only if its signature is valid and fresh; unsigned packets are accepted only with
``accept_unsigned=True``; badly signed or replayed ones never. Rejected input (bad
signature, garbage, non-finite telemetry) is logged once per kind, then counted.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import operator
import threading
import time
from typing import Callable, TypeVar

from .errors import (
    ArmNotConfirmed,
    CommandDenied,
    CommandTimeout,
    HeartbeatTimeout,
    LinkClosed,
    ModeNotConfirmed,
    TelemetryTimeout,
)
from .adsb import TRAFFIC_MARKER_NAME, parse_traffic_tag
from .messages import (
    AdsbVehicle,
    CommandAck,
    CommandLong,
    ExtendedSysState,
    GpsGlobalOrigin,
    Heartbeat,
    LocalPositionNed,
    Message,
    NamedValueInt,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    BadData,
    Received,
    SetPositionTargetLocalNed,
    altitude_hold_setpoint,
    acceleration_setpoint,
)
from .codec import MAVLINK_MSG_ID
from .port import MavlinkPort
from .ratelog import RejectLog
from .signing import SIG_UNSIGNED, SIG_VALID, SigningConfig
from .px4 import (
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    MavAutopilot,
    MavCmd,
    MavModeFlag,
    MavParamType,
    MavResult,
    MavState,
    MavType,
    Px4Mode,
)
from .tlog import TlogWriter

GPS_GLOBAL_ORIGIN_ID = MAVLINK_MSG_ID["GPS_GLOBAL_ORIGIN"]

__all__ = ["VehicleLink", "COMPANION_COMPONENT_ID"]

log = logging.getLogger(__name__)

COMPANION_COMPONENT_ID = 191
"""MAV_COMP_ID_ONBOARD_COMPUTER: the companion computer's component id (issue 4)."""

MAX_PARAMS = 4096
"""Most parameter names a link keeps (a forged PARAM_VALUE flood must not grow it forever)."""

M = TypeVar("M", bound=Message)

_BY_ICAO = operator.attrgetter("icao_address")


class VehicleLink:
    """A MAVLink link from a companion computer to one vehicle (system ``target_system``)."""

    def __init__(
        self,
        port: MavlinkPort,
        target_system: int,
        target_component: int = 1,
        tlog: TlogWriter | None = None,
        heartbeat_rate_hz: float = 1.0,
        command_retry_interval_s: float = 0.5,
        accept_unsigned: bool = False,
    ) -> None:
        if not (1 <= target_system <= 255):
            raise ValueError(f"target_system must be 1..255 (never broadcast 0), got {target_system}")
        if not (0 <= target_component <= 255):
            raise ValueError(f"target_component must be 0..255, got {target_component}")
        self.port = port
        self.target_system = int(target_system)
        self.target_component = int(target_component)
        self._tlog = tlog
        self._retry_s = command_retry_interval_s
        self._cond = threading.Condition()
        self._latest: dict[type, Message] = {}
        self._acks: collections.deque[CommandAck] = collections.deque(maxlen=64)
        self._params: dict[str, ParamValue] = {}
        self._closed = threading.Event()
        self._command_lock = threading.Lock()
        self._t0 = time.monotonic()
        self.n_ignored_other_system = 0
        self.n_bad = 0
        self.accept_unsigned = bool(accept_unsigned)
        self.rejects = RejectLog(log)
        """Rejected input by kind (``rejects.counts``); each kind is logged once, then counted."""
        self._traffic: dict[int, dict[int, AdsbVehicle]] = {}      # tag time_boot_ms -> icao -> report
        self._traffic_markers: dict[int, NamedValueInt] = {}        # tag time_boot_ms -> completion marker
        self._held: SetPositionTargetLocalNed | None = None
        self._held_time_boot_ms: int | None = None
        self._stream_stop: threading.Event | None = None
        self._stream_thread: threading.Thread | None = None
        self.rx_cpu_s = 0.0
        """CPU time (``time.thread_time``) the receive thread has used so far, updated after each read."""
        self._rx_thread = threading.Thread(target=self._rx_loop, name=f"mav-rx-{target_system}", daemon=True)
        self._rx_thread.start()
        self._hb_period_s = 1.0 / heartbeat_rate_hz if heartbeat_rate_hz > 0 else math.inf
        self._hb_thread = threading.Thread(target=self._hb_loop, name=f"mav-hb-{target_system}", daemon=True)
        self._hb_thread.start()

    # ------------------------------------------------------------------ opening / closing
    @classmethod
    def open(
        cls,
        url: str,
        target_system: int = 1,
        target_component: int = 1,
        source_system: int = 1,
        source_component: int = COMPANION_COMPONENT_ID,
        tlog_path: str | None = None,
        heartbeat_rate_hz: float = 1.0,
        signing_key: bytes | None = None,
        signing_link_id: int = 0,
        accept_unsigned: bool = False,
    ) -> "VehicleLink":
        """Open ``url`` (``udpin:127.0.0.1:14540``, ``udpout:``, ``tcp:``, ``/dev/ttyUSB0:921600``).

        ``signing_key`` (32 bytes, e.g. from ``load_signing_key(path)``): sign everything
        sent with link id ``signing_link_id`` and drop every received packet whose
        signature is not valid and fresh -- unsigned ones too unless ``accept_unsigned``.
        Without a key nothing is signed or checked (the behaviour before issue 10)."""
        signing = None if signing_key is None else SigningConfig(bytes(signing_key), signing_link_id)
        tlog = TlogWriter(tlog_path) if tlog_path else None
        try:
            port = MavlinkPort.open(url, source_system, source_component, tlog, signing=signing)
        except BaseException:
            if tlog is not None:
                tlog.close()
            raise
        return cls(port, target_system, target_component, tlog, heartbeat_rate_hz, accept_unsigned=accept_unsigned)

    @property
    def signing(self) -> bool:
        """True if this link signs what it sends and checks what it receives."""
        return self.port.signing is not None

    def close(self) -> None:
        """Stop the threads, close the transport and the tlog. Idempotent."""
        if self._closed.is_set():
            return
        self.stop_setpoint_stream()
        self._closed.set()
        with self._cond:
            self._cond.notify_all()
        self._hb_thread.join(timeout=2.0)
        self._rx_thread.join(timeout=2.0)
        self.port.close()
        if self._tlog is not None:
            self._tlog.close()

    def __enter__(self) -> "VehicleLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ threads
    def _rx_loop(self) -> None:
        while not self._closed.is_set():
            try:
                received = self.port.recv(0.1)
            except (OSError, ValueError):
                if self._closed.is_set():
                    return
                log.exception("receive failed on %s", self.port.name)
                time.sleep(0.1)
                continue
            if received:
                self._on_messages(received)
            self.rx_cpu_s = time.thread_time()

    def _on_messages(self, received: list[Received]) -> None:
        """One datagram's messages: filtered and stored under one lock acquisition with one
        wake-up of the waiters (a traffic set of N reports wakes a waiting control loop once).

        The ADSB_VEHICLE reports of a traffic set (the bulk of a lockstep step's datagram) take
        a shorter path with the same effect as ``_accept`` and ``_store``: on an unsigned link
        only the sender is checked, the set's tag is parsed and its set looked up once per run
        of equal callsigns, and ``_latest[AdsbVehicle]`` is set once, to the last report kept."""
        signing = self.port.signing is not None
        target = self.target_system
        kept = False
        with self._cond:
            traffic = self._traffic
            last_report = None
            callsign = tag = reports = None
            for r in received:
                msg = r.msg
                if type(msg) is not AdsbVehicle or signing:
                    if self._accept(r):
                        kept = True
                        self._store(msg)
                        callsign = None         # a marker may have made or dropped a set: look it up again
                    continue
                if r.src_system != target:
                    self.n_ignored_other_system += 1
                    continue
                kept = True
                last_report = msg
                if msg.callsign != callsign:
                    callsign = msg.callsign
                    tag = parse_traffic_tag(callsign)
                    reports = None if tag is None else traffic.get(tag)
                if tag is None:
                    continue                    # traffic that is not part of a tagged set (e.g. real ADS-B): not the sensor
                if reports is None:
                    self._on_traffic(msg)       # a new set: made, and the oldest ones dropped, there
                    reports = traffic.get(tag)
                else:
                    reports[msg.icao_address] = msg
            if last_report is not None:
                self._latest[AdsbVehicle] = last_report
            if kept:
                self._cond.notify_all()

    def _accept(self, r: Received) -> bool:
        """Whether a received message is used (the checks that need no lock)."""
        msg = r.msg
        if isinstance(msg, BadData):
            self.n_bad += 1
            self.rejects.reject("bad packet", f"{msg.reason} ({msg.n_bytes} bytes)")
            return False
        if self.port.signing is not None and r.signature != SIG_VALID:
            if not (r.signature == SIG_UNSIGNED and self.accept_unsigned):
                self.rejects.reject(
                    f"{r.signature} packet", f"{type(msg).MSG_NAME} from {r.src_system}/{r.src_component}"
                )
                return False
        if r.src_system != self.target_system:
            self.n_ignored_other_system += 1
            return False
        if isinstance(msg, LocalPositionNed) and not all(
            map(math.isfinite, (msg.x_m, msg.y_m, msg.z_m, msg.vx_m_s, msg.vy_m_s, msg.vz_m_s))
        ):
            self.rejects.reject("non-finite LOCAL_POSITION_NED", f"from {r.src_system}/{r.src_component}")
            return False
        if isinstance(msg, Heartbeat) and r.src_component != self.target_component and self.target_component != 0:
            return False  # e.g. a camera or gimbal of the same vehicle
        return True

    def _store(self, msg: Message) -> None:
        """Keep an accepted message; caller holds ``_cond``."""
        if isinstance(msg, (AdsbVehicle, NamedValueInt)):
            self._on_traffic(msg)
        if isinstance(msg, CommandAck):
            if msg.target_system in (0, self.port.source_system) and msg.target_component in (0, self.port.source_component):
                self._acks.append(msg)
        elif isinstance(msg, ParamValue):
            if len(self._params) < MAX_PARAMS or msg.param_id in self._params:
                self._params[msg.param_id] = msg
            else:
                self.rejects.reject("PARAM_VALUE beyond the parameter table limit", f"{MAX_PARAMS} names already")
        self._latest[type(msg)] = msg

    TRAFFIC_SETS_KEPT = 32

    def _on_traffic(self, msg: AdsbVehicle | NamedValueInt) -> None:
        """Collect tagged traffic sets (docs/proximity.md); caller holds ``_cond``."""
        if isinstance(msg, NamedValueInt):
            if msg.name != TRAFFIC_MARKER_NAME:
                return
            tag = msg.time_boot_ms
            self._traffic_markers[tag] = msg
            self._traffic.setdefault(tag, {})
        else:
            tag = parse_traffic_tag(msg.callsign)
            if tag is None:
                return  # traffic that is not part of a tagged set (e.g. real ADS-B): not the sensor
            self._traffic.setdefault(tag, {})[msg.icao_address] = msg
        while len(self._traffic) > self.TRAFFIC_SETS_KEPT:
            oldest = min(self._traffic)
            self._traffic.pop(oldest)
            self._traffic_markers.pop(oldest, None)

    def _complete_traffic(self, tag: int) -> list[AdsbVehicle] | None:
        marker = self._traffic_markers.get(tag)
        if marker is None:
            return None
        reports = self._traffic.get(tag, {})
        if len(reports) < marker.value:
            return None
        return sorted(reports.values(), key=_BY_ICAO)

    def has_traffic_sensor(self) -> bool:
        """True once the vehicle has sent a traffic-set marker: it has a proximity sensor."""
        with self._cond:
            return bool(self._traffic_markers)

    def wait_traffic_sensor(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a first traffic-set marker; True if the vehicle has a
        proximity sensor (it re-sends its current set several times a second)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._traffic_markers:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closed.is_set():
                    return False
                self._cond.wait(min(remaining, 0.2))
            return True

    def sensed_traffic(self, time_boot_ms: int, timeout_s: float) -> list[AdsbVehicle]:
        """The complete traffic set the vehicle sensed at ``time_boot_ms`` (lockstep: the
        set of the step whose LOCAL_POSITION_NED is stamped so), sorted by ICAO address.
        Raises TelemetryTimeout if it is not complete within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                got = self._complete_traffic(int(time_boot_ms))
                if got is not None:
                    return got
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TelemetryTimeout(f"traffic set (ADSB_VEHICLE + {TRAFFIC_MARKER_NAME}) at {time_boot_ms} ms",
                                           self.target_system, timeout_s)
                if self._closed.is_set():
                    raise LinkClosed(f"link to system {self.target_system} closed while waiting for traffic")
                self._cond.wait(min(remaining, 0.2))

    def latest_traffic(self, max_age_s: float) -> tuple[int, list[AdsbVehicle]] | None:
        """Real time: (time_boot_ms, reports) of the newest complete traffic set whose marker
        arrived less than ``max_age_s`` ago, or None."""
        now = time.monotonic()
        with self._cond:
            for tag in sorted(self._traffic_markers, reverse=True):
                if now - self._traffic_markers[tag].received_monotonic_s >= max_age_s:
                    continue
                got = self._complete_traffic(tag)
                if got is not None:
                    return tag, got
        return None

    def _hb_loop(self) -> None:
        next_t = time.monotonic()
        while not self._closed.wait(max(0.0, min(next_t - time.monotonic(), 0.5))):
            now = time.monotonic()
            if now >= next_t:
                try:
                    self._send(
                        Heartbeat(
                            type=MavType.ONBOARD_CONTROLLER,
                            autopilot=MavAutopilot.INVALID,
                            base_mode=0,
                            custom_mode=0,
                            system_status=MavState.ACTIVE,
                        )
                    )
                except LinkClosed:
                    return  # closed between the wait and the send
                next_t = now + self._hb_period_s
            if self._tlog is not None:
                self._tlog.maybe_flush()

    def _send(self, msg: Message) -> float:
        """Send to the target; returns ``time.monotonic()`` when the packet was handed to the transport."""
        if self._closed.is_set():
            raise LinkClosed(f"link to system {self.target_system} is closed")
        return self.port.send_timed(msg)[1]

    # ------------------------------------------------------------------ telemetry
    def latest(self, msg_type: type[M]) -> M | None:
        """The latest message of ``msg_type`` from the target system, or None."""
        with self._cond:
            return self._latest.get(msg_type)  # type: ignore[return-value]

    def latest_heartbeat(self) -> Heartbeat | None:
        return self.latest(Heartbeat)

    def latest_local_position(self) -> LocalPositionNed | None:
        """Latest LOCAL_POSITION_NED (``received_monotonic_s`` = its arrival time)."""
        return self.latest(LocalPositionNed)

    def _age_s(self, msg_type: type) -> float:
        m = self.latest(msg_type)
        return math.inf if m is None else time.monotonic() - m.received_monotonic_s

    def heartbeat_age_s(self) -> float:
        """Seconds since the vehicle's last HEARTBEAT (inf if none yet)."""
        return self._age_s(Heartbeat)

    def telemetry_age_s(self) -> float:
        """Seconds since the last LOCAL_POSITION_NED (inf if none yet)."""
        return self._age_s(LocalPositionNed)

    def wait_for(self, msg_type: type[M], predicate: Callable[[M], bool], timeout_s: float) -> M | None:
        """Wait until the latest ``msg_type`` satisfies ``predicate``; None on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                m = self._latest.get(msg_type)
                if m is not None and predicate(m):  # type: ignore[arg-type]
                    return m  # type: ignore[return-value]
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                if self._closed.is_set():
                    raise LinkClosed(f"link to system {self.target_system} closed while waiting for {msg_type.MSG_NAME}")
                self._cond.wait(min(remaining, 0.2))

    def wait_heartbeat(self, timeout_s: float, newer_than_monotonic_s: float | None = None) -> Heartbeat:
        """The vehicle's HEARTBEAT (the latest one if already seen, or the first received
        after ``newer_than_monotonic_s``). Raises HeartbeatTimeout."""
        after = -math.inf if newer_than_monotonic_s is None else newer_than_monotonic_s
        hb = self.wait_for(Heartbeat, lambda h: h.received_monotonic_s > after, timeout_s)
        if hb is None:
            raise HeartbeatTimeout(self.target_system, self.target_component, timeout_s)
        return hb

    def wait_local_position(self, after_time_boot_ms: int | None, timeout_s: float) -> LocalPositionNed:
        """The first LOCAL_POSITION_NED with ``time_boot_ms > after_time_boot_ms`` (any if None).
        Raises TelemetryTimeout."""
        after = -1 if after_time_boot_ms is None else after_time_boot_ms
        m = self.wait_for(LocalPositionNed, lambda p: p.time_boot_ms > after, timeout_s)
        if m is None:
            raise TelemetryTimeout("LOCAL_POSITION_NED" + ("" if after_time_boot_ms is None else f" after {after} ms"), self.target_system, timeout_s)
        return m

    # ------------------------------------------------------------------ setpoints
    def time_boot_ms(self) -> int:
        """Milliseconds since this link was opened (the default setpoint timestamp)."""
        return int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF

    def _setpoint(self, acc_ned_m_s2, time_boot_ms: int, z_m: float | None) -> SetPositionTargetLocalNed:
        if z_m is None:
            return acceleration_setpoint(self.target_system, self.target_component, acc_ned_m_s2, time_boot_ms)
        return altitude_hold_setpoint(self.target_system, self.target_component, acc_ned_m_s2[0:2], z_m, time_boot_ms)

    def send_acc_setpoint(self, acc_ned_m_s2: tuple[float, float, float], time_boot_ms: int | None = None,
                          z_m: float | None = None) -> float:
        """One SET_POSITION_TARGET_LOCAL_NED, LOCAL_NED frame, to the target vehicle only:
        acceleration-only (type_mask 3135), or with ``z_m`` (down, m, relative to the EKF origin)
        horizontal acceleration with altitude hold (type_mask 3387). Returns ``time.monotonic()``
        when it was handed to the transport. Raises ValueError for non-finite input."""
        sp = self._setpoint(acc_ned_m_s2, self.time_boot_ms() if time_boot_ms is None else time_boot_ms, z_m)
        return self._send(sp)

    def step_lockstep(
        self, acc_ned_m_s2: tuple[float, float, float], time_boot_ms: int, timeout_s: float, retry_interval_s: float = 0.25
    ) -> LocalPositionNed:
        """One lockstep control step (docs/lockstep.md): send the setpoint stamped with the
        vehicle's current simulated ``time_boot_ms`` and return the first LOCAL_POSITION_NED
        after it, re-sending the same setpoint every ``retry_interval_s`` (idempotent on the
        vehicle side, so UDP loss only costs time). Raises TelemetryTimeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.send_acc_setpoint(acc_ned_m_s2, time_boot_ms)
            wait_s = min(retry_interval_s, deadline - time.monotonic())
            m = self.wait_for(LocalPositionNed, lambda p: p.time_boot_ms > time_boot_ms, max(0.0, wait_s))
            if m is not None:
                return m
            if time.monotonic() >= deadline:
                raise TelemetryTimeout(f"lockstep LOCAL_POSITION_NED after {time_boot_ms} ms", self.target_system, timeout_s)

    def set_held_setpoint(self, acc_ned_m_s2: tuple[float, float, float], time_boot_ms: int | None = None,
                          z_m: float | None = None) -> None:
        """The setpoint the stream repeats (stamped ``time_boot_ms``, or the link clock if None);
        with ``z_m`` an altitude-hold setpoint (``send_acc_setpoint``). Raises ValueError for
        non-finite input."""
        sp = self._setpoint(acc_ned_m_s2, 0 if time_boot_ms is None else time_boot_ms, z_m)
        with self._cond:
            self._held = sp
            self._held_time_boot_ms = time_boot_ms

    def start_setpoint_stream(self, rate_hz: float = 20.0, acc_ned_m_s2: tuple[float, float, float] | None = None,
                              z_m: float | None = None) -> None:
        """Stream the held setpoint at ``rate_hz`` from a thread: with ``acc_ned_m_s2`` (and ``z_m``:
        altitude hold, type_mask 3387) a new one, else the one ``set_held_setpoint`` holds (acceleration
        0 if none). PX4 (offboardCheck.cpp) enters OFFBOARD only with a setpoint younger than
        COM_OF_LOSS_T and fails safe when the stream stops for that long."""
        if not (rate_hz > 0):
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        if acc_ned_m_s2 is not None or self._held is None:
            self.set_held_setpoint(acc_ned_m_s2 or (0.0, 0.0, 0.0), z_m=z_m)
        self.stop_setpoint_stream()
        stop = threading.Event()
        self._stream_stop = stop
        period = 1.0 / rate_hz

        def run() -> None:
            next_t = time.monotonic()
            while not stop.is_set() and not self._closed.is_set():
                with self._cond:
                    sp, t_ms = self._held, self._held_time_boot_ms
                if sp is not None:
                    sp_t = sp if t_ms is not None else dataclasses.replace(sp, time_boot_ms=self.time_boot_ms())
                    try:
                        self._send(sp_t)
                    except LinkClosed:
                        return
                next_t += period
                stop.wait(max(0.0, next_t - time.monotonic()))

        self._stream_thread = threading.Thread(target=run, name=f"mav-sp-{self.target_system}", daemon=True)
        self._stream_thread.start()

    def stop_setpoint_stream(self) -> None:
        if self._stream_stop is not None:
            self._stream_stop.set()
        if self._stream_thread is not None:
            self._stream_thread.join(timeout=2.0)
        self._stream_stop = None
        self._stream_thread = None

    @property
    def streaming(self) -> bool:
        return self._stream_thread is not None and self._stream_thread.is_alive()

    # ------------------------------------------------------------------ commands
    def command_long(self, command: int, params: tuple[float, ...], timeout_s: float) -> CommandAck:
        """Send COMMAND_LONG and wait for its COMMAND_ACK (retransmitting every
        ``command_retry_interval_s``; IN_PROGRESS keeps waiting). Raises CommandTimeout,
        or CommandDenied for any result other than ACCEPTED."""
        with self._command_lock:  # one command in flight at a time (acks carry no sequence)
            return self._command_long(int(command), params, timeout_s)

    def _command_long(self, command: int, params: tuple[float, ...], timeout_s: float) -> CommandAck:
        p = tuple(float(x) for x in params) + (0.0,) * (7 - len(params))
        deadline = time.monotonic() + timeout_s
        confirmation = 0
        with self._cond:
            self._acks.clear()
        while True:
            self._send(CommandLong(self.target_system, self.target_component, int(command), p[:7], confirmation))
            retry_at = min(deadline, time.monotonic() + self._retry_s)
            with self._cond:
                while True:
                    for i, ack in enumerate(self._acks):
                        if ack.command == command:
                            del self._acks[i]
                            if ack.result == MavResult.IN_PROGRESS:
                                retry_at = deadline  # stop retransmitting, wait for the final ack
                                break
                            if ack.result != MavResult.ACCEPTED:
                                raise CommandDenied(int(command), int(ack.result), self.target_system)
                            return ack
                    else:
                        remaining = retry_at - time.monotonic()
                        if remaining <= 0:
                            break
                        if self._closed.is_set():
                            raise LinkClosed(f"link to system {self.target_system} closed while waiting for COMMAND_ACK")
                        self._cond.wait(min(remaining, 0.2))
            if time.monotonic() >= deadline:
                raise CommandTimeout(int(command), self.target_system, timeout_s)
            confirmation = min(confirmation + 1, 255)

    def _base_mode(self) -> int:
        hb = self.latest_heartbeat()
        armed = hb is not None and hb.armed
        return int(MavModeFlag.CUSTOM_MODE_ENABLED | (MavModeFlag.SAFETY_ARMED if armed else 0))

    def set_mode(self, mode: Px4Mode, timeout_s: float) -> Heartbeat:
        """DO_SET_MODE(base, main, sub), wait for ACCEPTED, then for a HEARTBEAT in ``mode``.
        Raises CommandDenied, CommandTimeout or ModeNotConfirmed."""
        deadline = time.monotonic() + timeout_s
        sent_at = time.monotonic()
        self.command_long(MavCmd.DO_SET_MODE, (self._base_mode(), mode.main_mode, mode.sub_mode), timeout_s)
        hb = self.wait_for(
            Heartbeat,
            lambda h: h.received_monotonic_s > sent_at and h.px4_mode == mode,
            max(0.0, deadline - time.monotonic()),
        )
        if hb is None:
            last = self.latest_heartbeat()
            raise ModeNotConfirmed(mode.name, None if last is None else last.px4_mode.name, timeout_s)
        return hb

    def start_offboard(self, timeout_s: float) -> Heartbeat:
        """Enter OFFBOARD (PX4: DO_SET_MODE base|CUSTOM, main 6). Precondition: setpoints
        are streaming (``start_setpoint_stream``) -- PX4 refuses otherwise and this raises
        CommandDenied."""
        if not self.streaming:
            log.warning("start_offboard without a setpoint stream: PX4 will refuse unless setpoints are sent")
        return self.set_mode(PX4_OFFBOARD, timeout_s)

    def hold(self, timeout_s: float) -> Heartbeat:
        """PX4 Hold (AUTO.LOITER: main 4, sub 3)."""
        return self.set_mode(PX4_HOLD, timeout_s)

    def land(self, timeout_s: float) -> Heartbeat:
        """PX4 Land (AUTO.LAND: main 4, sub 6): descend at MPC_LAND_SPEED, touch down, auto-disarm
        COM_DISARM_LAND later (``wait_disarmed``)."""
        return self.set_mode(PX4_LAND, timeout_s)

    def takeoff(self, alt_amsl_m: float | None, timeout_s: float) -> CommandAck:
        """MAV_CMD_NAV_TAKEOFF (22): AUTO.TAKEOFF to ``alt_amsl_m`` (param 7; None: the vehicle's
        MIS_TAKEOFF_ALT above where it is), then Hold (AUTO.LOITER). Only the command's ACK is waited
        for; the climb is watched with ``wait_landed_state`` / the position. PX4 accepts it while
        disarmed too (a mode change; the climb starts at arming). Raises CommandDenied, CommandTimeout."""
        nan = math.nan
        alt = nan if alt_amsl_m is None else float(alt_amsl_m)
        return self.command_long(MavCmd.NAV_TAKEOFF, (nan, 0.0, 0.0, nan, nan, nan, alt), timeout_s)

    def wait_origin(self, timeout_s: float, request_every_s: float = 1.0) -> GpsGlobalOrigin:
        """The vehicle's EKF origin (GPS_GLOBAL_ORIGIN, #49), asking for it with MAV_CMD_REQUEST_MESSAGE
        every ``request_every_s`` until it comes (PX4 sends it when the origin is set and on request;
        a vehicle without a GPS fix has none yet). Raises TelemetryTimeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = self.latest(GpsGlobalOrigin)
            if got is not None:
                return got
            left = deadline - time.monotonic()
            if left <= 0:
                raise TelemetryTimeout("GPS_GLOBAL_ORIGIN", self.target_system, timeout_s)
            try:
                self.request_message(GPS_GLOBAL_ORIGIN_ID, min(left, request_every_s))
            except (CommandDenied, CommandTimeout):
                pass                                   # no origin yet (or the request was lost): ask again
            got = self.wait_for(GpsGlobalOrigin, lambda m: True, max(0.0, min(request_every_s, deadline - time.monotonic())))
            if got is not None:
                return got

    def wait_landed_state(self, states: tuple[int, ...], timeout_s: float) -> ExtendedSysState:
        """The first EXTENDED_SYS_STATE whose landed_state is one of ``states`` (MavLandedState).
        Raises TelemetryTimeout."""
        m = self.wait_for(ExtendedSysState, lambda e: e.landed_state in states, timeout_s)
        if m is None:
            raise TelemetryTimeout(f"EXTENDED_SYS_STATE landed_state in {tuple(int(s) for s in states)}", self.target_system, timeout_s)
        return m

    def wait_disarmed(self, timeout_s: float) -> Heartbeat:
        """The first HEARTBEAT without SAFETY_ARMED (at once if the latest one is): e.g. PX4's auto-disarm
        COM_DISARM_LAND after a landing. Raises ArmNotConfirmed."""
        hb = self.wait_for(Heartbeat, lambda h: not h.armed, timeout_s)
        if hb is None:
            raise ArmNotConfirmed(False, timeout_s)
        return hb

    def _arm_disarm(self, arm: bool, timeout_s: float, force: bool) -> Heartbeat:
        deadline = time.monotonic() + timeout_s
        sent_at = time.monotonic()
        self.command_long(MavCmd.COMPONENT_ARM_DISARM, (1.0 if arm else 0.0, 21196.0 if force else 0.0), timeout_s)
        hb = self.wait_for(
            Heartbeat, lambda h: h.received_monotonic_s > sent_at and h.armed == arm, max(0.0, deadline - time.monotonic())
        )
        if hb is None:
            raise ArmNotConfirmed(arm, timeout_s)
        return hb

    def arm(self, timeout_s: float) -> Heartbeat:
        """COMMAND_LONG 400 (param1 = 1), ACK, then a HEARTBEAT with SAFETY_ARMED.
        Raises CommandDenied (e.g. preflight checks failed), CommandTimeout, ArmNotConfirmed."""
        return self._arm_disarm(True, timeout_s, force=False)

    def disarm(self, timeout_s: float, force: bool = False) -> Heartbeat:
        """COMMAND_LONG 400 (param1 = 0; param2 = 21196 if ``force``). PX4 refuses it in the air
        (TEMPORARILY_REJECTED, "Disarming denied: not landed") unless forced, which stops the motors."""
        return self._arm_disarm(False, timeout_s, force=force)

    def set_message_interval(self, msg_id: int, interval_s: float, timeout_s: float) -> CommandAck:
        """MAV_CMD_SET_MESSAGE_INTERVAL (511): ``interval_s`` > 0 sets the period, 0 restores
        the default, < 0 disables the message (-1 us on the wire)."""
        interval_us = -1.0 if interval_s < 0 else interval_s * 1e6
        return self.command_long(MavCmd.SET_MESSAGE_INTERVAL, (msg_id, interval_us), timeout_s)

    def request_message(self, msg_id: int, timeout_s: float) -> CommandAck:
        """MAV_CMD_REQUEST_MESSAGE (512)."""
        return self.command_long(MavCmd.REQUEST_MESSAGE, (msg_id,), timeout_s)

    # ------------------------------------------------------------------ parameters
    def get_param(self, name: str, timeout_s: float) -> float:
        """PARAM_REQUEST_READ by name, wait for its PARAM_VALUE. Raises TelemetryTimeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._params.pop(name, None)
        while True:
            self._send(ParamRequestRead(self.target_system, self.target_component, name, -1))
            pv = self._wait_param(name, min(deadline, time.monotonic() + self._retry_s))
            if pv is not None:
                return pv.value
            if time.monotonic() >= deadline:
                raise TelemetryTimeout(f"PARAM_VALUE {name}", self.target_system, timeout_s)

    def set_param(self, name: str, value: float, timeout_s: float) -> float:
        """PARAM_SET, wait for the PARAM_VALUE echo; returns the value the vehicle kept
        (which differs from ``value`` if it refused it). Raises TelemetryTimeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._params.pop(name, None)
        while True:
            self._send(ParamSet(self.target_system, self.target_component, name, float(value), MavParamType.REAL32))
            pv = self._wait_param(name, min(deadline, time.monotonic() + self._retry_s))
            if pv is not None:
                return pv.value
            if time.monotonic() >= deadline:
                raise TelemetryTimeout(f"PARAM_VALUE {name} (after PARAM_SET)", self.target_system, timeout_s)

    def list_params(self, timeout_s: float) -> dict[str, float]:
        """PARAM_REQUEST_LIST; returns all parameters once ``param_count`` have arrived."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._params.clear()
        self._send(ParamRequestList(self.target_system, self.target_component))
        with self._cond:
            while True:
                if self._params:
                    count = next(iter(self._params.values())).param_count
                    if len(self._params) >= count:
                        return {k: v.value for k, v in self._params.items()}
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TelemetryTimeout(f"PARAM_VALUE list ({len(self._params)} received)", self.target_system, timeout_s)
                self._cond.wait(min(remaining, 0.2))

    def _wait_param(self, name: str, until: float) -> ParamValue | None:
        with self._cond:
            while True:
                pv = self._params.get(name)
                if pv is not None:
                    return pv
                remaining = until - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(min(remaining, 0.2))
