"""Traffic (ADSB_VEHICLE) as local NED states: the controller side of the emulated
proximity sensor (docs/proximity.md).

A vehicle with a proximity sensor forwards every vehicle it senses as ADSB_VEHICLE (#246),
as PX4 forwards ADS-B/FLARM traffic for traffic avoidance, followed by one completion
marker NAMED_VALUE_INT(time_boot_ms = t, name = ``TRAFFIC_MARKER_NAME``, value = count).
Every ADSB_VEHICLE of the set carries the same ``t`` in its callsign
(``traffic_tag(t)`` = 8 hex digits), so a set is complete when its marker and ``count``
reports tagged ``t`` have arrived, whatever the arrival order.

Wire resolution (common.xml): lat/lon 1e-7 deg (~1.1 cm north, ~0.75 cm east at 47 deg),
hor_velocity 1 cm/s, heading 0.01 deg. Positions are flat-earth offsets from the swarm's
shared home, in whole degE7 steps from the home's own degE7 (what HOME_POSITION carries),
so the conversion never depends on float rounding of absolute latitudes.

``traffic_to_local_ned`` is the one decoding function: the link uses it on received
messages, and the simulator's ``mock_vehicle.proximity.quantise_sensed_states`` uses it on
the integers the mock would send, so both give bit-identical states (test_proximity.py).
It is exact IEEE arithmetic only (integer differences times constants, a cos/sin table
indexed by the integer heading): no vectorised transcendental whose last bit could
depend on the array length.
"""

from __future__ import annotations

import math
import operator

import numpy as np

from .messages import AdsbVehicle, HomePosition

__all__ = [
    "EARTH_RADIUS_M",
    "TRAFFIC_MARKER_NAME",
    "ADSB_FLAGS_EMULATED",
    "traffic_tag",
    "parse_traffic_tag",
    "metres_per_e7",
    "home_e7",
    "traffic_to_local_ned",
    "adsb_states",
    "vehicle_id_of_icao",
    "icao_of_vehicle_id",
]

EARTH_RADIUS_M = 6_378_137.0
"""WGS84 equatorial radius; the mock's flat-earth conversion uses the same (GLOBAL_POSITION_INT)."""

TRAFFIC_MARKER_NAME = "TRAFFIC_N"
"""NAMED_VALUE_INT name of the completion marker of a traffic set (value = its size)."""

ADSB_FLAGS_EMULATED = 1 | 2 | 4 | 8 | 16 | 64
"""VALID_COORDS | VALID_ALTITUDE | VALID_HEADING | VALID_VELOCITY | VALID_CALLSIGN | SIMULATED."""

_DEG_PER_E7 = 1e-7
_TRIG_CDEG: dict[int, tuple[float, float]] = {}
"""heading (cdeg) -> (cos, sin), filled as headings are seen: the full 36,000-entry table of
scalar ``math`` calls cost ~12 ms of CPU in every process's start-up (mock, world and controller)."""
_TRIG_TABLE: np.ndarray | None = None   # (36000, 2), built once for large sets (the simulator at large N)
_TRIG_TABLE_FROM = 4096


def _cos_sin_cdeg(h: int) -> tuple[float, float]:
    cs = _TRIG_CDEG.get(h)
    if cs is None:
        r = math.radians(h * 0.01)
        cs = _TRIG_CDEG[h] = (math.cos(r), math.sin(r))
    return cs


def _trig(hdg: np.ndarray) -> np.ndarray:
    """(m, 2) [cos, sin] of headings (m,) in 0..35999 cdeg: scalar ``math`` of h * 0.01 degrees,
    the same bits for any m."""
    global _TRIG_TABLE
    if hdg.shape[0] >= _TRIG_TABLE_FROM:
        if _TRIG_TABLE is None:
            _TRIG_TABLE = np.array([_cos_sin_cdeg(h) for h in range(36000)])
        return _TRIG_TABLE[hdg]
    return np.array([_cos_sin_cdeg(h) for h in hdg.tolist()], dtype=np.float64).reshape(-1, 2)


def traffic_tag(time_boot_ms: int) -> str:
    """The callsign that tags a traffic report with the set it belongs to."""
    return f"{int(time_boot_ms) & 0xFFFFFFFF:08X}"


