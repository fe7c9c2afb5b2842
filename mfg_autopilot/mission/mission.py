"""A swarm mission: geodetic, validated at load, refused before any vehicle moves if malformed or unsafe.

The file format is a JSON document described by ``mission.schema.json`` (docs/mission.md). Loading
is two steps:

1. the JSON Schema (jsonschema, draft 2020-12): types, ranges, required and unknown fields;
2. safety checks in the swarm frame (pymap3d for every conversion, shapely for the geofence):
   duplicate system ids, slots or launch grids closer than twice the safety radius, a site's
   slots or a launch grid outside the geofence, groups whose slot blocks overlap, cruise altitude
   above the fence's ceiling, a datum far from the field.

Every refusal is a :class:`MissionError` whose message starts with the field as a JSON path
(``groups[1].site.lat_deg``) and says why. A loaded :class:`Mission` gives the controller what it
needs in swarm-frame metres: each vehicle's group, site, slot, launch point and cruise altitude.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import shapely
from scipy.spatial import cKDTree

from mfg_autopilot.mission.frames import GeodeticPoint, SwarmFrame

__all__ = ["MissionError", "Group", "Mission", "load_mission", "mission_from_ne", "grid_offsets_m", "DEFAULT_DATUM",
           "SCHEMA"]

DEFAULT_DATUM = GeodeticPoint(47.397742, 8.545594, 488.0)
"""The datum of missions generated from the built-in scenarios: PX4 SITL's default home (Zurich)."""

MAX_DATUM_DISTANCE_M = 50_000.0
"""A datum farther than this from every geofence vertex is a mistake (a tangent plane is not meant for it)."""

SCHEMA: dict = json.loads(resources.files(__package__).joinpath("mission.schema.json").read_text(encoding="utf-8"))
_VALIDATOR = jsonschema.Draft202012Validator(SCHEMA)


class MissionError(ValueError):
    """A malformed or unsafe mission. ``field`` is the JSON path of the offending field."""

    def __init__(self, field_path: str, reason: str):
        super().__init__(f"{field_path or '(mission)'}: {reason}")
        self.field = field_path
        self.reason = reason


