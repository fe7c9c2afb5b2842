"""A real field, end to end (issue 19): mock vehicles on the ground with their own EKF origins, the
controllers' whole lifecycle (origin, arm, takeoff, the t = 0 exchange, offboard flight, land,
disarm) over real UDP MAVLink and Zenoh, metrics in the swarm frame, and the simulator agreeing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mavlink_bridge import ExtendedSysState, Heartbeat, MavLandedState, read_tlog
from mfg_autopilot.mission import load_mission, mission_from_ne

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
FIELD = ROOT / "examples" / "field.json"
LIFECYCLE = ["origin", "armed", "takeoff", "at_altitude", "t0_exchange", "offboard", "land", "landed"]


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "mfg_swarm.cli", *args], capture_output=True, text=True, timeout=timeout)


def _events(path: Path) -> list[dict]:
    out = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("type") == "event":
            out.append(rec)
    return out


def _landed_and_disarmed(tlog: Path, system_id: int) -> bool:
    last_hb, last_ext = None, None
    for _, r in read_tlog(tlog, only=("HEARTBEAT", "EXTENDED_SYS_STATE")):
        if r.src_system == system_id and isinstance(r.msg, Heartbeat):
            last_hb = r.msg
        elif r.src_system == system_id and isinstance(r.msg, ExtendedSysState):
            last_ext = r.msg
    return last_hb is not None and not last_hb.armed and last_ext is not None and last_ext.landed_state == MavLandedState.ON_GROUND


def _check_flight(out: Path, mission, steps: int) -> dict:
    metrics = json.loads((out / "metrics.json").read_text())
    assert not metrics["partial"], metrics.get("end_reason")
    assert metrics["steps"] == steps and metrics["collision_pairs"] == 0 and metrics["arrived_fraction"] == 1.0
    assert metrics["min_pair_distance_m"] >= 2 * mission.safety_radius_m
    assert metrics["comm_states_per_uav"] == mission.n - 1                   # MFG: the t = 0 exchange only
    for i in range(mission.n):
        what = [e["what"] for e in _events(out / "controllers" / f"controller{i}.jsonl")]
        assert [w for w in what if w in LIFECYCLE] == LIFECYCLE, (i, what)
        assert _landed_and_disarmed(out / "vehicles" / f"vehicle{i}.tlog", i + 1), i
    return metrics


def test_field_mission_flies_from_the_ground_to_landing_and_the_simulator_agrees(tmp_path):
    mission = load_mission(FIELD)
    steps = 340
    proc = _cli("run", "--mission", str(FIELD), "--steps", str(steps), "--out", str(tmp_path / "run"), "--no-progress", "--no-plot")
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = _check_flight(tmp_path / "run", mission, steps)
    # every vehicle reported its own origin: launch points spread over more than a kilometre
    offsets = np.array([[e for e in _events(tmp_path / "run" / "controllers" / f"controller{i}.jsonl") if e["what"] == "origin"][0]
                        ["offset_ned_m"][:2] for i in range(mission.n)])
    assert np.max(np.linalg.norm(offsets[:, None] - offsets[None], axis=2)) > 1000.0
    # trajectories are in the swarm frame: they start at the mission's launch points and end in the slots
    traj = np.load(tmp_path / "run" / "trajectories.npz")
    assert np.max(np.linalg.norm(traj["pos_m"][0] - mission.arrays()["launch_ne_m"], axis=1)) < 0.5
    # the same mission through the simulator
    proc = _cli("sim", "--mission", str(FIELD), "--steps", str(steps), "--out", str(tmp_path / "sim"), "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    sim = json.loads((tmp_path / "sim" / "metrics.json").read_text())
    assert sim["collision_pairs"] == 0 and sim["arrived_fraction"] == 1.0
    assert sim["arrival_time_s"] == run["arrival_time_s"]
    sim_pos = np.load(tmp_path / "sim" / "trajectories.npz")["pos_m"]
    assert np.max(np.abs(sim_pos - traj["pos_m"])) < 0.05                   # the lockstep processes fly the simulator's flight


def test_vehicles_whose_origins_are_2_km_apart_share_one_frame_and_keep_their_separation(tmp_path):
    """Two groups launched 2 km apart (each vehicle's EKF origin at its launch point) fly to adjacent
    slots in the middle. Had a controller taken its LOCAL_NED for the swarm frame, the t = 0
    exchange would have put both groups at the same place, and nobody would reach its slot."""
    groups = [{"name": "south", "system_ids": [1, 2], "launch_ne_m": (-1000.0, 0.0), "site_ne_m": (-3.0, 0.0),
               "slot_spacing_m": 3.0, "altitude_agl_m": 10.0},
              {"name": "north", "system_ids": [3, 4], "launch_ne_m": (1000.0, 0.0), "site_ne_m": (3.0, 0.0),
               "slot_spacing_m": 3.0, "altitude_agl_m": 10.0}]
    mission = mission_from_ne(groups_ne=groups, safety_radius_m=0.5, on_arrival="land", name="two-km")
    path = tmp_path / "two_km.json"
    path.write_text(json.dumps(mission.to_dict()))
    steps = 560
    proc = _cli("run", "--mission", str(path), "--steps", str(steps), "--out", str(tmp_path / "run"), "--no-progress", "--no-plot")
    assert proc.returncode == 0, proc.stderr[-3000:]
    _check_flight(tmp_path / "run", mission, steps)
    origins = [[e for e in _events(tmp_path / "run" / "controllers" / f"controller{i}.jsonl") if e["what"] == "origin"][0]
               for i in range(4)]
    assert np.linalg.norm(np.subtract(origins[2]["offset_ned_m"], origins[0]["offset_ned_m"])[:2]) == pytest.approx(2000.0, abs=5.0)
    traj = np.load(tmp_path / "run" / "trajectories.npz")
    final = traj["pos_m"][-1]
    assert np.all(np.abs(final[:, 0]) < 6.0)                                # everyone in the middle, in one frame


def test_a_malformed_or_unsafe_mission_is_refused_before_any_vehicle_moves(tmp_path):
    doc = json.loads(FIELD.read_text())
    doc["groups"][2]["site"]["lat_deg"] = 47.5                                # outside the geofence
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    out = tmp_path / "run"
    proc = _cli("run", "--mission", str(bad), "--out", str(out), "--no-progress", "--no-plot", timeout=60)
    assert proc.returncode == 2
    assert "groups[2].site" in proc.stderr and "outside the geofence" in proc.stderr
    assert not (out / "vehicles").exists()                                  # no process was started
    proc = subprocess.run([sys.executable, "-m", "mfg_autopilot.runtime.cli", "--instance", "0", "--n", "20", "--mission", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "groups[2].site" in proc.stderr


def test_a_denied_arming_ends_with_a_clear_error_and_the_vehicle_left_on_the_ground_disarmed(tmp_path):
    """A field mission whose vehicle refuses to arm (a failed preflight check): the controller says so and
    exits 1; the vehicle never left the ground and nothing else was commanded."""
    from _net import running_mock_vehicle

    mission = mission_from_ne(groups_ne=[{"name": "solo", "system_ids": [1], "launch_ne_m": (0.0, 0.0), "site_ne_m": (30.0, 0.0),
                                          "slot_spacing_m": 3.0, "altitude_agl_m": 10.0}], safety_radius_m=0.5, on_arrival="land")
    path = tmp_path / "solo.json"
    path.write_text(json.dumps(mission.to_dict()))
    o, d = mission.launch_geodetic(1), mission.datum
    with running_mock_vehicle("--start", "ground", f"--origin={o.lat_deg},{o.lon_deg},{o.alt_amsl_m}", "--deny-arming",
                              "--home-lat", str(d.lat_deg), "--home-lon", str(d.lon_deg), gcs=True) as mock:
        log = tmp_path / "controller0.jsonl"
        proc = subprocess.run([sys.executable, "-m", "mfg_autopilot.runtime.cli", "--instance", "0", "--n", "1", "--mission", str(path),
                               "--connect", f"udpin:127.0.0.1:{mock.onboard_port}", "--log", str(log), "--exchange-timeout-s", "20",
                               "--zenoh-listen", "tcp/127.0.0.1:0"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 1
        errors = [e for e in _events(log) if e["what"] == "error"]
        assert len(errors) == 1 and "denied" in errors[0]["error"].lower(), errors
        what = [e["what"] for e in _events(log)]
        assert "origin" in what and "takeoff" not in what and "offboard" not in what
        assert "on_ground" in what                                        # the end state: nothing commanded on the ground
        from mavlink_bridge import VehicleLink

        with VehicleLink.open(mock.gcs_url, target_system=1) as gcs:
            hb = gcs.wait_heartbeat(timeout_s=5.0)
            lp = gcs.wait_local_position(None, timeout_s=5.0)
        assert not hb.armed and lp.z_m == 0.0
