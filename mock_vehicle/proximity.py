"""The emulated onboard proximity sensor: which vehicles a vehicle senses, and what it
reports of them as ADSB_VEHICLE (docs/proximity.md). Pure functions; the world process
(``mock_vehicle.world``), the mock vehicle and the in-process simulator all use them, so
the sensed sets and their wire resolution are the same on every path.

- ``sensed_pairs``: every pair within ``range_m`` (Euclidean, <=) of the float32-rounded
  true positions, by scipy's cKDTree over all N vehicles in id order (the simulator's
  query, the same array in the same order, so boundary cases agree too).
- ``encode_traffic``: a state -> ADSB_VEHICLE integers (scalar ``math``, per vehicle).
- ``quantise_sensed_states``: what a controller decodes from those integers
  (``mavlink_bridge.adsb.traffic_to_local_ned``), i.e. encode then the bridge's decode.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mavlink_bridge import AdsbVehicle
from mavlink_bridge.adsb import (
    ADSB_FLAGS_EMULATED,
    home_e7,
    icao_of_vehicle_id,
    metres_per_e7,
    traffic_tag,
    traffic_to_local_ned,
)

__all__ = ["DEFAULT_HOME_DEG", "DEFAULT_HOME_ALT_AMSL_M", "sensed_pairs", "sensed_rows", "encode_traffic",
           "traffic_reports", "quantise_sensed_states"]

DEFAULT_HOME_DEG = (47.397742, 8.545594)
"""The mock's default home (PX4 SITL's Zurich home); every mock of a swarm shares one home."""
DEFAULT_HOME_ALT_AMSL_M = 488.0


def sensed_pairs(states_f32: np.ndarray, range_m: float) -> np.ndarray:
    """Undirected pairs (p, 2), i < j, of vehicles within ``range_m`` of each other.
    states_f32: (n, 4) float32-rounded true states in vehicle-id order."""
    from scipy.spatial import cKDTree      # here, not at module level: a mock vehicle imports this module but
                                           # never calls this (the world does); scipy.spatial is ~0.6 s of its start-up
    s = np.asarray(states_f32, dtype=np.float64)
    if s.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    return np.asarray(cKDTree(s[:, 0:2]).query_pairs(float(range_m), output_type="ndarray"), dtype=np.int64).reshape(-1, 2)


_RADIX_IDS = 1 << 16
"""``sensed_rows`` sorts by radix passes while every vehicle id fits 16 bits (below this), else by one argsort."""


def sensed_rows(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both directions of each pair as (owner (m,), other (m,)), sorted by (owner, other):
    the order in which a vehicle receives its traffic (by ICAO address)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
    other = np.concatenate([pairs[:, 1], pairs[:, 0]])
    if owner.size == 0:
        return owner, other
    if int(pairs.min()) >= 0 and int(pairs.max()) < _RADIX_IDS:
        # two stable passes, by other then by owner (least significant key first): (owner, other) order. A stable
        # sort of 16-bit keys is numpy's radix sort, linear in the m rows; the argsort of the combined int64 key
        # below is O(m log m), most of a step once thousands of vehicles crowd within the range (~10^6 rows)
        by_other = np.argsort(other.astype(np.uint16), kind="stable")
        owner = owner[by_other]
        by_owner = np.argsort(owner.astype(np.uint16), kind="stable")
        return owner[by_owner], other[by_other[by_owner]]
    order = np.argsort(owner * (int(other.max()) + 1) + other)   # keys are distinct: any sort gives one order
    return owner[order], other[order]


def encode_traffic(states: np.ndarray, home_deg: tuple[float, float] = DEFAULT_HOME_DEG) -> np.ndarray:
    """ADS-B integers (m, 4) [lat_e7, lon_e7, hor_velocity_cm_s, heading_cdeg] of states (m, 4).

    Flat earth around the home: lat = home_lat + round(x / m_north) degE7, likewise east;
    speed = round(|v| * 100) cm/s (capped at 65535), heading = round(atan2(vy, vx) in
    0.01 deg) mod 36000 (0 when at rest). The integers do not depend on how many vehicles
    are encoded together: |v| and atan2 are Python's scalar ``math.hypot`` / ``math.atan2``
    per vehicle (numpy's vectorised hypot/arctan2 differ from them in the last bit for ~0.5 %
    / ~7 % of inputs, and SIMD loops may treat an array's tail differently); the rest is
    elementwise IEEE arithmetic (division, * 180/pi, round half to even), the same bits in
    numpy as in scalar Python (tests/test_proximity.py checks against the scalar formulas)."""
    h_lat, h_lon = home_e7(home_deg)
    m_n, m_e = metres_per_e7(h_lat)
    s = np.asarray(states, dtype=np.float64).reshape(-1, 4)
    m = s.shape[0]
    out = np.empty((m, 4), dtype=np.int64)
    if m == 0:
        return out
    if not np.all(np.isfinite(s)):
        raise ValueError("traffic states must be finite")
    vx, vy = s[:, 2].tolist(), s[:, 3].tolist()
    speed = np.fromiter(map(math.hypot, vx, vy), dtype=np.float64, count=m)
    ang = np.fromiter(map(math.atan2, vy, vx), dtype=np.float64, count=m)
    out[:, 0] = h_lat + np.rint(s[:, 0] / m_n).astype(np.int64)
    out[:, 1] = h_lon + np.rint(s[:, 1] / m_e).astype(np.int64)
    out[:, 2] = np.minimum(np.rint(speed * 100.0).astype(np.int64), 65535)
    out[:, 3] = np.where(speed > 0, np.mod(np.rint(np.degrees(ang) * 100.0).astype(np.int64), 36000), 0)
    return out


_SCALAR_LIMIT = 1e15
"""``_encode_traffic_rows`` computes states whose every |value| is below this (m, m/s) with the
scalar formulas: their integers fit int64 (|x| / m_north and 100 |v| < 2^62), where numpy's and
Python's are the same; anything else (non-finite, absurd) goes through ``encode_traffic``."""


def _encode_traffic_rows(states: np.ndarray, home_deg: tuple[float, float]) -> list:
    """``encode_traffic(states, home_deg).tolist()``: per vehicle with the scalar formulas it
    reproduces bit for bit (tests/test_proximity.py), cheaper than numpy for a mock's few
    sensed vehicles per step."""
    h_lat, h_lon = home_e7(home_deg)
    m_n, m_e = metres_per_e7(h_lat)
    rows = []
    lim = _SCALAR_LIMIT
    hypot, atan2, degrees = math.hypot, math.atan2, math.degrees
    for x, y, vx, vy in np.asarray(states, dtype=np.float64).reshape(-1, 4).tolist():
        if not (-lim < x < lim and -lim < y < lim and -lim < vx < lim and -lim < vy < lim):   # NaN fails too
            return encode_traffic(states, home_deg).tolist()
        speed = hypot(vx, vy)
        rows.append((h_lat + round(x / m_n), h_lon + round(y / m_e), min(round(speed * 100.0), 65535),
                     round(degrees(atan2(vy, vx)) * 100.0) % 36000 if speed > 0 else 0))
    return rows


_ADSB_FIELDS = ("icao_address", "lat_e7", "lon_e7", "altitude_type", "altitude_mm", "heading_cdeg", "hor_velocity_cm_s",
                "ver_velocity_cm_s", "callsign", "emitter_type", "tslc_s", "flags", "squawk", "received_monotonic_s")
_ADSB_DIRECT = ([f.name for f in dataclasses.fields(AdsbVehicle)] == list(_ADSB_FIELDS)
                and not hasattr(AdsbVehicle, "__post_init__") and "__slots__" not in vars(AdsbVehicle))
_ADSB_UNSTAMPED = dataclasses.fields(AdsbVehicle)[-1].default     # received_monotonic_s of a message built locally (NaN)
"""AdsbVehicle is a plain frozen dataclass (these fields in this order, no __post_init__, no
slots): ``traffic_reports`` may then fill a new instance's ``__dict__`` directly, the object
its constructor would build (the same fields, values and order) at a third of the cost of
the frozen ``__init__`` (one object.__setattr__ per field). Otherwise it calls the constructor."""


def traffic_reports(ids: np.ndarray, states: np.ndarray, time_boot_ms: int, home_deg: tuple[float, float] = DEFAULT_HOME_DEG,
                    altitude_amsl_m: float = DEFAULT_HOME_ALT_AMSL_M + 10.0) -> list[AdsbVehicle]:
    """The ADSB_VEHICLE messages of one traffic set (tagged ``time_boot_ms``)."""
    enc = _encode_traffic_rows(states, home_deg)
    tag = traffic_tag(time_boot_ms)
    alt_mm = int(round(altitude_amsl_m * 1000.0))
    ids = np.asarray(ids).reshape(-1).tolist()
    if not _ADSB_DIRECT:
        return [AdsbVehicle(icao_address=icao_of_vehicle_id(v), lat_e7=lat, lon_e7=lon, altitude_type=1, altitude_mm=alt_mm,
                            heading_cdeg=hdg, hor_velocity_cm_s=speed, ver_velocity_cm_s=0, callsign=tag, emitter_type=14,
                            tslc_s=0, flags=ADSB_FLAGS_EMULATED, squawk=0)
                for v, (lat, lon, speed, hdg) in zip(ids, enc)]
    out = []
    new, unstamped, flags = object.__new__, _ADSB_UNSTAMPED, ADSB_FLAGS_EMULATED
    for v, (lat, lon, speed, hdg) in zip(ids, enc):
        m = new(AdsbVehicle)
        m.__dict__.update(icao_address=icao_of_vehicle_id(v), lat_e7=lat, lon_e7=lon, altitude_type=1, altitude_mm=alt_mm,
                          heading_cdeg=hdg, hor_velocity_cm_s=speed, ver_velocity_cm_s=0, callsign=tag, emitter_type=14,
                          tslc_s=0, flags=flags, squawk=0, received_monotonic_s=unstamped)
        out.append(m)
    return out


def quantise_sensed_states(states: np.ndarray, home_deg: tuple[float, float] = DEFAULT_HOME_DEG) -> np.ndarray:
    """States (m, 4) as a controller decodes them from ADSB_VEHICLE: bit-identical to
    ``mavlink_bridge.adsb.adsb_states`` of the messages ``traffic_reports`` builds."""
    enc = encode_traffic(states, home_deg)
    h_lat, h_lon = home_e7(home_deg)
    return traffic_to_local_ned(enc[:, 0], enc[:, 1], enc[:, 2], enc[:, 3], h_lat, h_lon)
