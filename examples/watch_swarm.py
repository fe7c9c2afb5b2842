"""Watch a swarm: print every state and membership change published under ``mfg/<swarm>/``.

An independent client: it uses zenoh directly and decodes the state payload with ``struct``
from the layout in docs/zenoh.md (it does not import the flight stack).

    python examples/watch_swarm.py --swarm demo --connect tcp/127.0.0.1:7447
    python examples/watch_swarm.py --swarm demo --connect tcp/127.0.0.1:7447 --count 20
    python examples/watch_swarm.py --swarm demo --connect tcp/127.0.0.1:7447 --vehicles 9

Output, one line per sample:

    state vehicle=3 step=12 t=12.000s x=148.20m y=101.40m vx=0.91m/s vy=-1.02m/s
    alive vehicle=3 joined | alive vehicle=3 left
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import threading
import time

import zenoh

# docs/zenoh.md, "State payload v1": little-endian, 56 bytes
STATE_FORMAT = "<2sBBIqd4d"  # magic b"MF", version u8 = 1, flags u8 = 0, vehicle_id u32,
STATE_SIZE = struct.calcsize(STATE_FORMAT)  # step i64, time_s f64, x_m, y_m, vx_m_s, vy_m_s f64


def decode_state(payload: bytes) -> tuple[int, int, float, tuple[float, ...]]:
    if len(payload) != STATE_SIZE:
        raise ValueError(f"length {len(payload)} != {STATE_SIZE}")
    magic, version, _flags, vid, step, t_s, *state = struct.unpack(STATE_FORMAT, payload)
    if magic != b"MF" or version != 1:
        raise ValueError(f"magic/version {magic!r}/{version}")
    if not all(math.isfinite(v) for v in (t_s, *state)):
        raise ValueError("non-finite value")
    return vid, step, t_s, tuple(state)


INIT_WAIT_S = 10.0  # longest wait for the t = 0 states
QUIET_S = 1.0      # swarm size unknown: nothing new for this long, all answered


def main(conf: zenoh.Config, swarm: str, count: int, duration_s: float, vehicles: int = 0) -> int:
    done = threading.Event()
    lock = threading.Lock()
    printed = 0

    def emit(line: str) -> None:
        nonlocal printed
        with lock:
            if done.is_set():
                return
            print(line, flush=True)
            printed += 1
            if count and printed >= count:
                done.set()

    def on_state(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            vid, step, t_s, (x, y, vx, vy) = decode_state(sample.payload.to_bytes())
        except ValueError as e:
            print(f"bad payload on {key}: {e}", flush=True)
            return
        kind = "init" if "/init/" in key else "state"
        emit(f"{kind} vehicle={vid} step={step} t={t_s:.3f}s x={x:.2f}m y={y:.2f}m "
             f"vx={vx:.2f}m/s vy={vy:.2f}m/s")

    alive: set[str] = set()    # vehicle ids whose liveliness token is up

    def on_alive(sample: zenoh.Sample) -> None:
        vid = str(sample.key_expr).rsplit("/", 1)[-1]
        joined = sample.kind == zenoh.SampleKind.PUT
        with lock:
            (alive.add if joined else alive.discard)(vid)
        print(f"alive vehicle={vid} {'joined' if joined else 'left'}", flush=True)

    with zenoh.open(conf) as session:
        session.declare_subscriber(f"mfg/{swarm}/state/*", on_state)
        session.liveliness().declare_subscriber(f"mfg/{swarm}/alive/*", on_alive, history=True)
        # t = 0 states of vehicles that already did their initial exchange. In peer mode this session reaches a
        # vehicle's queryable only once it has its own link to that vehicle, learnt by gossip from the one it
        # connected to: a moment after it opens, longer on a loaded machine. So ask again until `vehicles` have
        # answered (when given), else until every vehicle whose token is up has answered and nothing new (answer,
        # token, peer link) came for QUIET_S; at most INIT_WAIT_S in all.
        seen_init: set[str] = set()

        def on_init(reply) -> None:
            if reply.ok is not None and str(reply.ok.key_expr) not in seen_init:
                seen_init.add(str(reply.ok.key_expr))
                on_state(reply.ok)

        deadline = time.monotonic() + INIT_WAIT_S
        last_news, last_seen = time.monotonic(), None
        while not done.is_set() and time.monotonic() < deadline:
            for reply in session.get(f"mfg/{swarm}/init/*", target=zenoh.QueryTarget.ALL, timeout=2.0):
                on_init(reply)
            with lock:
                answered = {k.rsplit("/", 1)[-1] for k in seen_init}
                seen = (frozenset(answered), frozenset(alive), frozenset(str(z) for z in session.info.peers_zid()))
            if seen != last_seen:
                last_news, last_seen = time.monotonic(), seen
            if vehicles:
                if len(answered) >= vehicles:
                    break
            elif answered and alive <= answered and time.monotonic() - last_news >= QUIET_S:
                break
            time.sleep(0.1)
        print(f"watching mfg/{swarm}/**", flush=True)
        done.wait(duration_s if duration_s > 0 else None)
        done.set()
    return 0


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--swarm", default="demo")
    ap.add_argument("--mode", choices=["peer", "client"], default="peer")
    ap.add_argument("--connect", action="append", default=[], help="e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--vehicles", type=int, default=0,
                    help="swarm size: wait (<= 10 s) for this many t = 0 states (0: until none new for 1 s)")
    ap.add_argument("--count", type=int, default=0, help="exit after this many states (0: never)")
    ap.add_argument("--duration", type=float, default=0.0, help="exit after this many s (0: never)")
    args = ap.parse_args()
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(args.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    conf.insert_json5("listen/endpoints", json.dumps(args.listen or ["tcp/127.0.0.1:0"]))
    try:
        raise SystemExit(main(conf, args.swarm, args.count, args.duration, args.vehicles))
    except KeyboardInterrupt:
        raise SystemExit(130)