def _json_path(path) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def grid_offsets_m(n: int, spacing_m: float) -> np.ndarray:
    """n points row by row on a square grid of ceil(sqrt(n)) columns, centred on 0, (n, 2) [north, east]."""
    cols = int(math.ceil(math.sqrt(n)))
    rows = int(math.ceil(n / cols))
    idx = np.arange(n)
    pts = np.stack([idx // cols, idx % cols], axis=1).astype(float) * spacing_m
    return pts - np.array([(rows - 1) * spacing_m / 2.0, (cols - 1) * spacing_m / 2.0])


@dataclass(frozen=True)
class Group:
    """One group: vehicles flying from one launch area to one site at one cruise altitude."""

    name: str
    system_ids: tuple[int, ...]
    launch: GeodeticPoint                 # centre of the launch area (alt: the datum's, the field being flat)
    launch_spacing_m: float
    site: GeodeticPoint
    slot_spacing_m: float
    altitude_agl_m: float
    launch_ne_m: np.ndarray = field(repr=False, compare=False)      # (2,) in the swarm frame
    site_ne_m: np.ndarray = field(repr=False, compare=False)        # (2,)

    @property
    def slots_ne_m(self) -> np.ndarray:
        """The group's slots, (n, 2): a square grid of slot_spacing_m centred on the site, in system-id order."""
        return self.site_ne_m[None, :] + grid_offsets_m(len(self.system_ids), self.slot_spacing_m)

    @property
    def launch_positions_ne_m(self) -> np.ndarray:
        """Where the group's vehicles stand at launch, (n, 2): a grid of launch_spacing_m on the launch point."""
        return self.launch_ne_m[None, :] + grid_offsets_m(len(self.system_ids), self.launch_spacing_m)


@dataclass(frozen=True)
class Mission:
    """A validated mission (build it with :func:`load_mission`)."""

    datum: GeodeticPoint
    safety_radius_m: float
    max_speed_m_s: float
    geofence_latlon: tuple[tuple[float, float], ...]
    max_alt_agl_m: float | None
    on_arrival: str
    groups: tuple[Group, ...]
    name: str = ""
    description: str = ""
    frame: SwarmFrame = field(init=False, repr=False, compare=False)
    geofence_ne: shapely.Polygon = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame", SwarmFrame(self.datum))
        ne = self.frame.geodetic_to_ned([p[0] for p in self.geofence_latlon], [p[1] for p in self.geofence_latlon],
                                        [self.datum.alt_amsl_m] * len(self.geofence_latlon))
        object.__setattr__(self, "geofence_ne", shapely.Polygon(ne[:, 0:2]))

    # -------------------------------------------------------------- per vehicle
    @property
    def system_ids(self) -> tuple[int, ...]:
        return tuple(sorted(s for g in self.groups for s in g.system_ids))

    @property
    def n(self) -> int:
        return sum(len(g.system_ids) for g in self.groups)

    def require_system_id(self, system_id: int) -> None:
        if system_id not in self.system_ids:
            raise MissionError("groups", f"unknown system id {system_id}: the mission has {_ranges(self.system_ids)}")

    def group_of(self, system_id: int) -> Group:
        self.require_system_id(system_id)
        return next(g for g in self.groups if system_id in g.system_ids)

    def _row(self, system_id: int) -> tuple[Group, int]:
        g = self.group_of(system_id)
        return g, g.system_ids.index(system_id)

    def site_ne_m(self, system_id: int) -> np.ndarray:
        return self.group_of(system_id).site_ne_m.copy()

    def slot_ne_m(self, system_id: int) -> np.ndarray:
        g, i = self._row(system_id)
        return g.slots_ne_m[i]

    def launch_ne_m(self, system_id: int) -> np.ndarray:
        g, i = self._row(system_id)
        return g.launch_positions_ne_m[i]

    def launch_geodetic(self, system_id: int) -> GeodeticPoint:
        """Where the vehicle stands at launch (its EKF origin on a real field), on the datum's altitude."""
        ne = self.launch_ne_m(system_id)
        lat, lon, _ = self.frame.ned_to_geodetic([ne[0], ne[1], 0.0])
        return GeodeticPoint(float(lat), float(lon), self.datum.alt_amsl_m)

    def altitude_agl_m(self, system_id: int) -> float:
        return self.group_of(system_id).altitude_agl_m

    def arrays(self) -> dict[str, np.ndarray]:
        """Per vehicle in system-id order: system_id (N,), group (N,), launch_ne_m (N, 2), site_ne_m (N, 2),
        slot_ne_m (N, 2), altitude_agl_m (N,)."""
        ids = self.system_ids
        gi = {s: k for k, g in enumerate(self.groups) for s in g.system_ids}
        return {"system_id": np.array(ids, dtype=np.int64),
                "group": np.array([gi[s] for s in ids], dtype=np.int64),
                "launch_ne_m": np.array([self.launch_ne_m(s) for s in ids]).reshape(-1, 2),
                "site_ne_m": np.array([self.site_ne_m(s) for s in ids]).reshape(-1, 2),
                "slot_ne_m": np.array([self.slot_ne_m(s) for s in ids]).reshape(-1, 2),
                "altitude_agl_m": np.array([self.altitude_agl_m(s) for s in ids], dtype=float)}

    # -------------------------------------------------------------- file
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"schema_version": 1}
        if self.name:
            d["name"] = self.name
        if self.description:
            d["description"] = self.description
        d["datum"] = _point3(self.datum)
        d["safety_radius_m"] = self.safety_radius_m
        d["max_speed_m_s"] = self.max_speed_m_s
        d["geofence"] = {"polygon": [[lat, lon] for lat, lon in self.geofence_latlon]}
        if self.max_alt_agl_m is not None:
            d["geofence"]["max_alt_agl_m"] = self.max_alt_agl_m
        d["on_arrival"] = self.on_arrival
        d["groups"] = [{"name": g.name, "system_ids": list(g.system_ids),
                        "launch": {"lat_deg": g.launch.lat_deg, "lon_deg": g.launch.lon_deg, "spacing_m": g.launch_spacing_m},
                        "site": {"lat_deg": g.site.lat_deg, "lon_deg": g.site.lon_deg},
                        "slot_spacing_m": g.slot_spacing_m, "altitude_agl_m": g.altitude_agl_m} for g in self.groups]
        return d


def _point3(p: GeodeticPoint) -> dict:
    return {"lat_deg": p.lat_deg, "lon_deg": p.lon_deg, "alt_amsl_m": p.alt_amsl_m}


def _ranges(ids) -> str:
    ids = sorted(ids)
    return f"{len(ids)} ids from {ids[0]} to {ids[-1]}" if ids else "no ids"


def load_mission(source: str | Path | dict) -> Mission:
    """A mission from a file path, a JSON text or a dict; MissionError if malformed or unsafe."""
    if isinstance(source, dict):
        doc = source
    else:
        text = str(source)
        if isinstance(source, Path) or not text.lstrip().startswith("{"):
            try:
                text = Path(source).read_text(encoding="utf-8")
            except OSError as exc:
                raise MissionError("", f"cannot read mission file {str(source)!r}: {exc.strerror or exc}") from None
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MissionError("", f"not JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    err = jsonschema.exceptions.best_match(_VALIDATOR.iter_errors(doc))
    if err is not None:
        raise MissionError(_json_path(err.absolute_path), err.message)
    datum = GeodeticPoint(**doc["datum"])
    frame = SwarmFrame(datum)
    groups = []
    for k, g in enumerate(doc["groups"]):
        lau = GeodeticPoint(g["launch"]["lat_deg"], g["launch"]["lon_deg"], datum.alt_amsl_m)
        site = GeodeticPoint(g["site"]["lat_deg"], g["site"]["lon_deg"], datum.alt_amsl_m)
        groups.append(Group(name=g["name"], system_ids=tuple(int(s) for s in g["system_ids"]), launch=lau,
                            launch_spacing_m=float(g["launch"].get("spacing_m", g["slot_spacing_m"])), site=site,
                            slot_spacing_m=float(g["slot_spacing_m"]), altitude_agl_m=float(g["altitude_agl_m"]),
                            launch_ne_m=frame.geodetic_to_ned(lau.lat_deg, lau.lon_deg, lau.alt_amsl_m)[0:2],
                            site_ne_m=frame.geodetic_to_ned(site.lat_deg, site.lon_deg, site.alt_amsl_m)[0:2]))
    fence = doc["geofence"]
    m = Mission(datum=datum, safety_radius_m=float(doc["safety_radius_m"]), max_speed_m_s=float(doc["max_speed_m_s"]),
                geofence_latlon=tuple((float(a), float(b)) for a, b in fence["polygon"]),
                max_alt_agl_m=fence.get("max_alt_agl_m"), on_arrival=doc["on_arrival"], groups=tuple(groups),
                name=doc.get("name", ""), description=doc.get("description", ""))
    _check_safety(m)
    return m


def _check_safety(m: Mission) -> None:
    """The semantic checks of a schema-valid mission (module docstring); MissionError naming the field."""
    seen: dict[int, int] = {}
    for k, g in enumerate(m.groups):
        for j, s in enumerate(g.system_ids):
            if s in seen:
                raise MissionError(f"groups[{k}].system_ids[{j}]", f"system id {s} is already in groups[{seen[s]}]")
            seen[s] = k
    fence = m.geofence_ne
    if not fence.is_valid or fence.area <= 0:
        raise MissionError("geofence.polygon", f"not a simple polygon with an area ({shapely.is_valid_reason(fence)})")
    d_datum = min(math.hypot(*p) for p in np.asarray(fence.exterior.coords))
    if d_datum > MAX_DATUM_DISTANCE_M and not fence.contains(shapely.Point(0.0, 0.0)):
        raise MissionError("datum", f"{d_datum / 1000:.1f} km from the geofence (at most {MAX_DATUM_DISTANCE_M / 1000:.0f} km)")
    clearance = 2.0 * m.safety_radius_m
    for k, g in enumerate(m.groups):
        if g.slot_spacing_m < clearance:
            raise MissionError(f"groups[{k}].slot_spacing_m", f"{g.slot_spacing_m} m is closer than twice the safety radius "
                                                            f"({clearance} m)")
        if g.launch_spacing_m < clearance:
            raise MissionError(f"groups[{k}].launch.spacing_m", f"{g.launch_spacing_m} m is closer than twice the safety "
                                                              f"radius ({clearance} m)")
        for what, pts, path in (("slot", g.slots_ne_m, f"groups[{k}].site"), ("launch position", g.launch_positions_ne_m,
                                                                                   f"groups[{k}].launch")):
            # every point with its safety disc inside the fence
            inside = fence.buffer(-m.safety_radius_m)
            out = ~shapely.contains_xy(inside, pts[:, 0], pts[:, 1]) if not inside.is_empty else np.ones(len(pts), bool)
            if np.any(out):
                i = int(np.flatnonzero(out)[0])
                raise MissionError(path, f"{what} of system id {g.system_ids[i]} at ({pts[i, 0]:.1f}, {pts[i, 1]:.1f}) m "
                                         f"north/east of the datum is outside the geofence (or within the safety radius of it)")
        if m.max_alt_agl_m is not None and g.altitude_agl_m > m.max_alt_agl_m:
            raise MissionError(f"groups[{k}].altitude_agl_m", f"{g.altitude_agl_m} m is above the geofence ceiling "
                                                            f"max_alt_agl_m = {m.max_alt_agl_m} m")
    # slots of different groups (and launch positions) at least twice the safety radius apart
    for what, attr, key in (("slots", "slots_ne_m", "site"), ("launch positions", "launch_positions_ne_m", "launch")):
        pts = np.concatenate([getattr(g, attr) for g in m.groups])
        owner = np.concatenate([np.full(len(g.system_ids), k) for k, g in enumerate(m.groups)])
        pairs = cKDTree(pts).query_pairs(clearance * (1 - 1e-9), output_type="ndarray")
        pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]] if len(pairs) else pairs
        if len(pairs):
            a, b = sorted((int(owner[pairs[0, 0]]), int(owner[pairs[0, 1]])))
            d = float(np.linalg.norm(pts[pairs[0, 0]] - pts[pairs[0, 1]]))
            raise MissionError(f"groups[{b}].{key}", f"its {what} come within {d:.2f} m of groups[{a}]'s "
                                                     f"(at least twice the safety radius, {clearance} m)")


