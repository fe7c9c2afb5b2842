"""`mfg-swarm run --live [PORT]`: the recording's per-instant topics served live over the Foxglove WebSocket
protocol (foxglove-sdk's ``start_server``, subprotocol ``foxglove.websocket.v1``) on 127.0.0.1 while a process
swarm flies.

The source is what the controllers log (docs/controller_log.md): every step record's ``state`` (as the
controller received it) and ``acc_m_s2`` (what it commanded). An instant t_k is published once every
controller has logged step k, in step order: /uav<i>/fix, /uav<i>/state, /uav<i>/setpoint, /swarm/scene,
/swarm/separation (docs/formats.md; distances to the group's site, as the controllers' slots are known only
at the end). Clock: simulation time t_k = k dt in lockstep; in real time t_0 + k dt with t_0 the wall time of
the first step record of the first instant. Events, the controller logs and the exact collision checks are in
flight.mcap, written after the flight.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mfg_autopilot.mission import DEFAULT_DATUM, GeodeticPoint

from .flightlog import read_new_lines
from .recording import DEFAULT_ALTITUDE_AGL_M, InstantPublisher, RecordingChannels

__all__ = ["LiveView", "DEFAULT_LIVE_PORT"]

DEFAULT_LIVE_PORT = 8765
"""Foxglove's default WebSocket port."""


class LiveView:
    """A Foxglove WebSocket server and an incremental reader of the controllers' logs. Call :meth:`poll` often
    (the launcher does, every 0.2 s) and :meth:`close` at the end."""

    def __init__(self, ctrl_logs: list[Path], *, dt_s: float, dest_m: np.ndarray, lockstep: bool, port: int = DEFAULT_LIVE_PORT,
                 datum: GeodeticPoint | None = None, altitude_agl_m: np.ndarray | None = None, safety_radius_m: float = 0.05,
                 host: str = "127.0.0.1") -> None:
        import foxglove

        n = len(ctrl_logs)
        if not 0 <= port <= 65535:
            raise ValueError(f"--live port must be in 0..65535, got {port}")
        self.paths, self.n, self.dt_s, self.lockstep = list(ctrl_logs), n, float(dt_s), lockstep
        self._ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(name="mfg-swarm", host=host, port=port, context=self._ctx)
        except Exception as exc:          # e.g. the port is taken
            raise ValueError(f"cannot serve Foxglove WebSocket on {host}:{port}: {exc}") from None
        self.host = host
        self.channels = RecordingChannels(self._ctx, n)
        self._pub_args = dict(datum=datum or DEFAULT_DATUM, dest_m=np.asarray(dest_m, dtype=float),
                              altitude_agl_m=(np.full(n, DEFAULT_ALTITUDE_AGL_M) if altitude_agl_m is None
                                              else np.asarray(altitude_agl_m, dtype=float)),
                              safety_radius_m=safety_radius_m)
        self._pub: InstantPublisher | None = InstantPublisher(self.channels, base_s=0.0, **self._pub_args) if lockstep else None
        self._offsets = [0] * n
        self._pending: dict[int, dict[int, dict]] = {}
        self.next_step = 0
        self.published = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def poll(self) -> int:
        """Read the controllers' new log lines; publish every instant all of them have reached. Returns how many."""
        for i, p in enumerate(self.paths):
            lines, self._offsets[i] = read_new_lines(p, self._offsets[i])
            for line in lines:
                if not line.startswith(b'{"type":"step"'):
                    continue
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:
                    continue
                k = int(rec.get("step", -1))
                if k >= self.next_step and rec.get("state") is not None:
                    self._pending.setdefault(k, {})[i] = rec
        done = 0
        while len(self._pending.get(self.next_step, ())) == self.n:
            self._publish(self.next_step, self._pending.pop(self.next_step))
            self.next_step += 1
            done += 1
        self.published += done
        return done

    def _publish(self, k: int, recs: dict[int, dict]) -> None:
        rows = [recs[i] for i in range(self.n)]
        state = np.array([r["state"][:4] for r in rows], dtype=float)
        acc = np.array([(r.get("acc_m_s2") or [np.nan, np.nan])[:2] for r in rows], dtype=float)
        backstop = np.array([bool(r.get("backstop_active", False)) for r in rows])
        # which safety layer made each command (the default controllers log it: safety.backstop.Layer bits)
        layer = (np.array([int(r.get("backstop_layer", 0)) for r in rows], dtype=np.uint8)
                 if any("backstop_layer" in r for r in rows) else None)
        if self._pub is None:                       # real time: t_0 is the wall time of the first instant
            t0 = min(float(r.get("wall_s", 0.0)) for r in rows) - k * self.dt_s
            self._pub = InstantPublisher(self.channels, base_s=t0, **self._pub_args)
        self._pub.log(k * self.dt_s, state[:, 0:2], state[:, 2:4], acc, backstop, backstop_layer=layer)

    def close(self) -> None:
        self.poll()
        self.server.stop()
