"""flight.mcap (issue 21): written by `sim --record`, `run` and `convert`, read back with the mcap library and
every channel decoded with its own schema (protobuf: the Foxglove SDK's well-known schemas; JSON Schema: ours).

Tolerances: the JSON topics carry the trajectories' float64 exactly (JSON keeps a double's shortest repr);
LocationFix carries latitude and longitude as doubles, so swarm-frame metres -> WGS84 -> metres through
pymap3d returns the position to GEODETIC_TOL_M; a run's trajectories come from float32 telemetry
(LOCAL_POSITION_NED), and convert rebuilds them from the same tlogs, so they agree exactly.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil
import pytest
from mcap.decoder import DecoderFactory as _DecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

from mfg_autopilot.mission import DEFAULT_DATUM, SwarmFrame
from mfg_swarm.animate import frame_steps
from mfg_swarm.cli import main
from mfg_swarm.results import load_trajectories

GEODETIC_TOL_M = 1e-6
RUN_TIMEOUT_S = 240


class _JsonDecoderFactory(_DecoderFactory):
    def decoder_for(self, message_encoding, schema):
        if message_encoding == "json" and schema is not None and schema.encoding == "jsonschema":
            return lambda data: json.loads(data)
        return None


def read_mcap(path: Path) -> tuple[dict[str, list[tuple[int, object]]], dict[str, tuple[str, str]], dict[str, dict]]:
    """Every message decoded with its channel's schema: ({topic: [(log_time_ns, message)]}, {topic: (schema name,
    schema encoding)}, {metadata name: {key: value}})."""
    msgs: dict[str, list] = defaultdict(list)
    schemas = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[ProtobufDecoderFactory(), _JsonDecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            assert schema is not None, f"{channel.topic} has no schema"
            schemas[channel.topic] = (schema.name, schema.encoding)
            msgs[channel.topic].append((message.log_time, decoded))
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return dict(msgs), schemas, meta


def _sim(out: Path, *args: str) -> dict:
    assert main(["sim", "--n", "9", "--steps", "40", "--no-progress", "--out", str(out), *args]) == 0
    return json.loads((out / "metrics.json").read_text())


def _no_leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".flight") or p.name == "flight.mcap")


@pytest.fixture(scope="module")
def paper_sim(tmp_path_factory) -> tuple[Path, dict]:
    """The paper preset collides (4 pairs within 40 steps at N = 9, seed 0)."""
    out = tmp_path_factory.mktemp("rec") / "paper"
    m = _sim(out, "--preset", "paper", "--record")
    return out, m


def test_sim_record_positions_setpoints_and_counts_match_the_run_folder(paper_sim):
    out, m = paper_sim
    traj = load_trajectories(out / "trajectories.npz")
    msgs, schemas, meta = read_mcap(out / "flight.mcap")
    n, T = m["n"], m["steps"]
    assert json.loads(meta["recording"]["n"]) == n and json.loads(meta["recording"]["clock"]) == "simulation"
    assert {t for t in msgs if t.endswith("/fix")} == {f"/uav{i}/fix" for i in range(n)}
    for topic, (name, enc) in schemas.items():
        assert enc in ("protobuf", "jsonschema"), (topic, enc)
    assert schemas["/uav0/fix"] == ("foxglove.LocationFix", "protobuf")
    assert schemas["/swarm/scene"] == ("foxglove.SceneUpdate", "protobuf")
    frame = SwarmFrame(DEFAULT_DATUM)
    t_ns = np.round(traj.t_s * 1e9).astype(np.int64)
    for i in range(n):
        fixes = msgs[f"/uav{i}/fix"]
        assert len(fixes) == T + 1
        assert [lt for lt, _ in fixes] == t_ns.tolist()                 # simulation time
        ned = frame.geodetic_to_ned([f.latitude for _, f in fixes], [f.longitude for _, f in fixes],
                                    [f.altitude for _, f in fixes])
        np.testing.assert_allclose(ned[:, 0:2], traj.pos_m[:, i], rtol=0, atol=GEODETIC_TOL_M)
        states = [s for _, s in msgs[f"/uav{i}/state"]]
        assert np.array_equal([[s["x_north_m"], s["y_east_m"]] for s in states], traj.pos_m[:, i])
        assert np.array_equal([[s["vx_north_m_s"], s["vy_east_m_s"]] for s in states], traj.vel_m_s[:, i])
        sps = [s for _, s in msgs[f"/uav{i}/setpoint"]]
        assert len(sps) == T
        assert np.array_equal([[s["acc_north_m_s2"], s["acc_east_m_s2"]] for s in sps], traj.acc_m_s2[:, i])
    # the scene: every vehicle as a sphere of the safety radius, every step
    scenes = [s for _, s in msgs["/swarm/scene"]]
    assert len(scenes) == T + 1
    uavs = [e for e in scenes[-1].entities if e.id.startswith("uav")]
    assert len(uavs) == n and all(abs(e.spheres[0].size.x - 2 * 0.05) < 1e-12 for e in uavs)
    assert {e.id for e in scenes[-1].entities} >= {"slots", "closest_pair"}
    # collisions: one event per collided pair, the pairs of metrics.json
    assert m["collision_pairs"] > 0
    events = [e for _, e in msgs["/events/collision"]]
    assert len(events) == m["collision_pairs"]
    pairs = sorted([int(kv["uav_i"]), int(kv["uav_j"])] for kv in ({p.key: p.value for p in e.metadata} for e in events))
    assert pairs == sorted(m["collided_pairs_list"])
    # separation: per instant, never below the flight's closest approach (which is over whole segments)
    sep = [s["min_separation_m"] for _, s in msgs["/swarm/separation"]]
    assert len(sep) == T + 1 and min(sep) >= m["min_separation_m"] - 1e-12
    assert sum(1 for _, lg in msgs["/log"] if "collision" in lg.message) == m["collision_pairs"]


def test_backstop_interventions_are_events_whose_steps_add_up_to_the_metric(tmp_path):
    # HJB_0.3 in the 0.5 m dense grid hears nobody and senses everybody: its backstop acts (MFG's rigid plans leave
    # the backstop idle when nobody is off the plan); on the paper's plant (with PX4's lag, the default airframe, this
    # flight's backstop does not act in 40 steps)
    m = _sim(tmp_path / "fail", "--scenario", "dense", "--mode", "hjb", "--range-m", "0.3", "--record", "--acc-lag-s", "0")
    msgs, _, _ = read_mcap(tmp_path / "fail" / "flight.mcap")
    assert m["backstop_activations"] > 0
    steps = [int({p.key: p.value for p in e.metadata}["steps"]) for _, e in msgs["/events/backstop"]]
    assert sum(steps) == m["backstop_activations"]
    # which layer acted (safety.backstop.Layer): HJB_d's backstop is the planned vehicles' reciprocal push, so every
    # intervention event names it, and every setpoint carries the bits the trajectories recorded, with their names
    assert {{p.key: p.value for p in e.metadata}["layers"] for _, e in msgs["/events/backstop"]} == {"planned"}
    layer = load_trajectories(tmp_path / "fail" / "trajectories.npz").extra["backstop_layer"]
    for i in range(m["n"]):
        sps = [s for _, s in msgs[f"/uav{i}/setpoint"]]
        assert [s["backstop_layer"] for s in sps] == layer[:, i].tolist()
        assert all(s["backstop_layers"] == ("planned" if s["backstop_active"] else "-") for s in sps)
    # HJB_0.3 is no safe controller (with dense starting at rest it collides once here): whatever it does, the
    # recording has one collision event per collided pair of the metric
    assert len(msgs.get("/events/collision", [])) == m["collision_pairs"]


def test_sim_without_record_writes_no_mcap(tmp_path):
    assert main(["sim", "--n", "4", "--steps", "3", "--no-progress", "--out", str(tmp_path / "q")]) == 0
    assert not (tmp_path / "q" / "flight.mcap").exists()


def test_convert_refuses_a_corrupt_or_truncated_npz_and_leaves_nothing(paper_sim, tmp_path, capsys):
    src, _ = paper_sim
    for name, damage in (("truncated", lambda b: b[: len(b) // 2]), ("garbage", lambda b: b"not a zip file" * 10)):
        d = tmp_path / name
        shutil.copytree(src, d)
        (d / "flight.mcap").unlink()
        npz = d / "trajectories.npz"
        npz.write_bytes(damage(npz.read_bytes()))
        assert main(["convert", str(d)]) == 2
        err = capsys.readouterr().err
        assert "trajectories.npz" in err and "corrupt or truncated" in err, err
        assert _no_leftovers(d) == []


def test_animate_writes_a_gif_with_one_frame_per_drawn_step(paper_sim, capsys):
    from PIL import Image

    out, m = paper_sim
    assert main(["plot", "--animate", "--max-frames", "11", str(out)]) == 0
    gif = out / "flight.gif"
    assert str(gif) in capsys.readouterr().out
    expected = frame_steps(m["steps"] + 1, 11)
    assert expected.tolist() == list(range(0, 41, 4))
    with Image.open(gif) as im:
        assert im.n_frames == len(expected)
    assert gif.stat().st_size < 2_000_000


# ------------------------------------------------------------------------------------- a process swarm

def _children() -> set[int]:
    return {p.pid for p in psutil.Process().children(recursive=True)}


def _assert_no_children_left(before: set[int]) -> None:
    left = [p for p in psutil.Process().children(recursive=True)
            if p.pid not in before and p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, f"processes left behind: {[p.cmdline()[:4] for p in left]}"


def _ws_decoder(channel: dict):
    """A decoder for one advertised channel (Foxglove WebSocket protocol: protobuf schemas come base64-encoded)."""
    import base64

    from mcap.records import Schema

    if channel["encoding"] == "protobuf":
        schema = Schema(id=channel["id"], name=channel["schemaName"], encoding="protobuf", data=base64.b64decode(channel["schema"]))
        return ProtobufDecoderFactory().decoder_for("protobuf", schema)
    assert channel["encoding"] == "json", channel
    return json.loads


@dataclass
class LiveRun:
    """A process swarm flown with ``run --live 0`` while a WebSocket client watched it."""

    out: Path
    subprotocol: str
    states: dict[int, dict[float, list[float]]]      # vehicle -> {t_s: [x_north_m, y_east_m]} as served live
    decoded_topics: set[str]


@pytest.fixture(scope="module")
def live_run(tmp_path_factory) -> LiveRun:
    """`mfg-swarm run --n 4 --steps 20 --live 0` (lockstep, mock vehicles + controllers on loopback, recorded by
    default), watched by a real WebSocket client (websockets) on loopback: advertise -> subscribe -> binary
    MessageData (opcode 1, u32 subscription id, u64 log time, payload), each payload decoded with its channel's
    schema. foxglove-sdk 0.30 speaks the protocol under the subprotocol name foxglove.sdk.v1 (a client offering
    only foxglove.websocket.v1 gets HTTP 400); the client offers both."""
    import queue
    import re
    import struct
    import threading
    import time

    from websockets.sync.client import connect

    n, out = 4, tmp_path_factory.mktemp("run") / "run4"
    before = _children()
    proc = subprocess.Popen([sys.executable, "-m", "mfg_swarm.cli", "run", "--n", str(n), "--steps", "20", "--live", "0",
                             "--out", str(out), "--no-progress", "--no-plot"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stderr], daemon=True).start()
    states: dict[int, dict[float, list[float]]] = defaultdict(dict)
    decoded: set[str] = set()
    try:
        port, deadline = None, time.monotonic() + 60
        while port is None and time.monotonic() < deadline:
            try:
                m = re.search(r"live: ws://127\.0\.0\.1:(\d+)", lines.get(timeout=max(0.1, deadline - time.monotonic())))
            except queue.Empty:
                break
            port = int(m.group(1)) if m else None
        assert port, "the launcher did not print its live port within 60 s"
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                     open_timeout=10, proxy=None, compression=None) as ws:
            subprotocol = ws.subprotocol
            subs: dict[int, tuple[str, object]] = {}
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline and not all(len(states[i]) >= 5 for i in range(n)):
                try:
                    frame = ws.recv(timeout=2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg["op"] == "advertise":
                        new = []
                        for ch in msg["channels"]:
                            sid = len(subs) + 1
                            subs[sid] = (ch["topic"], _ws_decoder(ch))
                            new.append({"id": sid, "channelId": ch["id"]})
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    continue
                assert frame[0] == 0x01, f"unexpected binary opcode {frame[0]}"
                sid, log_time_ns = struct.unpack_from("<IQ", frame, 1)
                topic, decode = subs[sid]
                payload = decode(bytes(frame[13:]))
                decoded.add(topic)
                m = re.fullmatch(r"/uav(\d+)/state", topic)
                if m:
                    assert log_time_ns == round(payload["t_s"] * 1e9)          # lockstep: simulation time
                    states[int(m.group(1))][payload["t_s"]] = [payload["x_north_m"], payload["y_east_m"]]
        rc = proc.wait(timeout=RUN_TIMEOUT_S)
        assert rc == 0, "".join(lines.queue)[-3000:]
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=60)
    _assert_no_children_left(before)
    return LiveRun(out, subprotocol, dict(states), decoded)


@pytest.fixture(scope="module")
def swarm_run(live_run) -> Path:
    return live_run.out


@pytest.mark.e2e
def test_run_records_by_default_with_the_controllers_logs(swarm_run):
    m = json.loads((swarm_run / "metrics.json").read_text())
    msgs, _, _ = read_mcap(swarm_run / "flight.mcap")
    for i in range(m["n"]):
        assert len(msgs[f"/uav{i}/fix"]) == m["steps"] + 1
        assert len(msgs[f"/uav{i}/controller"]) >= m["steps"]
        assert any("offboard" in lg.message for _, lg in msgs[f"/uav{i}/controller_log"])
    # the default controllers log which safety layer made each command; run keeps it and the recording carries it
    layer = load_trajectories(swarm_run / "trajectories.npz").extra["backstop_layer"]
    assert m["safety_interventions_by_layer"]["escape"] == int(np.count_nonzero(layer & 2))
    for i in range(m["n"]):
        sps = [s for _, s in msgs[f"/uav{i}/setpoint"]]
        assert [s["backstop_layer"] for s in sps] == layer[:, i].tolist()
        assert [c["backstop_layer"] for _, c in msgs[f"/uav{i}/controller"]][:len(sps)] == layer[:, i].tolist()


@pytest.mark.e2e
def test_convert_rebuilds_the_flight_from_the_tlogs_alone(swarm_run, tmp_path):
    d = tmp_path / "tlogs_only"
    shutil.copytree(swarm_run, d)
    (d / "trajectories.npz").unlink()
    (d / "flight.mcap").unlink()
    assert main(["convert", str(d)]) == 0
    traj = load_trajectories(swarm_run / "trajectories.npz")
    msgs, _, meta = read_mcap(d / "flight.mcap")
    assert json.loads(meta["recording"]["source"]) == "4 tlog(s)"
    for i in range(4):
        states = [s for _, s in msgs[f"/uav{i}/state"]]
        assert np.array_equal([[s["x_north_m"], s["y_east_m"]] for s in states], traj.pos_m[:, i])
        sps = [s for _, s in msgs[f"/uav{i}/setpoint"]]
        assert np.array_equal([[s["acc_north_m_s2"], s["acc_east_m_s2"]] for s in sps], traj.acc_m_s2[:, i])


@pytest.mark.e2e
@pytest.mark.parametrize("damage,word", [
    (lambda b: b[:-5], "truncated"),                                    # a record cut short
    (lambda b: b[:4000] + b"\x00" * 64 + b[4064:], "corrupt"),          # a stretch of zeros: no stamp, no magic
])
def test_convert_refuses_a_damaged_tlog_and_leaves_nothing(swarm_run, tmp_path, capsys, damage, word):
    d = tmp_path / "bad"
    shutil.copytree(swarm_run, d)
    (d / "flight.mcap").unlink()
    (d / "trajectories.npz").unlink()          # convert reads the tlogs only without an npz
    tlog = d / "vehicles" / "vehicle2.tlog"
    tlog.write_bytes(damage(tlog.read_bytes()))
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "convert", str(d)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode != 0
    assert "vehicle2.tlog" in proc.stderr and word in proc.stderr, proc.stderr
    assert _no_leftovers(d) == []


def test_the_layout_in_docs_is_the_generated_one_and_names_only_recorded_topics(paper_sim):
    import re

    from mfg_swarm.foxglove_layout import layout_json

    doc = (Path(__file__).resolve().parents[1] / "docs" / "foxglove_layout.json").read_text()
    assert doc == layout_json(9), "docs/foxglove_layout.json is stale: python -m mfg_swarm.foxglove_layout --out it"
    msgs, _, _ = read_mcap(paper_sim[0] / "flight.mcap")
    named = set(re.findall(r'"(/(?:uav\d+|swarm|log)[^".]*)', doc))
    assert named and named <= set(msgs), named - set(msgs)


@pytest.mark.e2e
def test_run_live_serves_every_vehicle_over_the_foxglove_websocket_protocol(live_run):
    assert live_run.subprotocol == "foxglove.sdk.v1"
    assert all(len(live_run.states.get(i, {})) >= 5 for i in range(4)), {i: len(v) for i, v in live_run.states.items()}
    assert {f"/uav{i}/fix" for i in range(4)} | {"/swarm/scene", "/swarm/separation"} <= live_run.decoded_topics
    # what was served live is what the vehicles flew (the controllers log the float32 telemetry they received)
    traj = load_trajectories(live_run.out / "trajectories.npz")
    for i in range(4):
        for t_s, xy in live_run.states[i].items():
            np.testing.assert_allclose(xy, traj.pos_m[round(t_s / traj.dt_s), i], rtol=0, atol=1e-9)


def test_check_tlog_frames_records_and_names_a_cut_or_corrupt_one(tmp_path):
    from mavlink_bridge import TlogError, TlogWriter, check_tlog

    def v2_packet(payload: bytes, msg_id: int = 32) -> bytes:     # framing only: check_tlog does not verify the CRC
        return bytes([0xFD, len(payload), 0, 0, 7, 1, 1]) + msg_id.to_bytes(3, "little") + payload + b"\x00\x00"

    good = tmp_path / "good.tlog"
    with TlogWriter(good) as w:
        for k in range(3):
            w.write(v2_packet(bytes(28)), unix_time_s=1.8e9 + k)
    info = check_tlog(good)
    assert info.n_records == 3 and info.first_unix_s == 1.8e9 and info.last_unix_s == 1.8e9 + 2
    data = good.read_bytes()
    record = len(data) // 3
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[:-3])
    with pytest.raises(TlogError, match=rf"cut.tlog: truncated: record 2 at offset {2 * record}"):
        check_tlog(cut)
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(data[:record] + data[record:record + 8] + b"\x55" + data[record + 9:])
    with pytest.raises(TlogError, match=rf"bad.tlog: corrupt: record 1 at offset {record} does not hold a MAVLink packet"):
        check_tlog(bad)
    stamp = tmp_path / "stamp.tlog"
    stamp.write_bytes(bytes(8) + data[8:])
    with pytest.raises(TlogError, match="corrupt: record 0 at offset 0 has no UNIX time stamp"):
        check_tlog(stamp)


def test_the_recording_draws_the_scenarios_default_safety_radius():
    from mfg_swarm import recording, scenarios

    assert recording.DEFAULT_SAFETY_RADIUS_M == scenarios.DEFAULT_SAFETY_RADIUS_M
