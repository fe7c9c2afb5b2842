"""The mock vehicle's I/O loop: MAVLink ports (onboard + GCS), one tlog, select() on the
sockets, ``MockVehicle.tick`` between packets. Single-threaded and event-driven: it blocks
in select() until a packet arrives or the vehicle's next deadline (``next_deadline``: the
next telemetry message, physics sub-step, failsafe check, re-send) is due, never longer than
``max_wait_s`` (how quickly a set ``stop`` is noticed). Stops when ``stop`` is set (the CLI
sets it on SIGINT/SIGTERM) and closes the tlog cleanly."""

from __future__ import annotations

import gc
import logging
import select
import threading
import time

from mavlink_bridge import MavlinkPort, Message, TlogWriter
from mavlink_bridge.signing import SigningConfig

from .vehicle import MockVehicle, VehicleConfig
from .world import WorldClient

__all__ = ["run_vehicle"]

log = logging.getLogger("mock_vehicle")


def run_vehicle(
    cfg: VehicleConfig,
    urls: list[str],
    stop: threading.Event,
    tlog_path: str | None = None,
    max_wait_s: float = 0.25,
    signing: SigningConfig | None = None,
    world_url: str | None = None,
) -> MockVehicle:
    """Serve ``cfg`` on every url in ``urls`` until ``stop`` is set. Returns the vehicle.
    With ``signing`` every packet sent is signed and only validly signed input is used.
    With ``world_url`` (``udp:127.0.0.1:P``, ``mock_vehicle.world``) the vehicle has a
    proximity sensor and forwards what it senses as ADSB_VEHICLE (docs/proximity.md)."""
    tlog = TlogWriter(tlog_path) if tlog_path else None
    ports: list[MavlinkPort] = []
    world: WorldClient | None = None
    try:
        for url in urls:
            ports.append(MavlinkPort.open(url, cfg.system_id, cfg.component_id, tlog, signing=signing))
            log.info(
                "MAVLink on %s as system %d component %d%s",
                url,
                cfg.system_id,
                cfg.component_id,
                "" if signing is None else f", signing on (link id {signing.link_id}): unsigned input is ignored",
            )

        def send(msg: Message, port: object | None) -> None:
            for p in ports if port is None else [port]:
                p.send(msg)  # type: ignore[union-attr]

        def send_batch(msgs: list[Message], port: object | None) -> None:
            for p in ports if port is None else [port]:
                p.send_many(msgs)  # type: ignore[union-attr]

        vehicle = MockVehicle(cfg, send, require_signed=signing is not None, send_batch=send_batch)
        if world_url is not None:
            world = WorldClient(world_url)
            vehicle.attach_world(lambda t_ms, state: world.report(cfg.instance, t_ms, state))  # type: ignore[union-attr]
            log.info("proximity sensor: world at %s:%d", *world.address)
        log.info(
            "instance %d at %s m, v %s m/s, %s clock",
            cfg.instance,
            vehicle.state[0:2].tolist(),
            vehicle.state[2:4].tolist(),
            "lockstep" if cfg.lockstep else "real-time",
        )
        sources: list = ports + ([world] if world is not None else [])
        gc.collect()
        gc.freeze()  # start-up objects (imports, dialect tables) are never scanned again
        while not stop.is_set():
            wait_s = min(max(0.0, vehicle.next_deadline() - time.monotonic()), max_wait_s)
            try:
                readable, _, _ = select.select(sources, [], [], wait_s)
            except (OSError, ValueError):
                if stop.is_set():
                    break
                raise
            for p in readable:
                if p is world:
                    for a in world.receive():
                        if a.vehicle_id == cfg.instance:
                            vehicle.on_world_answer(a.time_boot_ms, a.ids, a.states)
                    continue
                for _ in range(256):  # drain what is queued, but keep ticking
                    received = p.recv(0.0)
                    if not received:
                        break
                    for r in received:
                        vehicle.handle(r, p)
            vehicle.tick()
            if tlog is not None:
                tlog.maybe_flush()
        vehicle.rejects.summary()
        for p in ports:
            log.info(
                "link %s: %d datagrams, %d packets, %d bad, %d sent", p.name, p.n_datagrams, p.n_received, p.n_bad, p.n_sent
            )
        return vehicle
    finally:
        if world is not None:
            world.close()
        for p in ports:
            p.close()
        if tlog is not None:
            tlog.close()
            log.info("tlog closed: %s (%d records)", tlog.path, tlog.n_records)
