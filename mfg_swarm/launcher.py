"""`mfg-swarm run`: a whole swarm as separate processes on one machine (issue 6).

N ``mock-vehicle`` processes (PX4-like, MAVLink over loopback UDP) and N ``mfg-autopilot``
processes (one controller per vehicle), the controllers meeting over Zenoh (peer mode on
loopback by default; ``--zenoh-router`` runs a router and the controllers as clients).
The launcher waits for the mission to end, stops everything, and writes to the output
folder: metrics.json (same keys as ``mfg-swarm sim``, computed from the vehicles' tlogs),
trajectories.npz, every vehicle's tlog, every controller's log, and every process's stderr.

Ctrl-C (or SIGTERM) stops the whole swarm cleanly: controllers first (each commands HOLD
and closes its log), then vehicles (each closes its tlog), then the router; a child that
does not exit in time is killed. The results folder then says it is partial.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mfg_autopilot.presets import inner_loop_on, make_controller, preset_by_name
from mfg_autopilot.safety.layers import counts_by_layer
from mock_vehicle.proximity import DEFAULT_HOME_DEG

from .flightlog import lockstep_grid, read_controller_log, read_new_lines, read_vehicle_tlog, realtime_grid
from .metrics import separation_guarantee
from .results import METRIC_KEYS, Trajectories, compute_metrics, write_json_atomic, write_npz_atomic
from .scenarios import Scenario
from .sim import airframe_acc_lag_s, plant_params_for

__all__ = ["RunConfig", "run_swarm", "LaunchError"]


PEER_MESH_MAX_N = 25
"""Above this many vehicles the launcher joins the controllers through a Zenoh router (client
mode) instead of a full peer mesh: N = 81 peers on loopback (3,240 links) did not finish
their t = 0 exchange within 120 s on a 2-core machine."""


LOCKSTEP_PHYSICS_DT_S = 0.1
"""The mocks' plant sub-step in lockstep: the simulator's default, so that a lockstep swarm flies it bit for bit."""

REALTIME_PHYSICS_DT_S = 0.02
"""... and in real time (50 Hz, as a real vehicle's estimator publishes). A mock reports the state of its last sub-step:
at 10 Hz each vehicle's telemetry and its world reports were up to 0.1 s old, by a phase that differed from vehicle
to vehicle; a formation whose UAVs each saw the others ~0.1-0.3 m behind themselves braked together and fell metres
behind its plan (``mfg-swarm run --realtime --n 4``: 29 m at 20 s; twenty-seventh session, docs/proximity.md)."""


REALTIME_TRAFFIC_RATE_HZ = 20.0
"""The mocks' proximity sensor rate in real time (``mock-vehicle --traffic-rate-hz``; its default, 5 Hz, is kept for a
mock started by hand). The default controller's formation feedback reads each neighbour's deviation from its plan
particle: at 5 Hz a set was up to 0.2 s old at a step, the neighbours' velocities that much behind in the departure's
acceleration, and a formation of four fell 0.6-0.8 m behind its plan together (0.095 m at 20 Hz, as in lockstep;
twenty-seventh session)."""


START_CPU_S_PER_PAIR = 1.5
"""CPU seconds one vehicle pair needs to start on a quiet machine (a mock imports in ~0.3 s,
a controller in ~0.8 s, then its link, Zenoh session and t = 0 exchange): the unit of the
start-up budget."""


def default_startup_timeout_s(n: int, cores: int | None = None, load1: float | None = None) -> float:
    """Start-up budget for ``n`` vehicle pairs started at once: 60 s plus three times the CPU
    time they need, spread over the machine's cores and stretched by how busy the machine
    already is (1-min load average per core, at least 1); at most 30 min. E.g. N = 81 on an
    idle 2-core machine: 242 s; N = 9: 80 s (at least 120 s is kept, the old fixed value)."""
    cores = max(1, int(cores or os.cpu_count() or 1))
    if load1 is None:
        try:
            load1 = os.getloadavg()[0]
        except OSError:
            load1 = 0.0
    busy = max(1.0, float(load1) / cores)
    return float(min(1800.0, max(120.0, 60.0 + 3.0 * n * START_CPU_S_PER_PAIR / cores * busy)))


class LaunchError(RuntimeError):
    """The swarm could not be started or run; the message says what and how to fix it."""


@dataclass(frozen=True)
class RunConfig:
    scenario: Scenario
    mode: str
    preset_name: str
    out: Path
    seed: int = 0
    steps: int = 200
    range_m: float | None = None
    lockstep: bool = True
    zenoh_router: bool | None = None          # None: peers up to PEER_MESH_MAX_N vehicles, a router beyond
    mavlink_base_port: int | None = None     # None: pick free ports; else base + I (PX4: 14540)
    zenoh_base_port: int | None = None
    gcs_url: str = "none"
    physics_dt_s: float | None = None         # the mocks' plant sub-step; None: 0.1 s in lockstep (the simulator's, bit
                                              # for bit), REALTIME_PHYSICS_DT_S in real time
    acc_lag_s: float | None = None            # the mocks' acceleration response lag (mock-vehicle --acc-lag-s); None:
                                              # the preset's airframe (sim.airframe_acc_lag_s: PX4's for the default
                                              # guidance, none for the paper's)
    inner_loop: bool | None = None            # every controller's telemetry-rate inner loop (mfg-autopilot
                                              # --inner-loop); None: the preset's (on in the default guidance's)
    time_limit_s: float | None = None
    startup_timeout_s: float | None = None    # None: default_startup_timeout_s(N) (scales with N and the machine)
    progress: bool | None = None
    extra_controller_args: tuple[str, ...] = ()
    controller_rt_priority: int | None = None  # SCHED_FIFO priority of every controller (mfg-autopilot --rt-priority)
    mavlink_key_file: str | None = None       # MAVLink 2 signing between every controller and its vehicle
    swarm: str | None = None                  # Zenoh key prefix mfg/<swarm>/ (default: run<pid>)
    zenoh_router_config: str | None = None    # router json5 (e.g. with access control, docs/security.md)
    zenoh_client_config: str | None = None    # controllers' json5; "{i}" is replaced by the vehicle id
    python: str = field(default_factory=lambda: sys.executable)
    mission: object | None = None             # a field mission (mfg_autopilot.mission.Mission); scenario = its swarm frame
    mission_file: Path | None = None          # ... and its file, handed to every controller
    on_poll: Callable[[], object] | None = None   # called every 0.2 s while the swarm flies and once after (run --live)

    @property
    def plant_dt_s(self) -> float:
        """The mocks' plant sub-step: physics_dt_s, or by default the lockstep or real-time one."""
        return self.physics_dt_s or (LOCKSTEP_PHYSICS_DT_S if self.lockstep else REALTIME_PHYSICS_DT_S)

    @property
    def acc_lag_flown_s(self) -> float:
        """The mocks' acceleration lag: ``acc_lag_s``, or the preset's airframe's (sim.airframe_acc_lag_s)."""
        return self.acc_lag_s if self.acc_lag_s is not None else airframe_acc_lag_s(preset_by_name(self.preset_name))

    @property
    def inner_loop_on(self) -> bool:
        """Whether the controllers fly the inner loop: ``inner_loop``, or the preset's (presets.inner_loop_on)."""
        return inner_loop_on(preset_by_name(self.preset_name), self.inner_loop)

    @property
    def lockstep_sub_step_ms(self) -> int | None:
        """Lockstep with the inner loop: the mocks are stepped by their plant sub-step (ms), each control step's
        acceleration being its sub-steps' mean (flightlog.lockstep_grid); else None."""
        return int(round(self.plant_dt_s * 1000)) if self.inner_loop_on and self.lockstep else None


