"""Missions and the shared swarm frame: what the vehicles are asked to do, and where, in one frame.

:mod:`.mission` loads a geodetic mission file (``mission.schema.json``, docs/mission.md) and refuses
a malformed or unsafe one before any vehicle moves; :mod:`.frames` converts between the mission's
swarm frame (a tangent plane at the datum) and each vehicle's own LOCAL_NED (relative to its EKF
origin). May import only the standard library and third-party geometry (numpy, scipy, jsonschema,
pymap3d, shapely); nothing else of the project.
"""

from mfg_autopilot.mission.frames import GeodeticPoint, SwarmFrame, VehicleFrame
from mfg_autopilot.mission.mission import DEFAULT_DATUM, Group, Mission, MissionError, load_mission, mission_from_ne

__all__ = ["GeodeticPoint", "SwarmFrame", "VehicleFrame", "DEFAULT_DATUM", "Group", "Mission", "MissionError", "load_mission",
           "mission_from_ne"]