def parse_traffic_tag(callsign: str) -> int | None:
    """time_boot_ms of a tag, or None if the callsign is not a tag."""
    if len(callsign) != 8:
        return None
    try:
        return int(callsign, 16)
    except ValueError:
        return None


def icao_of_vehicle_id(vehicle_id: int) -> int:
    """ICAO address of a swarm vehicle: its MAVLink system id (vehicle id + 1)."""
    return int(vehicle_id) + 1


def vehicle_id_of_icao(icao_address: int) -> int:
    return int(icao_address) - 1


def home_e7(home: HomePosition | tuple[float, float]) -> tuple[int, int]:
    """Home latitude/longitude in whole degE7 (exactly what HOME_POSITION carries)."""
    lat, lon = (home.lat_deg, home.lon_deg) if isinstance(home, HomePosition) else home
    return int(round(lat * 1e7)), int(round(lon * 1e7))


def metres_per_e7(home_lat_e7: int) -> tuple[float, float]:
    """Flat-earth size of one degE7 step north and east at the home latitude, m."""
    north = math.radians(_DEG_PER_E7) * EARTH_RADIUS_M
    return north, north * math.cos(math.radians(home_lat_e7 * _DEG_PER_E7))


def traffic_to_local_ned(lat_e7, lon_e7, hor_velocity_cm_s, heading_cdeg, home_lat_e7: int, home_lon_e7: int) -> np.ndarray:
    """Traffic in wire units -> local NED states (m, 4) [x_m, y_m, vx_m_s, vy_m_s].

    x = (lat - home_lat) * m_north, y = (lon - home_lon) * m_east (degE7 steps), speed
    = hor_velocity / 100, (vx, vy) = speed * (cos, sin)(heading)."""
    lat = np.asarray(lat_e7, dtype=np.int64).reshape(-1)
    lon = np.asarray(lon_e7, dtype=np.int64).reshape(-1)
    spd = np.asarray(hor_velocity_cm_s, dtype=np.int64).reshape(-1)
    hdg = np.asarray(heading_cdeg, dtype=np.int64).reshape(-1) % 36000
    m_n, m_e = metres_per_e7(home_lat_e7)
    out = np.empty((lat.shape[0], 4))
    out[:, 0] = (lat - home_lat_e7).astype(np.float64) * m_n
    out[:, 1] = (lon - home_lon_e7).astype(np.float64) * m_e
    speed = spd.astype(np.float64) / 100.0
    cs = _trig(hdg)
    out[:, 2] = speed * cs[:, 0]
    out[:, 3] = speed * cs[:, 1]
    return out


def adsb_states(reports: list[AdsbVehicle], home: HomePosition | tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(vehicle ids (m,), local NED states (m, 4)) of a traffic set, sorted by vehicle id.

    The states are ``traffic_to_local_ned`` of the reports' wire values. A sensor's set (a few
    dozen reports, every control step) is converted with scalar float arithmetic, which is
    the same IEEE operations on the same values as the array version (integer differences
    converted exactly, then one multiplication; speed / 100.0 times the tabled cos/sin),
    without its dozen small-array calls; larger sets use the array version. (Same bits for
    any values within +-2**62; wire values are 32-bit. The array version's int64 would
    raise or wrap beyond that.)"""
    reports = sorted(reports, key=_BY_ICAO)
    h_lat, h_lon = home_e7(home)
    m = len(reports)
    if 0 < m < _TRIG_TABLE_FROM:
        m_n, m_e = metres_per_e7(h_lat)
        rows = []
        for r in reports:
            c, s = _cos_sin_cdeg(r.heading_cdeg % 36000)
            speed = r.hor_velocity_cm_s / 100.0
            rows.append((float(r.lat_e7 - h_lat) * m_n, float(r.lon_e7 - h_lon) * m_e, speed * c, speed * s))
        return np.array([r.icao_address - 1 for r in reports], dtype=np.int64), np.array(rows, dtype=np.float64)
    wire = np.array([(r.icao_address, r.lat_e7, r.lon_e7, r.hor_velocity_cm_s, r.heading_cdeg) for r in reports],
                    dtype=np.int64).reshape(-1, 5)
    ids = wire[:, 0] - 1                       # vehicle_id_of_icao
    states = traffic_to_local_ned(wire[:, 1], wire[:, 2], wire[:, 3], wire[:, 4], h_lat, h_lon)
    return ids, states


_BY_ICAO = operator.attrgetter("icao_address")
