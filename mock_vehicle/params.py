"""The mock vehicle's parameters, PX4-style: declared once with unit, bounds and default
(STYLE habit 6), served over the MAVLink parameter protocol as REAL32."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .plant import PX4_ACC_LAG_S

__all__ = ["ParamSpec", "PARAM_SPECS", "ParamTable"]


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float
    min: float
    max: float
    unit: str
    description: str

    def __post_init__(self) -> None:
        if len(self.name) > 16:
            raise ValueError(f"MAVLink param ids have at most 16 characters: {self.name}")


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("COM_OF_LOSS_T", 1.0, 0.0, 60.0, "s", "Offboard setpoint loss timeout before the Hold failsafe (PX4)"),
    ParamSpec("MPC_ACC_HOR_MAX", 2.0, 0.01, 50.0, "m/s^2", "Airframe horizontal acceleration limit (plant acc_limit_m_s2)"),
    ParamSpec("MPC_ACC_HOR", 3.0, 2.0, 15.0, "m/s^2", "Hold's braking-stop point: the deceleration PX4 plans it with (navigator)"),
    ParamSpec("MPC_VEL_MANUAL", 10.0, 3.0, 20.0, "m/s", "Position mode: the stick-full speed, whose ratio to MPC_ACC_HOR sets the braking drag"),
    ParamSpec("SIM_WIND_C0", 0.1, 1e-4, 10.0, "1/s", "c0: velocity relaxation rate to the wind (eq. 1)"),
    ParamSpec("SIM_WIND_VN", 1.0, -50.0, 50.0, "m/s", "v_o north: mean wind (eq. 1)"),
    ParamSpec("SIM_WIND_VE", -1.0, -50.0, 50.0, "m/s", "v_o east: mean wind (eq. 1)"),
    ParamSpec("SIM_WIND_V11", 0.1, -10.0, 10.0, "m/s/sqrt(s)", "V_o[0][0]: wind diffusion (eq. 1)"),
    ParamSpec("SIM_WIND_V12", 0.0, -10.0, 10.0, "m/s/sqrt(s)", "V_o[0][1]: wind diffusion (eq. 1)"),
    ParamSpec("SIM_WIND_V21", 0.0, -10.0, 10.0, "m/s/sqrt(s)", "V_o[1][0]: wind diffusion (eq. 1)"),
    ParamSpec("SIM_WIND_V22", 0.1, -10.0, 10.0, "m/s/sqrt(s)", "V_o[1][1]: wind diffusion (eq. 1)"),
    ParamSpec("SIM_ACC_TAU", PX4_ACC_LAG_S, 0.0, 2.0, "s", "Acceleration response lag: first-order time constant (0: none; PX4's "
              "attitude loop ~ 1 / MC_ROLL_P = 0.154 s, the default)"),
    ParamSpec("SIM_ARM_DENY", 0.0, 0.0, 1.0, "bool", "1: refuse arming as a failed PX4 preflight check would"),
    ParamSpec("MIS_TAKEOFF_ALT", 2.5, 0.0, 1000.0, "m", "Takeoff altitude above home when MAV_CMD_NAV_TAKEOFF gives none (PX4)"),
    ParamSpec("MPC_TKO_SPEED", 1.5, 0.1, 10.0, "m/s", "Takeoff climb speed (PX4)"),
    ParamSpec("MPC_LAND_SPEED", 0.7, 0.1, 5.0, "m/s", "Landing descent speed (PX4)"),
    ParamSpec("MPC_Z_VEL_MAX_UP", 3.0, 0.1, 10.0, "m/s", "Largest climb speed of the altitude loop (PX4)"),
    ParamSpec("MPC_Z_VEL_MAX_DN", 1.5, 0.1, 10.0, "m/s", "Largest descent speed of the altitude loop (PX4)"),
    ParamSpec("COM_DISARM_LAND", 2.0, -1.0, 20.0, "s", "Auto-disarm this long after a touchdown that followed a takeoff; <= 0 never (PX4)"),
    ParamSpec("COM_DISARM_PRFLT", 10.0, -1.0, 60.0, "s", "Ground start: auto-disarm this long after arming without a takeoff; <= 0 never (PX4)"),
    ParamSpec("COM_OBL_RC_ACT", 0.0, 0.0, 7.0, "enum", "Offboard loss action (PX4: 0 Position ... 4 Land, 5 Hold); the mock: 4 Land, else Hold"),
    ParamSpec("MPC_Z_P", 1.0, 0.0, 1.5, "1/s", "Altitude loop: vertical velocity setpoint per metre of z error (PX4)"),
    ParamSpec("MPC_Z_VEL_P_ACC", 4.0, 2.0, 15.0, "1/s", "Altitude loop: vertical acceleration per m/s of vz error (PX4)"),
    ParamSpec("NAV_MC_ALT_RAD", 0.8, 0.05, 200.0, "m", "AUTO.TAKEOFF is over within this of its altitude (PX4 navigator)"),
    ParamSpec("MPC_JERK_AUTO", 4.0, 1.0, 80.0, "m/s^3", "Auto modes (Takeoff, Hold, Land): the largest change of acceleration per second (PX4 PositionSmoothing)"),
)


class ParamTable:
    """Current values, in declaration order (the order is the MAVLink param_index)."""

    def __init__(self, overrides: dict[str, float] | None = None) -> None:
        self.specs = {s.name: s for s in PARAM_SPECS}
        self.names = [s.name for s in PARAM_SPECS]
        self.values = {s.name: float(s.default) for s in PARAM_SPECS}
        for k, v in (overrides or {}).items():
            err = self.set(k, v)
            if err:
                raise ValueError(err)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def set(self, name: str, value: float) -> str | None:
        """Set ``name``; returns None, or why the value was refused (unknown, non-finite, out of bounds)."""
        spec = self.specs.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        value = float(value)
        if not math.isfinite(value):
            return f"{name}: non-finite value {value}"
        if not (spec.min <= value <= spec.max):
            return f"{name}: {value} outside [{spec.min}, {spec.max}] {spec.unit}"
        self.values[name] = value
        return None

    def index(self, name: str) -> int:
        return self.names.index(name)
