"""`mfg-swarm`: the swarm's command line (simulate, fly as processes, plot, reproduce)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from mfg_autopilot.paper.params import radio_range_m
from mfg_autopilot.presets import DEFAULT_PRESET_NAME, MODES, preset_by_name, with_inner_loop

__all__ = ["main", "build_parser"]


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="paper",
                   help="paper | crossing | dense | swap4 (four streams through the middle) | circle (each to its antipode) | "
                        "merge (k sources to one site) | random (random starts and shared sites); seeded by --seed "
                        "(mfg_swarm/scenarios.py; default: paper)")
    p.add_argument("--safety-radius-m", type=float, default=None,
                   help="the airframe's safety radius: a scenario whose starts or slots are closer than twice it is refused "
                        "(default: 0.05 m, half the 0.1 m collision distance; a mission file has its own)")
    p.add_argument("--mission", type=Path, default=None, metavar="FILE",
                   help="a field mission (docs/mission.md, e.g. examples/field.json) instead of --scenario and --n: "
                        "`run` starts every vehicle on the ground at its launch point with its own EKF origin, takes off, "
                        "flies, then holds or lands; `sim` flies the same mission in the swarm frame, airborne")
    p.add_argument("--n", type=int, default=25, help="number of UAVs N (default: 25)")
    p.add_argument("--mode", choices=MODES, default="mfg",
                   help="mfg: MFG learning control (Alg. 4); hjb: HJB_d learning control (Alg. 3); *-pde: the solved controllers (Alg. 2 / 1); "
                        "orca: the ORCA baseline, no communication (default preset) (default: mfg)")
    rng = p.add_mutually_exclusive_group()
    rng.add_argument("--range-m", type=float, default=None, help="HJB_d radio range d in metres")
    rng.add_argument("--power-mw", type=float, default=None, help="HJB_d transmit power P in mW; d = [P/(theta sigma^2)]^(1/alpha)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the wind streams (default: 0)")
    p.add_argument("--steps", type=int, default=200, help="control steps (default: 200: 100 s at the default preset's dt = 0.5 s, 200 s at the paper's dt = 1 s)")
    p.add_argument("--preset", default=DEFAULT_PRESET_NAME, help=f"controller preset: default (the product controller) or paper (default: {DEFAULT_PRESET_NAME})")
    p.add_argument("--out", type=Path, required=True, help="output folder")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="mfg-swarm", description=__doc__)
    ap.add_argument("--log-level", default="WARNING")
    sub = ap.add_subparsers(dest="cmd", required=True)
    sim = sub.add_parser("sim", help="in-process simulator: the controller core driving all N UAVs at once")
    _add_common(sim)
    sim.add_argument("--physics-dt-s", type=float, default=0.1, help="plant sub-step (default: 0.1 s)")
    sim.add_argument("--acc-lag-s", type=float, default=None, metavar="TAU",
                     help="the airframes fly their acceleration command through a first-order lag of TAU s (PX4's "
                          "attitude loop: about 1 / MC_ROLL_P = 0.154 s); 0: at once, as the paper's eq. 9; default: "
                          "the preset's airframe, PX4's 0.154 s for the default guidance, 0 for the paper's presets")
    sim.add_argument("--inner-loop", action=argparse.BooleanOptionalAction, default=None,
                     help="track each period's command at every physics sub-step (TrackingParams.inner_loop: against "
                          "an airframe's lag, --acc-lag-s, and gusts); default: the preset's (on in the default "
                          "guidance's presets; the paper's has none)")
    sim.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    sim.add_argument("--fail-vehicle", type=int, action="append", default=None, metavar="K",
                     help="fault: vehicle K stops following its controller and holds where it is (PX4 Hold); "
                          "repeat for several failed vehicles")
    sim.add_argument("--fail-at", type=float, action="append", default=None, metavar="T",
                     help="fault: time in s at which --fail-vehicle fails (default: 0); one for all, or one per "
                          "--fail-vehicle, in the same order; between two control instants it fails at the next "
                          "physics sub-step (a real failure does not wait for the next sample)")
    sim.add_argument("--hold-jerk", type=float, default=4.0, metavar="J",
                     help="fault: the failed vehicle's Hold changes its acceleration at most J m/s^3 (PX4 MPC_JERK_AUTO; "
                          "default 4); 0 (with --hold-model pd): it brakes at the airframe's limit from the first "
                          "instant (pessimistic)")
    sim.add_argument("--hold-model", choices=("px4", "pd"), default="px4",
                     help="fault: the failed vehicle's Hold: px4 = PX4's trajectory (PositionSmoothing, "
                          "MPC_JERK_AUTO = --hold-jerk) tracked by PX4's position/velocity loops, as the mock flies it "
                          "(default); pd = a saturated PD towards the braking stop, jerk-limited at --hold-jerk (the "
                          "model before PX4's was ported; --hold-jerk 0 needs it)")
    sim.add_argument("--gust", action="store_true", help="fault: a wind gust beyond V_o (mfg_swarm.sim.GustParams: 1 m/s^2 +-50 %%, t = 20-25 s)")
    sim.add_argument("--record", action="store_true",
                     help="also write flight.mcap (Foxglove: map, 3D scene, plots, events; docs/formats.md)")

    run = sub.add_parser("run", help="fly the swarm as processes: N mock vehicles + N controllers over MAVLink and Zenoh")
    _add_common(run)
    run.set_defaults(n=9, out=None)
    for a in run._actions:
        if a.dest == "out":
            a.required = False
            a.help = "output folder (default: runs/<scenario>-<mode>-n<N>-seed<S>)"
        if a.dest == "n":
            a.help = "number of UAVs N (default: 9)"
    clock = run.add_mutually_exclusive_group()
    clock.add_argument("--lockstep", dest="lockstep", action="store_true", default=True,
                       help="simulated time advances one step per setpoint (default; reproduces `sim`)")
    clock.add_argument("--realtime", dest="lockstep", action="store_false", help="wall-clock time (dt = 1 s is 1 s)")
    zr = run.add_mutually_exclusive_group()
    zr.add_argument("--zenoh-router", dest="zenoh_router", action="store_true", default=None,
                    help="run a Zenoh router; controllers join it in client mode (default above 25 vehicles)")
    zr.add_argument("--zenoh-peers", dest="zenoh_router", action="store_false",
                    help="controllers form a Zenoh peer mesh on loopback (default up to 25 vehicles)")
    run.add_argument("--mavlink-base-port", type=int, default=None,
                     help="vehicle I uses UDP base+I (PX4 SITL: 14540); default: free ports picked by the OS")
    run.add_argument("--gcs", action="store_true", help="also stream each vehicle's GCS link to udp 127.0.0.1:14550 (QGroundControl, MAVProxy)")
    run.add_argument("--swarm", default=None, help="Zenoh key prefix mfg/<swarm>/ (default: run<pid>)")
    run.add_argument("--zenoh-router-config", default=None, metavar="FILE",
                     help="the router's zenoh json5 (e.g. access control, examples/zenoh_acl/router.json5)")
    run.add_argument("--zenoh-client-config", default=None, metavar="FILE",
                     help="the controllers' zenoh json5 (credentials); '{i}' in the name is the vehicle id")
    run.add_argument("--mavlink-key", default=None, metavar="FILE",
                     help="MAVLink 2 signing between every controller and its vehicle (64 hex chars, mode 600)")
    run.add_argument("--acc-lag-s", type=float, default=None, metavar="TAU",
                     help="the mock vehicles fly their acceleration command through a first-order lag of TAU s "
                          "(mock-vehicle --acc-lag-s; PX4's attitude loop: about 0.154 s); default: the preset's "
                          "airframe, PX4's 0.154 s for the default guidance, 0 for the paper's presets")
    run.add_argument("--inner-loop", action=argparse.BooleanOptionalAction, default=None,
                     help="every controller tracks its command at each LOCAL_POSITION_NED between steps "
                          "(mfg-autopilot --inner-loop; against --acc-lag-s and gusts); lockstep steps the mocks by "
                          "sub-steps; default: the preset's (on in the default guidance's presets)")
    run.add_argument("--time-limit-s", type=float, default=None, help="stop the swarm after this wall time")
    run.add_argument("--startup-timeout-s", type=float, default=None,
                     help="every controller must reach OFFBOARD within this (default: scales with N, the cores and "
                          "the load average, 120 s to 30 min); also each controller's start-up waits")
    run.add_argument("--rt-priority", type=int, default=None, metavar="P",
                     help="controllers run at SCHED_FIFO priority P (1-99; needs CAP_SYS_NICE), as on a flight computer")
    run.add_argument("--no-progress", action="store_true")
    run.add_argument("--no-plot", action="store_true", help="do not draw the figures after the flight")
    run.add_argument("--live", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                     help="serve the recording's topics live over the Foxglove WebSocket protocol on 127.0.0.1:PORT "
                          "(default port 8765; 0: one the OS picks) while the swarm flies")
    rec = run.add_mutually_exclusive_group()
    rec.add_argument("--record", dest="record", action="store_true", default=True,
                     help="write flight.mcap after the flight (default; Foxglove: docs/formats.md)")
    rec.add_argument("--no-record", dest="record", action="store_false", help="no flight.mcap")

    mis = sub.add_parser("mission", help="write a built-in scenario as a field mission file (docs/mission.md) to fly with --mission")
    mis.add_argument("--scenario", default="paper", help="a grid-launched family: paper, crossing, dense, swap4 (default: paper)")
    mis.add_argument("--n", type=int, default=9)
    mis.add_argument("--seed", type=int, default=0)
    mis.add_argument("--safety-radius-m", type=float, default=None, help="the airframe's (default: 0.05 m)")
    mis.add_argument("--altitude-agl-m", type=float, default=10.0, help="cruise altitude of every group (default: 10 m)")
    mis.add_argument("--on-arrival", choices=("hold", "land"), default="land")
    mis.add_argument("--out", type=Path, required=True, help="the mission file to write")

    plot = sub.add_parser("plot", help="the paper's figures (Fig. 3, 4, 5) as PNG for a run or a folder of runs")
    plot.add_argument("dirs", nargs="+", type=Path, help="run folders, or folders holding run folders")
    plot.add_argument("--animate", action="store_true",
                      help="an animated replay of each run (flight.gif; flight.mp4 too with --mp4 if ffmpeg exists) instead of the figures")
    plot.add_argument("--fps", type=float, default=10.0, help="--animate: frames per second (default: 10)")
    plot.add_argument("--max-frames", type=int, default=200,
                      help="--animate: at most this many frames: every k-th control step (default: 200)")
    plot.add_argument("--mp4", action="store_true", help="--animate: also an MP4 (needs ffmpeg on the PATH)")

    conv = sub.add_parser("convert", help="turn a run folder (trajectories.npz, or the vehicles' tlogs) into flight.mcap for Foxglove")
    conv.add_argument("run_dir", type=Path, help="a run folder (mfg-swarm sim/run), or a folder of a real vehicle's .tlog files")
    conv.add_argument("--out", type=Path, default=None, help="the MCAP to write (default: RUN_DIR/flight.mcap)")
    conv.add_argument("--mission", type=Path, default=None, metavar="FILE",
                      help="the mission flown (its datum, altitudes and safety radius)")
    conv.add_argument("--datum", default=None, metavar="LAT,LON,ALT",
                      help="the swarm frame's origin (deg, deg, m AMSL; default: metrics.json's, the mission's, "
                           "the default datum, or for bare tlogs the first vehicle's first fix)")
    conv.add_argument("--safety-radius-m", type=float, default=None, help="sphere radius drawn per vehicle (default: 0.05 m)")

    rep = sub.add_parser("reproduce", help="the paper's comparison and every claim beside the measured figure (claims.md)")
    rep.add_argument("--out", type=Path, required=True)
    rep.add_argument("--presets", default="paper,default", help="comma-separated presets (default: paper,default)")
    rep.add_argument("--ns", default=",".join(map(str, (9, 16, 25, 36, 49, 64, 81))), help="swarm sizes")
    rep.add_argument("--seeds", default="0,1,2", help="seeds (default: 0,1,2)")
    rep.add_argument("--steps", type=int, default=200)
    rep.add_argument("--workers", type=int, default=2, help="parallel simulator processes (default: 2)")
    rep.add_argument("--no-processes", action="store_true", help="skip the process-swarm check")
    bench = sub.add_parser("bench", help="benchmarks: controller step, simulator scaling, process swarm, latency (docs/benchmarks.md)")
    bench.add_argument("--out", type=Path, required=True, help="output folder (bench.json)")
    bench.add_argument("--quick", action="store_true", help="small sizes and few steps (a smoke run, not figures)")
    bench.add_argument("--only", default=None, help="comma-separated sections: step,sim,swarm,latency,pde (default: all)")
    bench.add_argument("--sim-timeout-s", type=float, default=900.0, help="give up on a simulator point after this wall time")
    return ap


def _cmd_bench(args) -> int:
    from .bench import SECTIONS, format_table, run_bench

    only = tuple(x for x in args.only.split(",") if x) if args.only else SECTIONS
    res = run_bench(args.out, quick=args.quick, only=only, sim_timeout_s=args.sim_timeout_s)
    print(format_table(res))
    print(f"figures in {args.out}/bench.json", file=sys.stderr)
    return 0


def _range_from(args) -> float | None:
    if args.power_mw is not None:
        return radio_range_m(args.power_mw)
    return args.range_m


def _mission(args):
    """The --mission file, validated (MissionError, a ValueError naming the field: before anything moves)."""
    if getattr(args, "mission", None) is None:
        return None
    from mfg_autopilot.mission import load_mission

    return load_mission(args.mission)


def _scenario(args):
    from .scenarios import DEFAULT_SAFETY_RADIUS_M, check_flyable, make_scenario, scenario_from_mission

    mission = _mission(args)
    if mission is not None:
        sc = scenario_from_mission(mission)
        check_flyable(sc, mission.safety_radius_m)
        return sc
    sc = make_scenario(args.scenario, args.n, args.seed)
    check_flyable(sc, DEFAULT_SAFETY_RADIUS_M if args.safety_radius_m is None else args.safety_radius_m)
    return sc


def _cmd_mission(args) -> int:
    from .scenarios import DEFAULT_SAFETY_RADIUS_M, make_scenario, mission_of_scenario

    m = mission_of_scenario(make_scenario(args.scenario, args.n, args.seed),
                            safety_radius_m=DEFAULT_SAFETY_RADIUS_M if args.safety_radius_m is None else args.safety_radius_m,
                            altitude_agl_m=args.altitude_agl_m, on_arrival=args.on_arrival)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(m.to_dict(), indent=1) + "\n")
    print(f"{args.out}: {m.n} vehicles in {len(m.groups)} groups around {m.datum.lat_deg}, {m.datum.lon_deg}", file=sys.stderr)
    return 0


def _one_or_tuple(values: list | None):
    """An appended option: None, its one value, or a tuple of its values."""
    if not values:
        return None
    return values[0] if len(values) == 1 else tuple(values)


def _cmd_sim(args) -> int:
    from .results import write_json_atomic, write_npz_atomic
    from .sim import GustParams, SimConfig, simulate

    preset = preset_by_name(args.preset)
    if args.inner_loop is not None:
        preset = with_inner_loop(preset, args.inner_loop)
    cfg = SimConfig(scenario=_scenario(args), mode=args.mode, preset=preset,
                    seed=args.seed, steps=args.steps, range_m=_range_from(args), physics_dt_s=args.physics_dt_s,
                    fail_vehicle=_one_or_tuple(args.fail_vehicle), fail_at_s=_one_or_tuple(args.fail_at) or 0.0,
                    hold_jerk_m_s3=args.hold_jerk, gust=GustParams() if args.gust else None,
                    hold_model=args.hold_model, acc_lag_s=args.acc_lag_s)
    traj, metrics = simulate(cfg, progress=False if args.no_progress else None)
    args.out.mkdir(parents=True, exist_ok=True)
    write_npz_atomic(args.out / "trajectories.npz", traj.arrays())
    write_json_atomic(args.out / "metrics.json", metrics)
    summary = {k: metrics[k] for k in ("n", "mode", "range_m", "collision_pairs", "arrived_fraction", "arrival_time_s",
                                       "comm_states_per_uav", "motion_energy_per_uav", "wall_s")}
    print(json.dumps(summary))
    recorded = f", {_record(args.out, args, _mission(args))}" if args.record else ""
    print(f"results in {args.out}/ (metrics.json, trajectories.npz{recorded})", file=sys.stderr)
    return 0


def _record(out: Path, args, mission) -> str:
    """flight.mcap for a finished run folder; returns what to tell the user."""
    from .recording import record_run

    summary = record_run(out, mission=mission, safety_radius_m=getattr(args, "safety_radius_m", None))
    return f"{summary.path} ({sum(summary.messages_by_topic.values())} messages, {summary.collision_events} collision events)"


def _cmd_convert(args) -> int:
    from mfg_autopilot.mission import GeodeticPoint

    from .recording import record_run

    datum = None
    if args.datum is not None:
        try:
            lat, lon, alt = (float(x) for x in args.datum.split(","))
        except ValueError:
            raise ValueError(f"--datum must be LAT,LON,ALT (deg, deg, m), got {args.datum!r}") from None
        datum = GeodeticPoint(lat, lon, alt)
    summary = record_run(args.run_dir, args.out, mission=_mission(args), datum=datum, safety_radius_m=args.safety_radius_m)
    print(summary.path)
    print(f"{sum(summary.messages_by_topic.values())} messages on {len(summary.messages_by_topic)} topic groups, "
          f"{summary.collision_events} collision events, {summary.backstop_events} backstop events; open it in Foxglove "
          f"(layout: docs/foxglove_layout.json)", file=sys.stderr)
    return 0


def _cmd_run(args) -> int:
    from mock_vehicle.plant import PlantParams

    from .launcher import LaunchError, RunConfig, run_swarm

    out = args.out or Path("runs") / f"{args.scenario}-{args.mode}-n{args.n}-seed{args.seed}"
    mission = _mission(args)
    if mission is not None:
        out = args.out or Path("runs") / f"mission-{mission.name or 'mission'}-{args.mode}-seed{args.seed}"
        args.n = mission.n
    cfg = RunConfig(scenario=_scenario(args), mode=args.mode, preset_name=args.preset, out=out, mission=mission,
                    mission_file=None if args.mission is None else args.mission.resolve(),
                    seed=args.seed, steps=args.steps, range_m=_range_from(args), lockstep=args.lockstep,
                    zenoh_router=args.zenoh_router, mavlink_base_port=args.mavlink_base_port,
                    gcs_url="udpout:127.0.0.1:14550" if args.gcs else "none", time_limit_s=args.time_limit_s,
                    startup_timeout_s=args.startup_timeout_s,
                    progress=False if args.no_progress else None, mavlink_key_file=args.mavlink_key, swarm=args.swarm,
                    zenoh_router_config=args.zenoh_router_config, zenoh_client_config=args.zenoh_client_config,
                    controller_rt_priority=args.rt_priority, acc_lag_s=args.acc_lag_s, inner_loop=args.inner_loop)
    if args.inner_loop is not None:
        with_inner_loop(preset_by_name(args.preset), args.inner_loop)   # a preset without it fails before any process starts
    try:
        if args.acc_lag_s is not None:
            PlantParams(acc_lag_s=args.acc_lag_s)      # the plant's own check, before any process starts
    except ValueError as exc:
        raise ValueError(f"--acc-lag-s: {exc}") from None
    if args.mavlink_key:
        from mavlink_bridge import load_signing_key
        load_signing_key(args.mavlink_key)    # a missing or loose key file fails before any process starts
    preset_by_name(args.preset)           # a bad preset name fails before any process starts
    if args.mode.startswith("hjb") and cfg.range_m is None:
        raise ValueError("HJB_d needs a radio range: give --range-m D or --power-mw P")
    live = None
    if args.live is not None:
        import dataclasses

        from .live import LiveView

        live = LiveView([out / "controllers" / f"controller{i}.jsonl" for i in range(cfg.scenario.n)],
                        dt_s=preset_by_name(args.preset).dt_s, dest_m=cfg.scenario.destination_m, lockstep=args.lockstep,
                        port=args.live, datum=None if mission is None else mission.datum,
                        altitude_agl_m=None if mission is None else mission.arrays()["altitude_agl_m"],
                        safety_radius_m=(mission.safety_radius_m if mission is not None else args.safety_radius_m or 0.05))
        cfg = dataclasses.replace(cfg, on_poll=live.poll)
        print(f"live: {live.url} (Foxglove: Open connection -> Foxglove WebSocket -> {live.url}; "
              f"layout docs/foxglove_layout.json)", file=sys.stderr, flush=True)
    clock = "lockstep" if args.lockstep else "real time"
    print(f"flying {args.n} vehicles ({args.mode}, preset {args.preset}, {args.scenario}, {clock}) as processes ...", file=sys.stderr)
    try:
        out, metrics = run_swarm(cfg)
    except LaunchError as exc:
        print(f"mfg-swarm: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if live is not None:
            live.close()
    summary = {k: metrics.get(k) for k in ("n", "mode", "range_m", "steps", "collision_pairs", "arrived_fraction",
                                            "arrival_time_s", "comm_states_per_uav", "motion_energy_per_uav", "wall_s", "partial")}
    print(json.dumps(summary))
    figures = ""
    if not args.no_plot:
        try:
            from .plots import plot_run
            figures = ", figures: " + ", ".join(p.name for p in plot_run(out))
        except Exception as exc:  # figures are a convenience; the results are already written
            print(f"mfg-swarm: could not draw figures: {exc}", file=sys.stderr)
    if args.record and metrics.get("steps"):
        try:
            figures += ", " + _record(out, args, mission)
        except Exception as exc:      # the recording is a view; the results are already written
            print(f"mfg-swarm: could not write flight.mcap: {exc}", file=sys.stderr)
    if metrics.get("partial"):
        print(f"mfg-swarm: the run did not complete: {metrics.get('end_reason')}", file=sys.stderr)
    state = "PARTIAL results" if metrics.get("partial") else "results"
    print(f"{state} in {out}/ (metrics.json, trajectories.npz, vehicles/*.tlog, controllers/*.jsonl{figures})", file=sys.stderr)
    return 1 if metrics.get("partial") else 0


def _cmd_plot(args) -> int:
    from .plots import find_runs, plot_energy, plot_regularizer, plot_run

    made = []
    for d in args.dirs:
        if not d.exists():
            raise ValueError(f"{d} does not exist")
        runs = find_runs(d)
        if not runs:
            raise ValueError(f"no run in {d} (a run folder holds metrics.json and trajectories.npz)")
        if args.animate:
            from .animate import animate_run

            for r in runs:
                made += animate_run(r, fps=args.fps, max_frames=args.max_frames, mp4=args.mp4)
            continue
        if runs == [d]:
            made += plot_run(d)
            continue
        for r in runs:
            made += plot_run(r)
        made.append(plot_regularizer(runs, d / "fig4_regularizer.png"))
        fig5 = plot_energy([json.loads((r / "metrics.json").read_text()) for r in runs], d / "fig5_energy.png")
        if fig5 is not None:
            made.append(fig5)
    for p in made:
        print(p)
    return 0


def _cmd_reproduce(args) -> int:
    from .reproduce import reproduce

    presets = [p for p in args.presets.split(",") if p]
    for p in presets:
        preset_by_name(p)
    claims = reproduce(args.out, presets, ns=tuple(int(x) for x in args.ns.split(",")),
                       seeds=tuple(int(x) for x in args.seeds.split(",")), steps=args.steps, workers=args.workers,
                       process_check=not args.no_processes, log=lambda s: print(s, file=sys.stderr))
    print(claims)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        if args.cmd == "sim":
            return _cmd_sim(args)
        if args.cmd == "mission":
            return _cmd_mission(args)
        if args.cmd == "run":
            return _cmd_run(args)
        if args.cmd == "plot":
            return _cmd_plot(args)
        if args.cmd == "convert":
            return _cmd_convert(args)
        if args.cmd == "reproduce":
            return _cmd_reproduce(args)
        if args.cmd == "bench":
            return _cmd_bench(args)
    except ValueError as exc:
        print(f"mfg-swarm: error: {exc}", file=sys.stderr)
        return 2
    return 2


if __name__ == "__main__":
    sys.exit(main())
