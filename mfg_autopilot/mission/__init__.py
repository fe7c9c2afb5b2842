"""Missions and the shared swarm frame: what the vehicles are asked to do, and where, in one frame.

May import only the standard library and third-party geometry (numpy, jsonschema, pymap3d,
shapely); nothing else of the project.
"""
