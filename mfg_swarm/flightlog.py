"""Read what a process swarm flew: vehicles' tlogs and controllers' JSON Lines logs.

The metrics of ``mfg-swarm run`` come from the vehicles' own telemetry (their tlogs:
LOCAL_POSITION_NED they sent, SET_POSITION_TARGET_LOCAL_NED they received), not from what
the controllers believe. Communication, computation and regulariser counts come from the
controllers' logs, which count states where they really arrived (the Zenoh exchange).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mavlink_bridge import GlobalPositionInt, GpsGlobalOrigin, LocalPositionNed, SetPositionTargetLocalNed, read_tlog

__all__ = ["VehicleTrack", "read_vehicle_tlog", "read_controller_log", "ControllerRecord", "lockstep_grid", "realtime_grid"]

log = logging.getLogger(__name__)


@dataclass
class VehicleTrack:
    """One vehicle's telemetry as it sent it, and the acceleration setpoints it received."""

    pos_time_boot_ms: np.ndarray     # (k,) LOCAL_POSITION_NED time_boot_ms
    pos_unix_s: np.ndarray           # (k,) tlog timestamps of those messages
    state: np.ndarray                # (k, 4) [x, y, vx, vy]
    sp_time_boot_ms: np.ndarray      # (j,) setpoints' time_boot_ms
    sp_unix_s: np.ndarray            # (j,)
    sp_acc: np.ndarray               # (j, 2)
    # with geodetic=True only (read_vehicle_tlog): the EKF origin and the vehicle's GLOBAL_POSITION_INT
    origin_deg_m: tuple[float, float, float] | None = None       # GPS_GLOBAL_ORIGIN (lat_deg, lon_deg, alt_amsl_m), the last one
    gpi_time_boot_ms: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))   # (g,)
    gpi_unix_s: np.ndarray = field(default_factory=lambda: np.zeros(0))                          # (g,)
    gpi: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))   # (g, 5) [lat_deg, lon_deg, alt_amsl_m, vn_m_s, ve_m_s]
    system_id: int | None = None


def read_vehicle_tlog(path: str | Path, system_id: int | None, geodetic: bool = False) -> VehicleTrack:
    """Positions the vehicle ``system_id`` sent and acceleration setpoints addressed to it. ``system_id``
    None: the first system that sent a LOCAL_POSITION_NED or GLOBAL_POSITION_INT (a one-vehicle tlog).
    ``geodetic``: also its GPS_GLOBAL_ORIGIN (the origin of its LOCAL_NED) and GLOBAL_POSITION_INT."""
    pt, pu, ps, st, su, sa = [], [], [], [], [], []
    gt, gu, gp = [], [], []
    origin = None
    if not Path(path).is_file():
        log.warning("no tlog at %s (the vehicle process never started?)", path)
        packets = []
    else:
        only = ("LOCAL_POSITION_NED", "SET_POSITION_TARGET_LOCAL_NED")
        packets = read_tlog(path, only=only + (("GPS_GLOBAL_ORIGIN", "GLOBAL_POSITION_INT") if geodetic else ()))
    if system_id is None:
        system_id = next((r.src_system for _, r in packets if isinstance(r.msg, (LocalPositionNed, GlobalPositionInt))), None)
    for unix_s, r in packets:
        m = r.msg
        if isinstance(m, GlobalPositionInt) and r.src_system == system_id:
            gt.append(m.time_boot_ms); gu.append(unix_s); gp.append((m.lat_deg, m.lon_deg, m.alt_amsl_m, m.vx_m_s, m.vy_m_s))
        elif isinstance(m, GpsGlobalOrigin) and r.src_system == system_id:
            origin = (m.lat_deg, m.lon_deg, m.alt_amsl_m)
        elif isinstance(m, LocalPositionNed) and r.src_system == system_id:
            pt.append(m.time_boot_ms); pu.append(unix_s); ps.append((m.x_m, m.y_m, m.vx_m_s, m.vy_m_s))
        elif isinstance(m, SetPositionTargetLocalNed) and m.target_system in (0, system_id):
            ax, ay, _ = m.acc_ned_m_s2
            if np.isfinite(ax) and np.isfinite(ay):
                st.append(m.time_boot_ms); su.append(unix_s); sa.append((ax, ay))
    return VehicleTrack(np.array(pt, dtype=np.int64), np.array(pu), np.array(ps, dtype=float).reshape(-1, 4),
                        np.array(st, dtype=np.int64), np.array(su), np.array(sa, dtype=float).reshape(-1, 2),
                        origin, np.array(gt, dtype=np.int64), np.array(gu), np.array(gp, dtype=float).reshape(-1, 5), system_id)