def _free_port_block(n_udp: int, n_tcp: int, lo: int = 20000, hi: int = 32000, tries: int = 200,
                     exclude: frozenset[int] | set[int] = frozenset()) -> tuple[list[int], list[int]]:
    """Consecutive loopback ports, all free at once: n_udp UDP ports from b and n_tcp TCP ports
    from b + n_udp. Chosen below Linux's ephemeral range (32768-60999), so that the source
    ports the OS hands to other sockets (a mock's udpout, a Zenoh connection) cannot take
    them between this check and the children binding them. None of them in ``exclude`` (ports
    already promised to this launch but not bound yet: free now, taken later)."""
    rng = random.Random(os.getpid() ^ int(time.time() * 1e3))
    span = n_udp + n_tcp
    for _ in range(tries):
        b = rng.randrange(lo, hi - span)
        if exclude and not exclude.isdisjoint(range(b, b + span)):
            continue
        socks = []
        try:
            for i in range(n_udp):
                socks.append(socket.socket(socket.AF_INET, socket.SOCK_DGRAM)); socks[-1].bind(("127.0.0.1", b + i))
            for i in range(n_tcp):
                socks.append(socket.socket(socket.AF_INET, socket.SOCK_STREAM)); socks[-1].bind(("127.0.0.1", b + n_udp + i))
            return list(range(b, b + n_udp)), list(range(b + n_udp, b + span))
        except OSError:
            continue
        finally:
            for s_ in socks:
                s_.close()
    raise LaunchError(f"no block of {span} free loopback ports in {lo}..{hi}: give --mavlink-base-port")


def _check_ports_free(kind: int, ports: list[int], what: str) -> None:
    for p in ports:
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", p))
            except OSError:
                raise LaunchError(f"{what} port {p} on 127.0.0.1 is in use: stop what holds it "
                                  f"(e.g. another swarm or PX4 SITL), or choose another base port") from None


