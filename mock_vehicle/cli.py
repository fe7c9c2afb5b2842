"""``mock-vehicle``: a PX4-like MAVLink vehicle process (issue 3). The only place that
reads the command line; everything below gets a ``VehicleConfig`` value."""

from __future__ import annotations

import argparse
import math
import logging
import signal
import sys
import threading

from .params import ParamTable
from .plant import PlantParams, WindParams
from .vehicle import VehicleConfig

__all__ = ["main", "build_parser", "config_from_args"]


def _floats(n: tuple[int, ...]):
    def parse(text: str) -> tuple[float, ...]:
        try:
            vals = tuple(float(t) for t in text.replace(" ", "").split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {' or '.join(map(str, n))} comma-separated numbers, got {text!r}") from None
        if len(vals) not in n:
            raise argparse.ArgumentTypeError(f"expected {' or '.join(map(str, n))} comma-separated numbers, got {text!r}")
        return vals

    return parse


def build_parser() -> argparse.ArgumentParser:
    d = VehicleConfig()
    w = WindParams()
    p = argparse.ArgumentParser(prog="mock-vehicle", description="PX4-like MAVLink mock vehicle flying the eq. 9 dynamics")
    p.add_argument("--instance", type=int, default=0, help="instance I: MAVLink system I+1, component 1")
    p.add_argument("--onboard-url", default=None, help="onboard link (default udpout:127.0.0.1:14540+I); 'none' disables")
    p.add_argument("--gcs-url", default="udpout:127.0.0.1:14550", help="GCS link (default udpout:127.0.0.1:14550); 'none' disables")
    p.add_argument("--extra-url", action="append", default=[], help="further MAVLink links (repeatable)")
    p.add_argument("--initial-pos-m", type=_floats((2,)), default=(0.0, 0.0), metavar="X,Y", help="initial north,east position, m")
    p.add_argument("--initial-vel-m-s", type=_floats((2,)), default=None, metavar="VX,VY", help="initial velocity (default: drawn from the wind)")
    p.add_argument("--seed", type=int, default=0, help="noise stream = (seed, instance)")
    p.add_argument("--home-lat", type=float, default=d.home_lat_deg, help="home latitude, deg")
    p.add_argument("--home-lon", type=float, default=d.home_lon_deg, help="home longitude, deg")
    p.add_argument("--home-alt-m", type=float, default=d.home_alt_amsl_m, help="home altitude AMSL, m")
    p.add_argument("--altitude-m", type=float, default=d.altitude_m, help="flight altitude above home, m (z = -altitude)")
    p.add_argument("--c0", type=float, default=w.c0_per_s, help="c0: wind relaxation rate, 1/s (eq. 1)")
    p.add_argument("--mean-wind", type=_floats((2,)), default=w.mean_wind_m_s, metavar="VN,VE", help="v_o: mean wind, m/s")
    p.add_argument("--wind-diffusion", type=_floats((1, 4)), default=(0.1,), metavar="S|V11,V12,V21,V22", help="V_o: isotropic S or a 2x2 matrix, m/s/sqrt(s)")
    p.add_argument("--acc-limit-m-s2", type=float, default=d.acc_limit_m_s2, help="airframe acceleration limit, m/s^2")
    p.add_argument("--physics-dt-s", type=float, default=d.physics_dt_s, help="largest physics sub-step, s")
    p.add_argument("--acc-lag-s", type=float, default=d.acc_lag_s, metavar="TAU",
                   help="fly the acceleration command through a first-order lag of TAU s (param SIM_ACC_TAU; PX4's "
                        "attitude loop: about 1 / MC_ROLL_P = 0.154 s, the default); 0: at once, as the paper's eq. 9")
    p.add_argument("--dt-s", type=float, default=d.dt_s, help="lockstep control step, s")
    p.add_argument("--lockstep", action="store_true", help="simulated time advances one dt_s per setpoint (docs/lockstep.md)")
    p.add_argument("--lockstep-resend-hz", type=float, default=d.lockstep_resend_hz, help="lockstep: wall-clock re-send rate of telemetry")
    p.add_argument("--com-of-loss-t-s", type=float, default=d.com_of_loss_t_s, help="COM_OF_LOSS_T: offboard loss timeout, s")
    p.add_argument("--deny-arming", action="store_true", help="refuse arming (a failed preflight check; param SIM_ARM_DENY)")
    p.add_argument("--start", choices=("air", "ground"), default="air",
                   help="air: hover at --initial-pos-m and --altitude-m, disarmed, frozen until OFFBOARD (the default); "
                        "ground: boot ON_GROUND, disarmed, at z = 0 at --initial-pos-m (the launch point, world frame), and "
                        "take off, land and disarm as PX4 does (docs/mavlink.md)")
    p.add_argument("--origin", type=_floats((3,)), default=None, metavar="LAT,LON,ALT",
                   help="the vehicle's own EKF origin (deg, deg, m AMSL): LOCAL_POSITION_NED relative to it, announced as "
                        "GPS_GLOBAL_ORIGIN (default: the home, which is also the simulated world's frame)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="set a vehicle parameter at boot, e.g. COM_OBL_RC_ACT=4 (offboard loss: Land), MIS_TAKEOFF_ALT=5 "
                        "(repeatable; the list: mock_vehicle/params.py, docs/mavlink.md)")
    for kind, hz in d.rates_hz.items():
        p.add_argument(f"--{kind.replace('_', '-')}-hz", type=float, default=hz, help=f"{kind.upper()} rate, Hz (0 disables)")
    p.add_argument("--signing-key", default=None, metavar="FILE",
                   help="MAVLink 2 signing: 64 hex chars, mode 600; sign everything sent, ignore unsigned/badly signed input")
    p.add_argument("--signing-link-id", type=int, default=0, help="signing link id stamped on what this vehicle sends (0..255)")
    p.add_argument("--world-url", default=None, metavar="udp:HOST:PORT",
                   help="proximity sensor: report the true state to this world (mock_vehicle.world) and forward the "
                        "vehicles it senses as ADSB_VEHICLE (docs/proximity.md); off by default")
    p.add_argument("--traffic-rate-hz", type=float, default=d.traffic_rate_hz,
                   help="with --world-url: sensed-traffic rate in real time, re-send rate in lockstep, Hz")
    p.add_argument("--hold-model", choices=VehicleConfig.HOLD_MODELS, default=d.hold_model,
                   help="auto modes (Takeoff, Hold, Land), horizontal: px4 = PX4's jerk-limited trajectory "
                        "(PositionSmoothing) tracked by PX4's position/velocity loops (mock_vehicle/smoothing.py; "
                        "default); pd = a saturated PD towards the Hold point, its acceleration jerk-limited at "
                        "MPC_JERK_AUTO")
    p.add_argument("--tlog", default=None, help="write a MAVLink .tlog of everything sent and received")
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ...")
    return p


def config_from_args(args: argparse.Namespace) -> tuple[VehicleConfig, list[str]]:
    if args.instance < 0 or args.instance > 253:
        raise ValueError(f"--instance must be 0..253, got {args.instance}")
    if args.lockstep and not args.lockstep_resend_hz > 0:
        # in lockstep the position follows the steps and is re-sent at this rate while idle: with 0 a
        # vehicle would never report its position before the first step, and no controller could start
        raise ValueError(f"--lockstep-resend-hz must be > 0 in lockstep, got {args.lockstep_resend_hz}")
    if args.origin is not None and not (-90 <= args.origin[0] <= 90 and -180 <= args.origin[1] <= 180 and math.isfinite(args.origin[2])):
        raise ValueError(f"--origin must be LAT,LON,ALT with |lat| <= 90, |lon| <= 180 and a finite altitude, got {args.origin}")
    try:
        PlantParams(acc_lag_s=args.acc_lag_s)          # the plant's own check of the lag
    except ValueError as exc:
        raise ValueError(f"--acc-lag-s: {exc}") from None
    params = []
    for item in args.param:
        name, sep, value = item.partition("=")
        try:
            params.append((name.strip(), float(value)))
        except ValueError:
            sep = ""
        if not sep:
            raise ValueError(f"--param must be NAME=VALUE with a number, got {item!r}")
    err = next((e for e in (ParamTable().set(n, v) for n, v in params) if e), None)
    if err:
        raise ValueError(f"--param: {err}")
    wd = args.wind_diffusion
    diffusion = ((wd[0], 0.0), (0.0, wd[0])) if len(wd) == 1 else ((wd[0], wd[1]), (wd[2], wd[3]))
    wind = WindParams(c0_per_s=args.c0, mean_wind_m_s=tuple(args.mean_wind), wind_diffusion_m_s=diffusion)
    rates = {k: getattr(args, f"{k}_hz") for k in VehicleConfig().rates_hz}
    cfg = VehicleConfig(
        instance=args.instance,
        initial_pos_m=tuple(args.initial_pos_m),
        initial_vel_m_s=None if args.initial_vel_m_s is None else tuple(args.initial_vel_m_s),
        seed=args.seed,
        home_lat_deg=args.home_lat,
        home_lon_deg=args.home_lon,
        home_alt_amsl_m=args.home_alt_m,
        altitude_m=args.altitude_m,
        wind=wind,
        acc_limit_m_s2=args.acc_limit_m_s2,
        physics_dt_s=args.physics_dt_s,
        acc_lag_s=args.acc_lag_s,
        dt_s=args.dt_s,
        lockstep=args.lockstep,
        com_of_loss_t_s=args.com_of_loss_t_s,
        deny_arming=args.deny_arming,
        start_on_ground=args.start == "ground",
        origin=None if args.origin is None else tuple(args.origin),
        params=tuple(params),
        rates_hz=rates,
        lockstep_resend_hz=args.lockstep_resend_hz,
        traffic_rate_hz=args.traffic_rate_hz,
        hold_model=args.hold_model,
    )
    onboard = args.onboard_url or f"udpout:127.0.0.1:{14540 + args.instance}"
    urls = [u for u in [onboard, args.gcs_url, *args.extra_url] if u and u.lower() != "none"]
    if not urls:
        raise ValueError("no MAVLink link: give --onboard-url or --gcs-url")
    return cfg, urls


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.INFO),
        format=f"%(asctime)s mock-vehicle[{args.instance}] %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    log = logging.getLogger("mock_vehicle")
    try:
        cfg, urls = config_from_args(args)
        signing = None
        if args.signing_key is not None:
            from mavlink_bridge.signing import SigningConfig, load_signing_key

            signing = SigningConfig(load_signing_key(args.signing_key), args.signing_link_id)
    except ValueError as exc:  # SigningKeyError is a ValueError
        log.error("%s", exc)
        return 2
    stop = threading.Event()

    def on_signal(signum, _frame) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    from .server import run_vehicle

    try:
        if args.world_url is not None:
            from .world import parse_world_url

            parse_world_url(args.world_url)
        run_vehicle(cfg, urls, stop, tlog_path=args.tlog, signing=signing, world_url=args.world_url)
    except Exception as exc:  # config errors surface here (bad url, port in use)
        log.error("mock vehicle failed: %s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
