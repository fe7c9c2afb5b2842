"""Mission scenarios: where the UAVs start and where each one is going.

- ``paper`` is Sec. V: N UAVs on a square grid with sqrt(2) m spacing centred at
  (150, 100) m, all flying to the origin.
- ``crossing``: two groups (N/2 and N - N/2) on sqrt(2) m grids centred at (-60, 0) and
  (60, 0) m; each group's site is the other's centre, so they swap sides through each other.
- ``dense``: the paper's scenario with grid spacing 0.5 m.

Positions are (x, y) = (north, east) in metres. ``destination_m`` is each UAV's mission
*site* (shared by its group); the default controller derives each UAV's slot from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Scenario", "grid_positions", "make_scenario", "SCENARIOS"]


@dataclass(frozen=True)
class Scenario:
    name: str
    initial_pos_m: np.ndarray      # (N, 2)
    destination_m: np.ndarray      # (N, 2) each UAV's destination
    group: np.ndarray              # (N,) group index (0 for single-group scenarios)
    initial_vel_m_s: np.ndarray | None = None   # (N, 2); None: drawn from the wind (the paper's start, airborne)

    @property
    def n(self) -> int:
        return self.initial_pos_m.shape[0]


def grid_positions(n: int, spacing_m: float, centre_m) -> np.ndarray:
    """n points row by row on a square grid of ceil(sqrt(n)) columns, centred on centre_m. (n, 2)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    idx = np.arange(n)
    pts = np.stack([idx // cols, idx % cols], axis=1).astype(float) * spacing_m
    pts -= np.array([(rows - 1) * spacing_m / 2.0, (cols - 1) * spacing_m / 2.0])
    return pts + np.asarray(centre_m, dtype=float)


def _paper(n: int, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    pos = grid_positions(n, spacing_m, (150.0, 100.0))
    return Scenario("paper", pos, np.zeros((n, 2)), np.zeros(n, dtype=np.int64))


def _dense(n: int) -> Scenario:
    sc = _paper(n, spacing_m=0.5)
    return Scenario("dense", sc.initial_pos_m, sc.destination_m, sc.group)


def _crossing(n: int, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    if n < 2:
        raise ValueError(f"crossing needs n >= 2, got {n}")
    na = n // 2
    west, east = np.array([-60.0, 0.0]), np.array([60.0, 0.0])
    pos = np.concatenate([grid_positions(na, spacing_m, west), grid_positions(n - na, spacing_m, east)])
    dest = np.concatenate([np.tile(east, (na, 1)), np.tile(west, (n - na, 1))])
    group = np.concatenate([np.zeros(na, dtype=np.int64), np.ones(n - na, dtype=np.int64)])
    return Scenario("crossing", pos, dest, group)


SCENARIOS = {"paper": _paper, "crossing": _crossing, "dense": _dense}


def scenario_from_mission(mission) -> Scenario:
    """A field mission (``mfg_autopilot.mission.Mission``) as a scenario in its swarm frame: every vehicle (in
    system-id order) from its launch position to its group's site, at the cruise altitude (the
    simulator flies the horizontal part only: no takeoff, no landing)."""
    a = mission.arrays()
    # at rest: a vehicle of a field mission starts from a hover at its altitude after its takeoff
    return Scenario(f"mission:{mission.name or 'mission'}", a["launch_ne_m"], a["site_ne_m"], a["group"],
                    initial_vel_m_s=np.zeros_like(a["launch_ne_m"]))


def make_scenario(name: str, n: int) -> Scenario:
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}") from None
    return factory(n)