@dataclass
class ControllerRecord:
    steps: list[dict]
    events: list[dict]
    end: dict | None
    start: dict | None


def read_controller_log(path: str | Path) -> ControllerRecord:
    """Parse a controller's JSON Lines log; a truncated last line (a killed process) is skipped."""
    steps, events, end, start = [], [], None, None
    p = Path(path)
    if not p.exists():
        return ControllerRecord([], [], None, None)
    for i, line in enumerate(p.read_text(encoding="utf-8").splitlines()):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            log.warning("%s line %d is not JSON (truncated?); skipped", p, i + 1)
            continue
        kind = rec.get("type")
        if kind == "step":
            steps.append(rec)
        elif kind == "event":
            events.append(rec)
        elif kind == "end":
            end = rec
        elif kind == "start":
            start = rec
    return ControllerRecord(steps, events, end, start)


def lockstep_grid(track: VehicleTrack, dt_ms: int, steps: int,
                  sub_ms: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lockstep: the state at each t_k = k dt (k = 0..steps) and the setpoint that advanced
    step k (stamped t_k). Missing samples are NaN. Returns valid (steps+1,) bool,
    states (steps+1, 4), acc (steps, 2). ``sub_ms``: a vehicle stepped by sub-steps (the inner
    loop): step k's acceleration is the mean of the setpoints that advanced its sub-steps
    t_k, t_k + sub, ... (NaN if one is missing), as the simulator logs it."""
    states = np.full((steps + 1, 4), np.nan)
    acc = np.full((steps, 2), np.nan)
    for t, s in zip(track.pos_time_boot_ms, track.state):
        if t % dt_ms == 0 and 0 <= t // dt_ms <= steps:
            states[t // dt_ms] = s
    unit = dt_ms if sub_ms is None else sub_ms
    first: dict[int, np.ndarray] = {}
    for t, a in zip(track.sp_time_boot_ms, track.sp_acc):
        if t % unit == 0 and 0 <= t < steps * dt_ms and t not in first:
            first[int(t)] = np.asarray(a, dtype=float)     # the first one stamped t is the one that advanced it
    per = dt_ms // unit
    for k in range(steps):
        got = [first.get(k * dt_ms + j * unit) for j in range(per)]
        if all(g is not None for g in got):
            acc[k] = got[0] if per == 1 else np.mean(got, axis=0)
    return ~np.isnan(states[:, 0]), states, acc


def realtime_grid(track: VehicleTrack, t0_unix_s: float, dt_s: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Real time: states interpolated at t0 + k dt (tlog clock) and the setpoint in force
    (the latest received before each instant, 0 before the first). (steps+1, 4), (steps, 2)."""
    grid = t0_unix_s + np.arange(steps + 1) * dt_s
    if track.pos_unix_s.size == 0:
        return np.full((steps + 1, 4), np.nan), np.full((steps, 2), np.nan)
    states = np.column_stack([np.interp(grid, track.pos_unix_s, track.state[:, d]) for d in range(4)])
    acc = np.zeros((steps, 2))
    if track.sp_unix_s.size:
        idx = np.searchsorted(track.sp_unix_s, grid[:-1], side="right") - 1
        ok = idx >= 0
        acc[ok] = track.sp_acc[idx[ok]]
    return states, acc


def read_new_lines(path: Path, offset: int) -> tuple[list[bytes], int]:
    """The complete lines a growing log (a controller's JSON Lines) gained since byte ``offset``, and the offset after
    the last of them (a line still being written is left for the next call). No file yet: ([], offset)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(offset)
            data = fh.read()
    except FileNotFoundError:
        return [], offset
    cut = data.rfind(b"\n")
    if cut < 0:
        return [], offset
    return data[: cut + 1].splitlines(), offset + cut + 1
