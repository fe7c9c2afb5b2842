"""Does the live view slow the control loop? (issue 21)

    .venv/bin/python bench/live_overhead.py --n 9 --steps 80 --reps 2 --out runs/live

Flies `mfg-swarm run --realtime` (real processes: mock vehicles, controllers, MAVLink, Zenoh) alternately
without and with `--live` (the Foxglove WebSocket server in the launcher), the live runs watched by a real
WebSocket client subscribed to every channel (so the server encodes and sends everything it offers). From
every controller's step records it takes the controller step on the critical path, `latency_compute_ms`
(observation and action, docs/controller_log.md), and the whole step's control time `timing.control_ms`;
it prints p50 and p99 of each configuration and the ratio with / without. Runs alternate (A B A B ...) so
that a drift of the host's speed hits both. Nothing is asserted: the numbers are the measurement
(docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np


def _watch(port: int, stop: threading.Event, counts: dict) -> None:
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                 open_timeout=10, proxy=None, compression=None) as ws:
        sid = 0
        while not stop.is_set():
            try:
                frame = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:            # the server closed: the flight ended
                return
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    subs = []
                    for ch in msg["channels"]:
                        sid += 1
                        subs.append({"id": sid, "channelId": ch["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            else:
                counts["messages"] = counts.get("messages", 0) + 1


def fly(n: int, steps: int, out: Path, live: bool) -> dict:
    cmd = [sys.executable, "-m", "mfg_swarm.cli", "run", "--realtime", "--n", str(n), "--steps", str(steps),
           "--out", str(out), "--no-progress", "--no-plot", "--no-record"]
    if live:
        cmd += ["--live", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stderr], daemon=True).start()
    stop, counts, watcher = threading.Event(), {}, None
    try:
        if live:
            deadline = time.monotonic() + 120
            port = None
            while port is None and time.monotonic() < deadline:
                try:
                    m = re.search(r"live: ws://127\.0\.0\.1:(\d+)", lines.get(timeout=1.0))
                except queue.Empty:
                    continue
                port = int(m.group(1)) if m else None
            if port is None:
                raise RuntimeError("the launcher printed no live port within 120 s")
            watcher = threading.Thread(target=_watch, args=(port, stop, counts), daemon=True)
            watcher.start()
        rc = proc.wait(timeout=60 + 3 * steps)
        if rc != 0:
            raise RuntimeError(f"run failed (rc {rc}): {''.join(lines.queue)[-2000:]}")
    finally:
        stop.set()
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=30)
        if watcher is not None:
            watcher.join(timeout=10)
    compute, control = [], []
    for f in sorted((out / "controllers").glob("controller*.jsonl")):
        for line in f.read_text().splitlines():
            r = json.loads(line)
            if r.get("type") == "step":
                if r.get("latency_compute_ms") is not None:
                    compute.append(r["latency_compute_ms"])
                if (r.get("timing") or {}).get("control_ms") is not None:
                    control.append(r["timing"]["control_ms"])
    return {"compute_ms": compute, "control_ms": control, "live_messages": counts.get("messages", 0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=9)
    ap.add_argument("--steps", type=int, default=80)
    ap.add_argument("--reps", type=int, default=2, help="flights per configuration, alternating")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    res = {False: {"compute_ms": [], "control_ms": [], "live_messages": 0},
           True: {"compute_ms": [], "control_ms": [], "live_messages": 0}}
    for rep in range(args.reps):
        for live in (False, True):
            r = fly(args.n, args.steps, args.out / f"{'live' if live else 'plain'}{rep}", live)
            for k in ("compute_ms", "control_ms"):
                res[live][k] += r[k]
            res[live]["live_messages"] += r["live_messages"]
    summary = {}
    for live in (False, True):
        name = "live" if live else "without"
        summary[name] = {"steps": len(res[live]["compute_ms"]), "live_messages_received": res[live]["live_messages"]}
        for k in ("compute_ms", "control_ms"):
            x = np.asarray(res[live][k])
            summary[name][k] = {"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99))} if x.size else None
    for k in ("compute_ms", "control_ms"):
        a, b = summary["without"][k], summary["live"][k]
        if a and b:
            summary[f"ratio_{k}_p99"] = b["p99"] / a["p99"]
            summary[f"ratio_{k}_p50"] = b["p50"] / a["p50"]
    (args.out / "live_overhead.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"N = {args.n}, {args.steps} steps x {args.reps} flights per configuration (real time)")
    print("| configuration | steps | compute p50 / p99 ms | control p50 / p99 ms | live messages received |")
    print("|---|---|---|---|---|")
    for name in ("without", "live"):
        s = summary[name]
        c, t = s["compute_ms"], s["control_ms"]
        print(f"| {name} | {s['steps']} | {c['p50']:.2f} / {c['p99']:.2f} | {t['p50']:.2f} / {t['p99']:.2f} | "
              f"{s['live_messages_received']} |")
    print(f"p99 ratio live / without: compute {summary.get('ratio_compute_ms_p99', float('nan')):.3f}, "
          f"control {summary.get('ratio_control_ms_p99', float('nan')):.3f}")


if __name__ == "__main__":
    main()
