"""The shared swarm frame and each vehicle's own local frame (SPEC section 4b).

On PX4 every vehicle's LOCAL_NED is relative to its *own* EKF origin (where it initialised,
announced by GPS_GLOBAL_ORIGIN), so two vehicles' local positions cannot be compared.
The swarm frame is one local tangent plane at the mission's datum: x north, y east, z down,
metres. Horizontal conversions go through geodetic coordinates with pymap3d (WGS84) on the
ellipsoid's surface; altitudes are differences of AMSL altitudes, as PX4 does (its local z is the
altitude below the origin's, with no curvature drop):

    swarm_ne = geodetic2ned(ned2geodetic(local_ne, origin_i at h = 0), datum at h = 0)
    swarm_d  = local_d + (datum_alt - origin_alt_i)

This is exact for any distance between origin and datum (no flat-earth step). Doing it at the
datum's altitude instead would scale every horizontal distance by (R + h) / R (7.7e-5 at 488 m
AMSL: 15 cm over 2 km), which PX4 does not do. The tangent planes of two points 2 km apart are
rotated by ~0.018 degrees (3.1e-4 rad) against each other, so a local velocity or acceleration is
turned into the swarm frame by the Jacobian of that map (a rotation within 3e-4 rad of the
identity), not copied: at 8 m/s the difference is 2.5 mm/s.

PX4's own local frame is an azimuthal-equidistant projection (``lib/geo``: ``MapProjection``), not
a tangent plane: within 2 km of the origin the two differ by about a millimetre
(``tests/test_frames.py`` measures it against the geodesic). The mock vehicle uses the tangent
plane (pymap3d), so the simulation is exact; on a real PX4 that millimetre is the frame's error.

Shapes: a position is (3,) [north_m, east_m, down_m] or (n, 3); a paper state is (4,) or
(n, 4) [x_m, y_m, vx_m_s, vy_m_s].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pymap3d

__all__ = ["GeodeticPoint", "SwarmFrame", "VehicleFrame"]


@dataclass(frozen=True)
class GeodeticPoint:
    """A WGS84 point: latitude and longitude in degrees, altitude above mean sea level in metres."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.lat_deg) and -90.0 <= self.lat_deg <= 90.0):
            raise ValueError(f"latitude must be in [-90, 90] deg, got {self.lat_deg}")
        if not (np.isfinite(self.lon_deg) and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError(f"longitude must be in [-180, 180] deg, got {self.lon_deg}")
        if not np.isfinite(self.alt_amsl_m):
            raise ValueError(f"altitude must be finite, got {self.alt_amsl_m}")


@dataclass(frozen=True)
class SwarmFrame:
    """The local tangent plane (NED) at the mission datum."""

    datum: GeodeticPoint

    def geodetic_to_ned(self, lat_deg, lon_deg, alt_amsl_m) -> np.ndarray:
        """(3,) for scalars, (n, 3) for arrays: [north_m, east_m, down_m] of the points."""
        d = self.datum
        lat, lon = np.asarray(lat_deg, float), np.asarray(lon_deg, float)
        n, e, _ = pymap3d.geodetic2ned(lat, lon, np.zeros_like(lat), d.lat_deg, d.lon_deg, 0.0)
        down = d.alt_amsl_m - np.asarray(alt_amsl_m, float)
        return np.stack(np.broadcast_arrays(n, e, down), axis=-1).astype(float)

    def ned_to_geodetic(self, ned_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lat_deg, lon_deg, alt_amsl_m) of swarm-frame points ned_m (3,) or (n, 3)."""
        p = np.asarray(ned_m, dtype=float)
        d = self.datum
        lat, lon, _ = pymap3d.ned2geodetic(p[..., 0], p[..., 1], np.zeros_like(p[..., 0]), d.lat_deg, d.lon_deg, 0.0)
        return np.asarray(lat, float), np.asarray(lon, float), d.alt_amsl_m - p[..., 2]

    def vehicle(self, origin: GeodeticPoint) -> "VehicleFrame":
        """The frame of a vehicle whose EKF origin is ``origin``."""
        return VehicleFrame(self, origin)


@dataclass(frozen=True)
class VehicleFrame:
    """One vehicle's LOCAL_NED (relative to its EKF origin) against the swarm frame."""

    swarm: SwarmFrame
    origin: GeodeticPoint
    origin_ned_m: np.ndarray = field(init=False, repr=False)        # d_i: the origin in the swarm frame, (3,)
    rotation: np.ndarray = field(init=False, repr=False)            # local -> swarm directions, (3, 3)

    def __post_init__(self) -> None:
        o = self.origin
        object.__setattr__(self, "origin_ned_m", self.swarm.geodetic_to_ned(o.lat_deg, o.lon_deg, o.alt_amsl_m))
        # the Jacobian of local -> swarm at the origin, by central differences over +-1 m (the map is smooth:
        # the second-order term is |p|/R_earth ~ 1.6e-7 per metre, so this is the rotation to ~1e-9)
        h = 1.0
        cols = [(self._to_swarm(np.eye(3)[k] * h) - self._to_swarm(-np.eye(3)[k] * h)) / (2 * h) for k in range(3)]
        object.__setattr__(self, "rotation", np.stack(cols, axis=1))

    def _to_swarm(self, local_ned_m: np.ndarray) -> np.ndarray:
        o = self.origin
        p = np.asarray(local_ned_m, dtype=float)
        lat, lon, _ = pymap3d.ned2geodetic(p[..., 0], p[..., 1], np.zeros_like(p[..., 0]), o.lat_deg, o.lon_deg, 0.0)
        return self.swarm.geodetic_to_ned(lat, lon, o.alt_amsl_m - p[..., 2])

    def local_to_swarm(self, local_ned_m) -> np.ndarray:
        """Positions in the vehicle's LOCAL_NED -> the swarm frame, (3,) or (n, 3)."""
        return self._to_swarm(local_ned_m)

    def swarm_to_local(self, swarm_ned_m) -> np.ndarray:
        """Swarm-frame positions -> the vehicle's LOCAL_NED (e.g. a position setpoint), (3,) or (n, 3)."""
        lat, lon, alt = self.swarm.ned_to_geodetic(swarm_ned_m)
        o = self.origin
        n, e, _ = pymap3d.geodetic2ned(lat, lon, np.zeros_like(lat), o.lat_deg, o.lon_deg, 0.0)
        return np.stack(np.broadcast_arrays(n, e, o.alt_amsl_m - alt), axis=-1).astype(float)

    def vector_to_swarm(self, local_vec) -> np.ndarray:
        """A velocity or acceleration (3,) or (n, 3) from local to swarm axes."""
        return np.asarray(local_vec, dtype=float) @ self.rotation.T

    def vector_to_local(self, swarm_vec) -> np.ndarray:
        """A velocity or acceleration (3,) or (n, 3) from swarm to local axes (the rotation's transpose)."""
        return np.asarray(swarm_vec, dtype=float) @ self.rotation

    def state_local_to_swarm(self, local_state, down_m: float = 0.0) -> np.ndarray:
        """A paper state [x, y, vx, vy] (4,) or (n, 4) in the vehicle's LOCAL_NED -> the swarm frame
        (at local altitude ``down_m``; the horizontal result barely depends on it)."""
        s = np.asarray(local_state, dtype=float)
        z = np.full(s.shape[:-1] + (1,), float(down_m))
        pos = self.local_to_swarm(np.concatenate([s[..., 0:2], z], axis=-1))
        vel = self.vector_to_swarm(np.concatenate([s[..., 2:4], np.zeros_like(z)], axis=-1))
        return np.concatenate([pos[..., 0:2], vel[..., 0:2]], axis=-1)

    def acc_swarm_to_local(self, acc_ne_m_s2) -> np.ndarray:
        """A horizontal acceleration [north, east] (2,) in the swarm frame -> the vehicle's local axes."""
        a = np.asarray(acc_ne_m_s2, dtype=float)
        return self.vector_to_local(np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1))[..., 0:2]