def mission_from_ne(*, groups_ne: list[dict], datum: GeodeticPoint = DEFAULT_DATUM, safety_radius_m: float = 0.1,
                    max_speed_m_s: float = 8.0, on_arrival: str = "hold", fence_margin_m: float = 200.0,
                    name: str = "", description: str = "") -> Mission:
    """A mission from swarm-frame metres (the built-in scenarios): each group a dict with ``name``,
    ``system_ids``, ``launch_ne_m`` (2,), ``site_ne_m`` (2,), ``slot_spacing_m``, ``altitude_agl_m`` and
    optionally ``launch_spacing_m``. The geofence is the bounding box of launches and sites grown by
    ``fence_margin_m``. Validated like a file."""
    frame = SwarmFrame(datum)
    pts = np.array([p for g in groups_ne for p in (g["launch_ne_m"], g["site_ne_m"])], dtype=float)
    lo, hi = pts.min(axis=0) - fence_margin_m, pts.max(axis=0) + fence_margin_m
    box = np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]], [hi[0], lo[1]]])
    lat, lon, _ = frame.ned_to_geodetic(np.column_stack([box, np.zeros(4)]))

    def geo(ne) -> dict:
        la, lo_, _ = frame.ned_to_geodetic([float(ne[0]), float(ne[1]), 0.0])
        return {"lat_deg": float(la), "lon_deg": float(lo_)}

    doc = {"schema_version": 1, "name": name, "description": description, "datum": _point3(datum),
           "safety_radius_m": safety_radius_m, "max_speed_m_s": max_speed_m_s,
           "geofence": {"polygon": [[float(a), float(b)] for a, b in zip(lat, lon)]}, "on_arrival": on_arrival,
           "groups": [{"name": g["name"], "system_ids": [int(s) for s in g["system_ids"]],
                       "launch": {**geo(g["launch_ne_m"]), "spacing_m": float(g.get("launch_spacing_m", g["slot_spacing_m"]))},
                       "site": geo(g["site_ne_m"]), "slot_spacing_m": float(g["slot_spacing_m"]),
                       "altitude_agl_m": float(g["altitude_agl_m"])} for g in groups_ne]}
    if not name:
        del doc["name"]
    if not description:
        del doc["description"]
    return load_mission(doc)
