"""`mfg-autopilot`: one vehicle's onboard controller process (issue 4).

    mfg-autopilot --instance I --connect udpin:127.0.0.1:14540+I --mode {mfg,hjb} --n N ...

Swapping the mock vehicle for a real PX4 is a change of ``--connect`` only. This is the only
place that reads the command line (and the mission file); everything below gets values.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading

from mfg_autopilot.mission import load_mission
from mfg_autopilot.paper.params import radio_range_m
from mfg_autopilot.presets import DEFAULT_PRESET_NAME, MODES
from mfg_autopilot.runtime.autopilot import AutopilotConfig, run_autopilot
from mfg_autopilot.runtime.exchange import ZenohSettings

__all__ = ["main", "build_parser", "config_from_args"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mfg-autopilot", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--instance", type=int, required=True, help="vehicle instance I (MAVLink system I+1, Zenoh id I)")
    p.add_argument("--connect", default=None, help="MAVLink connection string (default udpin:127.0.0.1:14540+I); "
                                                   "udpin:, udpout:, tcp:, or a serial device /dev/ttyX:BAUD")
    p.add_argument("--mode", choices=MODES, default="mfg", help="mfg (Algorithm 4), hjb (HJB_d, Algorithm 3), *-pde (Algorithms 2 / 1 solved), orca (the ORCA baseline: no communication)")
    p.add_argument("--preset", default=DEFAULT_PRESET_NAME, help=f"controller preset (default: {DEFAULT_PRESET_NAME})")
    p.add_argument("--n", type=int, required=True, help="swarm size N (ids 0..N-1)")
    p.add_argument("--swarm", default="swarm", help="swarm name: the Zenoh key prefix mfg/<swarm>/ (default: swarm)")
    rng = p.add_mutually_exclusive_group()
    rng.add_argument("--range-m", type=float, default=None, help="HJB_d radio range d, m")
    rng.add_argument("--power-mw", type=float, default=None, help="HJB_d transmit power P, mW (d from the path-loss model)")
    p.add_argument("--mission", default=None, metavar="FILE",
                   help="a field mission (docs/mission.md: geodetic, every vehicle by system id; the controller then waits "
                        "for the vehicle's EKF origin, arms, takes off to its group's altitude, flies, and holds or lands), or "
                        "the simulator's {\"sites_m\": [[x, y], ...]} (one site per vehicle id, a shared origin, airborne "
                        "vehicles); default: every vehicle to the origin")
    p.add_argument("--lockstep", action="store_true", help="one control step per simulated dt (docs/lockstep.md)")
    p.add_argument("--steps", type=int, default=200, help="mission time limit in control steps (default: 200)")
    p.add_argument("--inner-loop", action=argparse.BooleanOptionalAction, default=None,
                   help="track each step's command at every LOCAL_POSITION_NED until the next step (against the "
                        "airframe's acceleration lag and gusts; default: the preset's, on in the default guidance's "
                        "presets, --inner-loop refused for the paper's); lockstep: start the vehicle with "
                        "--dt-s = its --physics-dt-s so that it answers each sub-step")
    p.add_argument("--acc-lag-s", type=float, default=None, metavar="TAU",
                   help="the airframe's acceleration lag the controller's own-vehicle model assumes (the escape's "
                        "prediction of its own swerve; PX4 multicopters ~0.154 s, the mock's --acc-lag-s; default: the "
                        "preset's, TrackingParams.acc_lag_s)")
    p.add_argument("--hold-on-arrival", choices=("on", "off"), default=None,
                   help="command HOLD once within 1 m of the destination for 5 s (default: on in real time, off in lockstep)")
    p.add_argument("--log", default=None, help="controller log, JSON Lines (docs/controller_log.md)")
    p.add_argument("--log-fpk-weights-every", type=int, default=10, metavar="K",
                   help="write the FPK weights w_F into every K-th step record and the last (1: every step, 0: never; "
                        "default 10: they are half of each line)")
    p.add_argument("--tlog", default=None, help="MAVLink .tlog of this link")
    p.add_argument("--mavlink-key", default=None, metavar="FILE",
                   help="MAVLink 2 signing key file (64 hex characters, mode 600; docs/security.md): sign every "
                        "packet and accept only validly signed ones from the vehicle")
    p.add_argument("--state-dir", default=None, help="checkpoint folder: a restarted controller resumes from it "
                                                     "without a new swarm exchange (docs/controller_log.md)")
    p.add_argument("--vehicle-timeout-s", type=float, default=30.0, help="wait for the vehicle's heartbeat and position")
    p.add_argument("--exchange-timeout-s", type=float, default=60.0, help="wait for the swarm (t = 0 exchange / membership)")
    p.add_argument("--gossip-timeout-s", type=float, default=10.0, help="lockstep HJB_d: wait for neighbours' states of a step")
    p.add_argument("--vehicle-lost-s", type=float, default=3.0,
                   help="heartbeat silence after which the vehicle counts as lost (stop, wait, redo the handshake)")
    p.add_argument("--step-timeout-s", type=float, default=30.0, help="lockstep: wait for the vehicle to take a step")
    p.add_argument("--rt-priority", type=int, default=None, metavar="P",
                   help="run the controller's threads at SCHED_FIFO priority P (1-99; needs CAP_SYS_NICE), as a flight "
                        "computer would; refused -> a log line and normal scheduling")
    p.add_argument("--log-level", default="INFO")
    ZenohSettings.add_cli_args(p)
    return p


def config_from_args(args: argparse.Namespace) -> AutopilotConfig:
    sites, mission = None, None
    if args.mission:
        try:
            with open(args.mission, encoding="utf-8") as fh:
                doc = json.load(fh)
        except FileNotFoundError:
            raise ValueError(f"mission file {args.mission!r} not found") from None
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"mission file {args.mission!r} is not JSON: {exc}") from None
        if isinstance(doc, dict) and "sites_m" in doc:
            try:
                sites = tuple((float(x), float(y)) for x, y in doc["sites_m"])
            except (TypeError, ValueError) as exc:
                raise ValueError(f"mission file {args.mission!r} is not {{\"sites_m\": [[x, y], ...]}}: {exc}") from None
        else:
            mission = load_mission(doc)                    # MissionError (a ValueError) names the field
    range_m = radio_range_m(args.power_mw) if args.power_mw is not None else args.range_m
    hold = None if args.hold_on_arrival is None else args.hold_on_arrival == "on"
    return AutopilotConfig(
        instance=args.instance, connect=args.connect or f"udpin:127.0.0.1:{14540 + args.instance}", mode=args.mode,
        preset=args.preset, n=args.n, swarm=args.swarm, range_m=range_m, sites_m=sites, lockstep=args.lockstep,
        steps=args.steps, hold_on_arrival=hold, log_path=args.log, tlog_path=args.tlog, zenoh=ZenohSettings.from_args(args),
        vehicle_timeout_s=args.vehicle_timeout_s, exchange_timeout_s=args.exchange_timeout_s,
        gossip_timeout_s=args.gossip_timeout_s, step_timeout_s=args.step_timeout_s, state_dir=args.state_dir,
        vehicle_lost_s=args.vehicle_lost_s, mavlink_key_file=args.mavlink_key, rt_priority=args.rt_priority,
        log_fpk_weights_every=args.log_fpk_weights_every, mission=mission, inner_loop=args.inner_loop,
        acc_lag_s=args.acc_lag_s)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format=f"%(asctime)s mfg-autopilot[{args.instance}] %(levelname)s %(message)s", stream=sys.stderr)
    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        logging.getLogger("mfg_autopilot").error("%s", exc)
        return 2
    stop = threading.Event()

    def on_signal(signum, _frame) -> None:
        logging.getLogger("mfg_autopilot").info("signal %d: commanding HOLD and stopping", signum)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return run_autopilot(cfg, stop)


if __name__ == "__main__":
    sys.exit(main())
