"""A flight as an MCAP recording for Foxglove (`flight.mcap`; issue 21; topics in docs/formats.md).

One pure step and two thin shells around it:

- :func:`load_run` reads a run folder into a :class:`FlightRecord` (trajectories.npz, metrics.json,
  the controllers' logs), or, without trajectories.npz, rebuilds the trajectories from the vehicles'
  tlogs (LOCAL_POSITION_NED through each vehicle's GPS_GLOBAL_ORIGIN, else GLOBAL_POSITION_INT).
  Every input is checked first: a corrupt or truncated file raises :class:`RecordingError`.
- :func:`write_mcap` writes a FlightRecord with the Foxglove SDK's well-known schemas (protobuf)
  and JSON channels, into a temporary file renamed at the end: a reader never sees a partial file,
  and a failed write leaves nothing.
- :func:`record_run` is both: what ``mfg-swarm sim --record``, ``mfg-swarm run`` and
  ``mfg-swarm convert`` call.

Time: simulation time (t_k = k dt from the epoch, 1970-01-01) for ``sim`` and a lockstep process
swarm, wall time (t_0 = the first controller's OFFBOARD) for a real-time swarm or a tlog-only folder.
Frames: the swarm frame is NED at the datum (x north, y east); geodetic positions come from it through
pymap3d (mfg_autopilot.mission.SwarmFrame); the 3D scene is drawn in ENU (frame ``swarm_enu``: x east,
y north, z up), Foxglove's convention.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mfg_autopilot.mission import DEFAULT_DATUM, GeodeticPoint, SwarmFrame
from mfg_autopilot.safety.layers import layer_names

from . import metrics as M
from .flightlog import ControllerRecord, lockstep_grid, read_controller_log, read_vehicle_tlog, realtime_grid
from .results import Trajectories, compute_metrics, load_trajectories

__all__ = ["RecordingError", "FlightRecord", "RecordingSummary", "load_run", "write_mcap", "record_run", "MCAP_NAME",
           "collision_events", "backstop_intervals", "DEFAULT_ALTITUDE_AGL_M", "RecordingChannels", "InstantPublisher"]

MCAP_NAME = "flight.mcap"
DEFAULT_ALTITUDE_AGL_M = 0.0
"""Height drawn for a built-in scenario (the plant is planar; a mission gives each group's cruise altitude)."""
DEFAULT_SAFETY_RADIUS_M = 0.05
"""scenarios.DEFAULT_SAFETY_RADIUS_M, the sphere drawn without a mission (not imported: mfg_swarm.scenarios pulls in the
guidance room and numba, 0.6 s of a convert's start; tests/test_recording.py checks the two agree)."""



class RecordingError(ValueError):
    """A run folder that cannot be recorded (a missing, corrupt or truncated input); the message names the file."""


@dataclass
class FlightRecord:
    """What a recording shows. T control steps, N UAVs; positions in the swarm frame (NED at ``datum``)."""

    traj: Trajectories
    metrics: dict
    datum: GeodeticPoint
    safety_radius_m: float
    altitude_agl_m: np.ndarray                   # (N,) drawn height above the datum
    t0_unix_s: float | None = None               # None: simulation time; else the wall time of t_0
    backstop_active: np.ndarray | None = None    # (T, N) bool: the backstop changed the command
    backstop_layer: np.ndarray | None = None     # (T, N) uint8: which safety layer made it (safety.backstop.Layer bits)
    controller_logs: list[ControllerRecord] = field(default_factory=list)   # [] or N logs
    source: str = "trajectories.npz"

    @property
    def n(self) -> int:
        return int(self.traj.pos_m.shape[1])

    @property
    def steps(self) -> int:
        return int(self.traj.acc_m_s2.shape[0])


@dataclass(frozen=True)
class RecordingSummary:
    path: Path
    messages_by_topic: dict[str, int]
    collision_events: int
    backstop_events: int


# ------------------------------------------------------------------------------------------ events

def collision_events(pos_m: np.ndarray, radius_m: float = M.COLLISION_DISTANCE_M) -> list[tuple[int, int, int, int, float]]:
    """One event per collided pair (metrics.collisions' definition: a step segment closer than radius_m):
    (i, j, first step k, last step k, closest distance m), the contact from t_first to t_last + dt.
    pos_m (T+1, N, 2)."""
    pairs = M.collisions(pos_m, radius_m)["pairs"]
    out = []
    T1 = pos_m.shape[0]
    for i, j in pairs:
        d = pos_m[:, j] - pos_m[:, i]
        dseg = M.segment_min_distance(d[:-1], d[1:]) if T1 > 1 else np.linalg.norm(d, axis=1)
        hit = np.flatnonzero(dseg < radius_m)
        out.append((int(i), int(j), int(hit[0]), int(hit[-1]), float(dseg.min())))
    return out


def backstop_intervals(active: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs of consecutive steps in which the backstop acted, per vehicle: (vehicle, first k, last k).
    active (T, N) bool; the sum of (last - first + 1) is the number of active (vehicle, step) pairs."""
    out = []
    a = np.asarray(active, dtype=bool)
    for v in range(a.shape[1]):
        col = np.concatenate([[False], a[:, v], [False]]).astype(np.int8)
        edges = np.diff(col)
        for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            out.append((v, int(s), int(e) - 1))
    return sorted(out, key=lambda x: (x[1], x[0]))


# ------------------------------------------------------------------------------------------ reading

def _from_step_records(logs: list[ControllerRecord], key: str, T: int, dtype) -> np.ndarray:
    """(T, N) one key of the controllers' step records (controller i's record of step k at [k, i]; 0 where a record
    lacks the key or a step has no record)."""
    out = np.zeros((T, len(logs)), dtype=dtype)
    for i, lg in enumerate(logs):
        for rec in lg.steps:
            if 0 <= rec.get("step", -1) < T:
                out[rec["step"], i] = rec.get(key, 0)
    return out


def _load_json(path: Path, what: str) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingError(f"{path}: {what} is not readable JSON ({exc})") from None


def _load_npz(path: Path) -> Trajectories:
    try:
        traj = load_trajectories(path)
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zipfile.LargeZipFile) as exc:
        raise RecordingError(f"{path}: corrupt or truncated trajectories ({type(exc).__name__}: {exc})") from None
    T1, N = traj.pos_m.shape[:2]
    shapes = {"pos_m": (traj.pos_m.shape, (T1, N, 2)), "vel_m_s": (traj.vel_m_s.shape, (T1, N, 2)),
              "acc_m_s2": (traj.acc_m_s2.shape, (T1 - 1, N, 2)), "dest_m": (traj.dest_m.shape, (N, 2))}
    bad = [f"{k} {got} (expected {want})" for k, (got, want) in shapes.items() if tuple(got) != want]
    if bad or not (traj.dt_s > 0):
        raise RecordingError(f"{path}: inconsistent trajectories: {', '.join(bad) or f'dt_s = {traj.dt_s}'}")
    return traj


def _vehicle_tlogs(run_dir: Path) -> list[Path]:
    """vehicles/vehicle<i>.tlog in vehicle order (a launcher's folder), else every *.tlog in the folder, sorted."""
    launched = sorted((run_dir / "vehicles").glob("vehicle*.tlog"), key=lambda p: int("".join(c for c in p.stem if c.isdigit()) or 0))
    return launched or sorted(run_dir.glob("*.tlog"))


def _check_tlogs(paths: list[Path]) -> None:
    from mavlink_bridge import TlogError, check_tlog

    for p in paths:
        try:
            check_tlog(p)
        except TlogError as exc:
            raise RecordingError(str(exc)) from None


def _datum_from(metrics: dict, mission, datum: GeodeticPoint | None) -> GeodeticPoint | None:
    if datum is not None:
        return datum
    if mission is not None:
        return mission.datum
    d = metrics.get("datum")
    if isinstance(d, dict):
        return GeodeticPoint(float(d["lat_deg"]), float(d["lon_deg"]), float(d["alt_amsl_m"]))
    return None


def _inferred_origin(tr) -> tuple[float, float, float] | None:
    """A vehicle's LOCAL_NED origin when its tlog holds no GPS_GLOBAL_ORIGIN (PX4 sends it only when set or
    asked): from a LOCAL_POSITION_NED and a GLOBAL_POSITION_INT of the same time_boot_ms, the point
    (-north, -east) of the local position from the fix (horizontal only: the altitude is the fix's)."""
    if tr.state.shape[0] == 0 or tr.gpi.shape[0] == 0:
        return None
    common, ia, ib = np.intersect1d(tr.pos_time_boot_ms, tr.gpi_time_boot_ms, return_indices=True)
    if common.size == 0:
        return None
    fix = tr.gpi[ib[0]]
    lat, lon, _ = SwarmFrame(GeodeticPoint(float(fix[0]), float(fix[1]), float(fix[2]))).ned_to_geodetic(
        [-tr.state[ia[0], 0], -tr.state[ia[0], 1], 0.0])
    return float(lat), float(lon), float(fix[2])


def _tracks_from_tlogs(run_dir: Path, tlogs: list[Path], metrics: dict, datum: GeodeticPoint | None):
    """Trajectories rebuilt from tlogs (no trajectories.npz): (traj, datum, t0_unix_s)."""
    launched = tlogs and tlogs[0].parent.name == "vehicles"
    tracks = [read_vehicle_tlog(p, (i + 1) if launched else None, geodetic=True) for i, p in enumerate(tlogs)]
    for p, tr in zip(tlogs, tracks):
        if tr.state.shape[0] == 0 and tr.gpi.shape[0] == 0:
            raise RecordingError(f"{p}: no LOCAL_POSITION_NED or GLOBAL_POSITION_INT from the vehicle: nothing to draw")
    for tr in tracks:
        # a launcher's vehicle without GPS_GLOBAL_ORIGIN (a built-in scenario) has its LOCAL_NED origin at the world's
        # home, the default datum; a real vehicle's origin is inferred from its fixes
        if tr.origin_deg_m is None and not launched:
            tr.origin_deg_m = _inferred_origin(tr)
    if datum is None:
        if launched:
            datum = DEFAULT_DATUM          # the launcher's world frame (mock_vehicle's default home)
        else:                              # a real vehicle: its first fix, else its EKF origin
            tr = tracks[0]
            datum = (GeodeticPoint(*map(float, tr.gpi[0, 0:3])) if tr.gpi.shape[0]
                     else GeodeticPoint(*tr.origin_deg_m) if tr.origin_deg_m else DEFAULT_DATUM)
    frame = SwarmFrame(datum)
    swarm_tracks = []
    for tr in tracks:
        if tr.state.shape[0] and tr.origin_deg_m is not None:
            vf = frame.vehicle(GeodeticPoint(*tr.origin_deg_m))
            tr.state = vf.state_local_to_swarm(tr.state)
            if tr.sp_acc.shape[0]:
                tr.sp_acc = vf.vector_to_swarm(np.column_stack([tr.sp_acc, np.zeros(len(tr.sp_acc))]))[:, 0:2]
        elif tr.state.shape[0] == 0:
            # no LOCAL_POSITION_NED: the geodetic fixes, as states in the swarm frame
            ned = frame.geodetic_to_ned(tr.gpi[:, 0], tr.gpi[:, 1], tr.gpi[:, 2]).reshape(-1, 3)
            tr.state = np.column_stack([ned[:, 0:2], tr.gpi[:, 3:5]])
            tr.pos_time_boot_ms, tr.pos_unix_s = tr.gpi_time_boot_ms, tr.gpi_unix_s
        # else: LOCAL_POSITION_NED without an origin: its LOCAL_NED is taken as the swarm frame
        swarm_tracks.append(tr)
    n = len(swarm_tracks)
    lockstep = bool(metrics.get("lockstep", False))
    dt = metrics.get("dt_s")
    if dt is None:
        dts = np.diff(swarm_tracks[0].pos_unix_s)
        dt = float(np.median(dts)) if dts.size else 1.0
        dt = max(round(dt, 3), 1e-3)
    dt = float(dt)
    t0_unix = None
    if lockstep:
        dt_ms = int(round(dt * 1000))
        steps = int(min(tr.pos_time_boot_ms.max() // dt_ms for tr in swarm_tracks))
        states = np.full((steps + 1, n, 4), np.nan)
        acc = np.zeros((steps, n, 2))
        for i, tr in enumerate(swarm_tracks):
            _, states[:, i], a = lockstep_grid(tr, dt_ms, steps, metrics.get("lockstep_sub_step_ms"))
            acc[:, i] = np.nan_to_num(a)
    else:
        t0_unix = float(max(tr.pos_unix_s[0] for tr in swarm_tracks))
        t_end = float(min(tr.pos_unix_s[-1] for tr in swarm_tracks))
        steps = max(int(math.floor((t_end - t0_unix) / dt + 1e-9)), 0)
        states = np.empty((steps + 1, n, 4))
        acc = np.zeros((steps, n, 2))
        for i, tr in enumerate(swarm_tracks):
            states[:, i], acc[:, i] = realtime_grid(tr, t0_unix, dt, steps)
    known = ~np.isnan(states[:, :, 0]).any(axis=1)
    flown = int(np.argmin(known)) if not known.all() else states.shape[0]
    if flown < 1:
        raise RecordingError(f"{run_dir}: the tlogs hold no instant with every vehicle's position")
    states, acc = states[:flown], acc[: flown - 1]
    T = flown - 1
    dest = None
    mj = run_dir / "mission.json"
    if mj.is_file():
        sites = _load_json(mj, "mission.json").get("sites_m")
        if sites is not None and np.asarray(sites).shape == (n, 2):
            dest = np.asarray(sites, dtype=float)
    if dest is None:
        dest = states[-1, :, 0:2].copy()           # unknown destinations: where each vehicle ended
    z = np.zeros((T, n), dtype=np.int64)
    traj = Trajectories(dt_s=dt, pos_m=states[:, :, 0:2], vel_m_s=states[:, :, 2:4], acc_m_s2=acc, dest_m=dest,
                        comm_states=np.zeros((T + 1, n), dtype=np.int64), grad_evals=z, mf_evals=z.copy(),
                        reg_active=np.zeros((T, n), dtype=bool))
    return traj, datum, t0_unix


def load_run(run_dir: str | Path, *, mission=None, datum: GeodeticPoint | None = None,
             safety_radius_m: float | None = None) -> FlightRecord:
    """A run folder as a FlightRecord (module docstring). ``mission`` (mfg_autopilot.mission.Mission) or
    ``datum`` place the swarm frame on the Earth; otherwise metrics.json's ``datum``, else the default
    datum (mfg_autopilot.mission.DEFAULT_DATUM; for a folder of bare tlogs: the first vehicle's first fix)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RecordingError(f"{run_dir}: no such run folder")
    metrics = _load_json(run_dir / "metrics.json", "metrics.json") if (run_dir / "metrics.json").is_file() else {}
    tlogs = _vehicle_tlogs(run_dir)
    npz = run_dir / "trajectories.npz"
    datum = _datum_from(metrics, mission, datum)
    t0_unix = None
    if npz.is_file():
        traj = _load_npz(npz)
        source = "trajectories.npz"
        if "t0_unix_s" in traj.extra:
            t0_unix = float(traj.extra["t0_unix_s"])
    elif tlogs:
        _check_tlogs(tlogs)             # only the files it reads: with an npz the tlogs are not needed
        traj, datum, t0_unix = _tracks_from_tlogs(run_dir, tlogs, metrics, datum)
        source = f"{len(tlogs)} tlog(s)"
    else:
        raise RecordingError(f"{run_dir}: neither trajectories.npz nor a .tlog to record (docs/formats.md)")
    n = traj.pos_m.shape[1]
    if metrics.get("n") not in (None, n):
        raise RecordingError(f"{run_dir}: metrics.json says n = {metrics.get('n')}, the trajectories hold {n} vehicles")
    if not metrics:
        metrics = compute_metrics(traj, n=n, mode="unknown", range_m=None, seed=0, wall_s=0.0, path="tlogs")
    if datum is None:
        datum = DEFAULT_DATUM
    ctrl_paths = [run_dir / "controllers" / f"controller{i}.jsonl" for i in range(n)]
    logs = [read_controller_log(p) for p in ctrl_paths] if any(p.is_file() for p in ctrl_paths) else []
    if source != "trajectories.npz":
        for i, lg in enumerate(logs):      # the slot each controller flew to (as mfg-swarm run reads it)
            if lg.end is not None and lg.end.get("destination_m") is not None:
                traj.dest_m[i] = np.asarray(lg.end["destination_m"], dtype=float)[:2]
    T = traj.acc_m_s2.shape[0]
    backstop = traj.extra.get("backstop_active")
    if backstop is None and logs:
        backstop = _from_step_records(logs, "backstop_active", T, bool)
    layer = traj.extra.get("backstop_layer")
    if layer is None and any("backstop_layer" in rec for lg in logs for rec in lg.steps):
        # (the default controllers log it; a folder without trajectories.npz rebuilds it from their logs)
        layer = _from_step_records(logs, "backstop_layer", T, np.uint8)
    if mission is not None and mission.n == n:
        alt = mission.arrays()["altitude_agl_m"]
    else:
        alt = np.asarray(metrics.get("altitude_agl_m", DEFAULT_ALTITUDE_AGL_M), dtype=float) * np.ones(n)
    r = safety_radius_m if safety_radius_m is not None else (
        mission.safety_radius_m if mission is not None else metrics.get("safety_radius_m") or DEFAULT_SAFETY_RADIUS_M)
    return FlightRecord(traj=traj, metrics=metrics, datum=datum, safety_radius_m=float(r), altitude_agl_m=alt,
                        t0_unix_s=t0_unix, backstop_active=None if backstop is None else np.asarray(backstop, dtype=bool),
                        backstop_layer=None if layer is None else np.asarray(layer, dtype=np.uint8),
                        controller_logs=logs, source=source)


# ------------------------------------------------------------------------------------------ writing

_STATE_SCHEMA = {"title": "mfg_swarm.VehicleState", "type": "object", "properties": {
    "t_s": {"type": "number"}, "x_north_m": {"type": "number"}, "y_east_m": {"type": "number"},
    "vx_north_m_s": {"type": "number"}, "vy_east_m_s": {"type": "number"}, "speed_m_s": {"type": "number"},
    "distance_to_slot_m": {"type": "number"}}}
_SETPOINT_SCHEMA = {"title": "mfg_swarm.AccelerationSetpoint", "type": "object", "properties": {
    "t_s": {"type": "number"}, "acc_north_m_s2": {"type": "number"}, "acc_east_m_s2": {"type": "number"},
    "acc_norm_m_s2": {"type": "number"}, "backstop_active": {"type": "boolean"}, "backstop_layer": {"type": "integer"},
    "backstop_layers": {"type": "string"}}}
_SEPARATION_SCHEMA = {"title": "mfg_swarm.SwarmSeparation", "type": "object", "properties": {
    "t_s": {"type": "number"}, "min_separation_m": {"type": "number"}, "closest_i": {"type": "integer"},
    "closest_j": {"type": "integer"}, "arrived": {"type": "integer"}, "arrived_fraction": {"type": "number"},
    "collided_pairs_so_far": {"type": "integer"}}}
_CONTROLLER_SCHEMA = {"title": "mfg_swarm.ControllerStep", "type": "object", "properties": {
    "step": {"type": "integer"}, "time_s": {"type": "number"}, "grad_evals": {"type": "integer"},
    "mf_evals": {"type": "integer"}, "reg_active": {"type": "boolean"}, "residual": {"type": "number"},
    "states_received": {"type": "integer"}, "backstop_active": {"type": "boolean"}, "backstop_layer": {"type": "integer"},
    "latency_ms": {"type": "number"}}}
_CONTROLLER_STEP_KEYS = tuple(_CONTROLLER_SCHEMA["properties"])


def _palette(n: int) -> np.ndarray:
    """n distinct RGB colours (tab10 cycled), (n, 3) in [0, 1]."""
    tab10 = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75],
                      [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], dtype=float) / 255.0
    return tab10[np.arange(n) % 10]


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


def _closest_pairs(pos_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per instant: smallest distance between two UAVs and the pair. (T+1,), (T+1, 2); inf/-1 for N < 2."""
    from scipy.spatial import cKDTree

    T1, N, _ = pos_m.shape
    d = np.full(T1, np.inf)
    ij = np.full((T1, 2), -1, dtype=np.int64)
    if N < 2:
        return d, ij
    for k in range(T1):
        rows = np.flatnonzero(np.isfinite(pos_m[k]).all(axis=1))      # a UAV without a position is left out
        if rows.size < 2:
            continue
        dd, idx = cKDTree(pos_m[k, rows]).query(pos_m[k, rows], k=2)
        a = int(np.argmin(dd[:, 1]))
        d[k] = dd[a, 1]
        ij[k] = sorted((int(rows[a]), int(rows[idx[a, 1]])))
    return d, ij


class RecordingChannels:
    """The recording's channels in one Foxglove context (an MCAP writer's, or ``run --live``'s WebSocket server's)."""

    def __init__(self, ctx, n: int, controllers: bool = False) -> None:
        import foxglove
        from foxglove.channels import EventChannel, LocationFixChannel, LogChannel, SceneUpdateChannel

        def js(topic: str, schema: dict) -> foxglove.Channel:
            s = foxglove.Schema(name=schema["title"], encoding="jsonschema", data=json.dumps(schema).encode())
            return foxglove.Channel(topic, schema=s, message_encoding="json", context=ctx)

        self.fix = [LocationFixChannel(f"/uav{i}/fix", context=ctx) for i in range(n)]
        self.state = [js(f"/uav{i}/state", _STATE_SCHEMA) for i in range(n)]
        self.setpoint = [js(f"/uav{i}/setpoint", _SETPOINT_SCHEMA) for i in range(n)]
        self.separation = js("/swarm/separation", _SEPARATION_SCHEMA)
        self.scene = SceneUpdateChannel("/swarm/scene", context=ctx)
        self.collision = EventChannel("/events/collision", context=ctx)
        self.backstop = EventChannel("/events/backstop", context=ctx)
        self.log = LogChannel("/log", context=ctx)
        self.controller = [js(f"/uav{i}/controller", _CONTROLLER_SCHEMA) for i in range(n)] if controllers else []
        self.controller_log = [LogChannel(f"/uav{i}/controller_log", context=ctx) for i in range(n)] if controllers else []


class _Counter(dict):
    def add(self, topic: str, k: int = 1) -> None:
        self[topic] = self.get(topic, 0) + k


class InstantPublisher:
    """Logs one control instant of the swarm on the per-instant topics (/uav<i>/fix, /uav<i>/state,
    /uav<i>/setpoint, /swarm/scene, /swarm/separation): what flight.mcap holds at t_k and what ``run --live``
    serves. ``channels``: a :class:`RecordingChannels`; positions in the swarm frame (NED at ``datum``)."""

    def __init__(self, channels: "RecordingChannels", *, datum: GeodeticPoint, altitude_agl_m: np.ndarray, dest_m: np.ndarray,
                 safety_radius_m: float, base_s: float = 0.0) -> None:
        from foxglove.messages import Color, Pose, Quaternion, SpherePrimitive, Vector3

        self.ch, self.n = channels, int(dest_m.shape[0])
        self.frame, self.alt = SwarmFrame(datum), np.asarray(altitude_agl_m, dtype=float)
        self.dest, self.r_m, self.base_s = np.asarray(dest_m, dtype=float), float(safety_radius_m), float(base_s)
        self.colours = _palette(self.n)
        r2 = 2.0 * self.r_m
        self._q_id = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        self._slots = [SpherePrimitive(pose=Pose(position=Vector3(x=float(self.dest[i, 1]), y=float(self.dest[i, 0]),
                                                                  z=float(self.alt[i])), orientation=self._q_id),
                                       size=Vector3(x=r2, y=r2, z=r2),
                                       color=Color(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=0.35))
                       for i, c in enumerate(self.colours)]
        self.counts = _Counter()

    def stamp(self, t_s: float):
        from foxglove.messages import Timestamp

        ns = _ns(self.base_s + t_s)
        return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)

    def log(self, t_s: float, pos_m: np.ndarray, vel_m_s: np.ndarray, acc_m_s2: np.ndarray | None = None,
            backstop_active: np.ndarray | None = None, collided_pairs_so_far: int | None = None,
            backstop_layer: np.ndarray | None = None) -> None:
        """The instant t_s: pos_m, vel_m_s (N, 2); acc_m_s2 (N, 2) applied from t_s on (None at the last instant);
        backstop_active (N,) bool or None; backstop_layer (N,) safety.backstop.Layer bits or None (the setpoint then
        carries them and their names). A UAV whose position is NaN is left out."""
        from foxglove.messages import (ArrowPrimitive, Color, KeyValuePair, LinePrimitive, LocationFix, Point3, Pose,
                                       Quaternion, SceneEntity, SceneUpdate, SpherePrimitive, TextPrimitive, Vector3)

        ch, q_id = self.ch, self._q_id
        lt, ts = _ns(self.base_s + t_s), self.stamp(t_s)
        pos = np.asarray(pos_m, dtype=float)
        vel = np.asarray(vel_m_s, dtype=float)
        ned = np.column_stack([pos, -self.alt])
        lat, lon, alt = self.frame.ned_to_geodetic(ned)
        slot_dist = np.linalg.norm(pos - self.dest, axis=1)
        ok = np.isfinite(pos).all(axis=1)
        d, ij = _closest_pairs(pos[None])
        r2 = 2.0 * self.r_m
        entities = []
        for i in np.flatnonzero(ok):
            i = int(i)
            c = self.colours[i]
            colour = Color(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=1.0)
            v_ne = vel[i]
            speed = float(np.hypot(*v_ne))
            ch.fix[i].log(LocationFix(timestamp=ts, frame_id=f"uav{i}", latitude=float(lat[i]), longitude=float(lon[i]),
                                      altitude=float(alt[i]), velocity=Vector3(x=float(v_ne[1]), y=float(v_ne[0]), z=0.0),
                                      color=colour), log_time=lt)
            ch.state[i].log({"t_s": t_s, "x_north_m": float(pos[i, 0]), "y_east_m": float(pos[i, 1]),
                             "vx_north_m_s": float(v_ne[0]), "vy_east_m_s": float(v_ne[1]), "speed_m_s": speed,
                             "distance_to_slot_m": float(slot_dist[i])}, log_time=lt)
            self.counts.add("/uav*/fix"); self.counts.add("/uav*/state")
            if acc_m_s2 is not None:
                a = acc_m_s2[i]
                sp = {"t_s": t_s, "acc_north_m_s2": float(a[0]), "acc_east_m_s2": float(a[1]), "acc_norm_m_s2": float(np.hypot(*a))}
                if backstop_active is not None:
                    sp["backstop_active"] = bool(backstop_active[i])
                if backstop_layer is not None:
                    sp["backstop_layer"] = int(backstop_layer[i])
                    sp["backstop_layers"] = layer_names(backstop_layer[i])
                ch.setpoint[i].log(sp, log_time=lt); self.counts.add("/uav*/setpoint")
            p3 = Vector3(x=float(pos[i, 1]), y=float(pos[i, 0]), z=float(self.alt[i]))
            yaw = math.atan2(float(v_ne[0]), float(v_ne[1]))        # ENU: angle from x (east) towards y (north)
            arrows = [ArrowPrimitive(pose=Pose(position=p3, orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))),
                                     shaft_length=0.7 * speed, shaft_diameter=0.05, head_length=0.3 * speed, head_diameter=0.15,
                                     color=colour)] if speed > 1e-6 else []
            entities.append(SceneEntity(timestamp=ts, frame_id="swarm_enu", id=f"uav{i}",
                                        metadata=[KeyValuePair(key="speed_m_s", value=f"{speed:.3f}")],
                                        spheres=[SpherePrimitive(pose=Pose(position=p3, orientation=q_id),
                                                                 size=Vector3(x=r2, y=r2, z=r2), color=colour)],
                                        arrows=arrows,
                                        texts=[TextPrimitive(pose=Pose(position=p3, orientation=q_id), billboard=True, font_size=12.0,
                                                             scale_invariant=True, color=colour, text=str(i))]))
        entities.append(SceneEntity(timestamp=ts, frame_id="swarm_enu", id="slots", spheres=self._slots))
        if ij[0, 0] >= 0 and np.isfinite(d[0]):
            i, j = (int(x) for x in ij[0])
            hot = Color(r=1.0, g=0.1, b=0.1, a=1.0) if d[0] < M.COLLISION_DISTANCE_M else Color(r=1.0, g=0.6, b=0.0, a=1.0)
            pi = (float(pos[i, 1]), float(pos[i, 0]), float(self.alt[i]))
            pj = (float(pos[j, 1]), float(pos[j, 0]), float(self.alt[j]))
            mid = Vector3(x=(pi[0] + pj[0]) / 2, y=(pi[1] + pj[1]) / 2, z=(pi[2] + pj[2]) / 2)
            entities.append(SceneEntity(timestamp=ts, frame_id="swarm_enu", id="closest_pair",
                                        lines=[LinePrimitive(pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=q_id),
                                                             thickness=3.0, scale_invariant=True, color=hot,
                                                             points=[Point3(x=pi[0], y=pi[1], z=pi[2]), Point3(x=pj[0], y=pj[1], z=pj[2])])],
                                        texts=[TextPrimitive(pose=Pose(position=mid, orientation=q_id), billboard=True, font_size=12.0,
                                                             scale_invariant=True, color=hot, text=f"{d[0]:.2f} m ({i}, {j})")]))
        ch.scene.log(SceneUpdate(entities=entities), log_time=lt); self.counts.add("/swarm/scene")
        inside = (slot_dist <= M.ARRIVAL_TOLERANCE_M) & ok
        sep = {"t_s": t_s, "min_separation_m": float(d[0]) if np.isfinite(d[0]) else None,
               "closest_i": int(ij[0, 0]), "closest_j": int(ij[0, 1]), "arrived": int(inside.sum()),
               "arrived_fraction": float(inside.mean())}
        if collided_pairs_so_far is not None:
            sep["collided_pairs_so_far"] = int(collided_pairs_so_far)
        ch.separation.log(sep, log_time=lt); self.counts.add("/swarm/separation")