_WARM_IMPORTS = ("import sys, mfg_autopilot.runtime.cli, mfg_autopilot.runtime.autopilot, mfg_autopilot.runtime.router, mock_vehicle.cli, "
                 "mock_vehicle.world, mfg_autopilot.guidance.controller, mfg_autopilot.pde.control, scipy.spatial\n"
                 "from mfg_autopilot.presets import warm_up\n"
                 "warm_up()\n"
                 "specs = [getattr(m, '__spec__', None) for m in list(sys.modules.values())]\n"
                 "names = sorted({s.origin + '\\t' + s.cached for s in specs if s is not None and s.has_location "
                 "and s.cached and str(s.origin).endswith('.py')})\n"
                 "open(sys.argv[1], 'w', encoding='utf-8').write('\\n'.join(names))\n")
"""What the children import, and what loading the numba kernels from their cache imports (~70
numba modules numba loads lazily; mfg_autopilot.presets imports the controller rooms on first use).
The child lists every source module it loaded in the manifest file named by its argument."""


def _bytecode_cache_env(py: str, log_path: Path) -> dict[str, str] | None:
    """The children's environment when this environment forbids writing byte-code
    (PYTHONDONTWRITEBYTECODE, as some sandboxes and CI set it): then each of the 2N + 2
    processes would compile the same modules from source at start-up (a controller: ~120
    modules, ~0.8 CPU s, most of them numba's, loaded when the kernels come from numba's cache).
    Instead one child imports them and loads the kernels once, writing the byte-code into a
    private cache (PYTHONPYCACHEPREFIX, a 0700 directory of this user) that every child reads.
    Done again only when a module of the manifest that child wrote is newer than its cached
    byte-code or has none; None (children inherit the environment) if
    not needed or not possible."""
    if not os.environ.get("PYTHONDONTWRITEBYTECODE") or os.environ.get("PYTHONPYCACHEPREFIX"):
        return None
    prefix = Path(tempfile.gettempdir()) / f"mfg-swarm-pycache-{os.getuid()}"
    try:
        prefix.mkdir(mode=0o700, exist_ok=True)
        st = prefix.stat()
        if st.st_uid != os.getuid() or st.st_mode & 0o077:
            return None                       # not ours alone: never read byte-code others could write
    except OSError:
        return None
    env = dict(os.environ, PYTHONPYCACHEPREFIX=str(prefix))
    tag = sys.implementation.cache_tag
    manifest = prefix / f"manifest-{hashlib.sha256(py.encode()).hexdigest()[:12]}.{tag}.txt"   # per interpreter
    try:      # source <TAB> its byte-code, one module per line
        pairs = [tuple(map(Path, line.split("\t"))) for line in manifest.read_text(encoding="utf-8").splitlines() if line]
    except (OSError, ValueError):
        pairs = []
    # (a project module that starts importing a new one is itself newer than its byte-code)
    stale = not pairs or any(len(p) != 2 for p in pairs)
    for src, pyc in pairs:
        if stale:
            break
        try:
            stale = pyc.stat().st_mtime < src.stat().st_mtime
        except OSError:
            stale = src.exists()              # a module that is gone is not imported any more
    if stale:
        warm = {k: v for k, v in env.items() if k != "PYTHONDONTWRITEBYTECODE"}
        try:
            with open(log_path, "wb") as fh:
                subprocess.run([py, "-c", _WARM_IMPORTS, str(manifest)], env=warm, stdout=fh, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL, timeout=300, check=False)
        except (OSError, subprocess.TimeoutExpired):
            return None
    return env


