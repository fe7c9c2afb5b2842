"""The vehicle process's configuration: read once at the command line (``cli.py``), passed down as a value."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mfg_autopilot.mission import Mission
from mfg_autopilot.presets import DEFAULT_PRESET_NAME
from mfg_autopilot.runtime.zenoh_config import ZenohSettings

__all__ = ["AutopilotError", "AutopilotConfig", "check_rt_priority"]


def check_rt_priority(priority: int) -> None:
    """The SCHED_FIFO priorities Linux accepts (1-99); ValueError otherwise."""
    if not 1 <= int(priority) <= 99:
        raise ValueError(f"--rt-priority must be 1..99, got {priority}")


class AutopilotError(RuntimeError):
    """A failure of the controller process, with what failed and what to do."""


@dataclass(frozen=True)
class AutopilotConfig:
    instance: int
    connect: str
    mode: str
    preset: str = DEFAULT_PRESET_NAME
    n: int = 1
    swarm: str = "swarm"
    range_m: float | None = None
    sites_m: tuple[tuple[float, float], ...] | None = None   # every vehicle's destination site (N)
    lockstep: bool = False
    steps: int = 200
    hold_on_arrival: bool | None = None        # default: on in real time, off in lockstep
    arrival_tol_m: float = 1.0
    arrival_hold_s: float = 5.0
    log_path: str | None = None
    tlog_path: str | None = None
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    vehicle_timeout_s: float = 30.0
    exchange_timeout_s: float = 60.0
    gossip_timeout_s: float = 10.0
    step_timeout_s: float = 30.0
    step_retry_s: float = 0.5
    command_timeout_s: float = 10.0
    telemetry_stale_s: float = 0.5
    setpoint_rate_hz: float = 20.0
    vehicle_lost_s: float = 3.0               # heartbeat silence after which the vehicle is lost
    state_dir: str | None = None              # checkpoints for a restart without a new exchange
    mavlink_key_file: str | None = None       # MAVLink 2 signing key (docs/security.md)
    traffic_probe_s: float = 10.0             # proximity sensor: wait this long at the first step for the vehicle's traffic
    traffic_max_age_s: float = 1.0            # real time: sensed traffic older than this is not used
    checkpoint_interval_s: float = 1.0        # wall time between checkpoints (0: every step)
    rt_priority: int | None = None            # SCHED_FIFO priority of the controller's threads (None: normal scheduling)
    log_fpk_weights_every: int = 10           # w_F in the step record every this many steps and at the last (0: never)
    mission: Mission | None = None            # a field mission (docs/mission.md): swarm frame, takeoff, landing
    origin_timeout_s: float = 60.0            # wait this long for the vehicle's EKF origin (GPS_GLOBAL_ORIGIN)
    takeoff_timeout_s: float = 120.0          # ... and for the climb to the group's altitude
    land_timeout_s: float = 120.0             # ... and for touchdown and disarm after the mission
    inner_loop: bool | None = None            # track each step's command at every LOCAL_POSITION_NED between steps
                                              # (TrackingParams.inner_loop, guidance/inner_loop.py); lockstep: a
                                              # vehicle stepped by its physics sub-step. None: the preset's (on in
                                              # the default guidance's presets)
    acc_lag_s: float | None = None            # the airframe's acceleration lag the own-vehicle model assumes
                                              # (TrackingParams.acc_lag_s; the escape's prediction). None: the preset's

    def __post_init__(self) -> None:
        if self.n < 1:
            raise ValueError(f"--n must be >= 1, got {self.n}")
        if not (0 <= self.instance < self.n):
            raise ValueError(f"--instance {self.instance} is not a vehicle of a swarm of {self.n} (0..{self.n - 1})")
        if self.mode.startswith("hjb") and (self.range_m is None or self.range_m < 0):
            raise ValueError("HJB_d needs a radio range: give --range-m D or --power-mw P")
        if self.sites_m is not None and len(self.sites_m) != self.n:
            raise ValueError(f"the mission gives {len(self.sites_m)} destination sites for {self.n} vehicles")
        if self.steps < 1:
            raise ValueError(f"--steps must be >= 1, got {self.steps}")
        if self.rt_priority is not None:
            check_rt_priority(self.rt_priority)
        if self.acc_lag_s is not None and not (np.isfinite(self.acc_lag_s) and 0.0 <= self.acc_lag_s <= 2.0):
            raise ValueError(f"--acc-lag-s must be in [0, 2] s (0: none), got {self.acc_lag_s}")
        if self.log_fpk_weights_every < 0:
            raise ValueError(f"--log-fpk-weights-every must be >= 0, got {self.log_fpk_weights_every}")
        if self.mission is not None:
            if self.sites_m is not None:
                raise ValueError("give the destinations either as a mission or as sites, not both")
            self.mission.require_system_id(self.system_id)
            if self.mission.system_ids != tuple(range(1, self.n + 1)):
                raise ValueError(f"the mission's system ids must be 1..N = 1..{self.n} (instance = system id - 1), got "
                                 f"{len(self.mission.system_ids)} ids from {min(self.mission.system_ids)} to {max(self.mission.system_ids)}")

    @property
    def system_id(self) -> int:
        return self.instance + 1

    def sites_array(self) -> np.ndarray:
        """Every vehicle's destination site (N, 2), in the swarm frame when there is a mission."""
        if self.mission is not None:
            return self.mission.arrays()["site_ne_m"]
        return np.zeros((self.n, 2)) if self.sites_m is None else np.asarray(self.sites_m, dtype=float)