def write_mcap(rec: FlightRecord, out_path: str | Path) -> RecordingSummary:
    """Write ``rec`` as MCAP (docs/formats.md, "flight.mcap") to ``out_path``, atomically: a temporary file in
    the same folder, renamed at the end; on any error nothing is left behind."""
    import foxglove
    from foxglove.messages import Event, KeyValuePair, Log, LogLevel

    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    traj, n, T = rec.traj, rec.n, rec.steps
    dt = float(traj.dt_s)
    base = 0.0 if rec.t0_unix_s is None else float(rec.t0_unix_s)
    t_s = np.arange(T + 1) * dt
    pos = traj.pos_m
    col_events = collision_events(pos) if n > 1 and np.all(np.isfinite(pos)) else []
    bs = backstop_intervals(rec.backstop_active) if rec.backstop_active is not None else []

    fd, tmp = tempfile.mkstemp(prefix=f".{out_path.name}.", suffix=".tmp", dir=out_path.parent)
    os.close(fd)
    writer = None
    try:
        ctx = foxglove.Context()
        writer = foxglove.open_mcap(tmp, allow_overwrite=True, context=ctx)
        ch = RecordingChannels(ctx, n, controllers=bool(rec.controller_logs))
        pub = InstantPublisher(ch, datum=rec.datum, altitude_agl_m=rec.altitude_agl_m, dest_m=traj.dest_m,
                               safety_radius_m=rec.safety_radius_m, base_s=base)
        counts = pub.counts
        info = {"n": n, "steps": T, "dt_s": dt, "clock": "simulation" if rec.t0_unix_s is None else "wall",
                "t0_unix_s": base, "datum": {"lat_deg": rec.datum.lat_deg, "lon_deg": rec.datum.lon_deg,
                                             "alt_amsl_m": rec.datum.alt_amsl_m},
                "safety_radius_m": rec.safety_radius_m, "source": rec.source, "frame": "swarm NED at the datum; scene in swarm_enu"}
        writer.write_metadata("recording", {k: json.dumps(v) for k, v in info.items()})
        writer.write_metadata("metrics", {k: json.dumps(v) for k, v in rec.metrics.items()})

        # events, stamped at their start (readers sort by log time)
        step_logs: dict[int, list[tuple[str, LogLevel]]] = {}
        for i, j, k0, k1, dmin_ij in col_events:
            ev = Event(start_time=pub.stamp(t_s[k0]), end_time=pub.stamp(t_s[min(k1 + 1, T)]),
                       metadata=[KeyValuePair(key="kind", value="collision"), KeyValuePair(key="uav_i", value=str(i)),
                                 KeyValuePair(key="uav_j", value=str(j)), KeyValuePair(key="first_step", value=str(k0)),
                                 KeyValuePair(key="last_step", value=str(k1)),
                                 KeyValuePair(key="min_distance_m", value=f"{dmin_ij:.4f}")])
            ch.collision.log(ev, log_time=_ns(base + t_s[k0])); counts.add("/events/collision")
            step_logs.setdefault(k0, []).append(
                (f"collision: UAVs {i} and {j} closer than {M.COLLISION_DISTANCE_M} m (closest {dmin_ij:.3f} m, "
                 f"steps {k0}-{k1})", LogLevel.Error))
        for v, k0, k1 in bs:
            # the layers that made the commands over the interval (their union), where the flight recorded them
            layers = (layer_names(int(np.bitwise_or.reduce(rec.backstop_layer[k0:k1 + 1, v])))
                      if rec.backstop_layer is not None else None)
            ev = Event(start_time=pub.stamp(t_s[k0]), end_time=pub.stamp(t_s[k1 + 1]),
                       metadata=[KeyValuePair(key="kind", value="backstop"), KeyValuePair(key="uav", value=str(v)),
                                 KeyValuePair(key="first_step", value=str(k0)), KeyValuePair(key="last_step", value=str(k1)),
                                 KeyValuePair(key="steps", value=str(k1 - k0 + 1))]
                       + ([KeyValuePair(key="layers", value=layers)] if layers is not None else []))
            ch.backstop.log(ev, log_time=_ns(base + t_s[k0])); counts.add("/events/backstop")
            step_logs.setdefault(k0, []).append(
                (f"backstop: UAV {v} corrected its command for {k1 - k0 + 1} step(s) from step {k0}"
                 + (f" ({layers})" if layers is not None else ""), LogLevel.Warning))

        first_contact = sorted(e[2] for e in col_events)
        collided = 0
        for k in range(T + 1):
            while collided < len(first_contact) and first_contact[collided] <= k:
                collided += 1
            pub.log(float(t_s[k]), pos[k], traj.vel_m_s[k], traj.acc_m_s2[k] if k < T else None,
                    rec.backstop_active[k] if (rec.backstop_active is not None and k < T) else None, collided,
                    rec.backstop_layer[k] if (rec.backstop_layer is not None and k < T) else None)
            for text, level in step_logs.get(k, []):
                ch.log.log(Log(timestamp=pub.stamp(float(t_s[k])), level=level, message=text, name="mfg_swarm"),
                           log_time=_ns(base + t_s[k]))
                counts.add("/log")
        if rec.controller_logs:
            _write_controller_logs(rec, ch, counts, base)
        writer.close()
        writer = None
        os.replace(tmp, out_path)
    except BaseException:
        if writer is not None:
            try:
                writer.close()
            except Exception:
                pass
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return RecordingSummary(out_path, dict(counts), len(col_events), len(bs))