def _die_with_parent() -> None:
    """In the child, before exec: get SIGTERM if the launcher dies (even by SIGKILL), so no
    vehicle or controller outlives it (Linux prctl PR_SET_PDEATHSIG; elsewhere a no-op)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


class _Child:
    def __init__(self, name: str, argv: list[str], log_path: Path, env: dict[str, str] | None = None) -> None:
        self.name, self.argv, self.log_path = name, argv, log_path
        self._fh = open(log_path, "wb")
        self.p = subprocess.Popen(argv, stdout=self._fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                  start_new_session=True, preexec_fn=_die_with_parent, env=env)

    def alive(self) -> bool:
        return self.p.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            try:
                os.killpg(self.p.pid, sig)
            except ProcessLookupError:
                pass

    def close(self) -> None:
        self._fh.close()


def _last_line(path: Path) -> str:
    """The last non-empty line of a child's stderr log (what it said before it stopped)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - 4096))
            lines = [ln.strip() for ln in fh.read().decode("utf-8", "replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][-300:] if lines else ""


def _named(children: list["_Child"], most: int = 5) -> str:
    """'controller3 (exit 1: <its last stderr line>), ...' for the first ``most``."""
    parts = []
    for c in children[:most]:
        code = c.p.poll()
        what = "running" if code is None else f"exit {code}"
        last = _last_line(c.log_path)
        parts.append(f"{c.name} ({what}{': ' + last if last else ''}; log {c.log_path})")
    more = f" and {len(children) - most} more" if len(children) > most else ""
    return ", ".join(parts) + more


_STARTUP_EVENTS = ("vehicle_found", "t0_exchange", "swarm_present", "armed", "offboard")


def _startup_report(controllers: list["_Child"], status: list[dict], vehicles: list["_Child"]) -> str:
    """Which controllers did not reach OFFBOARD, grouped by the last start-up stage they logged."""
    stages: dict[str, list[int]] = {}
    for i, s_ in enumerate(status):
        if s_.get("offboard"):
            continue
        last = next((e for e in reversed(_STARTUP_EVENTS) if s_.get(e)), "nothing logged (process starting)")
        stages.setdefault(last, []).append(i)
    parts = [f"{len(ids)} controller(s) last at '{stage}': {ids[:20]}{' ...' if len(ids) > 20 else ''}"
             for stage, ids in stages.items()]
    stuck = [controllers[ids[0]] for ids in stages.values()]
    dead_v = [v.name for v in vehicles if not v.alive()]
    return ("; ".join(parts) + (f"; vehicles not running: {dead_v}" if dead_v else "")
            + (f"; e.g. {_named(stuck, most=2)}" if stuck else ""))


def _stop_all(children: list[_Child], sig: int, timeout_s: float) -> list[str]:
    """Signal children, wait up to timeout_s, SIGKILL the rest. Returns the killed names."""
    for c in children:
        c.signal(sig)
    deadline = time.monotonic() + timeout_s
    for c in children:
        try:
            c.p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    killed = []
    for c in children:
        if c.alive():
            c.signal(signal.SIGKILL)
            killed.append(c.name)
            try:
                c.p.wait(5.0)
            except subprocess.TimeoutExpired:
                pass
        c.close()
    return killed


class _Progress:
    def __init__(self, enabled: bool, n: int) -> None:
        self.enabled, self.n, self.last = enabled, n, 0.0

    def show(self, text: str, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if force or now - self.last > 0.5:
            self.last = now
            sys.stderr.write("\r" + text.ljust(100)[:120])
            sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


_STEP_PREFIX = re.compile(rb'\{"type":"step","step":(\d+),"time_s":([-+0-9.eE]+),')
"""The head of a step record as ControllerLog writes it (compact separators, keys in this order)."""


def _controller_status(paths: list[Path], offsets: list[int], state: list[dict]) -> None:
    """Read new lines of each controller log (incrementally) into state[i]."""
    for i, p in enumerate(paths):
        lines, offsets[i] = read_new_lines(p, offsets[i])
        for line in lines:
            m = _STEP_PREFIX.match(line)
            if m is not None:      # a step record: only its step and time are needed (not its ~2 KB of weights)
                state[i]["step"] = int(m.group(1))
                state[i]["time_s"] = float(m.group(2))
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if rec.get("type") == "event":
                state[i][rec["what"]] = True
            elif rec.get("type") == "step":
                state[i]["step"] = rec["step"]
                state[i]["time_s"] = rec["time_s"]
            elif rec.get("type") == "end":
                state[i]["end"] = rec.get("reason")


_PREVIOUS_RUN_FILES = ("controllers/controller*.jsonl", "controllers/state*/checkpoint.pkl", "vehicles/vehicle*.tlog",
                       "stderr/*.log", "metrics.json", "trajectories.npz", "fig*.png", "flight.mcap", "flight.gif")


def clear_previous_run(out: Path) -> list[Path]:
    """Delete the files an earlier run left in ``out`` (it is reused when the same run is asked
    for again): controller logs are appended to (a restarted controller continues its own log),
    so an old log would merge two flights into one (the t = 0 exchange counted twice, Fig. 3 from
    the old flight); an old checkpoint of the same swarm name (``--swarm``) would make the new
    flight resume at the old one's last step; and an old metrics.json would outlive a new run
    that fails. Only the files
    a run writes (``_PREVIOUS_RUN_FILES``); anything else in the folder is left alone. Returns
    the deleted paths."""
    gone = []
    for pattern in _PREVIOUS_RUN_FILES:
        for f in sorted(out.glob(pattern)):
            if f.is_file():
                f.unlink()
                gone.append(f)
    return gone


def run_swarm(cfg: RunConfig) -> tuple[Path, dict]:
    """Fly the swarm as processes; return (output folder, metrics)."""
    sc = cfg.scenario
    n = sc.n
    if n < 1 or n > 253:
        raise LaunchError(f"N = {n} is impossible for a process swarm: MAVLink system ids allow 1..253 vehicles")
    if cfg.controller_rt_priority is not None:
        # the controller's own rule (its config module pulls in Zenoh's settings: only when asked)
        from mfg_autopilot.runtime.config import check_rt_priority
        try:
            check_rt_priority(cfg.controller_rt_priority)
        except ValueError as exc:
            raise LaunchError(str(exc)) from None
    preset = preset_by_name(cfg.preset_name)
    out = Path(cfg.out)
    gone = clear_previous_run(out)
    if gone:
        sys.stderr.write(f"{out}: replaced the previous run's results ({len(gone)} files)\n")
    for sub in ("vehicles", "controllers", "stderr"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    status_path = out / "STATUS.json"
    write_json_atomic(status_path, {"state": "running", "partial": True, "started_unix_s": time.time()})
    mission = {"sites_m": sc.destination_m.tolist()}
    write_json_atomic(out / "mission.json", mission)

    # every port this launch picks itself in one block (the world's UDP port after the vehicles'), clear of the ports
    # given: picked one block at a time, the world's port once landed on a controller's, free at the check and bound by
    # the world before that controller started (`./dev run`: "udpin:127.0.0.1:20129: Address already in use")
    given = set()
    if cfg.mavlink_base_port is not None:
        given |= set(range(cfg.mavlink_base_port, cfg.mavlink_base_port + n))
    if cfg.zenoh_base_port is not None:
        given |= set(range(cfg.zenoh_base_port, cfg.zenoh_base_port + n + 1))
    auto_udp, auto_z = _free_port_block(n + 1, n + 1, exclude=given)
    auto_mav, auto_world_port = auto_udp[:n], auto_udp[n]
    if cfg.mavlink_base_port is None:
        mav_ports = auto_mav
    else:
        mav_ports = [cfg.mavlink_base_port + i for i in range(n)]
        _check_ports_free(socket.SOCK_DGRAM, mav_ports, "MAVLink onboard")
    if cfg.zenoh_base_port is None:
        z_ports = auto_z
    else:
        z_ports = [cfg.zenoh_base_port + i for i in range(n + 1)]
        _check_ports_free(socket.SOCK_STREAM, z_ports, "Zenoh")
    use_router = cfg.zenoh_router if cfg.zenoh_router is not None else n > PEER_MESH_MAX_N
    if cfg.zenoh_router_config or cfg.zenoh_client_config:
        if cfg.zenoh_router is False:
            raise LaunchError("Zenoh router/client configs need the router topology: drop --zenoh-peers")
        use_router = True

    py = cfg.python
    startup_s = cfg.startup_timeout_s if cfg.startup_timeout_s is not None else default_startup_timeout_s(n)
    physics_dt_s = cfg.plant_dt_s
    inner_on = cfg.inner_loop_on
    wind = plant_params_for(preset, physics_dt_s).wind
    # proximity sensor (docs/proximity.md): a world process when the preset's controller has one
    sensor_range_m = getattr(make_controller(cfg.mode, preset, sc.destination_m[:1]), "sensor_range_m", None)
    world_port = auto_world_port if sensor_range_m is not None else None
    world: list[_Child] = []
    children: list[_Child] = []
    router: list[_Child] = []
    controllers: list[_Child] = []
    vehicles: list[_Child] = []
    interrupted = {"sig": None}

    def on_signal(signum, _frame):
        interrupted["sig"] = signum

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    bar = _Progress(sys.stderr.isatty() if cfg.progress is None else cfg.progress, n)
    t_start = time.perf_counter()
    killed: list[str] = []
    env = _bytecode_cache_env(py, out / "stderr" / "bytecode-cache.log")
    try:
        if use_router:
            router.append(_Child("zenoh-router", [py, "-m", "mfg_autopilot.runtime.router", "--zenoh-listen",
                                                  f"tcp/127.0.0.1:{z_ports[n]}"]
                                 + (["--zenoh-config", cfg.zenoh_router_config] if cfg.zenoh_router_config else []),
                                 out / "stderr" / "zenoh-router.log", env))
        if world_port is not None:
            world.append(_Child("world", [py, "-m", "mock_vehicle.world", "--listen", f"127.0.0.1:{world_port}", "--n", str(n),
                                          "--sensor-range-m", repr(float(sensor_range_m)), "--log-level", "WARNING",
                                          "--deadline-s", repr(max(60.0, float(startup_s)))]
                                + (["--lockstep"] if cfg.lockstep else []), out / "stderr" / "world.log", env))
        for i in range(n):
            x, y = (float(v) for v in sc.initial_pos_m[i])
            argv = [py, "-m", "mock_vehicle.cli", "--instance", str(i), "--onboard-url", f"udpout:127.0.0.1:{mav_ports[i]}",
                    "--gcs-url", cfg.gcs_url, f"--initial-pos-m={x!r},{y!r}", "--seed", str(cfg.seed),
                    "--c0", repr(float(wind.c0_per_s)), "--mean-wind", ",".join(repr(float(v)) for v in wind.mean_wind_m_s),
                    "--wind-diffusion", ",".join(repr(float(v)) for row in wind.wind_diffusion_m_s for v in row),
                    "--acc-limit-m-s2", repr(float(preset.learner.acc_max_m_s2)), "--physics-dt-s", repr(float(physics_dt_s)),
                    *([] if cfg.lockstep else ["--traffic-rate-hz", repr(REALTIME_TRAFFIC_RATE_HZ)]),
                    "--dt-s", repr(float(physics_dt_s if inner_on and cfg.lockstep else preset.dt_s)), "--tlog", str(out / "vehicles" / f"vehicle{i}.tlog"), "--log-level", "WARNING"]
            if cfg.lockstep:
                argv.append("--lockstep")
            # always given: the mock's own default is PX4's lag, the paper's presets fly none
            argv.append(f"--acc-lag-s={float(cfg.acc_lag_flown_s)!r}")
            v0 = getattr(sc, "initial_vel_m_s", None)
            if cfg.mission is None and v0 is not None:       # the scenario's start velocity (dense: at rest), else the wind's
                argv.append(f"--initial-vel-m-s={float(v0[i, 0])!r},{float(v0[i, 1])!r}")
            if cfg.mission is not None:
                # a real field: the world's frame is the mission's datum; each vehicle boots on the ground at its
                # launch point, its EKF origin there (so two vehicles' LOCAL_NED are not comparable)
                d, o = cfg.mission.datum, cfg.mission.launch_geodetic(i + 1)
                argv += ["--start", "ground", f"--origin={o.lat_deg!r},{o.lon_deg!r},{o.alt_amsl_m!r}",
                         "--home-lat", repr(d.lat_deg), "--home-lon", repr(d.lon_deg), "--home-alt-m", repr(d.alt_amsl_m)]
            if world_port is not None:
                argv += ["--world-url", f"udp:127.0.0.1:{world_port}"]
                if cfg.mission is None:
                    argv += ["--home-lat", repr(DEFAULT_HOME_DEG[0]), "--home-lon", repr(DEFAULT_HOME_DEG[1])]
            if cfg.mavlink_key_file:
                argv += ["--signing-key", str(cfg.mavlink_key_file)]
            vehicles.append(_Child(f"vehicle{i}", argv, out / "stderr" / f"vehicle{i}.log", env))
        ctrl_logs = [out / "controllers" / f"controller{i}.jsonl" for i in range(n)]
        for i in range(n):
            argv = [py, "-m", "mfg_autopilot.runtime.cli", "--instance", str(i), "--connect", f"udpin:127.0.0.1:{mav_ports[i]}",
                    "--mode", cfg.mode, "--preset", cfg.preset_name, "--n", str(n), "--swarm", cfg.swarm or f"run{os.getpid()}",
                    "--mission", str(cfg.mission_file or out / "mission.json"), "--steps", str(cfg.steps), "--log", str(ctrl_logs[i]),
                    "--state-dir", str(out / "controllers" / f"state{i}"),
                    "--log-level", "WARNING", "--exchange-timeout-s", repr(float(startup_s)),
                    # every start-up wait gets the start-up budget: with 2N processes starting on a
                    # few cores a vehicle (or the swarm's first lockstep step) can be that late
                    "--vehicle-timeout-s", repr(float(startup_s)), "--step-timeout-s", repr(max(30.0, float(startup_s)))]
            if cfg.range_m is not None:
                argv += ["--range-m", repr(float(cfg.range_m))]
            if cfg.lockstep:
                argv.append("--lockstep")
            if use_router:
                argv += ["--zenoh-mode", "client", "--zenoh-connect", f"tcp/127.0.0.1:{z_ports[n]}"]
                if cfg.zenoh_client_config:
                    argv += ["--zenoh-config", cfg.zenoh_client_config.replace("{i}", str(i))]
            else:
                argv += ["--zenoh-listen", f"tcp/127.0.0.1:{z_ports[i]}"]
                if i > 0:
                    argv += ["--zenoh-connect", f"tcp/127.0.0.1:{z_ports[0]}"]
            if cfg.mavlink_key_file:
                argv += ["--mavlink-key", str(cfg.mavlink_key_file)]
            if cfg.inner_loop is not None:
                argv.append("--inner-loop" if cfg.inner_loop else "--no-inner-loop")
            if cfg.controller_rt_priority is not None:
                argv += ["--rt-priority", str(int(cfg.controller_rt_priority))]
            argv += list(cfg.extra_controller_args)
            controllers.append(_Child(f"controller{i}", argv, out / "stderr" / f"controller{i}.log", env))
        children = router + world + vehicles + controllers

        # ---- wait for the mission to end, showing progress
        offsets = [0] * n
        status = [dict() for _ in range(n)]
        limit = cfg.time_limit_s if cfg.time_limit_s is not None else (
            startup_s + (cfg.steps * preset.dt_s * 2 + 60 if not cfg.lockstep else 30 + cfg.steps * 2.0 * max(1, n / 10)))
        deadline = time.monotonic() + limit
        startup_deadline = time.monotonic() + startup_s
        started = False
        reason = "completed"
        while True:
            _controller_status(ctrl_logs, offsets, status)
            if cfg.on_poll is not None:
                cfg.on_poll()
            done = [not c.alive() for c in controllers]
            armed = sum(1 for s in status if s.get("armed"))
            offb = sum(1 for s in status if s.get("offboard"))
            ended = sum(done)
            sim_t = max((s.get("time_s", 0.0) for s in status), default=0.0)
            bar.show(f"  N={n} {cfg.mode}: armed {armed}/{n}  offboard {offb}/{n}  finished {ended}/{n}  t_sim={sim_t:.0f} s"
                     f"  wall={time.perf_counter() - t_start:.0f} s")
            if all(done):
                break
            if interrupted["sig"] is not None:
                reason = "interrupted"
                break
            dead_vehicles = [v for v in vehicles + world + router if not v.alive()]
            if dead_vehicles:
                reason = f"process exited early: {_named(dead_vehicles)}"
                break
            if not started:
                # start-up: every controller must reach OFFBOARD within the start-up budget; a
                # controller that exits before (e.g. the t = 0 exchange timed out) ends the run
                failed = [c for c, d, s_ in zip(controllers, done, status) if d and not s_.get("offboard")]
                if failed:
                    reason = f"start-up failed: {_named(failed)}"
                    break
                if offb == n:
                    started = True
                elif time.monotonic() > startup_deadline:
                    reason = (f"start-up timed out after {startup_s:.0f} s (--startup-timeout-s): "
                              + _startup_report(controllers, status, vehicles))
                    break
            if time.monotonic() > deadline:
                reason = f"time limit {limit:.0f} s"
                break
            time.sleep(0.2)
        if cfg.on_poll is not None:
            cfg.on_poll()
        bar.show("", force=True)
        bar.done()
        killed += _stop_all(controllers, signal.SIGTERM, 20.0)
        killed += _stop_all(vehicles, signal.SIGTERM, 10.0)
        killed += _stop_all(world, signal.SIGTERM, 5.0)
        killed += _stop_all(router, signal.SIGTERM, 5.0)
    finally:
        if any(c.alive() for c in children):
            killed += _stop_all([c for c in children if c.alive()], signal.SIGKILL, 5.0)
        for s, h in old.items():
            signal.signal(s, h)

    wall_s = time.perf_counter() - t_start
    exit_codes = {c.name: c.p.returncode for c in controllers}
    traj, metrics = _collect(cfg, preset, n, out, wall_s)
    partial = reason != "completed" or any(code != 0 for code in exit_codes.values())
    metrics.update({"path": "processes", "lockstep": cfg.lockstep, "inner_loop": cfg.inner_loop_on, "acc_lag_s": cfg.acc_lag_flown_s,
                    "lockstep_sub_step_ms": cfg.lockstep_sub_step_ms, "partial": partial, "end_reason": reason,
                    "controller_exit_codes": exit_codes, "killed": killed})
    write_npz_atomic(out / "trajectories.npz", traj.arrays())
    write_json_atomic(out / "metrics.json", metrics)
    write_json_atomic(status_path, {"state": "complete" if not partial else "partial", "partial": partial,
                                    "reason": reason, "killed": killed, "wall_s": wall_s})
    return out, metrics


def _to_swarm_frame(track, mission, system_id: int):
    """A vehicle's telemetry from its own LOCAL_NED (origin: its launch point) into the mission's swarm frame,
    through WGS84 (mfg_autopilot.mission.frames), as its controller sees it."""
    import dataclasses

    vf = mission.frame.vehicle(mission.launch_geodetic(system_id))
    state = vf.state_local_to_swarm(track.state) if len(track.state) else track.state
    acc = vf.vector_to_swarm(np.column_stack([track.sp_acc, np.zeros(len(track.sp_acc))]))[:, 0:2] if len(track.sp_acc) else track.sp_acc
    return dataclasses.replace(track, state=state, sp_acc=acc)


def _collect(cfg: RunConfig, preset, n: int, out: Path, wall_s: float) -> tuple[Trajectories, dict]:
    """Trajectories from the vehicles' tlogs; counts from the controllers' logs."""
    T = cfg.steps
    dt = preset.dt_s
    dt_ms = int(round(dt * 1000))
    # the inner loop steps lockstep vehicles by their sub-steps: each step's acceleration is their mean
    sub_ms = cfg.lockstep_sub_step_ms
    states = np.full((T + 1, n, 4), np.nan)
    acc = np.full((T, n, 2), np.nan)
    tracks = [read_vehicle_tlog(out / "vehicles" / f"vehicle{i}.tlog", i + 1) for i in range(n)]
    if cfg.mission is not None:
        tracks = [_to_swarm_frame(tr, cfg.mission, i + 1) for i, tr in enumerate(tracks)]
    logs = [read_controller_log(out / "controllers" / f"controller{i}.jsonl") for i in range(n)]
    t0 = None
    if cfg.lockstep:
        for i, tr in enumerate(tracks):
            _, states[:, i], acc[:, i] = lockstep_grid(tr, dt_ms, T, sub_ms)
    else:
        starts = [e["wall_s"] for lg in logs for e in lg.events if e.get("what") == "offboard"]
        t0 = min(starts) if starts else min((tr.pos_unix_s[0] for tr in tracks if tr.pos_unix_s.size), default=0.0)
        for i, tr in enumerate(tracks):
            states[:, i], acc[:, i] = realtime_grid(tr, t0, dt, T)
    # steps the swarm actually flew: the longest prefix with every vehicle's state known
    known = ~np.isnan(states[:, :, 0]).any(axis=1)
    flown = int(np.argmin(known)) if not known.all() else T + 1
    if flown == 0:
        # not one instant with every vehicle's state: nothing flown to measure
        empty = {k: None for k in METRIC_KEYS}
        empty.update(n=n, mode=cfg.mode, seed=cfg.seed, steps=0, wall_s=wall_s, steps_requested=T,
                     scenario=cfg.scenario.name, preset=preset.name, error="no complete telemetry recorded")
        z = np.zeros((1, n, 2))
        return Trajectories(dt_s=dt, pos_m=np.full((1, n, 2), np.nan), vel_m_s=z, acc_m_s2=np.zeros((0, n, 2)),
                            dest_m=np.zeros((n, 2)), comm_states=np.zeros((1, n), dtype=np.int64),
                            grad_evals=np.zeros((0, n), dtype=np.int64), mf_evals=np.zeros((0, n), dtype=np.int64),
                            reg_active=np.zeros((0, n), dtype=bool)), empty
    T_eff = max(flown - 1, 0)
    states, acc = states[: T_eff + 1], np.nan_to_num(acc[:T_eff])
    comm = np.zeros((T_eff + 1, n), dtype=np.int64)
    grad = np.zeros((T_eff, n), dtype=np.int64)
    mfe = np.zeros((T_eff, n), dtype=np.int64)
    reg = np.zeros((T_eff, n), dtype=bool)
    backstop = np.zeros((T_eff, n), dtype=bool)
    layer = np.zeros((T_eff, n), dtype=np.uint8)       # safety.backstop.Layer bits, as the simulator records them
    layered = False                                     # (the default controllers log them; orca does not)
    plan_pos = np.full((T_eff + 1, n, 2), np.nan)       # each UAV's own plan particle (MFG default), from its log
    dest = np.array(json.loads((out / "mission.json").read_text())["sites_m"], dtype=float).reshape(n, 2)
    for i, lg in enumerate(logs):
        for ev in lg.events:
            if ev.get("what") == "t0_exchange":
                comm[0, i] += int(ev.get("states_received", 0))
        for rec in lg.steps:
            k = rec["step"]
            if k < T_eff:
                comm[k, i] += rec.get("states_received", 0)
                grad[k, i] = rec.get("grad_evals", 0)
                mfe[k, i] = rec.get("mf_evals", 0)
                reg[k, i] = rec.get("reg_active", False)
                backstop[k, i] = rec.get("backstop_active", False)
                if "backstop_layer" in rec:
                    layered = True
                    layer[k, i] = rec["backstop_layer"]
            if k <= T_eff and rec.get("plan_pos_m") is not None:
                plan_pos[k, i] = rec["plan_pos_m"]
        if lg.end is not None and lg.end.get("destination_m") is not None:
            dest[i] = lg.end["destination_m"]
    w_ref = np.array([rec["w_H"] for rec in logs[0].steps[: T_eff + 1]], dtype=float) if logs and logs[0].steps else None
    extra = {"backstop_active": backstop, **({"backstop_layer": layer} if layered else {})}
    if t0 is not None:
        extra["t0_unix_s"] = np.array(float(t0))      # real time: the wall time of t_0 (flight.mcap's clock)
    traj = Trajectories(dt_s=dt, pos_m=states[:, :, 0:2], vel_m_s=states[:, :, 2:4], acc_m_s2=acc, dest_m=dest,
                        comm_states=comm, grad_evals=grad, mf_evals=mfe, reg_active=reg, w_H_ref=w_ref, extra=extra)
    metrics = compute_metrics(traj, n=n, mode=cfg.mode, range_m=cfg.range_m if cfg.mode.startswith("hjb") else None,
                              seed=cfg.seed, wall_s=wall_s, scenario=cfg.scenario.name, preset=preset.name)
    metrics["steps_requested"] = T
    metrics["backstop_activations"] = int(backstop.sum())
    metrics["safety_interventions"] = metrics["backstop_activations"]   # (vehicle, step) pairs the backstop acted
    if layered:
        metrics["safety_interventions_by_layer"] = counts_by_layer(layer)     # as `sim` reports it
    plans = [ev["plan"] for lg in logs for ev in lg.events if ev.get("what") == "t0_exchange" and "plan" in ev]
    if plans:
        metrics["plan"] = plans[0]                   # every controller computes the same plan from the same exchange
        metrics["plans_agree"] = all(p == plans[0] for p in plans)
    metrics.update(start_spacing_m=cfg.scenario.min_start_spacing_m, slot_spacing_m=cfg.scenario.slot_spacing_m)
    logged = ~np.isnan(plan_pos[:, :, 0]).any(axis=1)
    upto = int(np.argmin(logged)) if not logged.all() else T_eff + 1      # instants with every particle logged
    if plans and upto >= 2:
        # the plan's guarantee on this flight, as `sim` reports it (a step record is written for t_0 .. t_T-1: the
        # last instant has no particle logged)
        metrics["guarantee"] = {"certified": plans[0].get("clearance_m") is not None,
                                **separation_guarantee(traj.pos_m[:upto], plan_pos[:upto])}
    return traj, metrics
