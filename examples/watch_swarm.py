"""Watch a swarm: print every state and membership change published under ``mfg/<swarm>/``.

An independent client: it uses zenoh directly and decodes the state payload with ``struct``
from the layout in docs/zenoh.md (it does not import the flight stack).

    python examples/watch_swarm.py --swarm demo --connect tcp/127.0.0.1:7447
    python examples/watch_swarm.py --swarm demo --connect tcp/127.0.0.1:7447 --count 20

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


def main(conf: zenoh.Config, swarm: str, count: int, duration_s: float) -> int:
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

    def on_alive(sample: zenoh.Sample) -> None:
        vid = str(sample.key_expr).rsplit("/", 1)[-1]
        what = "joined" if sample.kind == zenoh.SampleKind.PUT else "left"
        print(f"alive vehicle={vid} {what}", flush=True)

    with zenoh.open(conf) as session:
        session.declare_subscriber(f"mfg/{swarm}/state/*", on_state)
        session.liveliness().declare_subscriber(f"mfg/{swarm}/alive/*", on_alive, history=True)
        # t = 0 states of vehicles that already did their initial exchange; the vehicles' queryables reach a new
        # session a moment after it opens (longer on a loaded machine), so ask again until one answers (<= 10 s)
        seen_init: set[str] = set()

        def on_init(reply) -> None:
            if reply.ok is not None and str(reply.ok.key_expr) not in seen_init:
                seen_init.add(str(reply.ok.key_expr))
                on_state(reply.ok)

        deadline = time.monotonic() + 10.0
        while True:
            before = len(seen_init)
            for reply in session.get(f"mfg/{swarm}/init/*", target=zenoh.QueryTarget.ALL, timeout=2.0):
                on_init(reply)
            if (seen_init and len(seen_init) == before) or time.monotonic() > deadline or done.is_set():
                break               # answered, and a second round found nobody new (or waited long enough)
            time.sleep(0.2 if seen_init else 0.5)
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
        raise SystemExit(main(conf, args.swarm, args.count, args.duration))
    except KeyboardInterrupt:
        raise SystemExit(130)
