"""Where the mock vehicle is on the Earth: its world frame, its own EKF origin, its GPS (SPEC 4b).

The simulated world (like Gazebo's for PX4 SITL) has one frame: the tangent plane at the world's
home (``VehicleConfig.home_*``), x north, y east, z down from the home's altitude, on a flat field
at that altitude. The plant integrates eq. 9 in it, and the world backplane senses neighbours in it.

A real PX4 reports LOCAL_POSITION_NED relative to its *own* EKF origin, set where it initialised;
with ``VehicleConfig.origin`` the mock does the same: positions go world -> geodetic -> the
origin's tangent plane (pymap3d, WGS84, horizontal maps on the ellipsoid and altitudes as AMSL
differences, as PX4's own local frame has them). Velocities turn by the small rotation between the
two planes. Without an origin the local frame is the world frame, as before issue 19.

The vehicle never imports the controller: this is the vehicle's geodesy, written against the
same library, not the controller's code (a frame mistake on either side then shows in tests).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pymap3d

__all__ = ["LocalFrame"]


@dataclass(frozen=True)
class LocalFrame:
    """The world frame (home) and the vehicle's EKF origin; ``origin`` None: local = world."""

    home_lat_deg: float
    home_lon_deg: float
    home_alt_amsl_m: float
    origin: tuple[float, float, float] | None = None       # (lat_deg, lon_deg, alt_amsl_m)
    _rot: np.ndarray = field(init=False, repr=False)      # world -> local directions (2, 2)

    def __post_init__(self) -> None:
        if self.origin is None:
            object.__setattr__(self, "_rot", np.eye(2))
            return
        h = 1.0
        cols = [(self._ne_to_local(np.eye(2)[k] * h) - self._ne_to_local(-np.eye(2)[k] * h)) / (2 * h) for k in range(2)]
        object.__setattr__(self, "_rot", np.stack(cols, axis=1))

    @property
    def origin_lat_lon_alt(self) -> tuple[float, float, float]:
        return self.origin if self.origin is not None else (self.home_lat_deg, self.home_lon_deg, self.home_alt_amsl_m)

    def world_to_geodetic(self, x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_amsl_m) of a world-frame point."""
        lat, lon, _ = pymap3d.ned2geodetic(x_m, y_m, 0.0, self.home_lat_deg, self.home_lon_deg, 0.0)
        return float(lat), float(lon), self.home_alt_amsl_m - z_m

    def _ne_to_local(self, ne: np.ndarray) -> np.ndarray:
        lat, lon, _ = pymap3d.ned2geodetic(ne[0], ne[1], 0.0, self.home_lat_deg, self.home_lon_deg, 0.0)
        o = self.origin_lat_lon_alt
        n, e, _ = pymap3d.geodetic2ned(lat, lon, 0.0, o[0], o[1], 0.0)
        return np.array([float(n), float(e)])

    def world_to_local(self, x_m: float, y_m: float, z_m: float, vx_m_s: float, vy_m_s: float) -> tuple[float, ...]:
        """(x, y, z, vx, vy) in the vehicle's LOCAL_NED of a world-frame position and velocity."""
        if self.origin is None:
            return x_m, y_m, z_m, vx_m_s, vy_m_s
        n, e = self._ne_to_local(np.array([x_m, y_m]))
        v = self._rot @ np.array([vx_m_s, vy_m_s])
        return float(n), float(e), z_m + (self.origin[2] - self.home_alt_amsl_m), float(v[0]), float(v[1])

    def local_z_to_world(self, z_local_m: float) -> float:
        """A local z (down from the origin's altitude) as world z (down from the home's)."""
        return z_local_m if self.origin is None else z_local_m - (self.origin[2] - self.home_alt_amsl_m)

    def local_vec_to_world(self, vx: float, vy: float) -> tuple[float, float]:
        """A horizontal vector (e.g. an acceleration setpoint) from local to world axes."""
        if self.origin is None:
            return vx, vy
        w = self._rot.T @ np.array([vx, vy])
        return float(w[0]), float(w[1])
