"""The mock vehicle's I/O loop: MAVLink ports (onboard + GCS), one tlog, select() on the
sockets, ``MockVehicle.tick`` between packets. Single-threaded; stops when ``stop`` is set
(the CLI sets it on SIGINT/SIGTERM) and closes the tlog cleanly."""

from __future__ import annotations

import logging
import select
import threading
import time

from mavlink_bridge import MavlinkPort, Message, TlogWriter

from .vehicle import MockVehicle, VehicleConfig

__all__ = ["run_vehicle"]

log = logging.getLogger("mock_vehicle")


def run_vehicle(
    cfg: VehicleConfig,
    urls: list[str],
    stop: threading.Event,
    tlog_path: str | None = None,
    max_wait_s: float = 0.02,
) -> MockVehicle:
    """Serve ``cfg`` on every url in ``urls`` until ``stop`` is set. Returns the vehicle."""
    tlog = TlogWriter(tlog_path) if tlog_path else None
    ports: list[MavlinkPort] = []
    try:
        for url in urls:
            ports.append(MavlinkPort.open(url, cfg.system_id, cfg.component_id, tlog))
            log.info("MAVLink on %s as system %d component %d", url, cfg.system_id, cfg.component_id)

        def send(msg: Message, port: object | None) -> None:
            for p in ports if port is None else [port]:
                p.send(msg)  # type: ignore[union-attr]

        vehicle = MockVehicle(cfg, send)
        log.info(
            "instance %d at %s m, v %s m/s, %s clock",
            cfg.instance,
            vehicle.state[0:2].tolist(),
            vehicle.state[2:4].tolist(),
            "lockstep" if cfg.lockstep else "real-time",
        )
        while not stop.is_set():
            wait_s = min(max(0.0, vehicle.next_deadline() - time.monotonic()), max_wait_s)
            try:
                readable, _, _ = select.select(ports, [], [], wait_s)
            except (OSError, ValueError):
                if stop.is_set():
                    break
                raise
            for p in readable:
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
        return vehicle
    finally:
        for p in ports:
            p.close()
        if tlog is not None:
            tlog.close()
            log.info("tlog closed: %s (%d records)", tlog.path, tlog.n_records)