def _write_controller_logs(rec: FlightRecord, ch: RecordingChannels, counts: _Counter, base: float) -> None:
    """Each controller's log: its step records' scalars on /uav<i>/controller (at the step's time), its start, events
    and end on /uav<i>/controller_log (foxglove.Log; at the step the event happened in a lockstep flight, at its wall
    time otherwise)."""
    from foxglove.messages import Log, LogLevel, Timestamp

    dt = float(rec.traj.dt_s)
    lockstep = rec.t0_unix_s is None

    def ts(ns: int) -> Timestamp:
        return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)

    for i, lg in enumerate(rec.controller_logs):
        if not ch.controller:
            break
        # a wall-clock instant of the controller's log -> the recording's clock (lockstep: the last step logged before it)
        step_wall = [(float(s.get("wall_s", 0.0)), int(s["step"])) for s in lg.steps if "step" in s]

        def when(wall_s: float | None) -> int:
            if wall_s is None:
                return _ns(base)
            if not lockstep:
                return _ns(float(wall_s))
            before = [k for w, k in step_wall if w <= wall_s]
            return _ns(base + (max(before) + 1) * dt) if before else _ns(base)

        for s in lg.steps:
            k = int(s.get("step", -1))
            if not 0 <= k <= rec.steps:
                continue
            lt = _ns(base + k * dt) if lockstep else _ns(float(s.get("wall_s", base + k * dt)))
            ch.controller[i].log({key: s.get(key) for key in _CONTROLLER_STEP_KEYS if key in s}, log_time=lt)
            counts.add("/uav*/controller")
        records = ([("start", lg.start)] if lg.start else []) + [("event", e) for e in lg.events] + ([("end", lg.end)] if lg.end else [])
        for kind, r in records:
            what = r.get("what", kind) if kind == "event" else kind
            level = LogLevel.Error if what in ("error", "hold_failed", "offboard_resume_failed") else (
                LogLevel.Warning if what in ("telemetry_stale", "left_offboard", "hold") else LogLevel.Info)
            body = {k: v for k, v in r.items() if k not in ("type", "config")}
            lt = when(r.get("wall_s"))
            ch.controller_log[i].log(Log(timestamp=ts(lt), level=level, message=f"{what}: {json.dumps(body)}",
                                         name=f"controller{i}"), log_time=lt)
            counts.add("/uav*/controller_log")


def record_run(run_dir: str | Path, out_path: str | Path | None = None, **load_kw) -> RecordingSummary:
    """``load_run`` + ``write_mcap``: ``run_dir``/flight.mcap (or ``out_path``)."""
    rec = load_run(run_dir, **load_kw)
    return write_mcap(rec, Path(run_dir) / MCAP_NAME if out_path is None else out_path)
